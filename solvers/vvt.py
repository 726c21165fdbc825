"""``vvt``: the paper's alternating closed-form / dual-ascent solver (Feng et al., CVPR 2022).

Objective (paper Eq. 3, k modes, m voxels)::

    J = 1/(2k) sum_i y_i ||A_i u_i||^2 + alpha_u/(2k) sum_i ||P u_i - gamma_i||^2
        + alpha_w/(2m) ||L w||^2 + alpha_v/(2m) ||L v||^2 + alpha_mean (mean(w) - wbar)^2
    A_i = K(w) - lam_i M(v)

Each iteration (the order of the authors' code):

1. u-update, per mode, closed form: (y_i A_i^T A_i + alpha_u P^T P) u_i = alpha_u P^T gamma_i.
   Sparse: the system pattern is fixed, so it is analysed once (CHOLMOD, METIS). The modes are
   grouped by eigenvalue (ratio <= 1 + group_rtol); each group keeps one numeric Cholesky
   factor of the system at its centre, the preconditioner of warm-started PCG for its modes
   (all modes in lockstep, one multi-right-hand-side triangular solve per group and step),
   refactorized when its PCG steps exceed their running average including the
   factorization (counted in steps), so most iterations cost some block sparse mat-vecs and
   triangular solves instead of factorizations.
2. z = [w; v] update: the sparse 2m x 2m normal equations
   (1/k) sum_i y_i B_i^T B_i + (alpha_w/m) L^T L (+) (alpha_v/m) L^T L + 2 alpha_mean c c^T,
   B_i = [G_i, -lam_i H_i], G_i = stiffness_columns(u_i), H_i = mass_columns(u_i), c = 1/m
   on w; the dense rank-one anchor is applied by Sherman-Morrison (one sparse Cholesky).
   Optional positivity by an active-set projected solve.
3. eigenvalue update (alpha_e > 0): lam_i = (y_i (K u_i).(M u_i) + alpha_e lam_obs_i) /
   (y_i ||M u_i||^2 + alpha_e).
4. dual ascent: y_i += eta ||A_i u_i||.

Stops when ||dw||/||w|| and ||dv||/||v|| are both below ``tol`` or after ``max_iter``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from vvtbench.api import Estimate, Factorization, InverseProblem

__all__ = ["VVTSolver", "VVTConfig", "grid_laplacian", "ZSystem"]


# --------------------------------------------------------------------------- shared algebra


def grid_laplacian(voxel_map) -> sp.csr_matrix:
    """Graph Laplacian (degree - adjacency, 6-neighbour) of the active voxels of the grid:
    ``(L x)_e = sum_{f ~ e} (x_e - x_f)``, the second-difference operator of the authors."""
    shape = voxel_map.grid.shape
    active = voxel_map.active
    n = len(active)
    where = np.full(int(np.prod(shape)), -1)
    where[active] = np.arange(n)
    ijk = np.array(np.unravel_index(active, shape)).T
    rows, cols = [], []
    for axis in range(3):
        step = np.zeros(3, dtype=int)
        step[axis] = 1
        nb = ijk + step
        ok = nb[:, axis] < shape[axis]
        nbi = np.full(n, -1)
        nbi[ok] = where[np.ravel_multi_index(nb[ok].T, shape)]
        ok = nbi >= 0
        rows += [np.arange(n)[ok], nbi[ok]]
        cols += [nbi[ok], np.arange(n)[ok]]
    r, c = np.concatenate(rows), np.concatenate(cols)
    adj = sp.csr_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    return (sp.diags(deg) - adj).tocsr()


class ZSystem:
    """Sparse least squares for z = [w; v] given modes U and eigenvalues:

    min (1/k) sum_i c_i ||G_i w - lam_i H_i v||^2 + (alpha_w/m)||L w||^2/... (see module doc)
    """

    def __init__(self, problem: InverseProblem, alpha_w: float, alpha_v: float,
                 alpha_mean: float, w_mean: float) -> None:
        self.model = problem.model
        m = problem.n_params
        self.m = m
        L = grid_laplacian(problem.voxel_map)
        LtL = (L.T @ L).tocsr()
        self.reg = sp.block_diag([alpha_w / m * LtL, alpha_v / m * LtL]).tocsr()
        self.alpha_mean = alpha_mean
        self.w_mean = w_mean
        c = np.zeros(2 * m)
        c[:m] = 1.0 / m
        self.c = c
        self._cache: dict = {}

    def _plan(self) -> dict:
        """Fixed index maps of the node-block Gram assembly (built once).

        Row (free DOF d, mode i) of B_i has nonzeros only at the parameters of the elements
        around d's node, and every DOF of a node shares that column set: the Gram is a sum of
        small dense per-node blocks X_n X_n^T, X_n = (parameters at n) x (DOFs at n, modes)."""
        if "plan" in self._cache:
            return self._cache["plan"]
        mdl = self.model
        cells = mdl.mesh.cells
        ne, nn = cells.shape
        m, n_nodes = self.m, mdl.mesh.n_nodes
        param = np.broadcast_to(mdl.voxel_map.element_param[:, None], (ne, nn))
        pair = cells.astype(np.int64) * m + param
        uniq, inv = np.unique(pair.ravel(), return_inverse=True)
        node_of = uniq // m
        start = np.searchsorted(node_of, np.arange(n_nodes))
        slot = np.arange(len(uniq)) - start[node_of]
        width = int(slot.max()) + 1
        index = np.full((n_nodes, width), -1, dtype=np.int64)  # parameter per (node, slot)
        index[node_of, slot] = uniq % m
        gidx = np.concatenate([index, np.where(index >= 0, index + m, -1)], axis=1)
        valid = (gidx[:, :, None] >= 0) & (gidx[:, None, :] >= 0)
        rows = np.broadcast_to(gidx[:, :, None], valid.shape)[valid]
        cols = np.broadcast_to(gidx[:, None, :], valid.shape)[valid]
        reg = self.reg.tocoo()
        keys = np.concatenate([rows * (2 * m) + cols, reg.row.astype(np.int64) * (2 * m)
                               + reg.col])
        ukeys, pos = np.unique(keys, return_inverse=True)
        n_block = len(rows)
        plan = {
            "width": width,
            "scatter": sp.csr_matrix(  # (element, local node) -> (node, slot) rows, summed
                (np.ones(ne * nn), (node_of[inv] * width + slot[inv], np.arange(ne * nn))),
                shape=(n_nodes * width, ne * nn)),
            "valid": valid,
            "pos": pos[:n_block],
            "reg_data": np.bincount(pos[n_block:], weights=reg.data, minlength=len(ukeys)),
            "indices": (ukeys % (2 * m)).astype(np.int32),
            "indptr": np.searchsorted(ukeys // (2 * m), np.arange(2 * m + 1)).astype(np.int32),
        }
        self._cache["plan"] = plan
        return plan

    def gram(self, U: np.ndarray, lam: np.ndarray, weights: np.ndarray,
             with_reg: bool = False) -> sp.csr_matrix:
        """(1/k) sum_i weights_i B_i^T B_i, B_i = [G_i, -lam_i H_i] (plus the regularizer when
        ``with_reg``), from the unit element matrices as per-node dense blocks."""
        mdl = self.model
        plan = self._plan()
        k, m = U.shape[1], self.m
        n_nodes, width = mdl.mesh.n_nodes, plan["width"]
        ne, nn = mdl.mesh.cells.shape
        dpn = mdl.element_dofs.shape[1] // nn
        full = np.zeros((mdl.mesh.n_dofs, k))
        full[mdl.free_dofs] = U
        ue = full[mdl.element_dofs]  # (ne, nd, k)
        s = np.sqrt(np.asarray(weights, float) / k)
        free = (mdl.free_index[mdl.element_dofs] >= 0)[:, :, None]
        gy = np.matmul(mdl.Ke, ue) * (s * free)  # (ne, nd, k)
        hy = np.matmul(mdl.Me, ue) * (-s * lam * free)
        X = np.empty((n_nodes, 2 * width, dpn * k))
        for half, y in ((0, gy), (1, hy)):
            C = plan["scatter"] @ y.reshape(ne * nn, dpn * k)
            X[:, half * width:(half + 1) * width] = C.reshape(n_nodes, width, dpn * k)
        blocks = X @ X.transpose(0, 2, 1)  # (n_nodes, 2 width, 2 width)
        data = np.bincount(plan["pos"], weights=blocks[plan["valid"]],
                           minlength=len(plan["indices"]))
        if with_reg:
            data += plan["reg_data"]
        return sp.csr_matrix((data, plan["indices"], plan["indptr"]), shape=(2 * m, 2 * m))

    def solve(self, U, lam, weights, positive: bool = False, z_prev=None):
        """Minimizer z (2m,) and the Gram (for losses)."""
        S = self.gram(U, lam, weights, with_reg=True)
        S = sp.csc_matrix((S.data, S.indices, S.indptr), shape=S.shape)  # symmetric
        z = _anchored_solve(S, self.c, 2 * self.alpha_mean, self.w_mean, cache=self._cache)
        if positive and np.any(z <= 0):
            z = _positive_solve(S, self.c, 2 * self.alpha_mean, self.w_mean, z, self.m)
        return z, S


def _scaled_factor(S: sp.csc_matrix, free: np.ndarray | None = None,
                   cache: dict | None = None):
    """Jacobi-scaled Cholesky of S (restricted to ``free``): returns solve(b) for S x = b.

    ``cache`` (a dict kept by the caller): the CHOLMOD symbolic analysis is reused while the
    matrix's structure is unchanged (the z-system's is, from one iteration to the next)."""
    if free is not None:
        S = S[free][:, free]
    d = np.sqrt(np.maximum(S.diagonal(), 1e-300))
    Dinv = sp.diags(1.0 / d)
    Ss = (Dinv @ S @ Dinv).tocsc()
    Ss = (Ss + sp.identity(Ss.shape[0], format="csc") * 1e-12).tocsc()  # keep it definite
    Ss.sort_indices()
    F = None
    if cache is not None:
        try:
            from sksparse.cholmod import analyze
        except ImportError:
            analyze = None
        if analyze is not None:
            key = cache.get("structure")
            if key is None or not (np.array_equal(key[0], Ss.indptr)
                                   and np.array_equal(key[1], Ss.indices)):
                cache["symbolic"] = analyze(Ss, ordering_method="metis")
                cache["structure"] = (Ss.indptr.copy(), Ss.indices.copy())
            try:
                F = cache["symbolic"]
                F.cholesky_inplace(Ss)
            except Exception:  # not definite: the LU fallback below
                F = None
    if F is None:
        F = Factorization(Ss)
    return lambda b: F(b / d) / d


def _anchored_solve(S, c, beta, target, free=None, fixed_value=None, cache=None):
    """argmin z^T S z / 1 ... : solves (S + beta c c^T) z = beta target c (+ fixed part) by
    Sherman-Morrison; ``free`` restricts to a subset with the rest held at ``fixed_value``."""
    n = S.shape[0]
    if free is None:
        solve = _scaled_factor(S, cache=cache)
        x = solve(c)
        return beta * target * x / (1.0 + beta * (c @ x))
    fixed = np.setdiff1d(np.arange(n), free)
    zf = np.zeros(n)
    zf[fixed] = fixed_value
    # rhs for the free part: beta*target*c_f - S_fx z_x - beta c_f (c_x . z_x)
    Sfx = S[free][:, fixed]
    cf = c[free]
    r0 = -(Sfx @ zf[fixed])
    b_anchor = beta * (target - c[fixed] @ zf[fixed])
    solve = _scaled_factor(S, free)
    x_r = solve(r0)
    x_c = solve(cf)
    # (S_ff + beta cf cf^T) z = r0 + b_anchor cf
    z_free = x_r + b_anchor * x_c - beta * x_c * (cf @ x_r + b_anchor * (cf @ x_c)) / (
        1.0 + beta * (cf @ x_c))
    zf[free] = z_free
    return zf


def _positive_solve(S, c, beta, target, z, m, floor_frac=1e-3, max_rounds=20):
    """Active-set projected solve: variables that go non-positive are held at a small floor
    (``floor_frac`` times the mean of their block) and the rest re-solved, until none does."""
    n = S.shape[0]
    floors = np.empty(n)
    for block in (slice(0, m), slice(m, n)):
        pos = z[block][z[block] > 0]
        floors[block] = floor_frac * (pos.mean() if pos.size else 1.0)
    held = z <= 0
    for _ in range(max_rounds):
        free = np.flatnonzero(~held)
        z = _anchored_solve(S, c, beta, target, free=free, fixed_value=floors[held])
        new = (z <= 0) & ~held
        if not new.any():
            break
        held |= new
    return np.maximum(z, floors * (z <= 0) + z * (z > 0))


# --------------------------------------------------------------------------- the u-update


class USolver:
    """Per-mode solves of N_i u = a P^T gamma_i, N_i = y_i A_i^2 + a P^T P, A_i = K - lam_i M.

    All N_i share one sparsity pattern (that of K^2 plus P^T P, K and M sharing K's), which is
    analysed once (CHOLMOD, METIS) for every mode and iteration. Per iteration the three
    products K^2, KM + MK, M^2 are formed once (when several systems are factorized) and mapped
    onto that pattern; a mode's N_i is then a linear combination of three data arrays.

    ``method``:

    * "direct": numeric Cholesky of N_i per mode per iteration (the symbolic analysis reused),
      one triangular solve pair: the exact solution (forward error ~1e-13 here).
    * "pcg": the modes are grouped by eigenvalue (sorted; a group spans lam ratios of at most
      1 + ``group_rtol``) and each group keeps one numeric factor of N at its centre (geometric
      mean lam, mean y; a one-mode group: that mode's own N, solved exactly when new). Every
      mode is solved by PCG with its group's (possibly stale) factor as preconditioner,
      started from the N-norm best combination of its last ``n_history`` solutions (Galerkin
      on their span, which holds the extrapolation 2 u^(t-1) - u^(t-2)); all PCGs run in
      lockstep, one block mat-vec ([K; M; a P^T P] stacked: one sparse product a stage) and
      one triangular solve per group a step (several right-hand sides cost little more than
      one). PCG stops on the *error* estimate ||Q^-1 r|| / (theta ||u||) < ``rtol`` (not on
      the residual: N is ill-conditioned, ~1e6, and a residual test at 1e-8 would leave
      errors of 1e-3), theta = min(1, the smallest Ritz value of the preconditioned matrix
      from the CG coefficients), which keeps the estimate honest when a shared or stale
      factor is far from N_i. Refresh policy, per group, counted in PCG steps (a
      factorization costs ``refactor_steps`` steps of its group; measured 25-40 on 8^3 to
      16^3 grids): a group is refactorized at the next call when its PCG steps this
      iteration exceed its average per iteration since its last factorization (the
      factorization included) -- the optimal renewal rule for a cost growing with the
      factor's age, and deterministic (no timings), so reruns repeat bit for bit; a mode
      whose PCG does not converge within ``pcg_maxiter`` steps (default: max(30, 2
      ``refactor_steps``)) is solved directly and its group refactorized next time.
    * "auto": "pcg" for as many groups as their cached factors fit in ``cache_mb``, "direct"
      for the rest.
    """

    def __init__(self, model, PtP, alpha_u, method="auto", rtol=1e-8, pcg_maxiter=None,
                 cache_mb=2000.0, group_rtol: float = 1.0, n_history: int = 3,
                 refactor_steps: float = 30.0) -> None:
        self.model = model
        self.PtP = sp.csc_matrix(PtP)
        self.alpha_u = alpha_u
        self.method = method
        self.rtol = rtol
        self.pcg_maxiter = pcg_maxiter
        self.cache_mb = cache_mb
        self.group_rtol = group_rtol
        self._pattern = None
        self._symbolic = None
        self._work = None  # the one reusable numeric factor of "direct" solves
        self.groups: list[np.ndarray] | None = None
        self.factors: dict[int, dict] = {}  # group -> {"F", "iters", "cost"}
        self._stale: set[int] = set()
        self.stats = {"factorizations": 0, "pcg_iterations": 0, "solves": 0}
        self._factor_mb = None
        self._maps: dict[str, tuple] = {}
        self.n_history = n_history
        self.refactor_steps = refactor_steps
        self._history: list[np.ndarray] = []  # earlier solutions, newest first

    # -- the fixed pattern of N_i and fast mapping of products onto it
    def _build_pattern(self, K, M):
        absK, absM = abs(sp.csr_matrix(K)), abs(sp.csr_matrix(M))
        S0 = (absK @ absK + absK @ absM + absM @ absK + absM @ absM + abs(self.PtP)).tocsc()
        S0.sort_indices()
        self._pattern = S0
        n = S0.shape[0]
        col = np.repeat(np.arange(n), np.diff(S0.indptr))
        self._keys = col.astype(np.int64) * n + S0.indices
        self._ptp = self._on_pattern(self.PtP, "ptp")

    def _on_pattern(self, X, name: str) -> np.ndarray:
        """Data of X (symmetric, pattern within N's) laid out on N's pattern. The position map
        is cached per ``name`` and reused while X's structure is unchanged."""
        X = sp.csc_matrix(X)
        if not X.has_sorted_indices:
            X.sort_indices()
        cached = self._maps.get(name)
        if (cached is not None and cached[0].shape == X.indptr.shape
                and cached[1].shape == X.indices.shape and np.array_equal(cached[0], X.indptr)
                and np.array_equal(cached[1], X.indices)):
            pos = cached[2]
        else:
            n = self._pattern.shape[0]
            col = np.repeat(np.arange(n), np.diff(X.indptr))
            pos = np.searchsorted(self._keys, col.astype(np.int64) * n + X.indices)
            self._maps[name] = (X.indptr.copy(), X.indices.copy(), pos)
        out = np.zeros(len(self._keys))
        out[pos] = X.data  # positions are unique (X has no duplicate entries)
        return out

    def _products_on_pattern(self, K, M):
        KM = K @ M
        return (self._on_pattern(K @ K, "KK"), self._on_pattern(KM + KM.T, "KM"),
                self._on_pattern(M @ M, "MM"))

    def _system(self, lam, y, prods) -> sp.csc_matrix:
        S0 = self._pattern
        data = y * prods[0]
        data -= (y * lam) * prods[1]
        data += (y * lam * lam) * prods[2]
        data += self.alpha_u * self._ptp
        return sp.csc_matrix((data, S0.indices, S0.indptr), shape=S0.shape)

    def _system_of(self, K, M, lam, y) -> sp.csc_matrix:
        """N = y (K - lam M)^2 + alpha_u P^T P on the fixed pattern, from one product."""
        A = (K - lam * M).tocsr()
        data = y * self._on_pattern(A @ A, "AA")
        data += self.alpha_u * self._ptp
        S0 = self._pattern
        return sp.csc_matrix((data, S0.indices, S0.indptr), shape=S0.shape)

    def _factor(self, S, keep: bool):
        """Numeric Cholesky of S on the shared symbolic analysis; ``keep``: a new factor object
        (to cache), else the reusable work factor is overwritten. An S that is not numerically
        positive definite (a near-singular K - lam M beside a thin P^T P) gets the LU of
        :class:`Factorization`, as the z-step's systems do."""
        self.stats["factorizations"] += 1
        try:
            from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze
        except ImportError:
            return Factorization(S)
        if self._symbolic is None:
            self._symbolic = analyze(self._pattern, ordering_method="metis")
        if keep:
            F = self._symbolic.copy()
        else:
            if self._work is None:
                self._work = self._symbolic.copy()
            F = self._work
        try:
            F.cholesky_inplace(S)
        except CholmodNotPositiveDefiniteError:
            return Factorization(S)
        return F

    def _fits(self, n_more: int) -> bool:
        """Whether ``n_more`` more cached factors fit the memory budget."""
        if self.method == "direct":
            return False
        if self.method == "pcg" or self._factor_mb is None:
            return True
        return self._factor_mb * (len(self.factors) + n_more) <= self.cache_mb

    def _measure(self, F) -> None:
        if self._factor_mb is None:
            try:  # every factor shares the symbolic analysis: measure one only
                self._factor_mb = F.L().nnz * 12 / 2**20
            except Exception:
                self._factor_mb = float("inf")

    @staticmethod
    def _solver(F):
        """The preconditioner solve for a block of columns: one or two columns are solved one
        by one (CHOLMOD's one-column solve costs less than half its two-column one on small
        factors and about half on large ones), more in one multi-right-hand-side solve."""
        def solve(R):
            if R.shape[1] > 2:
                return F(R)
            return np.column_stack([F(R[:, j]) for j in range(R.shape[1])])
        return solve

    def _make_groups(self, lam):
        order = np.argsort(lam, kind="stable")
        groups, cur = [], [order[0]]
        for i in order[1:]:
            if lam[i] > lam[cur[0]] * (1.0 + self.group_rtol) or lam[cur[0]] <= 0:
                groups.append(np.array(cur))
                cur = [i]
            else:
                cur.append(i)
        groups.append(np.array(cur))
        return groups

    def solve(self, K, M, lam, y, gamma_rhs, U_prev):
        """All modes: returns U (n, k)."""
        if self._pattern is None:
            self._build_pattern(K, M)
        k = len(lam)
        if self.groups is None:
            self.groups = (self._make_groups(lam) if self.method != "direct"
                           else [np.array([i]) for i in range(k)])
        U = np.empty_like(U_prev)
        a = self.alpha_u
        PtP = self.PtP
        B = a * gamma_rhs
        solved = np.zeros(k, dtype=bool)
        prods = None

        # (re)factorize the groups without a (fresh) factor that fit the budget
        stale = [g for g in range(len(self.groups))
                 if g not in self.factors or g in self._stale]
        for g in stale:
            self.factors.pop(g, None)
        if self.method == "direct":
            stale = []
        if len(stale) > 2:
            prods = self._products_on_pattern(K, M)
        for g in stale:
            if not self._fits(1):
                break
            G = self.groups[g]
            lc = float(np.exp(np.mean(np.log(lam[G])))) if len(G) > 1 else float(lam[G[0]])
            yc = float(np.mean(y[G]))
            S = (self._system(lc, yc, prods) if prods is not None
                 else self._system_of(K, M, lc, yc))
            F = self._factor(S, keep=True)
            self._measure(F)
            self.factors[g] = {"F": F, "iters": 0, "cost": 0.0}
            self._stale.discard(g)
            if len(G) == 1:  # the mode's own N: the exact solution
                U[:, G[0]] = F(B[:, G[0]])
                solved[G[0]] = True
                self.stats["solves"] += 1

        # PCG for the other modes with a cached group factor, all in lockstep
        cols = [i for g, G in enumerate(self.groups) if g in self.factors
                for i in G if not solved[i]]
        if cols:
            cols = np.array(cols, dtype=int)
            where = {int(i): j for j, i in enumerate(cols)}
            lam_c, y_c = lam[cols], y[cols]

            n = K.shape[0]
            KMP = sp.vstack([K, M, a * PtP], format="csr")  # one sparse product per stage
            KM = KMP[:2 * n]

            def matvec(X, J):
                T = KMP @ X
                R = T[:n] - T[n:2 * n] * lam_c[J]
                S = KM @ R
                return (S[:n] - S[n:] * lam_c[J]) * y_c[J] + T[2 * n:]

            X0 = self._start(matvec, B[:, cols], U_prev[:, cols], cols)
            blocks = [(self._solver(self.factors[g]["F"]), np.array([where[int(i)] for i in G
                                                       if int(i) in where]))
                      for g, G in enumerate(self.groups) if g in self.factors]
            blocks = [(F, J) for F, J in blocks if J.size]
            maxiter = self.pcg_maxiter
            if maxiter is None:
                maxiter = int(max(30, 2 * self.refactor_steps))
            X, ok, its = _block_pcg(matvec, B[:, cols], blocks, X0, self.rtol, maxiter)
            self.stats["pcg_iterations"] += int(its.sum())
            self.stats["solves"] += int(ok.sum())
            U[:, cols[ok]] = X[:, ok]
            solved[cols[ok]] = True
            # refresh policy: refactorize a group next time when this iteration's PCG steps
            # exceed its average per iteration since the factorization (counted in steps)
            for g, G in enumerate(self.groups):
                if g not in self.factors:
                    continue
                J = [where[int(i)] for i in G if int(i) in where]
                if not J:
                    continue
                rec = self.factors[g]
                cost = float(np.max(its[J]) + 1)
                rec["iters"] += 1
                rec["cost"] += cost
                renew = self.refactor_steps + rec["cost"]
                if not np.all(ok[J]) or cost * rec["iters"] > renew:
                    self._stale.add(g)

        # the rest (no cached factor, or PCG failed): a direct solve per mode
        todo = np.flatnonzero(~solved)
        if len(todo) > 2 and prods is None:
            prods = self._products_on_pattern(K, M)
        for i in todo:
            S = (self._system(lam[i], y[i], prods) if prods is not None
                 else self._system_of(K, M, lam[i], y[i]))
            F = self._factor(S, keep=False)
            U[:, i] = F(B[:, i])
            self.stats["solves"] += 1
        self._history = [U_prev.copy()] + self._history[:self.n_history - 2]
        return U

    def _start(self, matvec, Bc, X0, cols):
        """PCG starting points: the N-norm best combination of the last ``n_history`` solutions
        of each mode (Galerkin on their span; it contains the extrapolation 2 u1 - u2)."""
        if self.n_history < 2 or not self._history:
            return X0
        V = np.stack([X0] + [h[:, cols] for h in self._history], axis=2)  # (n, c, h)
        have = np.all(np.any(V != 0, axis=0), axis=1)
        if not have.any():
            return X0
        J = np.flatnonzero(have)
        Q, _ = np.linalg.qr(V[:, J].transpose(1, 0, 2))  # (c, n, h)
        h = Q.shape[2]
        NQ = matvec(Q.transpose(1, 0, 2).reshape(-1, len(J) * h), np.repeat(J, h))
        NQ = NQ.reshape(-1, len(J), h).transpose(1, 0, 2)
        G = Q.transpose(0, 2, 1) @ NQ  # (c, h, h)
        r = np.einsum("cnh,nc->ch", Q, Bc[:, J])
        try:
            coef = np.linalg.solve(G, r[:, :, None])
        except np.linalg.LinAlgError:
            return X0
        X0 = X0.copy()
        X0[:, J] = (Q @ coef)[:, :, 0].T
        return X0


def _block_pcg(matvec, B, blocks, X0, rtol, maxiter):
    """Independent preconditioned CGs for the columns of B, run in lockstep so that each step
    costs one block mat-vec (``matvec(X[:, J], J)`` for the active columns J) and one
    multi-right-hand-side preconditioner application per block: ``blocks`` is a list of
    (solve, columns) pairs, the columns sharing that preconditioner. Column j starts at
    X0[:, j] (zero allowed) and stops when ||Q^-1 r|| < rtol theta_j ||x||, theta_j =
    min(1, smallest Ritz value of its preconditioned matrix from the CG coefficients).

    Returns (X, converged (k,) bool, iterations (k,) int); a column that does not converge
    within ``maxiter`` steps is not converged, with ``maxiter`` iterations counted.
    """
    from scipy.linalg import eigvalsh_tridiagonal

    n, k = B.shape
    X = np.array(X0, dtype=float, order="F", copy=True)
    its = np.zeros(k, dtype=int)
    ok = np.zeros(k, dtype=bool)
    R = B - matvec(X, np.arange(k))
    Z = np.empty_like(R)

    def precondition(J):
        Jset = np.zeros(k, dtype=bool)
        Jset[J] = True
        for solve, C in blocks:
            C = C[Jset[C]]
            if C.size:
                Z[:, C] = solve(np.asfortranarray(R[:, C])).reshape(n, -1)

    precondition(np.arange(k))
    alphas = [[] for _ in range(k)]
    betas = [[] for _ in range(k)]

    def theta(j):
        al, be = alphas[j], betas[j]
        if not al:
            return 1.0
        m = len(al)
        d = np.empty(m)
        e = np.empty(m - 1)
        d[0] = 1.0 / al[0]
        for t in range(1, m):
            d[t] = 1.0 / al[t] + be[t - 1] / al[t - 1]
            e[t - 1] = np.sqrt(be[t - 1]) / al[t - 1]
        lo = eigvalsh_tridiagonal(d, e, select="i", select_range=(0, 0))[0]
        return min(1.0, lo)

    def converged(J):
        zn = np.linalg.norm(Z[:, J], axis=0)
        xn = np.linalg.norm(X[:, J], axis=0)
        out = zn <= rtol * xn  # necessary; then the Ritz-corrected test
        for t in np.flatnonzero(out):
            out[t] = zn[t] <= rtol * theta(J[t]) * xn[t]
        return out

    live = np.arange(k)
    conv = converged(live)
    ok[live[conv]] = True
    active = live[~conv]
    Pd = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    for it in range(1, maxiter + 1):
        if active.size == 0:
            break
        J = active
        PJ = Pd[:, J]
        AP = matvec(PJ, J)
        alpha = rz[J] / np.einsum("ij,ij->j", PJ, AP)
        X[:, J] += alpha * PJ
        R[:, J] -= alpha * AP
        for t, j in enumerate(J):
            alphas[j].append(alpha[t])
        precondition(J)
        its[J] = it
        rz_new = np.einsum("ij,ij->j", R[:, J], Z[:, J])
        beta = rz_new / rz[J]
        for t, j in enumerate(J):
            betas[j].append(beta[t])
        conv = converged(J)
        ok[J[conv]] = True
        rest = ~conv
        Jr = J[rest]
        if Jr.size:
            Pd[:, Jr] = Z[:, Jr] + beta[rest] * Pd[:, Jr]
            rz[Jr] = rz_new[rest]
        active = Jr
    its[~ok] = maxiter
    return X, ok, its


# --------------------------------------------------------------------------- the plug-in


@dataclass
class VVTConfig:
    """Options of the paper's solver; ``None`` means "the preset's default"."""

    preset: str = field(default="sim", metadata={
        "help": "defaults of the authors for 'sim' (simulated cubes) or 'real' (real Jello)"})
    max_iter: int = field(default=100, metadata={"help": "maximum number of iterations"})
    tol: float | None = field(default=None, metadata={
        "help": "stop when rel. change of w and of v < tol (sim 1e-3, real 5e-3)"})
    alpha_u: float | None = field(default=None, metadata={
        "help": "data weight (sim: 10 if >= 10 modes else 1; real: 0.1)"})
    alpha_w: float | None = field(default=None, metadata={
        "help": "Laplacian smoothing of w, divided by the voxel count (sim/real 1e-10)"})
    alpha_v: float | None = field(default=None, metadata={
        "help": "Laplacian smoothing of v, divided by the voxel count (sim 1e-7, real 1e-8)"})
    alpha_mean: float = field(default=1.0, metadata={
        "help": "weight of the mean anchor (mean(w) - w_mean)^2 (on w only)"})
    alpha_e: float = field(default=1.0, metadata={
        "help": "eigenvalue update pulling lam toward the observed ones (0 disables)"})
    eta: float = field(default=1.0, metadata={"help": "dual ascent rate"})
    y0: float = field(default=1.0, metadata={"help": "initial dual variables"})
    w0: float | None = field(default=None, metadata={
        "help": "initial uniform w (default: the problem's prior)"})
    v0: float | None = field(default=None, metadata={
        "help": "initial uniform v (default: the problem's prior)"})
    w_mean: float | None = field(default=None, metadata={
        "help": "anchor for mean(w) (default: the problem's prior)"})
    positive: bool = field(default=False, metadata={
        "help": "enforce w, v > 0 (active-set projected z-solve)"})
    normalize_P: bool = field(default=True, metadata={
        "help": "divide P by max|P| as the authors' code does (their alpha_u assumes it)"})
    u_solver: str = field(default="auto", metadata={
        "help": "u-update: 'auto', 'direct' (factorize every mode every iteration), 'pcg'"})
    u_rtol: float = field(default=1e-6, metadata={
        "help": "PCG stop: estimated relative error of u (preconditioned residual / ||u||); "
                "1e-6 leaves w within 1e-6 of exact u-solves after 100 iterations, 1e-8 "
                "within 4e-9"})
    pcg_maxiter: int | None = field(default=None, metadata={
        "help": "PCG steps before a mode is solved directly and its group's factor refreshed "
                "(default: max(30, 2 refactor_steps))"})
    refactor_steps: float = field(default=30.0, metadata={
        "help": "cost of a factorization in PCG steps of its group, for the refresh rule "
                "(measured 25-40 on 8^3-16^3 grids; counted, not timed: reruns repeat)"})
    n_history: int = field(default=3, metadata={
        "help": "PCG starts from the best combination of this many previous solutions"})
    group_rtol: float = field(default=1.0, metadata={
        "help": "modes whose eigenvalues lie within a ratio 1 + group_rtol share one cached "
                "factor (the PCG preconditioner); 0: one factor per mode"})
    cache_mb: float = field(default=2000.0, metadata={
        "help": "memory budget (MiB) for cached per-mode factorizations ('auto')"})

    def resolved(self, n_modes: int) -> VVTConfig:
        if self.preset not in ("sim", "real"):
            raise ValueError(f"preset must be 'sim' or 'real', got {self.preset!r}")
        real = self.preset == "real"
        out = VVTConfig(**asdict(self))
        if out.tol is None:
            out.tol = 5e-3 if real else 1e-3
        if out.alpha_u is None:
            out.alpha_u = 0.1 if real else (10.0 if n_modes >= 10 else 1.0)
        if out.alpha_w is None:
            out.alpha_w = 1e-10
        if out.alpha_v is None:
            out.alpha_v = 1e-8 if real else 1e-7
        if out.u_solver not in ("auto", "direct", "pcg"):
            raise ValueError(f"u_solver must be 'auto', 'direct' or 'pcg', got {out.u_solver!r}")
        return out


class VVTSolver:
    """Visual vibration tomography (Feng et al. 2022): alternating closed-form u / z updates
    with dual ascent on the eigen-constraints; sparse and factorization-reusing."""

    name = "vvt"
    version = "1.1.0"
    description = ("The paper's solver: alternating closed-form 3-D mode / material updates "
                   "with dual ascent (Feng et al., CVPR 2022), sparse")
    Config = VVTConfig

    def __init__(self, config: VVTConfig | None = None) -> None:
        self.config = config if config is not None else VVTConfig()

    def solve(self, problem: InverseProblem, callback=None) -> Estimate:
        """The paper's alternating method: closed-form u-updates (3-D modes), the z = [w; v]
        least squares, dual ascent on the constraint weights y, until the relative change of
        w and v is below ``tol`` or ``max_iter``.

        Parameters
        ----------
        problem : the inverse problem (no truth).
        callback : called with each iteration's history record.

        Returns
        -------
        Estimate
            ``extra`` holds the final 3-D modes ``U`` and eigenvalues.
        """
        t_start = time.perf_counter()
        cfg = self.config.resolved(problem.n_modes)
        model = problem.model
        k, m = problem.n_modes, problem.n_params
        P = problem.P
        if cfg.normalize_P:
            P = P / abs(P).max()
        gamma = problem.gamma
        lam_obs = problem.eigenvalues.copy()
        lam = lam_obs.copy()
        w = np.full(m, problem.w0 if cfg.w0 is None else cfg.w0)
        v = np.full(m, problem.v0 if cfg.v0 is None else cfg.v0)
        w_mean = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        y = np.full(k, float(cfg.y0))
        PtP = (P.T @ P).tocsc()
        rhs = np.asarray(P.T @ gamma.T)  # (n, k)
        usolver = USolver(model, PtP, cfg.alpha_u, cfg.u_solver, cfg.u_rtol, cfg.pcg_maxiter,
                          cfg.cache_mb, cfg.group_rtol, cfg.n_history,
                          cfg.refactor_steps)
        zsys = ZSystem(problem, cfg.alpha_w, cfg.alpha_v, cfg.alpha_mean, w_mean)
        U = np.zeros((model.n_free, k))
        history: list[dict] = []
        converged = False
        K, M = model.K(w), model.M(v)
        for it in range(1, cfg.max_iter + 1):
            t0 = time.perf_counter()
            U = usolver.solve(K, M, lam, y, rhs, U)
            t1 = time.perf_counter()
            z, _ = zsys.solve(U, lam, y, positive=cfg.positive)
            w_new, v_new = z[:m], z[m:]
            t2 = time.perf_counter()
            dw = np.linalg.norm(w_new - w) / max(np.linalg.norm(w), 1e-300)
            dv = np.linalg.norm(v_new - v) / max(np.linalg.norm(v), 1e-300)
            w, v = w_new, v_new
            K, M = model.K(w), model.M(v)
            KU, MU = K @ U, M @ U
            if cfg.alpha_e > 0:
                num = y * np.einsum("ij,ij->j", KU, MU) + cfg.alpha_e * lam_obs
                den = y * np.einsum("ij,ij->j", MU, MU) + cfg.alpha_e
                lam = num / den
            res = np.linalg.norm(KU - MU * lam, axis=0)
            y = y + cfg.eta * res
            data = np.linalg.norm(P @ U - gamma.T, axis=0)
            rec = {
                "iteration": it,
                "time_s": time.perf_counter() - t0,
                "time_u_s": t1 - t0,
                "time_z_s": t2 - t1,
                "rel_change_w": float(dw),
                "rel_change_v": float(dv),
                "constraint": float(0.5 / k * np.sum(res**2)),
                "data": float(0.5 / k * np.sum(data**2)),
                "y_mean": float(y.mean()),
                "factorizations": usolver.stats["factorizations"],
                "pcg_iterations": usolver.stats["pcg_iterations"],
            }
            history.append(rec)
            if callback is not None:
                callback(rec)
            if not (np.all(np.isfinite(w)) and np.all(np.isfinite(v))):
                raise FloatingPointError(f"vvt diverged at iteration {it} (non-finite w or v)")
            if dw < cfg.tol and dv < cfg.tol:
                converged = True
                break
        return Estimate(
            w=w, v=v, history=history, runtime_s=time.perf_counter() - t_start,
            config=asdict(cfg), solver=self.name, version=self.version, converged=converged,
            extra={"U": U, "eigenvalues": lam, "dual": y},
        )
