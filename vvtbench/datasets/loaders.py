"""Map-style datasets for learning: fixed-shape numpy items from generated or exported samples.

:class:`InstanceDataset` indexes the instances of one split of a folder of samples
(``vvtbench generate FAMILY --split S``) or of an exported dataset (``vvtbench export``: a
``.zarr`` folder or an HDF5 file). ``len(ds)`` is the instance count and ``ds[i]`` one item: a
dict of numpy arrays and plain Python values that ``torch.utils.data.DataLoader`` collates as
it is (vvtbench never imports torch)::

    {"inputs": {...}, "targets": {"w": ..., "v": ...},
     "split": "train", "instance": "cube_defects-train-00000", "family": "cube_defects",
     "index": 0}

Every array has the same shape in every item of a dataset: the observed modes are padded to
``max_modes`` with a mode mask, and the observed vertices are scattered onto all nodes of the
family's inference mesh with a visibility mask (hidden nodes, fixed nodes and missing modes
are zeros and masked). The truth (w and v on the voxel grid) is only in ``targets``, which
``targets=False`` leaves out. :data:`FEATURES` declares every array (name, shape, dtype,
units, description); :meth:`InstanceDataset.features` gives the shapes of one dataset and
:meth:`InstanceDataset.describe` prints them.

Observation ``"true"`` observes the true image-space modes; ``"extracted"`` observes the modes
extracted from the video, computed once per sample, extractor and extraction revision and kept
beside the data (:func:`extracted_modes_folder`), never once per epoch.

Several DataLoader workers are safe: the dataset holds no open file. A packed dataset is
opened lazily, once per process (keyed by ``os.getpid()``), so a handle is never shared across
``fork``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..samples.reader import DatasetError, sha256_file
from .extracted import default_cache_dir, extracted_modes_folder, extraction_key

__all__ = ["FEATURES", "Feature", "InstanceDataset"]

#: Revision of the item layout (part of the key of cached items).
ITEM_REVISION = 1


@dataclass(frozen=True)
class Feature:
    """One array of an item.

    Attributes
    ----------
    name : key in ``item[part]``.
    part : ``"inputs"`` (what a method may use) or ``"targets"`` (the truth).
    shape : dimensions: integers, or symbols resolved per dataset: ``K`` (``max_modes``),
        ``N`` (nodes of the inference mesh), ``d`` (DOFs per node: 3 solids, 1 drums),
        ``D`` (coordinates per node), ``grid`` (the voxel grid's dimensions).
    dtype : numpy dtype name.
    units : SI units (``1``: dimensionless; ``bool`` masks have none).
    description : what the array holds.
    """

    name: str
    part: str
    shape: tuple
    dtype: str
    units: str
    description: str


FEATURES: tuple[Feature, ...] = (
    Feature("gamma", "inputs", ("K", "N", 2), "float32", "px (unit norm per mode)",
            "observed image-space modes: (x, y) image motion of each node, each present mode "
            "of unit L2 norm over its visible nodes; 0 at hidden nodes and missing modes"),
    Feature("eigenvalues", "inputs", ("K",), "float32", "rad^2/s^2",
            "observed (2 pi f)^2 of each mode; 0 for missing modes"),
    Feature("mode_mask", "inputs", ("K",), "bool", "",
            "True for an observed mode, False for padding"),
    Feature("visible", "inputs", ("N",), "bool", "",
            "True for a node seen by the camera (its gamma entries are observed)"),
    Feature("node_mask", "inputs", ("N",), "bool", "",
            "True for a node of this instance's mesh, False for padding"),
    Feature("fixed", "inputs", ("N",), "bool", "",
            "True for a node held fixed (clamped base, drum rim)"),
    Feature("points", "inputs", ("N", "D"), "float32", "m",
            "node coordinates of the inference mesh (lowest corner at the origin)"),
    Feature("jacobian", "inputs", ("N", 2, "d"), "float32", "px/m",
            "camera Jacobian of each visible node: image motion per unit displacement of its "
            "DOFs (gamma is jacobian @ u scaled to unit norm); 0 at hidden and fixed nodes"),
    Feature("camera_K", "inputs", (3, 3), "float32", "px", "camera intrinsics"),
    Feature("camera_R", "inputs", (3, 3), "float32", "1", "camera rotation (world to camera)"),
    Feature("camera_t", "inputs", (3,), "float32", "m", "camera translation (world to camera)"),
    Feature("image_size", "inputs", (2,), "int64", "px", "frame width and height"),
    Feature("active", "inputs", ("grid",), "bool", "",
            "True for a voxel holding material (an unknown), False for an empty voxel"),
    Feature("w_mean", "inputs", (), "float32", "Pa (N/m for drums)",
            "prior mean of the stiffness (the anchor of the stiffness/density scale)"),
    Feature("w0", "inputs", (), "float32", "Pa (N/m for drums)", "prior initial stiffness"),
    Feature("v0", "inputs", (), "float32", "kg/m^3 (kg/m^2 for drums)",
            "prior initial density"),
    Feature("w", "targets", ("grid",), "float32", "Pa (N/m for drums)",
            "true Young's modulus (tension for drums) per voxel; 0 in empty voxels"),
    Feature("v", "targets", ("grid",), "float32", "kg/m^3 (kg/m^2 for drums)",
            "true density (areal density for drums) per voxel; 0 in empty voxels"),
)


@dataclass(frozen=True)
class _Layout:
    modes: int
    nodes: int
    dofs: int
    dim: int
    grid: tuple[int, ...]

    def resolve(self, shape: tuple) -> tuple[int, ...]:
        sizes = {"K": self.modes, "N": self.nodes, "d": self.dofs, "D": self.dim}
        out: list[int] = []
        for s in shape:
            if s == "grid":
                out.extend(self.grid)
            else:
                out.append(int(sizes.get(s, s)) if isinstance(s, str) else int(s))
        return tuple(out)


class InstanceDataset:
    """The instances of one split as fixed-shape numpy items (map-style: ``len``, ``[i]``).

    Parameters
    ----------
    path : a folder of sample folders (or one sample folder), or an exported dataset (a
        ``.zarr`` folder or an HDF5 file written by ``vvtbench export``).
    split : ``"train"``, ``"val"``, ``"test"``, or None for every instance.
    observation : ``"true"`` (the true image-space modes) or ``"extracted"`` (modes extracted
        from each sample's video once, then read from the cache).
    max_modes : the mode count K every item is padded to (the lowest ``max_modes`` modes are
        observed; an instance with fewer has them masked).
    targets : include the truth (``item["targets"]``); False for inputs only.
    n_nodes : the node count N every item is padded to (default: the largest inference mesh
        of the split; give every split of a family the same value when its meshes vary).
    options : further :class:`vvtbench.observe.ObserveOptions` fields (``inference_shape``,
        ``visibility``, ``extract``, ...); ``observation`` and ``n_modes`` are set from the
        arguments above.
    cache_dir : where extracted modes (and cached items) are kept (default: a
        ``.vvtbench-extracted`` folder beside the samples or the dataset).
    cache_items : keep each finished item (inputs and targets) in ``cache_dir`` the first
        time it is read, and read it from there later (a few milliseconds instead of the
        sample's checks and its observation); keyed by the sample's manifest, the observe
        options and the padded sizes, and checked against its sha256 on every read.
    """

    def __init__(self, path: str | Path, split: str | None = None, *,
                 observation: str = "true", max_modes: int = 20, targets: bool = True,
                 n_nodes: int | None = None, options: Mapping[str, Any] | None = None,
                 cache_dir: str | Path | None = None, cache_items: bool = False) -> None:
        from ..observe import ObserveOptions
        from .instances import instance_info, instances, split_names
        from .packed import is_dataset

        self.cache_items = bool(cache_items)
        self.path = Path(path)
        self.split = split
        self.targets = bool(targets)
        given = dict(options or {})
        for key in ("observation", "n_modes"):
            if key in given:
                raise DatasetError(f"InstanceDataset: give {key} as an argument, not in options")
        self.options = ObserveOptions.from_mapping(
            {**given, "observation": observation, "n_modes": max_modes}, "InstanceDataset")
        self.max_modes = self.options.n_modes
        self.observation = self.options.observation
        self.n_nodes = None if n_nodes is None else int(n_nodes)
        self.packed = is_dataset(self.path)
        entries, sizes = [], []
        if self.packed:
            from .packed import open_dataset

            with open_dataset(self.path) as ds:  # closed before any worker forks
                for name in split_names(ds.names, split):
                    attrs = ds.root["samples"][name].attrs
                    entries.append((name, None, instance_info(name)))
                    sizes.append(self._inference_nodes(
                        json.loads(_text(attrs["truth"])),
                        tomllib.loads(_text(attrs["scene_toml"])), f"{self.path}:{name}"))
        else:
            for name, folder in instances(self.path, split):
                entries.append((name, Path(folder), instance_info(name, folder)))
                sizes.append(self._inference_nodes(
                    json.loads((folder / "truth.json").read_text()),
                    tomllib.loads((folder / "scene.toml").read_text()), str(folder)))
        self._entries = entries
        self._max_nodes = max(sizes, default=0)
        self.cache_dir = Path(default_cache_dir(self.path) if cache_dir is None else cache_dir)
        self._handles: dict[int, Any] = {}
        self._layout = self._first_layout()

    # ---------------------------------------------------------------- map-style protocol
    def __len__(self) -> int:
        return len(self._entries)

    @property
    def names(self) -> list[str]:
        """Instance names, in item order."""
        return [name for name, _, _ in self._entries]

    def __getitem__(self, i: int) -> dict[str, Any]:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
            raise TypeError(f"InstanceDataset indices are integers, got {type(i).__name__}")
        n = len(self._entries)
        if not -n <= i < n:
            raise IndexError(f"index {i} out of range for {n} instances")
        name, folder, info = self._entries[int(i) % n]
        item = self._cached_item(name, folder) if self.cache_items else None
        if item is None:
            source = self._source(name, folder)
            problem, truth = self._observe(name, source)
            layout = self.layout()
            item = {"inputs": _inputs(problem, source.camera, layout, name),
                    "targets": _targets(problem, truth, layout)}
            if self.cache_items:
                self._store_item(name, folder, item)
        if not self.targets:
            del item["targets"]
        split = info.get("split")
        item.update(split=str(split) if split is not None else "",
                    instance=name, family=str(info.get("family", "")),
                    index=int(info.get("index", -1)))
        return item

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_handles"] = {}
        return state

    # ---------------------------------------------------------------- the feature spec
    def layout(self) -> _Layout:
        """The padded sizes: modes, nodes, DOFs per node, coordinates per node, voxel grid."""
        return self._layout

    def _first_layout(self) -> _Layout:
        if not self._entries:
            from .instances import instance_info, instances

            here = sorted({str(instance_info(n, None if self.packed else s).get("split"))
                           for n, s in instances(self.path)})
            raise DatasetError(f"{self.path}: no instance of split {self.split!r} (here: "
                               f"{', '.join(here) or 'no instances'})")
        name, folder, _ = self._entries[0]
        opts = self.options.replace(observation="true", n_modes=1, modes=())
        if folder is not None:
            problem, _ = self._observe_plain(self._source(name, folder), opts)
        else:
            from .packed import open_dataset

            with open_dataset(self.path) as ds:  # closed before any worker forks
                problem, _ = self._observe_plain(ds[name], opts)
        nodes = max(problem.mesh.n_nodes, self._max_nodes) if self.n_nodes is None \
            else self.n_nodes
        return _Layout(self.max_modes, nodes, problem.mesh.dofs_per_node,
                       problem.mesh.points.shape[1],
                       tuple(int(s) for s in problem.voxel_map.grid.shape))

    def features(self) -> list[Feature]:
        """:data:`FEATURES` with this dataset's shapes (targets left out with
        ``targets=False``)."""
        layout = self.layout()
        return [Feature(f.name, f.part, layout.resolve(f.shape), f.dtype, f.units,
                        f.description)
                for f in FEATURES if self.targets or f.part != "targets"]

    def describe(self) -> str:
        """The feature spec as a text table (one line per array)."""
        rows = [("part", "name", "shape", "dtype", "units")]
        rows += [(f.part, f.name, "x".join(map(str, f.shape)) or "scalar", f.dtype,
                  f.units or "-") for f in self.features()]
        widths = [max(len(r[i]) for r in rows) for i in range(5)]
        lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip()
                 for r in rows]
        head = (f"{len(self)} instances of {self.path.name} (split {self.split or 'all'}, "
                f"observation {self.observation}); every item also has split, instance, "
                "family, index")
        return "\n".join([head, *lines])

    def __repr__(self) -> str:
        return (f"InstanceDataset({str(self.path)!r}, split={self.split!r}, "
                f"{len(self)} instances, observation={self.observation!r}, "
                f"max_modes={self.max_modes})")

    # ---------------------------------------------------------------- sources
    def _source(self, name: str, folder: Path | None) -> Any:
        if folder is not None:
            from ..samples.reader import open_sample

            return open_sample(folder)
        return self._dataset()[name]

    def _dataset(self) -> Any:
        pid = os.getpid()
        handle = self._handles.get(pid)
        if handle is None:
            from .packed import open_dataset

            handle = self._handles[pid] = open_dataset(self.path)  # a parent's stays unused
        return handle

    def close(self) -> None:
        """Close this process's dataset handle (reopened on the next item)."""
        handle = self._handles.pop(os.getpid(), None)
        if handle is not None:
            handle.close()

    def _observe(self, name: str, source: Any):
        opts = self.options
        if opts.observation == "true":
            n_true = len(_array(source, "modes/eigenvalues"))
            opts = opts.replace(n_modes=min(opts.n_modes, n_true))
        elif not opts.modes:
            folder = extracted_modes_folder(source, name, opts.extract, self._cache_for(name))
            if folder is not None:
                opts = opts.replace(modes=(str(folder),))
        return self._observe_plain(source, opts)

    def _inference_nodes(self, info: dict, scene: dict, where: str) -> int:
        """Nodes of an instance's inference mesh, from its truth.json and scene: a box's mesh
        is built on the inference grid, any other body's is its simulation mesh."""
        if scene.get("geometry", {}).get("kind") != "box":
            n = (info.get("mesh") or {}).get("n_nodes")
            if not isinstance(n, int):
                raise DatasetError(f"{where}: truth.json has no mesh.n_nodes; regenerate the "
                                   "sample with this vvtbench")
            return n
        shape = np.asarray(self.options.inference_shape or (8, 8, 8))
        return int(np.prod(self.options.inference_order * shape + 1))

    def _cache_for(self, name: str) -> Path:
        return self.cache_dir / name

    def _item_file(self, name: str, folder: Path | None) -> Path:
        from ..io.files import jsonable

        if folder is not None:
            from ..samples.reader import read_json

            manifest = read_json(folder / "manifest.json")
        else:
            manifest = self._dataset()[name].manifest
        opts = self.options.to_dict()
        extraction = (extraction_key(self.options.extract)
                      if self.observation == "extracted" else None)
        text = json.dumps(jsonable({"manifest": manifest, "options": opts,
                                    "extraction": extraction,
                                    "layout": dataclasses.asdict(self.layout()),
                                    "revision": ITEM_REVISION}), sort_keys=True, default=str)
        key = hashlib.sha256(text.encode()).hexdigest()[:16]
        return self._cache_for(name) / "items" / f"{key}.npz"

    def _cached_item(self, name: str, folder: Path | None) -> dict[str, Any] | None:
        path = self._item_file(name, folder)
        try:
            recorded = json.loads(path.with_suffix(".json").read_text()).get("sha256")
        except (OSError, ValueError, AttributeError):
            return None
        if not path.is_file() or sha256_file(path) != recorded:
            return None
        item: dict[str, Any] = {"inputs": {}, "targets": {}}
        with np.load(path, allow_pickle=False) as z:
            for key in z.files:
                part, _, feature = key.partition(".")
                value = z[key]
                item[part][feature] = value[()] if value.ndim == 0 else value
        return item

    def _store_item(self, name: str, folder: Path | None, item: dict[str, Any]) -> None:
        from ..io.files import write_json, write_npz

        path = self._item_file(name, folder)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_npz(path, {f"{part}.{k}": np.asarray(v) for part in ("inputs", "targets")
                         for k, v in item[part].items()}, compressed=False)
        write_json(path.with_suffix(".json"), {"instance": name, "sha256": sha256_file(path),
                                               "options": self.options.to_dict(),
                                               "revision": ITEM_REVISION})

    @staticmethod
    def _observe_plain(source: Any, opts: Any):
        from ..observe import observe

        return observe(source, opts)


def _text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _array(source: Any, name: str) -> np.ndarray:
    require = getattr(source, "require", None)
    return np.asarray(require(name) if require is not None else source[name])


# -------------------------------------------------------------------- items


def _inputs(problem: Any, camera: Any, layout: _Layout, name: str) -> dict[str, np.ndarray]:
    mesh = problem.mesh
    n, d, K = mesh.n_nodes, mesh.dofs_per_node, layout.modes
    if n > layout.nodes:
        raise DatasetError(f"{name}: its inference mesh has {n} nodes, more than the "
                           f"{layout.nodes} items are padded to; give n_nodes >= {n}")
    if d != layout.dofs or mesh.points.shape[1] != layout.dim:
        raise DatasetError(f"{name}: {d} DOFs per node, the first instance {layout.dofs}; "
                           "one dataset holds one kind of object")
    vis = problem.visible_nodes
    k = min(problem.n_modes, K)
    gamma = np.zeros((K, layout.nodes, 2), np.float32)
    gamma[:k, vis] = problem.gamma[:k].reshape(k, len(vis), 2)
    eig = np.zeros(K, np.float32)
    eig[:k] = problem.eigenvalues[:k]
    mode_mask = np.zeros(K, bool)
    mode_mask[:k] = True

    def per_node(dtype: Any, *tail: int) -> np.ndarray:
        return np.zeros((layout.nodes, *tail), dtype)

    visible, node_mask, fixed = per_node(bool), per_node(bool), per_node(bool)
    visible[vis] = True
    node_mask[:n] = True
    fixed[problem.model.fixed_nodes] = True
    points = per_node(np.float32, layout.dim)
    points[:n] = mesh.points
    jac = per_node(np.float32, 2, d)
    cols = problem.model.free_index[vis[:, None] * d + np.arange(d)[None, :]]  # (n_vis, d)
    P = problem.P.tocsr()
    rows = 2 * np.arange(len(vis))
    for c in range(d):
        ok = cols[:, c] >= 0
        for axis in range(2):
            jac[vis[ok], axis, c] = np.asarray(P[rows[ok] + axis, cols[ok, c]]).ravel()
    active = np.zeros(int(np.prod(layout.grid)), bool)
    active[problem.voxel_map.active] = True
    f32 = np.float32
    return {
        "gamma": gamma, "eigenvalues": eig, "mode_mask": mode_mask, "visible": visible,
        "node_mask": node_mask, "fixed": fixed, "points": points, "jacobian": jac,
        "camera_K": np.asarray(camera.K, f32), "camera_R": np.asarray(camera.R, f32),
        "camera_t": np.asarray(camera.t, f32).ravel(),
        "image_size": np.array([camera.width, camera.height], np.int64),
        "active": active.reshape(layout.grid),
        "w_mean": f32(problem.w_mean), "w0": f32(problem.w0), "v0": f32(problem.v0),
    }


def _targets(problem: Any, truth: Any, layout: _Layout) -> dict[str, np.ndarray]:
    return {"w": problem.to_grid(truth.w, 0.0).astype(np.float32).reshape(layout.grid),
            "v": problem.to_grid(truth.v, 0.0).astype(np.float32).reshape(layout.grid)}


# -------------------------------------------------------------------- extracted modes


