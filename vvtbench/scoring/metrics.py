"""Scores of an estimate against the truth. Exact formulas: docs/metrics.md.

* :func:`normalized_correlation` -- centered (Pearson, the main score; a constant field scores
  0) or uncentered (cosine), over the finite (active) voxels.
* :func:`intrinsic_resolution` -- blur the *true* field with a Gaussian of sigma voxels
  (NaN-aware normalized convolution over the voxel grid), NC with the estimate for each sigma;
  sigma* = argmax and the NC there.
* :func:`mode_match` -- forward-solve the inference model with the estimated fields, project
  the modes with P, match them to the observed image-space modes by MAC (optimal assignment),
  mean MAC and relative frequency errors, raw and after the one global scale s of w/v that the
  scale ambiguity allows (frequencies scale by sqrt(s)).
"""

from __future__ import annotations

import numpy as np

from ..modes.mac import mac_matrix, subspace_mac

__all__ = [
    "normalized_correlation",
    "gaussian_blur",
    "intrinsic_resolution",
    "mac_matrix",
    "mode_match",
    "invalid_reason",
    "evaluate",
    "is_constant",
    "false_contrast",
]


def normalized_correlation(estimate, truth, centered: bool = True) -> float:
    """NC over entries where both arrays are finite. Centered: Pearson correlation; 0 if either
    field is constant. Uncentered: cosine similarity; 0 if either field is all zero."""
    a = np.asarray(estimate, dtype=float).ravel()
    b = np.asarray(truth, dtype=float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"estimate and truth differ in size: {a.shape} vs {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size == 0:
        return 0.0
    if centered:
        a = a - a.mean()
        b = b - b.mean()
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    scale = max(np.abs(np.asarray(estimate, float)[np.isfinite(estimate)]).max(initial=0), 1e-300)
    if na <= 1e-12 * scale * np.sqrt(a.size) or nb == 0:
        return 0.0
    return float(np.clip((a @ b) / (na * nb), -1.0, 1.0))


def gaussian_blur(grid: np.ndarray, sigma: float) -> np.ndarray:
    """NaN-aware Gaussian blur of a voxel grid (sigma in voxels): normalized convolution
    G*(x m) / G*m with m the mask of finite voxels (mode 'constant' zero outside the grid, so
    the boundary is not biased); NaN voxels stay NaN. sigma = 0 returns a copy."""
    from scipy.ndimage import gaussian_filter

    g = np.asarray(grid, dtype=float)
    if sigma <= 0:
        return g.copy()
    mask = np.isfinite(g)
    x = np.where(mask, g, 0.0)
    num = gaussian_filter(x, sigma, mode="constant", cval=0.0)
    den = gaussian_filter(mask.astype(float), sigma, mode="constant", cval=0.0)
    out = np.divide(num, den, out=np.full_like(num, np.nan), where=den > 1e-12)
    out[~mask] = np.nan
    return out


def intrinsic_resolution(
    estimate_grid: np.ndarray,
    truth_grid: np.ndarray,
    sigmas=None,
    centered: bool = True,
) -> dict:
    """sigma* (voxels) maximizing NC(estimate, blur(truth, sigma)) over ``sigmas`` (default
    0, 0.1, ..., 4), the NC there, and the whole curve."""
    sigmas = np.round(np.arange(0.0, 4.0001, 0.1), 10) if sigmas is None else np.asarray(sigmas)
    e = np.asarray(estimate_grid, dtype=float)
    t = np.asarray(truth_grid, dtype=float)
    if e.shape != t.shape:
        raise ValueError(f"grids differ in shape: {e.shape} vs {t.shape}")
    ncs = np.array([normalized_correlation(e, gaussian_blur(t, s), centered) for s in sigmas])
    best = int(np.argmax(ncs))
    return {"sigma_star": float(sigmas[best]), "nc_at_sigma_star": float(ncs[best]),
            "sigmas": sigmas.tolist(), "nc": ncs.tolist()}


#: model modes whose frequencies agree to this are one repeated mode in the mode match
REPEATED_RTOL = 1e-5


def mode_match(problem, w: np.ndarray, v: np.ndarray, n_extra: int = 10, modes=None) -> dict:
    """Forward-solve K(w) phi = lam M(v) phi on the inference model (k + n_extra lowest modes),
    project with P and match to the observed gamma by MAC (Hungarian assignment, maximizing
    the total MAC); ``modes``, the forward model's modes if already computed (at least
    k + n_extra of them), are reused. Model modes whose frequencies agree to
    ``REPEATED_RTOL`` are one repeated mode whose basis the eigensolver's rounding picks: an
    observed mode is matched to its span (:func:`vvtbench.modes.mac.subspace_mac`), so the score
    does not depend on that basis. Frequencies f = sqrt(lam)/2pi; the scale c = sqrt(s)
    minimizing sum_i (c f_pred_i / f_obs_i - 1)^2 is c = sum r_i / sum r_i^2 with
    r_i = f_pred_i / f_obs_i."""
    from scipy.optimize import linear_sum_assignment

    from ..fem.modal import cluster_frequencies, eigenmodes

    model = problem.model
    k = problem.n_modes
    n_pred = min(k + n_extra, model.n_free - 1)
    if modes is None or modes.vectors.shape[1] < n_pred:
        modes = eigenmodes(model.K(w), model.M(v), n_pred)
    vectors, f_model = modes.vectors[:, :n_pred], modes.frequencies_hz[:n_pred]
    pred = (problem.P @ vectors).T  # (n_pred, 2 nv)
    mac = mac_matrix(problem.gamma, pred)  # (k, n_pred)
    for cluster in cluster_frequencies(f_model, REPEATED_RTOL):
        if cluster.size > 1:
            mac[:, cluster] = subspace_mac(problem.gamma, pred[cluster])[:, None]
    rows, cols = linear_sum_assignment(-mac)
    order = np.argsort(rows)
    rows, cols = rows[order], cols[order]
    matched_mac = mac[rows, cols]
    f_obs = problem.frequencies_hz[rows]
    f_pred = f_model[cols]
    ok = f_obs > 0
    r = f_pred[ok] / f_obs[ok]
    raw = np.abs(r - 1.0)
    c = float(r.sum() / (r @ r)) if r.size else 1.0
    scaled = np.abs(c * r - 1.0)
    return {
        "mean_mac": float(matched_mac.mean()),
        "mac": matched_mac.tolist(),
        "assignment": cols.tolist(),
        "freq_rel_error": float(raw.mean()) if raw.size else float("nan"),
        "freq_rel_error_scaled": float(scaled.mean()) if scaled.size else float("nan"),
        "freq_scale": c,
        "material_scale": c**2,
        "f_pred_hz": f_pred.tolist(),
        "f_obs_hz": f_obs.tolist(),
    }


def invalid_reason(w: np.ndarray, v: np.ndarray, n_params: int,
                   w_std: np.ndarray | None = None,
                   v_std: np.ndarray | None = None) -> str | None:
    """Why an estimate cannot be scored (wrong shape, a non-finite value, E or rho not
    positive in some voxel; a stated standard deviation of the wrong shape, not finite or
    negative), or None when it is valid. An invalid estimate is never scored on a subset of
    voxels, and a stated uncertainty that is not one never reaches the coverage score.

    >>> import numpy as np
    >>> invalid_reason(np.ones(3), np.ones(3), 3, w_std=np.array([0.1, -0.1, 0.1]))
    'w_std is negative in 1 of 3 voxels'
    """
    for name, x in (("w", w), ("v", v)):
        x = np.asarray(x)
        if x.shape != (n_params,):
            return f"{name} has shape {x.shape}, the problem has {n_params} parameters"
        bad = ~np.isfinite(x)
        if bad.any():
            return f"{name} is not finite in {int(bad.sum())} of {n_params} voxels"
        if (x <= 0).any():
            return f"{name} is not positive in {int((x <= 0).sum())} of {n_params} voxels"
    for name, x in (("w_std", w_std), ("v_std", v_std)):
        if x is None:
            continue
        x = np.asarray(x)
        if x.shape != (n_params,):
            return f"{name} has shape {x.shape}, the problem has {n_params} parameters"
        bad = ~np.isfinite(x)
        if bad.any():
            return f"{name} is not finite in {int(bad.sum())} of {n_params} voxels"
        if (x < 0).any():
            return f"{name} is negative in {int((x < 0).sum())} of {n_params} voxels"
    return None


CONSTANT_RTOL = 1e-9


def is_constant(field: np.ndarray, rtol: float = CONSTANT_RTOL) -> bool:
    """A field whose spread (max - min) is at most ``rtol`` times its largest magnitude: a
    defect-free truth, on which a correlation is undefined (its rounding noise, e.g.
    9000 +- 5e-12 Pa, would decide it)."""
    x = np.asarray(field, dtype=float)
    x = x[np.isfinite(x)]
    return x.size == 0 or float(np.ptp(x)) <= rtol * float(np.abs(x).max(initial=0.0))


def false_contrast(estimate: np.ndarray) -> float:
    """The coefficient of variation std / mean of an estimate over its voxels: the contrast
    it invents where the truth has none (0 is perfect)."""
    x = np.asarray(estimate, dtype=float)
    return float(np.std(x) / abs(np.mean(x)))


def evaluate(problem, truth, w: np.ndarray, v: np.ndarray, modes: bool = True,
             w_std: np.ndarray | None = None, v_std: np.ndarray | None = None) -> dict:
    """Every metric of a valid estimate: NC (centred and uncentred) of w and v against the
    truth, the intrinsic resolution of each (``sigma_star_*``, ``nc_at_sigma_star_*`` and the
    curves), optionally the mode match against the observed modes (``mode_mac``,
    ``freq_err_raw``, ``freq_err_scaled``; None with a note when the forward solve fails), and
    for stated per-parameter standard deviations the 95 % interval coverage
    (``interval_coverage_w``, ``interval_coverage_v``; None when not stated), and the fraction
    of the inference model's DOFs the observation sees (``observed_dof_fraction``, from the
    problem's ``meta``; None when it does not say).

    Returns ``{"metrics": {...}, "curves": {"w": {...}, "v": {...}}, "notes": [...]}``.
    """
    w, v = np.asarray(w, dtype=float), np.asarray(v, dtype=float)
    metrics: dict = {}
    curves: dict = {}
    notes: list[str] = []
    for name, est, tru in (("w", w, truth.w), ("v", v, truth.v)):
        metrics[f"false_contrast_{name}"] = None
        metrics[f"nc_{name}_uncentered"] = normalized_correlation(est, tru, centered=False)
        if is_constant(tru):  # NC is undefined: score the contrast the estimate invents
            metrics[f"nc_{name}"] = None
            metrics[f"false_contrast_{name}"] = false_contrast(est)
            metrics[f"sigma_star_{name}"] = metrics[f"nc_at_sigma_star_{name}"] = None
            notes.append(f"the true {name} is constant: NC undefined, false contrast scored")
            continue
        metrics[f"nc_{name}"] = normalized_correlation(est, tru)
        if is_constant(est):  # no pattern to match at any blur: resolution undefined
            metrics[f"sigma_star_{name}"] = metrics[f"nc_at_sigma_star_{name}"] = None
            notes.append(f"the estimated {name} is constant: intrinsic resolution undefined")
            continue
        ir = intrinsic_resolution(problem.to_grid(est), problem.to_grid(tru))
        metrics[f"sigma_star_{name}"] = ir["sigma_star"]
        metrics[f"nc_at_sigma_star_{name}"] = ir["nc_at_sigma_star"]
        curves[name] = {"sigmas": ir["sigmas"], "nc": ir["nc"]}
    for name, est, std, tru in (("w", w, w_std, truth.w), ("v", v, v_std, truth.v)):
        metrics[f"interval_coverage_{name}"] = (
            None if std is None else interval_coverage(est, std, tru, z=COVERAGE_Z))
    metrics.update(mode_mac=None, freq_err_raw=None, freq_err_scaled=None,
                   mode_mac_true=None, freq_err_true_scaled=None)
    if modes:
        from dataclasses import replace

        from ..fem.modal import eigenmodes

        k = min(len(truth.true_eigenvalues), max(problem.n_modes, 1))
        true_view = replace(problem, gamma=truth.image_modes[:k],
                            eigenvalues=truth.true_eigenvalues[:k])
        forward = None  # the estimate's modes: one eigen-solve serves both matches
        for target, keys in ((problem, ("mode_mac", "freq_err_raw", "freq_err_scaled")),
                             (true_view, ("mode_mac_true", None, "freq_err_true_scaled"))):
            try:
                if forward is None:
                    model = problem.model
                    forward = eigenmodes(model.K(w), model.M(v),
                                         min(max(problem.n_modes, k) + 10, model.n_free - 1))
                mm = mode_match(target, w, v, modes=forward)
            except Exception as error:  # a forward model without modes: say so
                notes.append(f"mode match not computed: {type(error).__name__}: {error}")
                break
            for key, val in zip(keys, (mm["mean_mac"], mm["freq_rel_error"],
                                       mm["freq_rel_error_scaled"]), strict=True):
                if key:
                    metrics[key] = val
    dof = (getattr(problem, "meta", None) or {}).get("observed_dof_fraction")
    metrics["observed_dof_fraction"] = (float(dof) if isinstance(dof, (int, float))
                                        and np.isfinite(dof) else None)
    for key, val in (truth.meta.get("extraction") or {}).items():
        if key in ("precision", "recall", "recall_all", "mean_rel_freq_error", "mean_mac",
                   "median_rel_damping_error", "frequency_efficiency",
                   "damping_efficiency"):
            metrics[f"extraction_{key}"] = val
    return {"metrics": metrics, "curves": curves, "notes": notes}


# --------------------------------------------------------------------------- calibration
# (uncertainty of solvers that report per-voxel standard deviations)


COVERAGE_Z = 1.96  # the interval scored in the results table: estimate +- 1.96 std (95 %)


def interval_coverage(estimate, std, truth, z: float = 1.96) -> float:
    """Calibration of stated per-voxel intervals: the fraction of voxels whose truth lies in
    [estimate - z std, estimate + z std], over the voxels where all three are finite
    (``z=1.96``: nominal 95 %; ``z=1``: nominal 68.3 %). A well-calibrated solver scores the
    nominal coverage; lower means overconfident intervals, higher underconfident ones.
    NaN when no voxel is finite."""
    e = np.asarray(estimate, dtype=float).ravel()
    s = np.asarray(std, dtype=float).ravel()
    t = np.asarray(truth, dtype=float).ravel()
    if not e.shape == s.shape == t.shape:
        raise ValueError(f"estimate, std and truth differ in size: {e.shape}, {s.shape}, "
                         f"{t.shape}")
    if z <= 0:
        raise ValueError(f"z must be positive, got {z}")
    ok = np.isfinite(e) & np.isfinite(s) & np.isfinite(t)
    if not ok.any():
        return float("nan")
    return float(np.mean(np.abs(t[ok] - e[ok]) <= z * np.abs(s[ok])))
