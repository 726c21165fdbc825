"""Peaks that are harmonics or intermodulation products of stronger ones, told apart from
true modes at the same frequencies by their phase and the envelope of their shape.

The measured motion is a memoryless, pixel-dependent non-linear function of the true
motion (the motion extractor's response, the image formation, the sensor's quantisation):
``u'(x, t) = g_x(u(x, t))``.  Modes ``u = sum_p q_p(t) s_p(x)`` with ``q_p = a_p cos(w_p t +
phi_p)`` then make lines at every integer combination ``sum_p n_p w_p`` (``2 w_1``, ``3
w_1``, ``w_1 + w_2``, ``2 w_1 - w_2``, ...), and such a line

* has the phase ``sum_p n_p phi_p`` at the record's start, modulo ``pi`` (the sign of the
  local non-linearity), in every pixel;
* has a sibling: the term of ``g_x`` that makes ``w_1 + w_2`` makes ``|w_1 - w_2|`` with the
  same shape and amplitude (``cos a cos b = (cos(a + b) + cos(a - b)) / 2``; likewise ``2 w_1
  + w_2`` and ``2 w_1 - w_2``), so when both are peaks their shapes agree (MAC ~1);
* lives where all its parents move: in a pixel where one parent is still, the local motion
  holds no term of that parent and ``g_x`` makes none of its products.  Its energy envelope
  is an increasing function of ``prod_p |s_p(x)|^|n_p|`` (``|s_p|`` the length of the
  parent's displacement vector), times a texture-dependent factor.

A true mode at a combination frequency has a shape of its own: unlike its sibling's, and
with an envelope that does not follow its would-be parents'.  :func:`find_combinations`
tests every candidate that sits at a combination of up to ``max_order`` stronger ones by
the phase residual and then by its sibling's shape when the sibling is a peak too, else by
the rank correlation of the locally averaged energies (:func:`envelope_correlation`).
:func:`reject_combinations` applies it to a :class:`.ModeSet`.  See docs/modes.md, "False
modes of the extractor's own making".
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .modeset import ModeSet

__all__ = [
    "Combination",
    "combination_phase_residual",
    "envelope_correlation",
    "find_combinations",
    "reject_combinations",
]


@dataclass(frozen=True)
class Combination:
    """An integer combination ``sum_p n_p f_p`` of parent peaks.

    Attributes
    ----------
    parents : tuple of int
        Parent indices (distinct).
    coefficients : tuple of int
        ``n_p`` per parent, signed so that ``sum_p n_p f_p > 0``.
    """

    parents: tuple[int, ...]
    coefficients: tuple[int, ...]

    @property
    def order(self) -> int:
        """``sum_p |n_p|``."""
        return int(sum(abs(n) for n in self.coefficients))

    @property
    def kind(self) -> str:
        """``"harmonic"`` (one parent), ``"sum"`` (all ``n_p > 0``) or ``"difference"``."""
        if len(self.parents) == 1:
            return "harmonic"
        return "sum" if all(n > 0 for n in self.coefficients) else "difference"

    def frequency(self, frequencies: ArrayLike) -> float:
        """``sum_p n_p f_p`` (Hz)."""
        f = np.asarray(frequencies, dtype=np.float64)
        return float(sum(n * f[p] for p, n in zip(self.parents, self.coefficients, strict=True)))

    def label(self, frequencies: ArrayLike) -> str:
        """How the parents make it, e.g. ``"3 x 113.0 Hz"``, ``"113.0 + 96.0 Hz"``,
        ``"2 x 113.0 - 96.0 Hz"`` (positive terms first).

        >>> Combination((0, 1), (2, -1)).label([113.0, 96.0])
        '2 x 113.0 - 96.0 Hz'
        """
        f = np.asarray(frequencies, dtype=np.float64)
        terms = []
        pairs = sorted(zip(self.parents, self.coefficients, strict=True), key=lambda t: t[1] < 0)
        for p, n in pairs:
            sign = "-" if n < 0 else "+"
            mag = abs(n)
            text = f"{mag} x {_hz(f[p])}" if mag > 1 else _hz(f[p])
            terms.append((sign, text))
        out = terms[0][1]
        for sign, text in terms[1:]:
            out += f" {sign} {text}"
        return out + " Hz"


def _hz(f: float) -> str:
    return f"{f:.1f}" if abs(f) >= 10 else f"{f:.3g}"


def _combination_table(n_parents: int, max_order: int, third_order_parents: int,
                       max_harmonic: int = 3
                       ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Every combination of order 2 .. ``max_order`` (at most 3) of the parents ranked ``0 ..
    n_parents - 1`` by strength (third-order ones of the first ``third_order_parents`` only),
    and the harmonics ``n f_p`` up to ``max_harmonic`` of those, each once up to its sign:
    ranks ``(N, 3)`` (``-1`` pads) and coefficients ``(N, 3)``."""
    rows: list[tuple[tuple[int, ...], tuple[int, ...]]] = []
    n3 = min(n_parents, third_order_parents) if max_order >= 3 else 0
    for i in range(n_parents):
        rows.append(((i,), (2,)))
        if i < n3:
            rows += [((i,), (n,)) for n in range(3, max(3, int(max_harmonic)) + 1)]
    for i, j in itertools.combinations(range(n_parents), 2):
        rows += [((i, j), (1, 1)), ((i, j), (1, -1))]
    for i, j in itertools.permutations(range(n3), 2):
        rows += [((i, j), (2, 1)), ((i, j), (2, -1))]
    for i, j, k in itertools.combinations(range(n3), 3):
        rows += [((i, j, k), c) for c in ((1, 1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1))]
    pos = np.full((len(rows), 3), -1, np.int64)
    coef = np.zeros((len(rows), 3), np.int64)
    for r, (p, c) in enumerate(rows):
        pos[r, : len(p)] = p
        coef[r, : len(c)] = c
    return pos, coef


