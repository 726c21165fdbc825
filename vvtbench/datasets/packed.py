"""Read a dataset written by ``vvtbench export`` (:func:`vvtbench.datasets.export.pack`).

``open_dataset(path)`` opens a Zarr folder or an HDF5 file and gives a
:class:`PackedDataset`; ``ds[name]`` is a :class:`PackedSample` with the read interface of
:class:`vvtbench.samples.reader.Sample`. The layout is described in :mod:`vvtbench.datasets.export`
and
docs/dataset.md ("Exported datasets"). This module also holds what the writer and the reader
share: the format name and version, the video chunk length, the dimensions and units of an
extracted ModeSet's arrays, and :class:`ExportError`.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..samples.reader import VIEW_GROUPS, SampleView, view_info

__all__ = ["ExportError", "FORMAT", "FORMAT_VERSION", "MODESET_ARRAYS", "PackedDataset",
           "PackedSample", "VIDEO_CHUNK", "is_dataset", "open_dataset", "view_info",
           "view_truth_path"]

FORMAT = "vvtbench.dataset-pack"
FORMAT_VERSION = 2
#: Frames per chunk of a packed video (the reader decodes one chunk at a time).
VIDEO_CHUNK = 64
#: The arrays of an extracted ModeSet packed under ``samples/<name>/extracted/<i>/``.
MODESET_ARRAYS = {  # name -> (dims, units)
    "frequencies_hz": (("extracted_mode",), "Hz"),
    "damping": (("extracted_mode",), "1"),
    "damping_half_power": (("extracted_mode",), "1"),
    "amplitudes_px": (("extracted_mode",), "px"),
    "peak_bins": (("extracted_mode",), None),
    "prominences": (("extracted_mode",), "decades"),
    "collinearity": (("extracted_mode",), "1"),
    "shake_mac": (("extracted_mode",), "1"),
    "camera_shake": (("extracted_mode",), None),
    "shapes": (("extracted_mode", "row", "col", "component"), "1"),
    "power": (("frequency",), "px2"),
    "confidence": (("row", "col"), "1"),
}


class ExportError(ValueError):
    """Export refused or failed for a reason the user can fix (the message says which path)."""


def _text(v: Any) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def view_truth_path(name: str) -> tuple[int, str] | None:
    """``(i, rest)`` for the truth.zarr name ``views/<i>/<rest>`` of view ``i`` >= 1."""
    parts = name.split("/", 2)
    if len(parts) == 3 and parts[0] == "views" and parts[1].isdigit() and int(parts[1]) >= 1:
        return int(parts[1]), parts[2]
    return None


class PackedSample(SampleView):
    """One sample of a packed dataset, with the read interface of
    :class:`vvtbench.samples.reader.Sample`: ``scene`` (Scene), ``camera`` (Camera), ``info``
    (truth.json), ``manifest``, ``s["modes/frequencies_hz"]`` (a truth array by its
    truth.zarr name), ``frames()`` / ``read_frames()``, ``extracted_modes()``, and
    ``n_views`` / ``view(i)`` for a sample filmed by several cameras."""

    def __init__(self, group, name: str, dataset_path: Path | None = None, *,
                 view: int = 0, chunks: _Chunks | None = None):
        from ..render import Camera
        from ..scene.scene import parse_scene

        self.group, self.name, self.dataset_path = group, name, dataset_path
        self._chunks = chunks
        a = group.attrs
        self.info: dict = json.loads(_text(a["truth"]))
        self.manifest: dict = json.loads(_text(a["manifest"]))
        self.scene_toml = _text(a["scene_toml"])
        self.scene = parse_scene(tomllib.loads(self.scene_toml),
                                 f"{dataset_path or 'dataset'}:samples/{name}/scene_toml")
        self.camera = Camera.from_dict(json.loads(_text(a["camera"])))
        self.seed = int(a["seed"])
        self.revision = _text(a["sample_revision"])
        self.truth_arrays: list[str] = json.loads(_text(a.get("truth_arrays", "[]")))
        self._extracted: list[str] = json.loads(_text(a.get("extracted", "[]")))
        self.view_index = int(view)
        self._view_group = group
        if view:
            where = f"{dataset_path or 'dataset'}:samples/{name}/views/{view}"
            if "views" not in group or str(view) not in group["views"]:
                raise ExportError(f"{where}: missing; the dataset was exported without the "
                                  "sample's other views (by an older vvtbench): export it "
                                  "again")
            vg = self._view_group = group["views"][str(view)]
            entry = json.loads(_text(vg.attrs["view"]))
            self.info = view_info(self.info, view, entry)
            self.camera = Camera.from_dict(json.loads(_text(vg.attrs["camera"])))
            prefix = f"views/{view}/"
            own = {n[len(prefix):] for n in self.truth_arrays if n.startswith(prefix)}
            self.truth_arrays = [n for n in self.truth_arrays if view_truth_path(n) is None
                                 and not n.startswith(VIEW_GROUPS)] + sorted(own)
            self._extracted = []

    # ---- several views
    @property
    def n_views(self) -> int:
        """Number of synchronised views of the simulation the sample holds; 1 for a
        single-view sample (as :attr:`vvtbench.samples.reader.Sample.n_views`)."""
        views = self.info.get("views")
        return len(views) if isinstance(views, list) and views else 1

    def view(self, index: int) -> PackedSample:
        """View ``index`` as a sample of its own: its camera, video and view arrays
        (``observation/*``, ``image/*``, ``crb/*``, ``modes/crb_*``) with the sample's shared
        arrays, as :meth:`vvtbench.samples.reader.Sample.view`. ``view(0)`` is the sample."""
        n = self.n_views
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not (
                0 <= index < n):
            raise ExportError(f"{self.dataset_path or 'dataset'}:samples/{self.name}: no view "
                              f"{index!r}; the sample holds views 0..{n - 1}")
        if int(index) == self.view_index:
            return self
        return PackedSample(self.group, self.name, self.dataset_path, view=int(index),
                            chunks=self._chunks)

    # ---- the Sample interface
    @property
    def path(self) -> Path | None:
        """The dataset file or folder this sample was read from."""
        return self.dataset_path

    @property
    def has_video(self) -> bool:
        return "video" in self._view_group

    @property
    def video(self):
        """The lazy (time, row, col) video array (slice it); every chunk the export wrote must
        be there (a missing one is an error, never frames of zeros)."""
        view = f"/views/{self.view_index}" if self.view_index else ""
        self._check(f"samples/{self.name}{view}/video", content=False)
        return self._view_group["video"]

    def _check(self, prefix: str, content: bool) -> None:
        if self._chunks is not None:
            self._chunks.check(prefix, content)

    @property
    def times(self) -> np.ndarray:
        return self["transient/times"]

    def __getitem__(self, name: str) -> np.ndarray:
        """The whole truth array ``name``, its chunk files checked against the sha256 the
        export recorded."""
        return np.asarray(self.array(name, content=True)[...])

    def __contains__(self, name: str) -> bool:
        return name in self.truth_arrays

    def array(self, name: str, *, content: bool = False):
        """The lazy array ``name`` of the truth (slice it to read part of it): a name of the
        sample's truth.zarr (``views/<i>/...`` is view ``i``'s array); in a view, its own
        arrays and the shared ones. Every chunk file the export wrote must be there (Zarr:
        a missing chunk would read as zeros), and with ``content`` match its sha256;
        ExportError naming the chunk otherwise."""
        if name not in self.truth_arrays:
            raise KeyError(f"{self.name}: no truth array {name!r}; arrays: "
                           f"{', '.join(self.truth_arrays)}")
        base = f"samples/{self.name}"
        if self.view_index and name.startswith(VIEW_GROUPS):
            self._check(f"{base}/views/{self.view_index}/truth/{name}", content)
            return self._view_group["truth"][name]
        found = view_truth_path(name)
        if found is not None:
            self._check(f"{base}/views/{found[0]}/truth/{found[1]}", content)
            return self.group["views"][str(found[0])]["truth"][found[1]]
        self._check(f"{base}/truth/{name}", content)
        return self.group["truth"][name]

    def frames(self, start: int = 0, stop: int | None = None, *,
               normalize: bool = False) -> Iterator[np.ndarray]:
        """Video frames ``start:stop`` one at a time: (H, W) uint16 DN, or float32 in [0, 1]
        with ``normalize``."""
        n = self.n_frames
        stop = n if stop is None else min(stop, n)
        if not 0 <= start <= stop:
            raise IndexError(f"frames {start}:{stop} out of range 0:{n}")
        if not self.has_video:
            raise ValueError(f"{self.name}: the dataset holds no video for this sample")
        v = self.video
        scale = np.float32(1.0 / (2 ** self.bit_depth - 1))
        for k0 in range(start, stop, VIDEO_CHUNK):
            block = np.asarray(v[k0:min(k0 + VIDEO_CHUNK, stop)])
            for f in block:
                yield f.astype(np.float32) * scale if normalize else f.astype(np.uint16)

    def read_frames(self, start: int = 0, stop: int | None = None, *,
                    normalize: bool = False) -> np.ndarray:
        """Frames ``start:stop`` as one (T, H, W) array."""
        out = list(self.frames(start, stop, normalize=normalize))
        dtype = np.float32 if normalize else np.uint16
        return np.stack(out) if out else np.zeros((0, *self.shape), dtype)

    def extracted_modes(self) -> list:
        """The extracted :class:`vvtbench.modes.ModeSet` packed with this sample (may be [])."""
        from ..modes import ModeSet

        out = []
        for i in range(len(self._extracted)):
            g = self.group["extracted"][str(i)]
            doc = json.loads(_text(g.attrs["modes_json"]))
            for a in (*MODESET_ARRAYS, "frequency"):
                if a in g:
                    self._check(f"samples/{self.name}/extracted/{i}/{a}", content=True)
            arrays = {a: np.asarray(g[a][...]) for a in MODESET_ARRAYS if a in g}
            out.append(ModeSet(**arrays, freqs_hz=np.asarray(g["frequency"][...]),
                               fps=float(g.attrs["fps"]), n_frames=int(g.attrs["n_frames"]),
                               metadata=doc.get("metadata", {})))
        return out

    def __repr__(self) -> str:
        H, W = self.shape
        which = f" view {self.view_index}" if self.view_index else ""
        return (f"PackedSample({self.name!r}{which}: {self.n_frames} frames at {self.fps:g} FPS, "
                f"{H}x{W}, {len(self.truth_arrays)} truth arrays, "
                f"{len(self._extracted)} extracted mode sets)")


class _Chunks:
    """The chunk files of a Zarr dataset, from its ``SHA256SUMS`` (written by the export),
    grouped by array: :meth:`check` refuses an array one of whose chunks is missing (Zarr
    reads a missing chunk as the fill value: zeros) or, with ``content``, changed."""

    def __init__(self, path: Path):
        from .release import ReleaseError, read_sums

        self.path = path
        sums_file = path / "SHA256SUMS"
        self.by_array: dict[str, dict[str, str]] | None = None
        self.problem: str | None = None
        if not sums_file.is_file():
            self.problem = (f"{sums_file}: missing (deleted, or written by an older vvtbench): "
                            "its chunks cannot be checked and a missing chunk would read as "
                            "zeros; export the dataset again")
            return
        try:
            sums = read_sums(sums_file)
        except ReleaseError as error:
            self.problem = str(error)
            return
        self.by_array = {}
        for rel, digest in sums.items():
            array, sep, _ = rel.rpartition("/c/")
            if sep:
                self.by_array.setdefault(array, {})[rel] = digest
        self.checked: dict[str, bool] = {}

    def check(self, prefix: str, content: bool) -> None:
        if self.by_array is None:
            raise ExportError(self.problem)
        if self.checked.get(prefix) or (self.checked.get(prefix) is False and not content):
            return
        from ..samples.reader import sha256_file

        for rel, digest in self.by_array.get(prefix, {}).items():
            f = self.path / rel
            if f.is_symlink() or not f.is_file():
                raise ExportError(f"{self.path}: chunk {rel} is missing (listed in "
                                  "SHA256SUMS; it would read as zeros): the dataset is "
                                  "damaged; copy or export it again")
            if content and sha256_file(f) != digest:
                raise ExportError(f"{self.path}: chunk {rel} differs from its sha256 in "
                                  "SHA256SUMS: the dataset is damaged; copy or export it again")
        self.checked[prefix] = content


class PackedDataset:
    """A dataset written by :func:`vvtbench.datasets.export.pack`: ``names``, ``ds[name]`` ->
    :class:`PackedSample`."""

    def __init__(self, root, path: Path, closer=None):
        self.root, self.path, self._closer = root, path, closer
        self._chunks = _Chunks(path) if path.is_dir() else None  # HDF5: one file
        self.attrs = {k: _text(v) if isinstance(v, bytes) else v
                      for k, v in root.attrs.items()}
        self.names: list[str] = json.loads(_text(self.attrs["samples"]))

    def __getitem__(self, name: str) -> PackedSample:
        if name not in self.names:
            raise KeyError(f"{self.path}: no sample {name!r}; samples: {', '.join(self.names)}")
        return PackedSample(self.root["samples"][name], name, self.path, chunks=self._chunks)

    def __iter__(self):
        return (self[n] for n in self.names)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def readme(self) -> str:
        return _text(self.attrs.get("README", ""))

    def __repr__(self) -> str:
        shown = ", ".join(self.names[:3]) + (", ..." if len(self.names) > 3 else "")
        return f"PackedDataset({str(self.path)!r}: {len(self)} samples: {shown})"

    def close(self) -> None:
        if self._closer:
            self._closer()
            self._closer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_dataset(path: str | Path) -> PackedDataset:
    """Open a dataset written by ``vvtbench export`` (Zarr folder or HDF5 file)."""
    path = Path(path)
    if path.is_dir():
        import zarr

        try:
            root = zarr.open_group(str(path), mode="r")
        except (FileNotFoundError, ValueError) as error:
            raise ExportError(f"{path}: not a vvtbench dataset ({error})") from None
        if root.attrs.get("format") != FORMAT:
            raise ExportError(f"{path}: not a vvtbench dataset (no format={FORMAT!r} "
                              "attribute)")
        return PackedDataset(root, path)
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as error:
        raise ExportError(f"{path}: cannot open as HDF5: {error}") from None
    if _text(f.attrs.get("format", "")) != FORMAT:
        f.close()
        raise ExportError(f"{path}: not a vvtbench dataset (no format={FORMAT!r} attribute)")
    return PackedDataset(f, path, f.close)


def is_dataset(path: Path) -> bool:
    """Whether ``path`` is an exported dataset (an HDF5 file or a ``.zarr`` folder that is not
    a sample)."""
    return path.is_file() or (path.is_dir() and (path / "zarr.json").is_file()
                              and not (path / "scene.toml").is_file())
