"""Harmonics and intermodulation products among identified poles, told from true modes by
frequency, decay, phase and shape together.

The measured motion is a memoryless, pixel-dependent non-linear function of the true motion
(the extractor's response to the texture, the image formation): ``u'(x, t) = g_x(u(x, t))``.
A product of parents ``p`` with integer coefficients ``n_p`` (``2 f_1``, ``3 f_1``, ``f_1 +
f_2``, ``2 f_1 - f_2``, ...; :class:`.combinations.Combination`) then

* sits at ``sum_p n_p f_p``, folded at the Nyquist frequency when above it, within the poles'
  frequency uncertainties (a pole-based identifier knows its frequencies to far better than a
  bin, so a mode a fraction of a bin from a product is not taken for it);
* in a free decay, decays at ``sum_p |n_p| sigma_p`` (``sigma = zeta omega``): the product of
  ``exp(lambda_1 t)`` and ``exp(lambda_2 t)`` (or its conjugate) is ``exp((lambda_1 +
  lambda_2) t)``;
* has at every pixel the phase ``sum_p n_p phi_p(x)`` modulo ``pi`` (the sign of the local
  non-linearity): its *phase coherence* (:func:`phase_coherence`) is near 1;
* has a shape that is a function of its parents' shapes: its local energy follows
  ``prod_p |s_p|^(2 |n_p|)`` (:func:`.combinations.envelope_correlation`, for the texture-locked
  products of phase-based motion), or it is explained by the monomials of the parents' fields
  with image-wide coefficients (:func:`explained_fraction`, for smooth non-linearities such as
  the image formation's).

A candidate is a product only when all of these hold: a true mode at a product's frequency has
a shape of its own, and in a driven record a phase of its own.  After a pluck every mode, and
so every product, starts at phase 0 modulo ``pi``, so there the phase test passes for true
modes too and the shape and the decay decide.  :func:`find_pole_products` applies the tests to
modes with complex full-field coefficients (:func:`.poles.project_poles`); see docs/modes.md.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .combinations import Combination, envelope_correlation

__all__ = ["combinations_of", "explained_fraction", "find_pole_products", "phase_coherence"]


def combinations_of(n_parents: int, *, max_harmonic: int = 7, max_order: int = 4,
                    rich_parents: int = 6, triple_parents: int = 5
                    ) -> list[Combination]:
    """Every combination of parents ranked ``0 .. n_parents - 1`` by strength, once up to
    its sign: harmonics ``n f_p`` for ``2 <= n <= max_harmonic`` (``n <= 3`` beyond the
    strongest ``rich_parents``), pairs ``a f_i +- b f_j`` with ``a + b <= max_order`` (``a =
    b = 1`` beyond the strongest ``rich_parents``) and triples ``f_i +- f_j +- f_k`` of the
    strongest ``triple_parents``.

    >>> [c.label([10.0, 3.5]) for c in combinations_of(2, max_harmonic=2, max_order=2)]
    ['2 x 10.0 Hz', '2 x 3.5 Hz', '10.0 + 3.5 Hz', '10.0 - 3.5 Hz']
    """
    out: list[Combination] = []
    for i in range(n_parents):
        top = max_harmonic if i < rich_parents else min(3, max_harmonic)
        out += [Combination((i,), (n,)) for n in range(2, top + 1)]
    for i, j in itertools.combinations(range(n_parents), 2):
        rich = j < rich_parents
        for a in range(1, (max_order if rich else 2)):
            for b in range(1, (max_order if rich else 2) - a + 1):
                out += [Combination((i, j), (a, b)), Combination((i, j), (a, -b))]
    for i, j, k in itertools.combinations(range(min(n_parents, triple_parents)), 3):
        out += [Combination((i, j, k), c) for c in ((1, 1, 1), (1, 1, -1), (1, -1, 1),
                                                   (-1, 1, 1))]
    return out


def _fold(f: float, fps: float | None) -> tuple[float, bool]:
    if not fps:
        return abs(f), f < 0
    r = abs(f) % fps
    return (fps - r, True) if r > fps / 2 else (r, False)


def phase_coherence(field: ArrayLike, parents: ArrayLike, coefficients: ArrayLike,
                    weights: ArrayLike | None = None, mirrored: bool = False) -> float:
    """How well the phase of ``field`` at every pixel is ``sum_p n_p`` times its parents'
    phases there, modulo ``pi``: ``|sum w |Z| exp(2 i (arg Z - sum n_p arg Z_p))| / sum w |Z|``
    over pixels and components (angles doubled: the sign is free), with the parents' phases
    taken per pixel on their stronger component.  1 for a product; for a mode of its own with
    a phase of its own, about 0.

    >>> rng = np.random.default_rng(0)
    >>> p = np.exp(1j * rng.uniform(0, 6, (8, 8, 1))) * rng.standard_normal((8, 8, 2))
    >>> round(phase_coherence(p**2 * rng.standard_normal((8, 8, 1)), p[None], [2]), 3)
    1.0
    >>> own = np.exp(1j * rng.uniform(0, 6, (8, 8, 1))) * rng.standard_normal((8, 8, 2))
    >>> phase_coherence(own, p[None], [2]) < 0.5
    True
    """
    Z = np.asarray(field, dtype=np.complex128)
    Ps = np.asarray(parents, dtype=np.complex128)
    n = np.asarray(coefficients, dtype=np.float64).reshape(-1)
    expected = np.zeros(Z.shape[:2])
    for p in range(Ps.shape[0]):
        pick = np.argmax(np.abs(Ps[p]), axis=-1)
        ph = np.angle(np.take_along_axis(Ps[p], pick[..., None], -1)[..., 0])
        expected += n[p] * ph
    if mirrored:
        expected = -expected
    w = np.ones(Z.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    a = np.abs(Z) * w[..., None]
    den = float(a.sum())
    if den <= 0:
        return 0.0
    rel = np.cos(2 * (np.angle(Z) - expected[..., None]))
    return float(np.sum(a * rel) / den)


def _monomials(parents: NDArray[np.complex128], powers: list[int]) -> NDArray[np.complex128]:
    """``(P, F)`` per-pixel monomials of the parents' components with degree ``|n_p|`` in
    parent ``p``: the terms a polynomial non-linearity puts at the combination."""
    per = []
    for Pp, n in zip(parents, powers, strict=True):
        x, y = Pp[..., 0].reshape(-1), Pp[..., 1].reshape(-1)
        per.append([x ** a * y ** (n - a) for a in range(n + 1)])
    feats = [np.prod(np.stack(c), axis=0) for c in itertools.product(*per)]
    return np.stack(feats, -1)


def explained_fraction(field: ArrayLike, parents: ArrayLike, coefficients: ArrayLike,
                       weights: ArrayLike | None = None, mirrored: bool = False) -> float:
    """Fraction of the (weighted) energy of ``field`` explained by the monomials of its
    parents' complex fields of the combination's degrees (negative coefficients take the
    parent's conjugate), with one complex coefficient per monomial and output component over
    the whole image: 1 for the product of a smooth, image-wide non-linearity.

    >>> rng = np.random.default_rng(1)
    >>> p = rng.standard_normal((16, 16, 2)) + 1j * rng.standard_normal((16, 16, 2))
    >>> prod = np.stack([0.3 * p[..., 0] ** 2, -0.2 * p[..., 0] * p[..., 1]], -1)
    >>> round(explained_fraction(prod, p[None], [2]), 6)
    1.0
    >>> explained_fraction(rng.standard_normal((16, 16, 2)), p[None], [2]) < 0.2
    True
    """
    Z = np.asarray(field, dtype=np.complex128)
    Ps = np.asarray(parents, dtype=np.complex128)
    n = [int(v) for v in np.asarray(coefficients).reshape(-1)]
    Ps = np.stack([np.conj(Ps[p]) if (n[p] < 0) != mirrored else Ps[p]
                   for p in range(len(n))])
    A = _monomials(Ps, [abs(v) for v in n])
    w = np.ones(Z.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = np.sqrt(w.reshape(-1))
    A = A * sw[:, None]
    total = 0.0
    resid = 0.0
    for c in range(Z.shape[-1]):
        b = Z[..., c].reshape(-1) * sw
        coef, *_ = np.linalg.lstsq(A, b, rcond=None)
        r = b - A @ coef
        total += float(np.vdot(b, b).real)
        resid += float(np.vdot(r, r).real)
    return 1.0 - resid / total if total > 0 else 0.0


def find_pole_products(frequencies: ArrayLike, damping: ArrayLike, amplitudes: ArrayLike,
                       fields: ArrayLike, *, fps: float | None = None,
                       frequency_std_hz: ArrayLike | None = None,
                       damping_std: ArrayLike | None = None,
                       weights: ArrayLike | None = None, decay: bool = True,
                       bin_hz: float | None = None, max_harmonic: int = 7,
                       max_order: int = 4, n_sigma: float = 3.0,
                       min_tolerance_hz: float | None = None,
                       decay_tolerance: float = 0.3, min_phase_coherence: float = 0.7,
                       min_envelope_correlation: float = 0.4,
                       min_explained: float = 0.9, sigma_px: float = 4.0,
                       roughness: ArrayLike | None = None, min_roughness: float = 0.15,
                       max_level: float = 0.3, max_explained_order: int = 2
                       ) -> tuple[NDArray[np.bool_], list[dict[str, Any]]]:
    """Which modes are products of stronger ones (see the module docstring).

    Parameters
    ----------
    frequencies, damping, amplitudes : array_like
        ``(K,)`` undamped frequencies (Hz), damping ratios and amplitudes of the modes.
    fields : array_like
        ``(K, H, W, 2)`` complex full-field coefficients (the same grid for all).
    fps : float, optional
        Frame rate: combinations above the Nyquist frequency are looked for where they fold.
    frequency_std_hz, damping_std : array_like, optional
        ``(K,)`` standard errors; a combination matches within ``n_sigma`` combined standard
        errors and at least ``min_tolerance_hz`` (default 0.05 of ``bin_hz``, or 1e-3 of the
        frequency).
    weights : array_like, optional
        ``(H, W)`` pixel weights of the shape and phase tests.
    decay : bool, default True
        The record is a free decay: a product's decay rate must be ``sum |n_p| sigma_p``
        within ``decay_tolerance`` (relative) or ``n_sigma`` standard errors.
    max_harmonic, max_order : int
        Highest harmonic of one parent and highest order ``a + b`` of two
        (:func:`combinations_of`); triples are ``f_i +- f_j +- f_k``.
    min_phase_coherence, min_envelope_correlation, min_explained : float
        The phase test (:func:`phase_coherence`) and the shape tests (envelope correlation
        or explained fraction, either suffices).  The explained fraction's bar is high: the
        few smooth fields of an object's lowest modes span much of any other smooth field, so
        a true mode can be half explained by its would-be parents' monomials (0.55 for a
        damped cube's 13.3 Hz mode against 5.56 + 7.68 Hz), a product of a smooth
        non-linearity wholly.
    max_level : float, default 0.3
        A product is weaker than its parents: its amplitude is at most ``max_level`` times
        ``prod_p a_p^|n_p| / a_max^(order - 1)`` (``a_max`` the strongest mode's; the
        extractor's products are about 1 % of it).  A candidate stronger than that is no
        product of these parents, whatever its frequency and shape.
    max_explained_order : int, default 2
        The explained-fraction test only for combinations up to this order: a product of
        three fields has eight monomials per component, which explain 90 % of a smooth
        mode of its own (a cube's 21.2 Hz mode against 15.3 + 13.7 - 7.7 Hz).
    roughness, min_roughness : array_like, float
        ``(K,)`` roughness of each mode's shape (:func:`.peaks.roughness`): with it, the
        envelope test also needs the candidate rough (at least ``min_roughness``).  A
        texture-locked product changes sign with the texture from pixel to pixel while its
        envelope follows its parents'; a smooth mode of its own can follow a smooth
        envelope by chance (rank correlations of 0.2-0.65 on 32² test fields), not with a
        rough field.  A smooth product (a smooth non-linearity) is told by the explained
        fraction instead.

    Returns
    -------
    kept : ndarray
        ``(K,)`` bool.
    products : list of dict
        One per product: ``index``, ``reason`` (``"product"``), ``product`` (e.g. ``"3 x
        113.0 Hz"``), ``test`` (``"envelope"`` or ``"explained"``), ``kind``, ``order``,
        ``parents_hz``, ``coefficients``, ``expected_hz``, ``frequency_error_hz``,
        ``tolerance_hz``, ``expected_decay_rate``, ``decay_rate``, ``phase_coherence``,
        ``envelope_correlation``, ``explained_fraction``.
    """
    f = np.asarray(frequencies, dtype=np.float64).reshape(-1)
    z = np.asarray(damping, dtype=np.float64).reshape(-1)
    a = np.asarray(amplitudes, dtype=np.float64).reshape(-1)
    Z = np.asarray(fields, dtype=np.complex128)
    K = f.size
    if z.shape != f.shape or a.shape != f.shape or Z.ndim != 4 or Z.shape[0] != K:
        raise ValueError(f"frequencies {f.shape}, damping {z.shape}, amplitudes {a.shape} and "
                         f"fields (K, H, W, 2) {Z.shape} do not agree")
    sf = np.zeros(K) if frequency_std_hz is None else np.nan_to_num(
        np.asarray(frequency_std_hz, dtype=np.float64).reshape(-1))
    sz = np.zeros(K) if damping_std is None else np.nan_to_num(
        np.asarray(damping_std, dtype=np.float64).reshape(-1))
    sigma = np.maximum(z, 0.0) * 2 * np.pi * f
    s_sigma = sz * 2 * np.pi * f
    mag = np.abs(Z)
    kept = np.ones(K, bool)
    out: list[dict[str, Any]] = []
    order = np.argsort(-a, kind="stable")
    combos = combinations_of(max(K - 1, 0), max_harmonic=max_harmonic, max_order=max_order)
    for r, k in enumerate(order):
        parents = order[:r]
        if not parents.size:
            continue
        floor = (min_tolerance_hz if min_tolerance_hz is not None else
                 (0.05 * bin_hz if bin_hz else 1e-3 * f[k]))
        best = None
        for comb in combos:
            if max(comb.parents) >= parents.size:
                continue
            ps = [int(parents[i]) for i in comb.parents]
            c = sum(n * f[p] for p, n in zip(ps, comb.coefficients, strict=True))
            if c == 0:
                continue
            seen, mirrored = _fold(c, fps)
            tol = max(n_sigma * math.sqrt(sf[k] ** 2 + sum(
                (n * sf[p]) ** 2 for p, n in zip(ps, comb.coefficients, strict=True))), floor)
            err = abs(seen - f[k])
            if err > tol:
                continue
            coefs = list(comb.coefficients) if c > 0 else [-n for n in comb.coefficients]
            order_c = sum(abs(n) for n in coefs)
            log_ref = sum(abs(n) * math.log(max(a[p], 1e-300)) for p, n in zip(ps, coefs,
                                                                               strict=True))
            log_ref -= (order_c - 1) * math.log(max(float(a.max()), 1e-300))
            if math.log(max(a[k], 1e-300)) > math.log(max_level) + log_ref:
                continue
            rate = sum(abs(n) * sigma[p] for p, n in zip(ps, coefs, strict=True))
            if decay:
                s_rate = math.sqrt(s_sigma[k] ** 2 + sum((n * s_sigma[p]) ** 2 for p, n in
                                                         zip(ps, coefs, strict=True)))
                if abs(sigma[k] - rate) > max(decay_tolerance * rate, n_sigma * s_rate):
                    continue
            pc = phase_coherence(Z[k], Z[ps], coefs, weights, mirrored)
            if pc < min_phase_coherence:
                continue
            env = envelope_correlation(mag[k], mag[ps], [abs(n) for n in coefs], weights,
                                       sigma_px)
            expl = (explained_fraction(Z[k], Z[ps], coefs, weights, mirrored)
                    if order_c <= max_explained_order else 0.0)
            rough_ok = roughness is None or float(np.asarray(roughness).reshape(-1)[k]) >= \
                min_roughness
            if (env < min_envelope_correlation or not rough_ok) and expl < min_explained:
                continue
            test = "explained" if expl >= min_explained else "envelope"
            key = (sum(abs(n) for n in coefs), err / tol)
            if best is None or key < best[0]:
                best = (key, Combination(tuple(ps), tuple(coefs)), seen, err, tol, rate, pc,
                        env, expl, test)
        if best is None:
            continue
        _, comb, seen, err, tol, rate, pc, env, expl, test = best
        kept[k] = False
        out.append({
            "index": int(k), "reason": "product", "product": comb.label(f), "test": test,
            "kind": comb.kind, "order": comb.order,
            "parents_hz": [float(f[p]) for p in comb.parents],
            "coefficients": [int(n) for n in comb.coefficients],
            "expected_hz": float(seen), "frequency_error_hz": float(err),
            "tolerance_hz": float(tol), "expected_decay_rate": float(rate),
            "decay_rate": float(sigma[k]), "phase_coherence": float(pc),
            "envelope_correlation": float(env), "explained_fraction": float(expl)})
    return kept, out
