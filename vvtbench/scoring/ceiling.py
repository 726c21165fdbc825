"""The ceiling of an instance: the highest NC any field on the inference grid reaches while its
modes explain the data a solver was given. Exact definitions: docs/metrics.md, "Ceiling".

A field is a point theta = [log w; log v] (one value per active voxel). Its **mode misfit**
against data (observed shapes gamma_i, unit length, seen through P, and eigenvalues lam_i) is

    D(theta) = (1/k) sum_i [ log(lam_p(i) / lam_i)^2 + (1 - MAC_i) ]

where the forward model's ``k + n_extra`` lowest modes are paired with the observed ones by
projected MAC (Hungarian, re-paired at every evaluation, so D is a function of theta alone);
model eigenvalues closer than ``cluster_rtol`` (relative, chained) form one cluster, and an
observation paired into a cluster is scored by the projection onto the span of the cluster's
projected modes (MAC_i = |Pi_C gamma_i|^2), which no rotation inside the cluster changes.
It is ``sensitivity``'s data cost with unit weights, divided by k.

Its gradient comes from eigenvalue and mode-shape sensitivities (Nelson's form, as in
``solvers/sensitivity.py``) in adjoint form: only dD/dtheta is needed, never the Jacobian,
so the data may be every DOF of the model (P = I, thousands of rows) at the cost of one
sparse factorization of K - sigma M and a few solves with one right-hand side per mode:

* d log lam_j / d log w_e = w_e phi_j^T K_e phi_j / lam_j, d / d log v_e = -v_e phi_j^T M_e phi_j;
* d(1 - MAC_i) = -2 sum_{c in C} a_ic e_i^T P dphi_c (e_i = gamma_i - Pi_C gamma_i, a_i the
  coefficients of the projection), and b^T dphi_c = x^T g_c + kappa_c b^T phi_c with
  x = A_c^+ b, g_c = -(dK - lam_c dM) phi_c, kappa_c = -1/2 phi_c^T dM phi_c; A_c^+ is the
  modal sum over the computed modes outside c's cluster plus the static-correction series
  for the modes above them (``series_terms``).

The ceiling search (:func:`penalty_path`) maximizes NC(w, w_ref) (or NC(v, v_ref)) over fields
with D <= eps: a penalty path, minimizing D / eps - t NC for increasing t (L-BFGS-B, warm
started), each path started from several fields; every evaluated field is kept as a candidate
(D, NC), so the ceiling at any eps is the best NC among the evaluated fields with D <= eps
(:func:`front`). It is the best found by this search: a lower bound on the true supremum.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["ModeData", "Misfit", "nc_and_gradient", "front", "ceiling_at", "Record",
           "constrained_minimum", "nc_objective", "distance_objective", "rows_above_ceiling",
           "log_bounds"]


@dataclass
class ModeData:
    """What a field must explain: observed shapes ``gamma`` (k, r), seen through ``P``
    (r, n_free; None: every free DOF, r = n_free), and eigenvalues (k,)."""

    gamma: np.ndarray
    eigenvalues: np.ndarray
    P: sp.spmatrix | None = None
    label: str = ""

    def __post_init__(self) -> None:
        g = np.asarray(self.gamma, dtype=float)
        self.gamma = g / np.linalg.norm(g, axis=1, keepdims=True)
        self.eigenvalues = np.asarray(self.eigenvalues, dtype=float)
        if self.P is not None:
            self.P = sp.csr_matrix(self.P)

    @property
    def k(self) -> int:
        return len(self.eigenvalues)

    def project(self, phi: np.ndarray) -> np.ndarray:
        return phi if self.P is None else np.asarray(self.P @ phi)

    def back(self, y: np.ndarray) -> np.ndarray:
        """P^T y."""
        return y if self.P is None else np.asarray(self.P.T @ y)


def _shift(lam: np.ndarray) -> float:
    top = float(np.abs(lam).max())
    return -1e-3 * max(float(lam[0]), 1e-3 * top) if lam[0] > 0 else -1e-3 * top - 1.0


class Misfit:
    """D(theta) and its gradient for one model and one :class:`ModeData`.

    Parameters
    ----------
    model : the inference ``ParametricModel``.
    data : the observation the field must explain.
    n_extra : model modes beyond the k observed (pairing candidates; exact part of dphi).
    cluster_rtol : model eigenvalues closer than this (relative, chained) are one cluster.
    series_terms : terms of the static-correction series (modes above the computed ones).
    """

    def __init__(self, model, data: ModeData, n_extra: int = 10, cluster_rtol: float = 1e-3,
                 series_terms: int = 4) -> None:
        self.model, self.data = model, data
        self.k = data.k
        self.n_model = min(self.k + n_extra, model.n_free - 1)
        self.cluster_rtol = cluster_rtol
        self.series_terms = series_terms
        self.m = model.voxel_map.n_params
        self.n_eval = 0
        # element-level unit matrices, their free DOFs, and the element -> parameter sum
        self._free_index = model.free_index
        self._element_dofs = model.element_dofs
        ne = model.element_dofs.shape[0]
        self._to_param = sp.csr_matrix(
            (np.ones(ne), (model.voxel_map.element_param, np.arange(ne))), shape=(self.m, ne))

    def _quad(self, unit: np.ndarray, U: np.ndarray, X: np.ndarray) -> np.ndarray:
        """(m, c): column j holds u_j^T A_e x_j for every parameter e, A_e the sum of the
        unit element matrices ``unit`` (model.Ke or model.Me) of the elements in voxel e."""
        n_dofs = len(self._free_index)
        free = self._free_index >= 0
        Uf = np.zeros((n_dofs, U.shape[1]))
        Xf = np.zeros((n_dofs, X.shape[1]))
        Uf[free] = U[self._free_index[free]]
        Xf[free] = X[self._free_index[free]]
        Ue = Uf[self._element_dofs]  # (ne, nd, c)
        Xe = Xf[self._element_dofs]
        per_element = np.einsum("eic,eic->ec", Ue, np.einsum("eij,ejc->eic", unit, Xe))
        return np.asarray(self._to_param @ per_element)

    # ------------------------------------------------------------------ forward
    def _forward(self, w: np.ndarray, v: np.ndarray):
        from scipy.optimize import linear_sum_assignment

        from ..fem.modal import cluster_frequencies, eigenmodes

        K, M = self.model.K(w), self.model.M(v)
        modes = eigenmodes(K, M, self.n_model)
        lam, phi = modes.eigenvalues[:self.n_model], modes.vectors[:, :self.n_model]
        Q = self.data.project(phi)
        G = self.data.gamma
        label = np.empty(len(lam), dtype=int)
        for g, members in enumerate(cluster_frequencies(lam, rtol=self.cluster_rtol)):
            label[members] = g
        qn = np.maximum(np.sum(Q * Q, axis=0), 1e-300)
        mac = (G @ Q) ** 2 / qn[None, :]
        for g in np.unique(label):
            members = np.flatnonzero(label == g)
            if len(members) > 1:
                Qc = Q[:, members]
                coef = np.linalg.lstsq(Qc, G.T, rcond=None)[0]
                proj = Qc @ coef
                mac[:, members] = np.sum(G.T * proj, axis=0)[:, None]
        _, pair = linear_sum_assignment(-mac)
        pair = np.asarray(pair)
        # projection of each observation onto its cluster's projected modes
        e = np.empty_like(G)
        a: list[tuple[np.ndarray, np.ndarray]] = []
        for i in range(self.k):
            members = np.flatnonzero(label == label[pair[i]])
            Qc = Q[:, members]
            coef = np.linalg.lstsq(Qc, G[i], rcond=None)[0]
            e[i] = G[i] - Qc @ coef
            a.append((members, coef))
        ell = np.log(np.maximum(lam[pair], 1e-300) / self.data.eigenvalues)
        shape = np.sum(e * e, axis=1)
        return K, M, lam, phi, label, pair, e, a, ell, shape

    def value(self, theta: np.ndarray) -> float:
        return self(theta, gradient=False)[0]

    #: the misfit reported for a field whose forward model cannot be solved (a trial step
    #: of the optimizer far outside the bounds it was given): large, so the step is refused
    FAILED = 1e6

    def __call__(self, theta: np.ndarray, gradient: bool = True):
        """(D, dD/dtheta or None, info) at ``theta`` = [log w; log v]."""
        m = self.m
        self.n_eval += 1
        with np.errstate(over="raise", invalid="raise"):
            try:
                w, v = np.exp(theta[:m]), np.exp(theta[m:])
            except FloatingPointError:
                w = v = None
        try:
            if w is None or not (np.all(np.isfinite(w)) and np.all(np.isfinite(v))):
                raise ValueError("non-finite field")
            K, M, lam, phi, label, pair, e, a, ell, shape = self._forward(w, v)
        except Exception:  # an eigensolver failure at an absurd trial field
            return self.FAILED, np.zeros(2 * m) if gradient else None, {
                "eig_rms": float("nan"), "mean_mac": float("nan"), "pair": None,
                "eig_term": float("nan"), "shape_term": float("nan"), "failed": True}
        k = self.k
        D = float(np.sum(ell ** 2 + shape) / k)
        info = {"eig_rms": float(np.sqrt(np.mean(np.expm1(ell) ** 2))),
                "mean_mac": float(np.mean(1.0 - shape)), "pair": pair,
                "eig_term": float(np.sum(ell ** 2) / k), "shape_term": float(np.sum(shape) / k)}
        if not gradient:
            return D, None, info
        grad = np.zeros(2 * m)
        # eigenvalue terms: d lam_j / d w_e = phi_j^T K_e phi_j,
        # d lam_j / d v_e = -lam_j phi_j^T M_e phi_j
        Pp = phi[:, pair]
        gK = self._quad(self.model.Ke, Pp, Pp)
        gM = self._quad(self.model.Me, Pp, Pp)
        grad[:m] += (2.0 / k) * (w[:, None] * gK / lam[pair][None, :]) @ ell
        grad[m:] += (2.0 / k) * (-v[:, None] * gM) @ ell
        # shape terms: adjoint vectors b_c (n,) for every model mode c in a used cluster
        B: dict[int, np.ndarray] = {}
        for i in range(k):
            members, coef = a[i]
            y = self.data.back(e[i])  # P^T e_i
            for c, ac in zip(members, coef, strict=True):
                B[c] = B.get(c, 0.0) + (-2.0 / k) * ac * y
        if B:
            cols = sorted(B)
            Bm = np.stack([B[c] for c in cols], axis=1)  # (n, nb)
            X = self._apply_pseudo_inverse(K, M, lam, phi, label, cols, Bm)
            Pc = phi[:, cols]
            bphi = np.sum(Bm * Pc, axis=0)
            grad[:m] += -w * (self._quad(self.model.Ke, Pc, X) @ np.ones(len(cols)))
            grad[m:] += v * (self._quad(self.model.Me, Pc, X) @ lam[cols]
                             - 0.5 * self._quad(self.model.Me, Pc, Pc) @ bphi)
        return D, grad, info

    def _apply_pseudo_inverse(self, K, M, lam, phi, label, cols, Bm):
        """x_c = A_c^+ b_c for each column: sum over computed modes outside c's cluster of
        phi_l phi_l^T b / (lam_l - lam_c), plus the static series for the modes above."""
        from ..fem.modal import Factorization

        sigma = _shift(lam)
        mu = lam - sigma
        PhiTB = phi.T @ Bm  # (N, nb)
        X = np.zeros_like(Bm)
        T = self.series_terms
        Z = []
        if T > 0:
            fac = Factorization((K - sigma * M).tocsc())
            z = fac(Bm)
            Z.append(z)
            for _ in range(T - 1):
                z = fac(np.asarray(M @ z))
                Z.append(z)
        for n_c, c in enumerate(cols):
            far = label != label[c]
            coef = np.where(far, 1.0 / np.where(far, lam - lam[c], 1.0), 0.0)
            series = sum(mu[c] ** p / mu ** (p + 1) for p in range(T)) if T else 0.0
            X[:, n_c] = phi @ ((coef - series) * PhiTB[:, n_c])
            for p in range(T):
                X[:, n_c] += mu[c] ** p * Z[p][:, n_c]
        return X


def nc_and_gradient(x: np.ndarray, ref: np.ndarray) -> tuple[float, np.ndarray]:
    """Centered NC(x, ref) (Pearson) and its gradient with respect to x."""
    a = x - x.mean()
    b = ref - ref.mean()
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 0.0, np.zeros_like(x)
    nc = float(a @ b / (na * nb))
    g = b / (na * nb) - nc * a / na ** 2
    return nc, g - g.mean()


class Record:
    """Every field a search evaluated: its misfit D, objective value, start, and optional
    extra scores (``scores``: name -> function of theta, e.g. the NC of the other field).

    ``best[tag]`` keeps (value, theta) of the lowest objective among fields with D <=
    ``eps[tag]``; ``lowest`` keeps (D, theta) of the lowest misfit seen.
    """

    def __init__(self, scores: dict | None = None) -> None:
        self.misfit: list[float] = []
        self.value: list[float] = []
        self.start: list[str] = []
        self.scores = dict(scores or {})
        self.extra: dict[str, list[float]] = {k: [] for k in self.scores}
        self.best: dict[str, tuple[float, np.ndarray]] = {}
        self.lowest: tuple[float, np.ndarray] | None = None

    def add(self, theta: np.ndarray, D: float, f: float, start: str,
            eps: dict[str, float]) -> None:
        self.misfit.append(float(D))
        self.value.append(float(f))
        self.start.append(start)
        for k, fn in self.scores.items():
            self.extra[k].append(float(fn(theta)))
        for tag, e in eps.items():
            if D <= e and (tag not in self.best or f < self.best[tag][0]):
                self.best[tag] = (float(f), theta.copy())
        if self.lowest is None or D < self.lowest[0]:
            self.lowest = (float(D), theta.copy())

    def best_score(self, name: str, eps: float) -> float:
        """The highest extra score ``name`` among fields with D <= eps (NaN if none)."""
        d = np.asarray(self.misfit)
        x = np.asarray(self.extra[name])
        ok = d <= eps
        return float(x[ok].max()) if ok.any() else float("nan")


def constrained_minimum(misfit: Misfit, objective, theta0: np.ndarray, eps: float,
                        start: str = "", record: Record | None = None,
                        eps_tags: dict[str, float] | None = None, outer: int = 8,
                        inner: int = 25, rho: float = 10.0, feas_tol: float = 1e-3,
                        bounds=None, log=None) -> dict:
    """Minimize ``objective(theta) -> (f, df)`` subject to D(theta) <= eps.

    Augmented Lagrangian on c = D / eps - 1 <= 0: each outer iteration minimizes
    f + (max(0, lam + rho c)^2 - lam^2) / (2 rho) by L-BFGS-B (at most ``inner``
    iterations, warm started), then lam <- max(0, lam + rho c) and rho grows 4x when the
    constraint violation did not halve. Stops after ``outer`` iterations or when c <=
    ``feas_tol`` and the objective changed by less than 1e-4 between outer iterations.

    Every evaluated field is added to ``record`` (its D and f), whose ``best[tag]`` keeps the
    lowest f among fields with D <= eps_tags[tag] (default {"eps": eps}). Returns the history:
    one dict per outer iteration (D, c, f, lam, rho, iterations, evaluations).
    """
    from scipy.optimize import minimize

    rec = record if record is not None else Record()
    tags = eps_tags if eps_tags is not None else {"eps": eps}
    lam = 0.0
    theta = np.array(theta0, dtype=float)
    history = []
    viol_prev = np.inf
    f_prev = np.inf
    for it in range(outer):
        n0 = len(rec.misfit)

        def L(th, lam=lam, rho=rho):
            D, gD, _ = misfit(th)
            f, gf = objective(th)
            rec.add(th, D, f, start, tags)
            c = D / eps - 1.0
            s = max(0.0, lam + rho * c)
            return f + (s * s - lam * lam) / (2.0 * rho), gf + (s / eps) * gD

        out = minimize(L, theta, jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": inner, "maxcor": 20})
        theta = out.x
        D = misfit.value(theta)
        f = float(objective(theta)[0])
        c = D / eps - 1.0
        lam = max(0.0, lam + rho * c)
        viol = max(c, 0.0)
        h = {"outer": it, "D": float(D), "c": float(c), "f": f, "lam": float(lam),
             "rho": float(rho), "iterations": int(out.nit),
             "evaluations": len(rec.misfit) - n0}
        history.append(h)
        if log is not None:
            log(dict(h, start=start))
        if viol <= feas_tol and abs(f - f_prev) < 1e-4:
            break
        if viol > 0.5 * viol_prev:
            rho *= 4.0
        viol_prev, f_prev = viol, f
    return {"theta": theta, "history": history}


def front(misfit: np.ndarray, nc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Pareto front of (misfit, NC) points: for increasing misfit, the running max NC."""
    order = np.argsort(misfit, kind="stable")
    d = np.asarray(misfit)[order]
    best = np.maximum.accumulate(np.asarray(nc)[order])
    keep = np.r_[True, np.diff(best) > 0]
    return d[keep], best[keep]


