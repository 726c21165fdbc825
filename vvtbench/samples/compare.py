"""Two samples of one scene compared value by value: a regenerated sample against a frozen one.

A sample's bytes are the same only where the floating-point arithmetic is the same (the CPU's
BLAS kernels, the library versions); its values agree everywhere to rounding. This module
says whether they do, within the tolerances of :data:`TOLERANCES` (chosen from measured
differences between machines: docs/dataset.md, "Comparing samples"):

* **files:** the same file names (the manifests list the same files); a file whose sha256 is
  the same is equal, the others are compared by what they hold;
* **text:** ``scene.toml`` byte for byte; JSON files (``truth.json``, ``camera.json``,
  ``family.json``, Zarr attributes) key by key: keys, strings, booleans, null and integers
  exactly, floats to ``rtol`` of the largest magnitude of the list they belong to (a lone
  float: of itself);
* **arrays** (``truth.zarr``): the same names, shapes and dtypes; integer and boolean arrays
  exactly; float arrays with NaN at the same places and ``max |a - b| <= rtol * max |a|``,
  ``rtol`` by dtype, taken per mode for the arrays indexed by mode (:data:`MODE_AXIS`: each
  eigenvalue, each mode shape to its own largest entry) and over the whole array otherwise;
* **modes up to sign:** a mode shape and its negative are the same mode. The sign (and, for
  modes whose eigenvalues are within ``group_rtol``, the orthogonal rotation of their
  subspace) that brings the rebuilt ``modes/vectors`` onto the frozen ones is applied to every
  array linear in the mode shapes (:data:`LINEAR_IN_MODES`), so a sample whose arrays disagree
  about a mode's sign still fails; per-mode quantities quadratic in the shapes (the ruler's
  ``modes/crb_*``) are compared by their sums over such a group;
* **images and videos** (``rest.png``, ``depth.png``, ``video.mkv``, ``video.mp4``): decoded,
  the same number and size of frames, and the counts (DN) at most ``dn`` apart on at most
  ``dn_fraction`` of the pixel values (rounding a value that lies within rounding of a
  half-count goes either way); ``preview.mp4`` (a magnified viewing aid, lossy): the same
  number and size of frames and a mean difference of at most ``dn`` counts.

:func:`compare_samples` returns a :class:`SampleComparison` (its ``problems``, one
``FILE: what differs`` line each, are empty when the samples agree);
``vvtbench release verify REBUILD --against COPY`` runs it over a release.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["LINEAR_IN_MODES", "MODE_AXIS", "TOLERANCES", "SampleComparison", "Tolerances",
           "compare_samples", "mode_groups"]


@dataclass(frozen=True)
class Tolerances:
    """How far two samples' values may be apart and still be the same sample."""

    rtol_f64: float = 1e-8
    """float64 arrays and JSON floats: relative to the largest magnitude of their unit."""
    rtol_f32: float = 1e-5
    """float32 arrays (rendered images, mode images, the transient): their rounding is 6e-8."""
    group_rtol: float = 1e-5
    """Modes whose eigenvalues are this close (relative) are compared as one subspace."""
    dn: int = 1
    """Image and video counts may differ by this many DN..."""
    dn_fraction: float = 1e-3
    """...on at most this fraction of the pixel values."""

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


TOLERANCES = Tolerances()

MODE_AXIS = {
    "modes/eigenvalues": 0, "modes/frequencies_hz": 0, "modes/damping_ratios": 0,
    "modes/vectors": 1, "modes/surface": 0, "observation/image_modes": 0,
    "observation/image_modes_surface": 0, "image/modes": 0, "modes/crb_snr": 0,
    "modes/crb_information": 0, "modes/crb_energy_px2": 0,
}
"""The axis along which each mode-indexed array runs over the modes (a view's arrays, under
``views/<i>/``, like view 0's)."""
LINEAR_IN_MODES = ("modes/vectors", "modes/surface", "observation/image_modes",
                   "observation/image_modes_surface", "image/modes")
"""Arrays that change sign with a mode shape."""
_ORDERED = ("modes/eigenvalues", "modes/frequencies_hz", "modes/damping_ratios")
"""Per-mode arrays sorted by frequency: compared mode by mode even inside a group."""
_IMAGES = ("rest.png", "depth.png")
_VIDEOS = ("video.mkv", "video.mp4")
_PREVIEW = "preview.mp4"
_VIEW = re.compile(r"^views/\d+/")


