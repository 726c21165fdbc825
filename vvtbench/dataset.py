"""Sample reader: open, check and read a generated sample folder (video + ground truth).

Samples are written by :func:`vvtbench.generate.generate`. ``open_sample(path)`` reads one
back lazily; :meth:`Sample.require` reads a ground-truth array and says clearly when a sample
is too old to hold it. The folder layout, every array's shape, dtype and unit, and the
conventions are in ``docs/dataset.md``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._version import __version__
from .scene import Scene, load_scene

__all__ = [
    "DatasetError",
    "FORMAT_VERSION",
    "Sample",
    "open_sample",
    "sha256_file",
]

#: Version of the sample folder format. 2: ``mesh/fixed_nodes``, ``mesh/node_sets/*``, the
#: element name on ``mesh``, voxel truth by volume-weighted overlap (``voxels/volume``), and
#: modes-only samples (no video).
FORMAT_VERSION = 2


class DatasetError(RuntimeError):
    """Generation or loading failed for a reason the user can fix (message says how)."""


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Sample:
    """A generated sample, opened lazily (see docs/dataset.md).

    ``sample["observation/jacobian"]`` reads a ground-truth array from ``truth.zarr``;
    :meth:`require` does the same with a clear error for arrays an older sample lacks;
    :meth:`frames` iterates over video frames without loading the whole video.
    """

    path: Path
    scene: Scene
    camera: Any
    info: dict
    manifest: dict
    truth: Any = field(repr=False)

    @property
    def format(self) -> int:
        """Dataset format version the sample was written with."""
        return int(self.info.get("format", 1))

    @property
    def has_video(self) -> bool:
        """False for a modes-only sample (``generate(..., video=False)``)."""
        return self.info["video"].get("file") is not None

    @property
    def n_frames(self) -> int:
        return int(self.info["video"]["frames"])

    @property
    def fps(self) -> float:
        return float(self.info["video"]["fps"])

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.info["video"]["height"]), int(self.info["video"]["width"]))

    @property
    def bit_depth(self) -> int:
        return int(self.info["video"]["bit_depth"])

    @property
    def video_path(self) -> Path:
        if not self.has_video:
            raise DatasetError(f"{self.path}: a modes-only sample has no video; generate it "
                               "with video (without --no-video)")
        return self.path / self.info["video"]["file"]

    @property
    def element(self) -> str:
        """Element type name of the simulation mesh (``truth.json`` ``mesh.element``)."""
        return str(self.info["mesh"]["element"])

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self["modes/frequencies_hz"]

    @property
    def damping_ratios(self) -> np.ndarray:
        return self["modes/damping_ratios"]

    @property
    def times(self) -> np.ndarray:
        return self.require("transient/times")

    def __getitem__(self, name: str) -> np.ndarray:
        return np.asarray(self.truth[name][...])

    def __contains__(self, name: str) -> bool:
        try:
            self.truth[name]
        except KeyError:
            return False
        return True

    def require(self, name: str) -> np.ndarray:
        """The ground-truth array ``name`` (e.g. ``"mesh/fixed_nodes"``), read whole.

        Raises
        ------
        DatasetError
            If the sample does not hold it, naming the file and the array: a sample of an
            older format (regenerate it), or a modes-only sample asked for ``transient/*``
            or ``image/modes``.
        """
        if name not in self:
            zpath = self.path / "truth.zarr"
            if not self.has_video and (name.startswith("transient/") or name == "image/modes"):
                why = "it is a modes-only sample (generated without video)"
                fix = "generate the sample with video"
            elif self.format < FORMAT_VERSION:
                why = (f"it was written in dataset format {self.format} and this vvtbench "
                       f"({__version__}) needs format {FORMAT_VERSION}")
                fix = f"regenerate it: vvtbench generate {self.scene.name} -o DIR --overwrite"
            else:
                why = "the array is not part of the format (docs/dataset.md)"
                fix = "check the array name"
            raise DatasetError(f"{zpath}: no array {name!r}: {why}; {fix}")
        return self[name]

    def array(self, name: str):
        """The lazy Zarr array ``name`` (slice it to read part of it)."""
        return self.truth[name]

    def frames(self, start: int = 0, stop: int | None = None, *,
               normalize: bool = False) -> Iterator[np.ndarray]:
        """Video frames ``start:stop`` one at a time: (H, W) uint16 DN, or float32 in [0, 1]
        (DN / (2^bit_depth - 1)) with ``normalize``. A modes-only sample raises
        :class:`DatasetError`."""
        from .video import VideoError, probe_video, read_frames

        if not self.has_video:
            raise DatasetError(f"{self.path}: modes-only sample (generated without video): "
                               "it has no frames; generate it with video to read frames")
        n = self.n_frames
        stop = n if stop is None else min(stop, n)
        if not 0 <= start <= stop:
            raise IndexError(f"frames {start}:{stop} out of range 0:{n}")
        if start == stop:
            return
        pix = self.info["video"]["pixel_format"]
        bpp = 2 if pix == "gray16le" else 1
        try:
            info = probe_video(self.video_path)
        except (VideoError, FileNotFoundError) as error:
            raise DatasetError(f"{self.video_path}: {error}") from None
        if self.info["video"].get("lossless") and info.pix_fmt != pix:
            found = info.pix_fmt or "of unknown pixel format"
            raise DatasetError(f"{self.video_path}: video stream is {found}, but truth.json "
                               f"(video.pixel_format) says {pix}; regenerate the sample with "
                               "this vvtbench")
        scale = 1.0 / (2 ** self.bit_depth - 1)
        for frame in read_frames(self.video_path, bpp=bpp, start=start, stop=stop, info=info):
            yield (frame.astype(np.float32) * np.float32(scale)) if normalize \
                else frame.astype(np.uint16)

    def read_frames(self, start: int = 0, stop: int | None = None, *,
                    normalize: bool = False) -> np.ndarray:
        """Frames ``start:stop`` as one (T, H, W) array."""
        out = list(self.frames(start, stop, normalize=normalize))
        dtype = np.float32 if normalize else np.uint16
        return np.stack(out) if out else np.zeros((0, *self.shape), dtype)

    def verify(self) -> list[str]:
        """Files whose sha256 differs from the manifest, or are missing or not listed."""
        bad = []
        listed = self.manifest["files"]
        for rel, entry in listed.items():
            p = self.path / rel
            if not p.is_file():
                bad.append(f"{rel}: missing")
            elif sha256_file(p) != entry["sha256"]:
                bad.append(f"{rel}: sha256 mismatch")
        for p in self.path.rglob("*"):
            rel = p.relative_to(self.path).as_posix()
            if p.is_file() and rel != "manifest.json" and rel not in listed:
                bad.append(f"{rel}: not in the manifest")
        return bad


def open_sample(path: str | Path) -> Sample:
    """Open a sample folder written by :func:`vvtbench.generate.generate`."""
    import zarr

    from .render import Camera

    path = Path(path)
    needed = ("manifest.json", "truth.json", "camera.json", "scene.toml", "truth.zarr")
    missing = [n for n in needed if not (path / n).exists()]
    if missing:
        raise DatasetError(f"{path}: not a vvtbench sample (missing {', '.join(missing)})")
    manifest = json.loads((path / "manifest.json").read_text())
    info = json.loads((path / "truth.json").read_text())
    if info.get("format", 0) > FORMAT_VERSION:
        raise DatasetError(f"{path}: dataset format {info['format']} is newer than this "
                           f"vvtbench ({__version__}) reads ({FORMAT_VERSION}); upgrade vvtbench")
    scene = load_scene(path / "scene.toml")
    camera = Camera.from_dict(json.loads((path / "camera.json").read_text()))
    truth = zarr.open_group(str(path / "truth.zarr"), mode="r")
    return Sample(path, scene, camera, info, manifest, truth)