def ceiling_at(misfit, nc, eps: float) -> float:
    """The best NC among evaluated fields with misfit <= eps (NaN if none)."""
    misfit, nc = np.asarray(misfit, float), np.asarray(nc, float)
    ok = misfit <= eps
    return float(nc[ok].max()) if ok.any() else float("nan")


def nc_objective(ref: np.ndarray, which: str, m: int):
    """``theta -> (-NC, gradient)`` of the field ``which`` ("w" or "v") against ``ref``."""
    sl = slice(0, m) if which == "w" else slice(m, 2 * m)

    def f(theta: np.ndarray):
        x = np.exp(theta[sl])
        nc, g = nc_and_gradient(x, ref)
        grad = np.zeros(2 * m)
        grad[sl] = -g * x
        return -nc, grad

    return f


def distance_objective(anchor: np.ndarray):
    """``theta -> (|theta - anchor|^2 / (2 n), gradient)``: mean squared log distance."""
    n = len(anchor)

    def f(theta: np.ndarray):
        d = theta - anchor
        return float(d @ d) / (2 * n), d / n

    return f


def rows_above_ceiling(ceiling: dict, rows: dict, tol: float = 1e-9) -> dict:
    """Which rows score above an instance's ceiling.

    Parameters
    ----------
    ceiling : ``{"eps": allowed misfit, "ceiling": NC}`` of one instance, field and data.
    rows : ``{name: {"nc": NC of the row's estimate, "D": its misfit on the same data}}``.

    Returns
    -------
    dict
        ``feasible_above``: rows above the ceiling that explain the data (D <= eps): each
        contradicts the ceiling, which must be at least the NC of every feasible field seen;
        ``infeasible_above``: rows above it that do not explain the data (D > eps), so are
        not fields the ceiling ranges over; ``unknown_above``: rows above it whose misfit is
        not known (None or NaN), which can be neither. Names sorted.
    """
    eps, top = float(ceiling["eps"]), float(ceiling["ceiling"])
    above = {n: r for n, r in rows.items()
             if r.get("nc") is not None and np.isfinite(r["nc"]) and r["nc"] > top + tol}
    known = {n: float(r["D"]) for n, r in above.items()
             if r.get("D") is not None and np.isfinite(float(r["D"]))}
    return {"feasible_above": sorted(n for n, D in known.items() if D <= eps),
            "infeasible_above": sorted(n for n, D in known.items() if D > eps),
            "unknown_above": sorted(n for n in above if n not in known)}


def log_bounds(fields, m: int, margin: float = 100.0) -> list[tuple[float, float]]:
    """L-BFGS-B bounds on theta = [log w; log v]: for w (and for v) from ``margin`` times below
    the smallest to ``margin`` times above the largest value of any of ``fields`` ((w, v)
    pairs), so that no trial step leaves the physical range by orders of magnitude."""
    out = []
    for part in (0, 1):
        vals = np.concatenate([np.asarray(f[part], float) for f in fields])
        lo, hi = np.log(vals.min() / margin), np.log(vals.max() * margin)
        out += [(float(lo), float(hi))] * m
    return out