@dataclass
class SampleComparison:
    """The outcome of :func:`compare_samples`."""

    frozen: Path
    rebuilt: Path
    problems: list[str] = field(default_factory=list)
    identical: int = 0
    """Files whose bytes are equal."""
    compared: int = 0
    """Files (or Zarr arrays) compared by value."""
    worst: dict[str, float] = field(default_factory=dict)
    """The largest difference found per compared item: relative to its scale for floats, in
    DN for images and videos."""
    flipped: list[int] = field(default_factory=list)
    """Modes whose sign differs between the two samples."""

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        """One line: byte-equal files, value-compared items and the largest difference."""
        floats = [v for k, v in self.worst.items() if not k.endswith(" (DN)")]
        dn = [v for k, v in self.worst.items() if k.endswith(" (DN)")]
        parts = [f"{self.identical} files byte-equal", f"{self.compared} compared by value"]
        if floats:
            parts.append(f"largest relative difference {max(floats):.1e}")
        if dn:
            parts.append(f"largest image difference {max(dn):g} DN")
        if self.flipped:
            parts.append(f"{len(self.flipped)} mode(s) of opposite sign")
        return ", ".join(parts)


def _manifest(path: Path) -> dict[str, str]:
    doc = json.loads((path / "manifest.json").read_text())
    return {str(k): str(v["sha256"]) for k, v in doc["files"].items()}


def _listing(path: Path) -> dict:
    """``manifest.json`` without the sha256 and size of each file (compared as the files)."""
    doc = json.loads((path / "manifest.json").read_text())
    doc["files"] = {k: {f: v for f, v in entry.items() if f not in ("sha256", "bytes")}
                    for k, entry in doc["files"].items()}
    return doc


def _base(rel: str) -> str:
    """A view's file or array name as view 0's (``views/1/image/modes`` -> ``image/modes``)."""
    return _VIEW.sub("", rel)


def compare_samples(frozen: str | Path, rebuilt: str | Path, tol: Tolerances = TOLERANCES,
                    *, verify: tuple[str, ...] = ("frozen", "rebuilt")) -> SampleComparison:
    """Compare the sample folder ``rebuilt`` with ``frozen`` value by value (the module's
    rules); ``frozen`` is the reference (scales, signs). The samples named in ``verify`` are
    first checked against their own manifests (every file hashed: the comparison trusts the
    manifests' sha256 for the files whose bytes are equal)."""
    from .reader import DatasetError, open_sample

    a, b = Path(frozen), Path(rebuilt)
    out = SampleComparison(a, b)
    for side, path in (("frozen", a), ("rebuilt", b)):
        if side in verify:
            try:
                damaged = open_sample(path, verify=False).verify()
            except DatasetError as error:
                damaged = [str(error)]
            out.problems += [f"{side} sample: {p}" for p in damaged]
    if out.problems:
        return out
    try:
        ma, mb = _manifest(a), _manifest(b)
    except (OSError, ValueError, KeyError, TypeError) as error:
        out.problems.append(f"manifest.json: cannot read: {error}")
        return out
    for rel in sorted(set(ma) - set(mb)):
        out.problems.append(f"{rel}: missing from the rebuilt sample")
    for rel in sorted(set(mb) - set(ma)):
        out.problems.append(f"{rel}: not in the frozen sample")
    common = sorted(set(ma) & set(mb))
    la, lb = _listing(a), _listing(b)
    files_a, files_b = la.pop("files"), lb.pop("files")
    _compare_json("manifest.json", la, lb, tol, out)
    for rel in common:
        if files_a[rel] != files_b[rel]:
            _compare_json(f"manifest.json: files.{rel}", files_a[rel], files_b[rel], tol, out)
    out.identical = sum(ma[r] == mb[r] for r in common)
    differ = [r for r in common if ma[r] != mb[r]]
    if any(r.startswith("truth.zarr/") for r in differ):
        _compare_truth(a, b, tol, out)
    for rel in differ:
        if rel.startswith("truth.zarr/"):
            continue
        out.compared += 1
        base = _base(rel)
        try:
            if rel.endswith(".json"):
                _compare_json(rel, json.loads((a / rel).read_text()),
                              json.loads((b / rel).read_text()), tol, out)
            elif base in _IMAGES:
                _compare_counts(rel, [_read_image(a / rel)], [_read_image(b / rel)], tol, out)
            elif base in _VIDEOS or base == _PREVIEW:
                _compare_video(rel, a / rel, b / rel, tol, out, preview=base == _PREVIEW)
            else:  # scene.toml and anything else: bytes
                out.problems.append(f"{rel}: differs (compared byte for byte)")
        except (OSError, ValueError, RuntimeError) as error:
            out.problems.append(f"{rel}: cannot compare: {error}")
    return out


