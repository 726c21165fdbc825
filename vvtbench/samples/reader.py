"""Sample reader: open, check and read a generated sample folder (video + ground truth).

Samples are written by :func:`vvtbench.samples.generate.generate`. ``open_sample(path)`` reads one
back lazily after checking it against its manifest (:func:`check_sample`: the sha256 of
``scene.toml``, ``truth.json``, ``camera.json`` and every file of ``truth.zarr``, the video's
size in bytes, and its frame count, frame size and pixel format by probing); a sample that
fails is a :class:`DatasetError` naming the file. :meth:`Sample.verify` also hashes the video
and counts its frames. :meth:`Sample.require` reads a ground-truth array and says clearly when
a sample is too old to hold it. The folder layout, every array's shape, dtype and unit, and
the conventions are in ``docs/dataset.md``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..scene.scene import Scene, load_scene

__all__ = [
    "DatasetError",
    "FORMAT_VERSION",
    "Sample",
    "check_sample",
    "open_sample",
    "sha256_file",
    "view_info",
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


class SampleView:
    """What a sample reader derives from ``self.info`` (truth.json) and ``self[name]``: the
    one definition shared by :class:`Sample` and :class:`vvtbench.datasets.packed.PackedSample`."""

    info: dict

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
    def frequencies_hz(self) -> np.ndarray:
        return self["modes/frequencies_hz"]

    @property
    def damping_ratios(self) -> np.ndarray:
        return self["modes/damping_ratios"]

    @property
    def sensor(self) -> dict[str, Any]:
        """The camera noise the video was filmed with (``truth.json`` ``video``).

        Returns
        -------
        dict
            ``read_noise_dn`` (DN), ``shot_noise``, ``full_well_electrons``, ``bit_depth``,
            ``frame_average``, ``noise_free`` (:func:`vvtbench.render.sensor.is_noise_free`:
            no shot and no read noise) and ``label``, the camera in words
            (:func:`vvtbench.render.sensor.describe_sensor`; ``"noise-free sensor ..."`` for
            a camera without noise).
        """
        from ..render.sensor import describe_sensor, is_noise_free

        v = self.info["video"]
        r, shot = float(v["read_noise_dn"]), bool(v["shot_noise"])
        fw, bits = float(v["full_well_electrons"]), int(v["bit_depth"])
        return {"read_noise_dn": r, "shot_noise": shot, "full_well_electrons": fw,
                "bit_depth": bits, "frame_average": int(v.get("frame_average", 1)),
                "noise_free": is_noise_free(r, shot),
                "label": describe_sensor(r, shot, fw, bits)}


@dataclass
class Sample(SampleView):
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
    def times(self) -> np.ndarray:
        return self.require("transient/times")

    @property
    def n_views(self) -> int:
        """Number of synchronised views of the simulation the sample holds (docs/dataset.md,
        "Several views"); 1 for a single-view sample."""
        views = self.info.get("views")
        return len(views) if isinstance(views, list) and views else 1

    def view(self, index: int) -> Sample:
        """View ``index`` of the sample as a :class:`Sample` of its own: its camera, video
        (``views/<i>/video.mkv``), ``observation/*``, ``image/*``, ``crb/*`` and
        ``modes/crb_*`` arrays (read from ``truth.zarr/views/<i>/``) and the sample's shared
        arrays (mesh, material, voxels, modes, transient). ``view(0)`` is the sample."""
        n = self.n_views
        if not isinstance(index, (int, np.integer)) or isinstance(index, bool) or not (
                0 <= index < n):
            raise DatasetError(f"{self.path}: no view {index!r}; the sample holds views "
                               f"0..{n - 1}")
        if index == 0:
            return self
        entries, problems = _view_entries(self.info)
        if problems:
            raise DatasetError(f"{self.path / problems[0]}")
        entry = entries[int(index) - 1]
        camera = _read_camera(self.path / entry["camera"])
        info = view_info(self.info, index, entry)
        return Sample(self.path, self.scene, camera, info, self.manifest,
                      _ViewTruth(self.truth, f"views/{int(index)}/"))

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

    @property
    def crb_snr(self) -> np.ndarray | None:
        """``(n,)`` CRB-limited SNR of each true mode in the video (``modes/crb_snr``,
        docs/dataset.md "The Cramér-Rao ruler"); ``None`` for a modes-only sample or one
        written before the ruler existed."""
        return self["modes/crb_snr"] if "modes/crb_snr" in self else None

    @property
    def crb_detection_snr(self) -> float | None:
        """The SNR a true mode needs to count as detectable (``truth.json`` ``crb``); ``None``
        without the ruler."""
        ruler = self.info.get("crb")
        return None if not isinstance(ruler, dict) else float(ruler["detection_snr"])

    def ruler(self, *, read_noise_dn: float | None = None, shot_noise: bool | None = None,
              full_well: float | None = None) -> dict[str, Any]:
        """The Cramér-Rao ruler of the filmed motion, for the sample's camera or another.

        The per-mode SNR of :mod:`vvtbench.render.crb` from the sample's rest render
        (``image/rest``), image-space modes (``image/modes``) and modal energies
        (``modes/crb_energy_px2``), with the noise of a camera given here; the arguments
        left out are the sample's (:attr:`sensor`). With none given it is the stored
        ``modes/crb_snr``. What the same motion would show to a noisier or a noise-free
        camera, without rendering it again.

        Parameters
        ----------
        read_noise_dn : float, optional
            Read noise per sub-frame (DN).
        shot_noise : bool, optional
            Poisson shot noise.
        full_well : float, optional
            Full-well capacity (electrons).

        Returns
        -------
        dict
            ``sensor`` (the camera in words, :func:`vvtbench.render.sensor.describe_sensor`),
            ``noise_free``, ``snr`` ``(n,)`` per true mode, ``detection_snr`` (the SNR a mode
            needs to count as detectable, :func:`vvtbench.render.crb.detection_snr_threshold`)
            and ``n_detectable``.

        Raises
        ------
        DatasetError
            For a modes-only sample or one written before the ruler existed.
        """
        from ..render import crb
        from ..render.sensor import describe_sensor, is_noise_free

        own = self.sensor
        r = own["read_noise_dn"] if read_noise_dn is None else float(read_noise_dn)
        shot = own["shot_noise"] if shot_noise is None else bool(shot_noise)
        fw = own["full_well_electrons"] if full_well is None else float(full_well)
        bits = own["bit_depth"]
        energy = np.asarray(self.require("modes/crb_energy_px2"), dtype=np.float64)
        intensity = np.asarray(self.require("image/rest"), dtype=np.float64)
        self.require("image/modes")
        var = crb.noise_variance_dn2(intensity, bits, r, shot, fw, own["frame_average"])
        fisher = crb.pixel_fisher(intensity * float(2**bits - 1), var)
        dense = self.array("image/modes")
        info, _ = crb.mode_information(fisher, (dense[m] for m in range(dense.shape[0])))
        snr = crb.mode_snr(info, energy)
        threshold = crb.detection_snr_threshold(self.n_frames)
        return {"sensor": describe_sensor(r, shot, fw, bits), "noise_free": is_noise_free(r, shot),
                "snr": snr, "detection_snr": threshold,
                "n_detectable": int(np.count_nonzero(snr >= threshold))}

    def array(self, name: str):
        """The lazy Zarr array ``name`` (slice it to read part of it)."""
        return self.truth[name]

    def frames(self, start: int = 0, stop: int | None = None, *,
               normalize: bool = False) -> Iterator[np.ndarray]:
        """Video frames ``start:stop`` one at a time: (H, W) uint16 DN, or float32 in [0, 1]
        (DN / (2^bit_depth - 1)) with ``normalize``. A modes-only sample raises
        :class:`DatasetError`."""
        from ..video.files import VideoError, probe_video, read_frames

        if not self.has_video:
            raise DatasetError(f"{self.path}: modes-only sample (generated without video): "
                               "it has no frames; generate it with video to read frames")
        name = self.info["video"]["file"]
        if name in (self.manifest.get("withheld") or []) and not (self.path / name).exists():
            raise DatasetError(f"{self.path}: its video {name} was not rendered (the truth of a "
                               "filmed sample generated without frames); generate it again "
                               "with its frames")
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
        """Everything wrong with the sample, one ``"FILE: what is wrong"`` line each (empty
        when it matches its manifest): :func:`check_sample` with ``full=True`` (every file
        hashed, the video's frames counted)."""
        return check_sample(self.path, self.manifest, self.info, full=True)

    def __repr__(self) -> str:
        import zarr

        try:
            n_arrays = sum(1 for _, obj in self.truth.members(max_depth=None)
                           if isinstance(obj, zarr.Array))
        except Exception:  # noqa: BLE001 -- a repr must not raise
            n_arrays = "?"
        H, W = self.shape
        video = (f"{self.n_frames} frames of {W}x{H} px at {self.fps:g} fps" if self.has_video
                 else "modes only (no video)")
        return f"Sample({self.scene.name!r}: {video}, {n_arrays} arrays, {str(self.path)!r})"


#: The small files checked against the manifest on every open (with all of ``truth.zarr``).
CHECKED_FILES = ("scene.toml", "truth.json", "camera.json")

#: Arrays every view of a multi-view sample has of its own (``truth.zarr/views/<i>/...``).
VIEW_GROUPS = ("observation/", "image/", "crb/", "modes/crb_")


class _ViewTruth:
    """The truth group as one view sees it: its own arrays from ``views/<i>/``, the shared
    ones from the root."""

    def __init__(self, root: Any, prefix: str) -> None:
        self.root, self.prefix = root, prefix

    def __getitem__(self, name: str) -> Any:
        if name.startswith(VIEW_GROUPS) or name == "crb":
            return self.root[self.prefix + name]
        return self.root[name]

    @property
    def attrs(self) -> Any:
        return self.root.attrs

    def members(self, max_depth: int | None = None):
        return self.root.members(max_depth=max_depth)


def _read_camera(path: Path) -> Any:
    from ..render import Camera

    try:
        return Camera.from_dict(read_json(path))
    except (KeyError, TypeError, ValueError, OSError) as error:
        raise DatasetError(f"{path}: not a camera ({error})") from None


def _view_entries(info: dict) -> tuple[list[dict], list[str]]:
    """The ``truth.json`` ``views`` entries of views 1.. (none for a single-view sample), and
    what is wrong with the others."""
    views = info.get("views")
    if views is None:
        return [], []
    if not isinstance(views, list):
        return [], ["truth.json: 'views' is not a list (docs/dataset.md, 'Several views')"]
    good, problems = [], []
    for i, entry in enumerate(views[1:], start=1):
        if not (isinstance(entry, dict) and entry.get("camera") == f"views/{i}/camera.json"
                and entry.get("folder") == f"views/{i}"):
            problems.append(f"truth.json: views[{i}] does not name views/{i}/camera.json and "
                            f"folder views/{i} (docs/dataset.md, 'Several views')")
        else:
            good.append(entry)
    return good, problems


def read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: not a JSON object")
    return data


def _strip(message: str, path: Path) -> str:
    prefix = f"{path}: "
    return message[len(prefix):] if message.startswith(prefix) else message


def check_sample(path: str | Path, manifest: dict, info: dict, *,
                 full: bool = False) -> list[str]:
    """What is wrong with the sample folder ``path``, one ``"FILE: problem"`` line each
    (``FILE`` relative to ``path``; empty when the sample matches its manifest).

    Always checked (cheap; :func:`open_sample` does it on every open): the sha256 of
    ``scene.toml``, ``truth.json``, ``camera.json`` and of every file of ``truth.zarr``
    (missing, truncated or unlisted chunks included), the video's size in bytes, and its
    frame size, pixel format (lossless videos) and frame count (from the container's
    duration) against ``truth.json``. With ``full``, every file listed in the manifest is
    hashed (the video too), unlisted files are reported, and the video's frames are counted
    packet by packet (a video cut short but with its header intact is caught too).
    """
    path = Path(path)
    listed = manifest.get("files")
    if not isinstance(listed, dict):
        return ["manifest.json: no 'files' table (not a manifest written by vvtbench)"]

    def check(rel: str) -> None:
        entry, p = listed.get(rel), path / rel
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            problems.append(f"{rel}: not in the manifest")
        elif not p.is_file():
            problems.append(f"{rel}: missing" + (" (a deleted zarr chunk would read as "
                                                 "zeros)" if rel.startswith("truth.zarr/")
                                                 else ""))
        elif isinstance(entry.get("bytes"), int) and p.stat().st_size != entry["bytes"]:
            problems.append(f"{rel}: {p.stat().st_size} bytes, the manifest says "
                            f"{entry['bytes']} (truncated or modified)")
        elif sha256_file(p) != entry["sha256"]:
            problems.append(f"{rel}: sha256 mismatch")

    video = info.get("video") if isinstance(info.get("video"), dict) else {}
    video_file = video.get("file")
    views, problems = _view_entries(info)
    on_disk = sorted(p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file())
    if full:
        wanted = [rel for rel in listed]
        extra = [rel for rel in on_disk if rel != "manifest.json" and rel not in listed]
    else:
        wanted = [*CHECKED_FILES, *(str(v.get("camera")) for v in views),
                  *(rel for rel in listed if rel.startswith("truth.zarr/"))]
        extra = [rel for rel in on_disk if rel.startswith("truth.zarr/") and rel not in listed]
    withheld = manifest.get("withheld") if isinstance(manifest.get("withheld"), list) else []
    if video_file is not None and not _withheld_here(path, str(video_file), withheld):
        problems += _check_video(path, str(video_file), video, listed, full)
    for entry in views:
        if entry.get("video_file") is not None and not _withheld_here(
                path, str(entry["video_file"]), withheld):
            problems += _check_video(path, str(entry["video_file"]), {**video, **{
                k: entry.get(k) for k in ("height", "width")}}, listed, full,
                folder=str(entry.get("folder", "")))
    for rel in dict.fromkeys(wanted):
        check(rel)
    problems += [f"{rel}: not in the manifest" for rel in extra]
    problems += _check_ruler(info, listed)
    return problems


def _withheld_here(path: Path, name: str, withheld: list) -> bool:
    """A video the manifest lists as withheld (a sample generated without frames) and that
    is indeed absent: not a problem. Present, it is checked like any video."""
    return name in withheld and not (path / name).exists()


#: The arrays of the Cramér-Rao ruler (docs/dataset.md) a sample with ``truth.json`` ``crb``
#: holds.
RULER_ARRAYS = ("crb/fisher", "crb/std_px", "crb/std_min_px", "modes/crb_snr",
                "modes/crb_information", "modes/crb_energy_px2")


def _check_ruler(info: dict, listed: dict) -> list[str]:
    """A sample that reports the Cramér-Rao ruler in ``truth.json`` lists all its arrays."""
    ruler = info.get("crb")
    if ruler is None:
        return []  # written before the ruler, or modes-only
    if not isinstance(ruler, dict) or not isinstance(ruler.get("detection_snr"), (int, float)):
        return ["truth.json: 'crb' has no number 'detection_snr' (docs/dataset.md, "
                "'The Cramér-Rao ruler')"]
    return [f"truth.zarr/{name}: missing (truth.json reports the Cramér-Rao ruler)"
            for name in RULER_ARRAYS if f"truth.zarr/{name}/zarr.json" not in listed]


def _check_video(path: Path, name: str, video: dict, listed: dict, full: bool,
                 folder: str = "") -> list[str]:
    from ..video.files import VideoError, count_frames, probe_video

    base = name[len(folder) + 1:] if folder and name.startswith(folder + "/") else name
    parts = folder.split("/") if folder else []
    if (Path(base).name != base or base in ("", ".", "..") or not (
            parts == [] or (len(parts) == 2 and parts[0] == "views" and parts[1].isdigit()))):
        key = "video.file" if not folder else "views[].video_file"
        return [f"truth.json: {key} {name!r} is not a file name inside the sample"]
    p, entry = path / name, listed.get(name)
    if not isinstance(entry, dict):
        return [f"{name}: not in the manifest"]
    if not p.is_file():
        return [] if full else [f"{name}: missing"]  # full: reported by the hash check
    problems = []  # what the video holds first, then its size (the more telling first)
    size = []
    if not full and isinstance(entry.get("bytes"), int) and p.stat().st_size != entry["bytes"]:
        size.append(f"{name}: {p.stat().st_size} bytes, the manifest says "
                    f"{entry['bytes']} (truncated or modified)")
    try:
        vi = probe_video(p)
        n = count_frames(p) if full else vi.n_frames
    except (VideoError, OSError) as error:
        return [f"{name}: {_strip(str(error), p)}", *size]
    try:
        want_hw = (int(video["height"]), int(video["width"]))
        want_n = int(video["frames"])
    except (KeyError, TypeError, ValueError):
        return ["truth.json: video.height, video.width or video.frames missing", *size]
    if (vi.height, vi.width) != want_hw:
        problems.append(f"{name}: frames are {vi.width}x{vi.height} px, truth.json "
                        f"(video.width x video.height) says {want_hw[1]}x{want_hw[0]}")
    pix = video.get("pixel_format")
    if video.get("lossless") and pix and vi.pix_fmt != pix:
        problems.append(f"{name}: video stream is {vi.pix_fmt or 'of unknown pixel format'}, "
                        f"but truth.json (video.pixel_format) says {pix}; regenerate the "
                        "sample with this vvtbench")
    # without decoding, the count comes from the container's duration, which ffmpeg prints to
    # 10 ms: that many frames of slack (the byte size above catches any truncation); `verify`
    # (full) counts the frames exactly
    slack = 0 if full else int(np.ceil(0.01 * float(vi.container_rate or 0))) + 1
    if n is not None and abs(n - want_n) > slack:
        problems.append(f"{name}: {n} frames, truth.json (video.frames) says {want_n} "
                        "(truncated or replaced video)")
    return problems + size


def _problems_error(path: Path, problems: list[str]) -> DatasetError:
    rel, _, what = problems[0].partition(": ")
    more = (f"; {len(problems) - 1} more problem(s), list them with `vvtbench verify {path}`"
            if len(problems) > 1 else "")
    return DatasetError(f"{path / rel}: {what} (sample {path} does not match its "
                        f"manifest.json: regenerate it){more}")


def open_sample(path: str | Path, *, verify: bool = True) -> Sample:
    """Open a sample folder written by :func:`vvtbench.samples.generate.generate`.

    With ``verify`` (the default) the sample is checked first (:func:`check_sample`: the
    truth files and arrays against the manifest's sha256, the video's size, frame count,
    frame size and pixel format); the first problem is raised as a :class:`DatasetError`
    naming the file. ``verify=False`` opens a damaged sample for inspection.
    """
    import zarr


    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: " + ("not a folder (a sample is a folder)" if path.exists()
                                          else "no such sample folder"))
    needed = ("manifest.json", "truth.json", "camera.json", "scene.toml", "truth.zarr")
    missing = [n for n in needed if not (path / n).exists()]
    if missing:
        raise DatasetError(f"{path}: not a vvtbench sample (missing {', '.join(missing)})")
    manifest = read_json(path / "manifest.json")
    info = read_json(path / "truth.json")
    fmt = info.get("format", 0)
    if not isinstance(fmt, int) or isinstance(fmt, bool):
        raise DatasetError(f"{path / 'truth.json'}: format must be an integer, got {fmt!r}")
    if fmt > FORMAT_VERSION:
        raise DatasetError(f"{path}: dataset format {info['format']} is newer than this "
                           f"vvtbench ({__version__}) reads ({FORMAT_VERSION}); upgrade vvtbench")
    if verify:
        problems = check_sample(path, manifest, info)
        if problems:
            raise _problems_error(path, problems)
    scene = load_scene(path / "scene.toml")
    camera = _read_camera(path / "camera.json")
    try:
        truth = zarr.open_group(str(path / "truth.zarr"), mode="r")
    except (OSError, ValueError, KeyError) as error:
        raise DatasetError(f"{path / 'truth.zarr'}: cannot be opened as a zarr group "
                           f"({error})") from None
    return Sample(path, scene, camera, info, manifest, truth)


def view_info(info: dict, index: int, entry: dict) -> dict:
    """``truth.json`` as view ``index`` of a multi-view sample sees it (``entry``: its item of
    ``truth.json``'s ``views`` list): its video file and frame size, visible nodes, peak image
    motion, Cramér-Rao SNR and a ``view`` entry with its index and time offset."""
    out = json.loads(json.dumps(info))
    out["video"].update(file=entry.get("video_file"), height=int(entry["height"]),
                        width=int(entry["width"]))
    out["mesh"]["n_visible"] = entry.get("n_visible")
    out["peak_image_motion_px"] = entry.get("peak_image_motion_px")
    out["view"] = {"index": int(index), "time_offset_s": entry.get("time_offset_s", 0.0)}
    if "crb_snr" in entry:
        out["modes"]["crb_snr"] = entry["crb_snr"]
    return out