def _fold_array(frequency: NDArray[np.float64], fps: float) -> NDArray[np.float64]:
    r = np.mod(frequency, fps)
    return np.minimum(r, fps - r)


def _folded(frequency: float, fps: float | None) -> tuple[float, bool]:
    """Where sampling at ``fps`` shows ``frequency`` Hz (``>= 0``) and whether it is mirrored
    (phase negated)."""
    if not fps:
        return frequency, False
    r = frequency % fps
    return (fps - r, True) if r > fps / 2 else (r, False)


def combination_phase_residual(phases: ArrayLike, frequencies: ArrayLike, k: int,
                               combination: Combination, *, fps: float | None = None) -> float:
    """Phase of peak ``k`` less the phase ``sum_p n_p phi_p`` of the combination of its
    parents (negated when the combination's frequency is folded at the Nyquist frequency of
    ``fps``), wrapped to ``[-pi/2, pi/2)``: phases are known modulo ``pi``.

    >>> round(combination_phase_residual([0.4, 1.1, 1.9 + np.pi], [5.0, 7.0, 17.0], 2,
    ...                                  Combination((0, 1), (2, 1))), 3)
    0.0
    """
    ph = np.asarray(phases, dtype=np.float64)
    f = np.asarray(frequencies, dtype=np.float64)
    c = combination.frequency(f)
    sign = 1.0 if c >= 0 else -1.0
    expected = sign * sum(n * ph[p] for p, n in zip(combination.parents,
                                                    combination.coefficients, strict=True))
    if _folded(abs(c), fps)[1]:
        expected = -expected
    return float((ph[k] - expected + math.pi / 2) % math.pi - math.pi / 2)