# --------------------------------------------------------------------------- JSON
def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _compare_json(where: str, x, y, tol: Tolerances, out: SampleComparison,
                  scale: float | None = None) -> None:
    if isinstance(x, dict) and isinstance(y, dict):
        if set(x) != set(y):
            out.problems.append(f"{where}: keys differ: only frozen {sorted(set(x) - set(y))}, "
                                f"only rebuilt {sorted(set(y) - set(x))}")
            return
        for k in sorted(x):
            _compare_json(f"{where}: {k}" if ": " not in where else f"{where}.{k}", x[k], y[k],
                          tol, out)
        return
    if isinstance(x, list) and isinstance(y, list):
        if len(x) != len(y):
            out.problems.append(f"{where}: {len(x)} items frozen, {len(y)} rebuilt")
            return
        flat = [v for v in x if isinstance(v, float)]
        unit = max((abs(v) for v in flat if np.isfinite(v)), default=0.0) if flat else None
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            _compare_json(f"{where}[{i}]", u, v, tol, out, unit)
        return
    if isinstance(x, float) and isinstance(y, float):
        if x == y or (np.isnan(x) and np.isnan(y)):
            return
        s = abs(x) if scale is None else max(scale, abs(x))
        err = abs(x - y) / s if s > 0 and np.isfinite(s) else np.inf
        key = re.sub(r"\[\d+\]", "", where)
        out.worst[key] = max(out.worst.get(key, 0.0), float(err))
        if not err <= tol.rtol_f64:
            out.problems.append(f"{where}: {x!r} frozen, {y!r} rebuilt (relative difference "
                                f"{err:.1e} > {tol.rtol_f64:g})")
        return
    if type(x) is not type(y) or x != y:  # strings, booleans, null, integers: exactly
        out.problems.append(f"{where}: {x!r} frozen, {y!r} rebuilt")


# --------------------------------------------------------------------------- truth.zarr
def _arrays(path: Path) -> tuple[dict[str, object], dict[str, dict]]:
    """(lazy arrays by name, attributes of every group and array by name) of truth.zarr."""
    import zarr

    root = zarr.open_group(str(path / "truth.zarr"), mode="r")
    arrays, attrs = {}, {"": dict(root.attrs)}

    def walk(group, prefix: str) -> None:
        for name, member in sorted(group.members()):
            key = prefix + name
            attrs[key] = dict(member.attrs)
            if isinstance(member, zarr.Group):
                walk(member, key + "/")
            else:
                arrays[key] = member

    walk(root, "")
    return arrays, attrs


def mode_groups(eigenvalues: np.ndarray, rtol: float) -> list[np.ndarray]:
    """Indices of (sorted) eigenvalues chained within ``rtol`` (relative) of each other."""
    lam = np.asarray(eigenvalues, dtype=np.float64)
    if lam.size == 0:
        return []
    scale = max(float(np.abs(lam).max()), 1e-300)
    gap = np.diff(lam) > rtol * np.maximum(np.abs(lam[1:]), 1e-3 * scale)
    return np.split(np.arange(len(lam)), np.flatnonzero(gap) + 1)


