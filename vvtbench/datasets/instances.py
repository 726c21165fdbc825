"""Instances for learning: ``(problem, truth)`` pairs from generated samples or a dataset.

>>> for problem, truth in iter_instances("data/cube_defects", "train"):  # doctest: +SKIP
...     ...

For fixed-shape numpy items that a DataLoader batches (padded modes and vertices with masks,
a feature spec), use :class:`vvtbench.datasets.loaders.InstanceDataset`.

A folder of samples (``vvtbench generate FAMILY --split S``, or any folder holding sample
folders) or an exported dataset (``vvtbench export``: a ``.zarr`` folder or an HDF5 file) is
read as it is: the simulator never runs (:func:`vvtbench.observe.observe`). An instance's split
comes from its ``family.json`` (family, split, index) or, in an exported dataset, from its
name, ``FAMILY-SPLIT-INDEX``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["instances", "iter_instances", "instance_info", "split_names"]

SPLITS = ("train", "val", "test")
_NAME = re.compile(r"^(?P<family>.+)-(?P<split>train|val|test)-(?P<index>\d+)$")


def instance_info(name: str, folder: Path | None = None) -> dict[str, Any]:
    """Family, split and index of an instance (``{}`` for a sample of no family)."""
    if folder is not None and (folder / "family.json").is_file():
        return json.loads((folder / "family.json").read_text())
    m = _NAME.match(name)
    if m is None:
        return {}
    return {"family": m["family"], "split": m["split"], "index": int(m["index"])}


def instances(path: str | Path, split: str | None = None) -> Iterator[tuple[str, Any]]:
    """``(name, source)`` of every instance in ``path`` (of ``split`` only, if given), in
    family and index order; ``source`` is a sample folder or a dataset entry."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}; got {split!r}")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such folder or dataset")
    from .packed import is_dataset

    if is_dataset(path):
        from .packed import open_dataset

        ds = open_dataset(path)
        for name in split_names(ds.names, split):
            yield name, ds[name]
        return
    from .export import find_samples

    found = []
    for folder in find_samples(path):
        info = instance_info(folder.name, folder)
        if split is None or info.get("split") == split:
            found.append((_order(info, folder.name), folder))
    for _, folder in sorted(found):
        yield folder.name, folder


def split_names(names: list[str], split: str | None = None) -> list[str]:
    """The names ``FAMILY-SPLIT-INDEX`` of an exported dataset that belong to ``split`` (all
    if None), in family and index order."""
    if split is not None and split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}; got {split!r}")
    kept = [n for n in names if split is None or instance_info(n).get("split") == split]
    return sorted(kept, key=lambda n: _order(instance_info(n), n))


def _order(info: dict, name: str) -> tuple:
    return (str(info.get("family", "")), int(info.get("index", -1)), name)


def iter_instances(path: str | Path, split: str | None = None, options=None, *,
                   cache_dir: str | Path | None = None,
                   **overrides: Any) -> Iterator[tuple[Any, Any]]:
    """``(InverseProblem, Truth)`` of every instance of ``split`` in ``path`` (observe options
    as for :func:`vvtbench.observe.observe`; default: the true image-space modes).

    With ``observation="extracted"`` (and no ``modes`` given) each sample's modes are
    extracted once and kept in ``cache_dir`` (default: a ``.vvtbench-extracted`` folder beside
    the samples or the dataset; :func:`vvtbench.datasets.extracted.extracted_modes_folder`), so a
    second
    pass reads them instead of extracting again.
    """
    from ..observe import ObserveOptions, observe
    from .extracted import default_cache_dir, extracted_modes_folder

    opts = ObserveOptions.resolve(options, **overrides)
    path = Path(path)
    cached = opts.observation == "extracted" and not opts.modes
    if cached and cache_dir is None:
        cache_dir = default_cache_dir(path)
    for name, source in instances(path, split):
        if not cached:
            yield observe(source, opts)
            continue
        if isinstance(source, Path):
            from ..samples.reader import open_sample

            source = open_sample(source)
        folder = extracted_modes_folder(source, name, opts.extract, Path(cache_dir) / name)
        yield observe(source, opts if folder is None else opts.replace(modes=(str(folder),)))