def _local_energy(e: NDArray[np.float64], w: NDArray[np.float64], sigma: float
                  ) -> NDArray[np.float64]:
    from scipy.ndimage import gaussian_filter

    num = gaussian_filter(w * e, sigma, mode="reflect")
    den = gaussian_filter(w, sigma, mode="reflect")
    return np.divide(num, den, out=np.zeros_like(num), where=den > 1e-12 * max(den.max(), 1e-300))


def envelope_correlation(shape: ArrayLike, parent_shapes: ArrayLike, powers: ArrayLike,
                         weights: ArrayLike | None = None, sigma_px: float = 4.0) -> float:
    """Rank correlation of a field's local energy with the envelope its parents predict.

    ``E(x) = G(w |s|^2) / G(w)`` and ``M(x) = G(w prod_p |s_p|^(2 n_p)) / G(w)`` (``G`` a
    Gaussian of ``sigma_px`` pixels, ``|.|`` the length of the displacement vector), compared
    by Spearman's rank correlation over the pixels of positive weight (sampled every
    ``sigma_px / 2`` pixels): near 1 for a product of the parents whatever the power law of
    the non-linearity, about 0 for a field of its own.

    Parameters
    ----------
    shape : array_like
        ``(H, W, 2)`` field of the peak.
    parent_shapes : array_like
        ``(P, H, W, 2)`` fields of its parents.
    powers : array_like
        ``(P,)`` ``|n_p|`` per parent.
    weights : array_like, optional
        ``(H, W)`` pixel weights (e.g. motion confidence); default uniform.
    sigma_px : float, default 4
        Scale of the local averages (pixels of ``shape``).

    Returns
    -------
    float
        In ``[-1, 1]``; 0 when either energy is constant.

    Examples
    --------
    >>> y, x = np.mgrid[0:64, 0:64] / 64.0
    >>> parent = np.stack([np.sin(2 * np.pi * x), 0 * x], -1)
    >>> texture = np.random.default_rng(0).standard_normal((64, 64, 1))
    >>> round(envelope_correlation(texture * parent**2, parent[None], [2]), 1)
    1.0
    >>> own = np.stack([np.cos(2 * np.pi * y), 0 * y], -1)
    >>> abs(envelope_correlation(own, parent[None], [2])) < 0.2
    True
    """
    from scipy.stats import spearmanr

    s = np.asarray(shape, dtype=np.float64)
    ps = np.asarray(parent_shapes, dtype=np.float64)
    n = np.asarray(powers, dtype=np.float64).reshape(-1)
    if s.ndim != 3 or ps.shape[1:] != s.shape or ps.shape[0] != n.size:
        raise ValueError(f"shape (H, W, C) {s.shape}, parent shapes (P, H, W, C) {ps.shape} "
                         f"and powers (P,) {n.shape} do not agree")
    w = np.ones(s.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != s.shape[:2]:
        raise ValueError(f"weights {w.shape} must be the shape's pixels {s.shape[:2]}")
    e = np.sum(s**2, axis=-1)
    log_m = np.zeros(s.shape[:2])
    for p in range(ps.shape[0]):
        log_m += n[p] * np.log(np.maximum(np.sum(ps[p] ** 2, axis=-1), 1e-300))
    m = np.exp(log_m - log_m.max())
    step = max(1, int(round(sigma_px / 2)))
    E = _local_energy(e, w, sigma_px)[::step, ::step]
    M = _local_energy(m, w, sigma_px)[::step, ::step]
    ok = (w[::step, ::step] > 0)
    E, M = E[ok], M[ok]
    if E.size < 3 or np.ptp(E) <= 0 or np.ptp(M) <= 0:
        return 0.0
    return float(spearmanr(E, M).statistic)


def _mac(a: NDArray, b: NDArray, w: NDArray[np.float64] | None) -> float:
    ww = 1.0 if w is None else w[..., None]
    ab = float(np.sum(ww * a * b))
    aa, bb = float(np.sum(ww * a * a)), float(np.sum(ww * b * b))
    return ab * ab / (aa * bb) if aa > 0 and bb > 0 else 0.0


def _sibling(shapes: NDArray, f: NDArray[np.float64], k: int, comb: Combination, tol: float,
             fps: float | None, weights: ArrayLike | None) -> tuple[int | None, float]:
    """The detected sibling of ``comb`` most like candidate ``k`` (the same term of the
    non-linearity at another sign pattern of its coefficients, e.g. ``f_1 - f_2`` for ``f_1 +
    f_2``), and the MAC of their shapes; ``(None, 0)`` when no sibling is a candidate."""
    if len(comb.parents) < 2:
        return None, 0.0
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    mags = [abs(n) for n in comb.coefficients]
    best: tuple[int | None, float] = (None, 0.0)
    own = {tuple(comb.coefficients), tuple(-n for n in comb.coefficients)}
    for signs in itertools.product((1, -1), repeat=len(mags) - 1):
        coefs = (mags[0], *(m * sg for m, sg in zip(mags[1:], signs, strict=True)))
        if coefs in own:
            continue
        c = abs(sum(n * f[p] for p, n in zip(comb.parents, coefs, strict=True)))
        seen, _ = _folded(c, fps)
        for j in np.flatnonzero(np.abs(f - seen) <= tol):
            if j == k or j in comb.parents:
                continue
            mac = _mac(np.asarray(shapes[k], np.float64), np.asarray(shapes[j], np.float64), w)
            if best[0] is None or mac > best[1]:
                best = (int(j), mac)
    return best

def _faint(a: NDArray[np.float64], k: int, comb: Combination, ratio: float) -> bool:
    """Whether candidate ``k`` has less than ``ratio`` times the power a product of ``comb``'s
    parents is expected to have, ``prod_p P_p^|n_p| / P_max^(order - 1)`` (``P = a**2``, the
    strongest candidate's ``P_max``: a product grows with its parents' amplitudes)."""
    log_p = 2.0 * np.log(np.maximum(a, 1e-300))
    ref = sum(abs(n) * log_p[p] for p, n in zip(comb.parents, comb.coefficients, strict=True))
    ref -= (comb.order - 1) * float(np.max(log_p))
    return bool(log_p[k] < math.log(ratio) + ref)


def find_combinations(
    frequencies: ArrayLike,
    amplitudes: ArrayLike,
    shapes: ArrayLike,
    bin_hz: float,
    *,
    phases: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    fps: float | None = None,
    max_order: int = 3,
    tolerance_bins: float = 0.5,
    max_phase_residual: float = 0.35,
    min_envelope_correlation: float = 0.4,
    min_sibling_mac: float = 0.8,
    sibling_amplitude_ratio: float = 1.1,
    sigma_px: float = 4.0,
    third_order_parents: int = 10,
    faint_ratio: float | None = None,
    max_harmonic: int = 7,
) -> tuple[NDArray[np.bool_], list[dict[str, Any]]]:
    """Which candidate peaks are products of stronger ones (see the module's docstring).

    Candidates are taken from the strongest to the weakest; the parents of a candidate are
    all stronger candidates, products included (a product of products is a product of
    higher order of the modes: ``(f_1 + f_2) - (f_1 - f_2)``).  A candidate is a product of a
    combination ``sum_p n_p f_p`` (order ``sum |n_p|`` from 2 to ``max_order``) when

    * its frequency is within ``tolerance_bins`` bins of the combination's (folded at the
      Nyquist frequency of ``fps`` when given);
    * its phase is within ``max_phase_residual`` rad of ``sum_p n_p phi_p`` modulo ``pi``
      (:func:`combination_phase_residual`; not tested when ``phases`` is None);
    * its shape is the shape of the combination's sibling (the same coefficients with other
      signs, e.g. ``|f_1 - f_2|`` for ``f_1 + f_2``) when a candidate sits there: MAC at least
      ``min_sibling_mac`` (weighted by ``weights``).  Pure sibling products have equal
      amplitudes, so of two unlike siblings the one more than ``sibling_amplitude_ratio``
      times stronger holds a mode of its own: the candidate is kept unless its sibling is
      that much stronger, and then the envelope test decides.  When no sibling is a
      candidate (harmonics have no observable sibling), the rank correlation of its local
      energy with its parents' envelope (:func:`envelope_correlation`) is at least
      ``min_envelope_correlation``.

    A candidate at a combination frequency that fails the phase or the envelope test is kept:
    the frequency alone decides nothing.

    Parameters
    ----------
    frequencies, amplitudes : array_like
        ``(k,)`` refined frequencies (Hz) and amplitudes (any unit) of the candidates.
    shapes : array_like
        ``(k, H, W, 2)`` real (phase-aligned) shapes.
    bin_hz : float
        Frequency resolution (Hz).
    phases : array_like, optional
        ``(k,)`` phases at the record's start modulo ``pi`` (rad), the phases the real
        shapes were aligned with (``metadata["phase_rad"]`` of an extraction).
    weights : array_like, optional
        ``(H, W)`` pixel weights of the envelope test.
    fps : float, optional
        Sampling rate (Hz): combinations above the Nyquist frequency are looked for where
        they fold.
    max_order : {2, 3}, default 3
        Highest order ``sum |n_p|``.
    tolerance_bins, max_phase_residual, min_sibling_mac, sibling_amplitude_ratio, \
    min_envelope_correlation, sigma_px :
        The tests above.  The defaults were chosen on seeded clean synthetic videos
        (``benchmarks/bench_false_modes.py``, seeds 0-39): products' sibling MACs 0.96-1.00
        and amplitude ratios 0.97-1.03, against MACs 0.14-0.34 for true modes at a
        combination frequency, products' envelope
        correlations 0.2-0.8 against at most 0.42 for those true modes.
    third_order_parents : int, default 10
        Third-order combinations are formed from the strongest this many candidates only
        (their number grows as the cube of the parents').
    max_harmonic : int, default 7
        Harmonics ``n f_p`` up to this ``n`` of those candidates (with ``max_order`` 3): a
        sensor's quantisation or the extractor's error makes odd harmonics of high order of a
        sub-pixel motion (``3 x 113`` and ``7 x 113 = 791`` Hz, folded to 209 Hz at 1000 fps,
        on a clean two-mode clip); tested like any product, by phase and envelope.
    faint_ratio : float, optional
        A candidate that fails the envelope test (with no informative sibling) is still a
        product when it passed the phase test and has less than this fraction of the power
        its parents' product is expected to have, ``prod_p P_p^|n_p| / P_max^(order - 1)``
        (``P = amplitude**2``, ``P_max`` the strongest candidate's).  The products of a
        sensor's quantisation (a staircase, not a smooth non-linearity) do not follow their
        parents' envelope, and on small images they are as smooth as modes; they are tiny.
        A true mode that faint at a combination is still kept when its phase or its
        sibling's shape shows it is not the product (a plucked one, whose phase is the
        product's, and without a sibling, is not).  Default None: shape and phase alone
        decide.

    Returns
    -------
    kept : ndarray
        ``(k,)`` bool.
    products : list of dict
        One per rejected candidate: ``index``, ``reason`` (``"product"``), ``product`` (e.g.
        ``"3 x 113.0 Hz"``), ``test`` (``"sibling"``, ``"envelope"`` or ``"faint"``: what
        showed it), ``kind``, ``order``, ``parents`` (indices), ``parents_hz``,
        ``parents_rejected`` (which parents are products themselves), ``coefficients``,
        ``expected_hz``, ``frequency_error_bins``, ``phase_residual_rad`` (None without
        phases), ``envelope_correlation``, ``sibling_hz`` and ``sibling_mac`` (None without
        a sibling).
    """
    f = np.asarray(frequencies, dtype=np.float64).reshape(-1)
    a = np.asarray(amplitudes, dtype=np.float64).reshape(-1)
    s = np.asarray(shapes)
    if a.shape != f.shape or s.ndim != 4 or s.shape[0] != f.size or s.shape[-1] != 2:
        raise ValueError(f"frequencies {f.shape}, amplitudes {a.shape} and shapes (k, H, W, 2) "
                         f"{s.shape} do not agree")
    ph = None if phases is None else np.asarray(phases, dtype=np.float64).reshape(-1)
    if ph is not None and ph.shape != f.shape:
        raise ValueError(f"phases {ph.shape} must be one per candidate {f.shape}")
    if max_order not in (2, 3):
        raise ValueError(f"max_order must be 2 or 3, got {max_order!r}")
    if not bin_hz > 0:
        raise ValueError(f"bin_hz must be > 0, got {bin_hz!r}")
    kept = np.ones(f.size, bool)
    root_order = np.ones(f.size, np.int64)
    out: list[dict[str, Any]] = []
    order = np.argsort(-a, kind="stable")
    pos, coef = _combination_table(f.size, max_order, third_order_parents, max_harmonic)
    tol = tolerance_bins * bin_hz
    for r, k in enumerate(order):
        parents_ok = np.asarray(order[:r], dtype=np.int64)
        if not parents_ok.size:
            continue
        usable = pos.max(axis=1) < parents_ok.size
        idx = np.where(pos[usable] >= 0, parents_ok[np.clip(pos[usable], 0, None)], -1)
        cf = np.sum(np.where(idx >= 0, coef[usable] * f[np.clip(idx, 0, None)], 0.0), axis=1)
        seen = np.abs(cf) if not fps else _fold_array(np.abs(cf), fps)
        close = np.flatnonzero((np.abs(seen - f[k]) <= tol) & (np.abs(cf) > 0))
        best = None
        for m in close:
            sign = 1 if cf[m] > 0 else -1
            members = idx[m] >= 0
            comb = Combination(tuple(int(p) for p in idx[m][members]),
                               tuple(int(sign * n) for n in coef[usable][m][members]))
            err = abs(float(seen[m]) - f[k])
            res = None if ph is None else combination_phase_residual(ph, f, int(k), comb,
                                                                     fps=fps)
            if res is not None and abs(res) > max_phase_residual:
                continue
            sib, sib_mac = _sibling(s, f, k, comb, tol, fps, weights)
            env = envelope_correlation(s[k], s[list(comb.parents)],
                                       [abs(n) for n in comb.coefficients], weights, sigma_px)
            if sib is not None and sib_mac < min_sibling_mac:
                if a[sib] <= sibling_amplitude_ratio * a[k]:
                    continue  # unlike its sibling product and as strong: a mode of its own
                sib = None  # the stronger sibling holds a mode: the envelope decides
            test = "sibling" if sib is not None else "envelope"
            if sib is None and env < min_envelope_correlation:
                if faint_ratio is None or not _faint(a, k, comb, faint_ratio):
                    continue
                test = "faint"
            # a product of products is named by the fewest root modes it needs
            n_roots = sum(abs(n) * int(root_order[p]) for p, n in
                          zip(comb.parents, comb.coefficients, strict=True))
            evidence = env if sib is None else sib_mac
            key = (n_roots, sum(not kept[p] for p in comb.parents), -evidence)
            if best is None or key < best[0]:
                best = (key, comb, float(seen[m]), err, res, env, sib, sib_mac, test)
        if best is None:
            continue
        _, comb, seen, err, res, env, sib, sib_mac, test = best
        kept[k] = False
        root_order[k] = best[0][0]
        out.append({
            "index": int(k),
            "reason": "product",
            "product": comb.label(f),
            "test": test,
            "kind": comb.kind,
            "order": comb.order,
            "parents": [int(p) for p in comb.parents],
            "parents_hz": [float(f[p]) for p in comb.parents],
            "parents_rejected": [bool(not kept[p]) for p in comb.parents],
            "coefficients": [int(n) for n in comb.coefficients],
            "expected_hz": float(seen),
            "frequency_error_bins": float(err / bin_hz),
            "phase_residual_rad": None if res is None else float(res),
            "envelope_correlation": float(env),
            "sibling_hz": None if sib is None else float(f[sib]),
            "sibling_mac": None if sib is None else float(sib_mac),
        })
    return kept, out


def reject_combinations(ms: ModeSet, *, weights: ArrayLike | str | None = "confidence",
                        **options: Any) -> ModeSet:
    """``ms`` without its modes that are products of stronger ones (:func:`find_combinations`),
    each listed in ``metadata["rejected"]`` with reason ``"product"`` and the combination that
    makes it (``"product"``: e.g. ``"3 x 113.0 Hz"``).

    Parameters
    ----------
    ms : ModeSet
        Modes of one video, with ``metadata["phase_rad"]`` mapped to them
        (:meth:`.ModeSet.analysed_index`); without it the phase test is skipped.
    weights : array_like, "confidence" or None, default "confidence"
        Pixel weights of the envelope test: ``(H, W)``; ``"confidence"``: the mode set's motion
        confidence saturated at its 90 % quantile (uniform without one); None: uniform.
    **options
        Passed to :func:`find_combinations` (``max_order``, ``tolerance_bins``,
        ``max_phase_residual``, ``min_sibling_mac``, ``sibling_amplitude_ratio``,
        ``min_envelope_correlation``, ``sigma_px``, ``third_order_parents``,
        ``faint_ratio``).

    Returns
    -------
    ModeSet
        The kept modes (``ms`` is not changed); ``metadata["combinations"]`` records the
        options used.
    """
    if len(ms) < 2:
        return ms
    w: NDArray[np.float64] | None
    if isinstance(weights, str):
        if weights != "confidence":
            raise ValueError(f"weights must be an array, 'confidence' or None, got {weights!r}")
        w = _confidence_weights(ms.confidence, ms.image_shape)
    else:
        w = None if weights is None else np.asarray(weights, dtype=np.float64)
    analysed = ms.analysed_index()
    phase_list = ms.metadata.get("phase_rad")
    phases = None
    if analysed is not None and isinstance(phase_list, list) and all(
            i < len(phase_list) for i in analysed):
        phases = np.array([phase_list[i] for i in analysed], dtype=np.float64)
    bin_hz = ms.fps / ms.n_frames
    kept, products = find_combinations(ms.frequencies_hz, ms.amplitudes_px, ms.shapes, bin_hz,
                                       phases=phases, weights=w, fps=ms.fps, **options)
    rough = ms.metadata.get("roughness")
    rejected = list(ms.metadata.get("rejected", []))
    for d in products:
        k = d.pop("index")
        d.pop("parents")
        entry = {"bin": int(ms.peak_bins[k]), "frequency_hz": float(ms.frequencies_hz[k]),
                 "amplitude_px": float(ms.amplitudes_px[k])}
        if analysed is not None and isinstance(rough, list) and analysed[k] < len(rough):
            entry["roughness"] = float(rough[analysed[k]])
        rejected.append({**entry, **d})
    out = ms.select(kept)
    out.metadata["rejected"] = rejected
    out.metadata["combinations"] = {"phase_tested": phases is not None,
                                    "weighted": w is not None, **options}
    return out


def _confidence_weights(confidence: ArrayLike | None, shape: tuple[int, int]
                        ) -> NDArray[np.float64] | None:
    if confidence is None or np.shape(confidence) != tuple(shape):
        return None
    c = np.asarray(confidence, dtype=np.float64)
    q = float(np.quantile(c, 0.9))
    return np.minimum(c / q, 1.0) if q > 0 else None