def _alignment(va: np.ndarray, vb: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
    """The block-diagonal orthogonal matrix W (modes x modes) with ``vb @ W`` nearest to
    ``va``: per group, the orthogonal factor of the least-squares fit (a sign for one mode)."""
    m = va.shape[1]
    W = np.eye(m)
    for g in groups:
        fit = np.linalg.lstsq(vb[:, g], va[:, g], rcond=None)[0]
        u, _, vt = np.linalg.svd(fit)
        W[np.ix_(g, g)] = u @ vt
    return W


def _compare_truth(a: Path, b: Path, tol: Tolerances, out: SampleComparison) -> None:
    import zarr

    try:
        arr_a, attrs_a = _arrays(a)
        arr_b, attrs_b = _arrays(b)
    except (OSError, ValueError, KeyError, zarr.errors.BaseZarrError) as error:
        out.problems.append(f"truth.zarr: cannot read: {error}")
        return
    for name in sorted(set(attrs_a) - set(attrs_b)):
        out.problems.append(f"truth.zarr/{name}: missing from the rebuilt sample")
    for name in sorted(set(attrs_b) - set(attrs_a)):
        out.problems.append(f"truth.zarr/{name}: not in the frozen sample")
    for name in sorted(set(attrs_a) & set(attrs_b)):
        if attrs_a[name] != attrs_b[name]:
            _compare_json(f"truth.zarr/{name} attributes", attrs_a[name], attrs_b[name], tol,
                          out)
    names = sorted(set(arr_a) & set(arr_b))
    W, groups = None, []
    if "modes/vectors" in arr_a and "modes/vectors" in arr_b:
        va, vb = np.asarray(arr_a["modes/vectors"][...]), np.asarray(arr_b["modes/vectors"][...])
        lam = np.asarray(arr_a["modes/eigenvalues"][...]) if "modes/eigenvalues" in arr_a \
            else np.arange(va.shape[1], dtype=float)
        if va.shape == vb.shape and va.shape[1] == len(lam):
            groups = mode_groups(lam, tol.group_rtol)
            W = _alignment(va, vb, groups)
            out.flipped = [int(g[0]) for g in groups if len(g) == 1 and W[g[0], g[0]] < 0]
    for name in names:
        xa, xb = arr_a[name], arr_b[name]
        if xa.shape != xb.shape or xa.dtype != xb.dtype:
            out.problems.append(f"truth.zarr/{name}: shape {xa.shape} {xa.dtype} frozen, "
                                f"{xb.shape} {xb.dtype} rebuilt")
            continue
        out.compared += 1
        _compare_array(name, xa, xb, W, groups, tol, out)


def _blocks(x, budget: int = 32 << 20) -> Iterator[slice]:
    """Slices along the first axis of about ``budget`` bytes each (whole when 0-d)."""
    if x.ndim == 0 or x.shape[0] == 0:
        yield slice(None)
        return
    row = max(1, int(np.prod(x.shape[1:])) * np.dtype(x.dtype).itemsize)
    step = max(1, budget // row)
    for i in range(0, x.shape[0], step):
        yield slice(i, min(i + step, x.shape[0]))


def _compare_array(name: str, xa, xb, W, groups, tol: Tolerances,
                   out: SampleComparison) -> None:
    base = _base(name)
    where = f"truth.zarr/{name}"
    axis = MODE_AXIS.get(base)
    if axis is not None and (W is None or xa.ndim <= axis or xa.shape[axis] != len(W)):
        axis = None  # not indexed by the frozen modes after all: the whole array is one unit
    dtype = np.dtype(xa.dtype)
    rtol = tol.rtol_f32 if dtype.itemsize <= 4 else tol.rtol_f64
    if dtype.kind not in "fc":
        if not all(np.array_equal(np.asarray(xa[sl]), np.asarray(xb[sl]))
                   for sl in _blocks(xa)):
            out.problems.append(f"{where}: values differ (integers and booleans are compared "
                                "exactly)")
        return
    if axis is None:  # one unit, read in blocks: the largest magnitude, then the differences
        scale = diff = 0.0
        for sl in _blocks(xa):
            ya, yb = np.asarray(xa[sl], np.float64), np.asarray(xb[sl], np.float64)
            if not _same_nonfinite(ya, yb):
                out.problems.append(f"{where}: NaN or infinity at other places")
                return
            ya, yb = _finite(ya), _finite(yb)
            scale = max(scale, float(np.abs(ya).max(initial=0.0)))
            diff = max(diff, float(np.abs(ya - yb).max(initial=0.0)))
        _record(where, np.array([diff]), np.array([scale]), None, rtol, out)
        return
    linear = base in LINEAR_IN_MODES
    if axis == 0 and xa.ndim > 1:  # large mode-indexed arrays: a group of modes at a time
        for g in groups:
            ya = np.asarray(xa[g[0]:g[-1] + 1], dtype=np.float64)
            yb = np.asarray(xb[g[0]:g[-1] + 1], dtype=np.float64)
            if linear:
                yb = np.tensordot(W[np.ix_(g, g)].T, yb, axes=1)
            _compare_floats(where, ya, yb, g, rtol, out)
        return
    ya, yb = np.asarray(xa[...], dtype=np.float64), np.asarray(xb[...], dtype=np.float64)
    ya, yb = np.moveaxis(ya, axis, 0), np.moveaxis(yb, axis, 0)
    modes = np.arange(len(W))
    if linear:
        yb = np.tensordot(W.T, yb, axes=1)
    elif base not in _ORDERED:  # quadratic in the shapes: a group's sum
        ya = np.array([ya[g].sum(axis=0) for g in groups])
        yb = np.array([yb[g].sum(axis=0) for g in groups])
        modes = np.array([g[0] for g in groups])
    _compare_floats(where, ya, yb, modes, rtol, out)


def _compare_floats(where: str, x: np.ndarray, y: np.ndarray, modes: np.ndarray, rtol: float,
                    out: SampleComparison) -> None:
    """Per mode (``modes``: the mode numbers along the first axis): NaN at the same places and
    ``max |x - y| <= rtol * max |x|``."""
    x, y = x.reshape(len(modes), -1), y.reshape(len(modes), -1)
    if not _same_nonfinite(x, y):
        out.problems.append(f"{where}: NaN or infinity at other places")
        return
    x, y = _finite(x), _finite(y)
    scale = np.abs(x).max(axis=1, initial=0.0)
    diff = np.abs(x - y).max(axis=1, initial=0.0)
    _record(where, diff, scale, modes, rtol, out)


def _same_nonfinite(x: np.ndarray, y: np.ndarray) -> bool:
    """NaN and infinities at the same places (and infinities of the same sign)."""
    bad = ~np.isfinite(x)
    return np.array_equal(bad, ~np.isfinite(y)) and np.array_equal(x[bad], y[bad],
                                                                   equal_nan=True)


def _finite(x: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(x), x, 0.0)


def _record(where: str, diff: np.ndarray, scale: np.ndarray, modes, rtol: float,
            out: SampleComparison) -> None:
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.where(diff == 0, 0.0, diff / scale)
    err = np.where(np.isnan(err), np.inf, err)
    key = _base(where.removeprefix("truth.zarr/"))
    out.worst[key] = max(out.worst.get(key, 0.0), float(err.max(initial=0.0)))
    bad = np.flatnonzero(err > rtol)
    if bad.size:
        i = bad[np.argmax(err[bad])]
        what = "" if modes is None else f" in mode {int(modes[i])}" + (
            f" and {bad.size - 1} other mode(s)" if bad.size > 1 else "")
        out.problems.append(f"{where}: values differ by {err[i]:.1e} of their largest magnitude"
                            f"{what} (tolerance {rtol:g})")


# --------------------------------------------------------------------------- images, videos
def _read_image(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(path))


def _frames(path: Path) -> Iterator[np.ndarray]:
    from ..video.files import probe_video, read_frames

    info = probe_video(path)
    bpp = 2 if info.high_depth else 1
    yield from read_frames(path, bpp=bpp, info=info)


def _compare_counts(rel: str, fa, fb, tol: Tolerances, out: SampleComparison,
                    preview: bool = False) -> None:
    """Frames (iterables of integer images) at most ``dn`` apart on at most ``dn_fraction`` of
    the values (``preview``: a mean difference of at most ``dn``)."""
    n = count = changed = over = 0
    worst = total = 0.0
    ia, ib = iter(fa), iter(fb)
    for x in ia:
        y = next(ib, None)
        if y is None:
            out.problems.append(f"{rel}: the rebuilt one has {n} frame(s), the frozen one more")
            return
        if x.shape != y.shape:
            out.problems.append(f"{rel}: frame {n}: shape {x.shape} frozen, {y.shape} rebuilt")
            return
        d = np.abs(x.astype(np.int64) - y.astype(np.int64))
        worst = max(worst, float(d.max(initial=0)))
        total += float(d.sum())
        over += int(np.count_nonzero(d > tol.dn))
        changed += int(np.count_nonzero(d))
        count += d.size
        n += 1
    if next(ib, None) is not None:
        out.problems.append(f"{rel}: the frozen one has {n} frame(s), the rebuilt one more")
        return
    key = f"{_base(rel)} (DN)"
    out.worst[key] = max(out.worst.get(key, 0.0), worst)
    count = max(count, 1)
    if preview:
        if total / count > tol.dn:
            out.problems.append(f"{rel}: mean difference {total / count:.2f} DN > {tol.dn} "
                                "(a lossy viewing aid: compared on average)")
    elif over:
        out.problems.append(f"{rel}: {over} value(s) differ by more than {tol.dn} DN (up to "
                            f"{worst:g})")
    elif changed / count > tol.dn_fraction:
        out.problems.append(f"{rel}: {changed} of {count} values differ by {tol.dn} DN "
                            f"({changed / count:.1e} > {tol.dn_fraction:g})")


def _compare_video(rel: str, a: Path, b: Path, tol: Tolerances, out: SampleComparison,
                   preview: bool) -> None:
    _compare_counts(rel, _frames(a), _frames(b), tol, out, preview=preview)
