"""ParametricModel: K(w) = sum_e w_e K_e and M(v) = sum_e v_e M_e as one sparse mat-vec each.

Each parameter (voxel) e owns the unit-E (unit tension) stiffness and unit-density (unit areal
density) mass of its elements. The global matrices over the free DOFs share one CSR pattern,
and a sparse map ``A`` takes parameters to its nonzeros: ``K.data = A_K @ w``.

>>> from vvtbench.fem.mesh import box_mesh
>>> mesh = box_mesh((2, 2, 2), (1.0, 1.0, 1.0))
>>> model = ParametricModel(mesh, fixed_nodes=mesh.node_sets["bottom"])
>>> model.n_free, model.n_params
(54, 8)
>>> K = model.K(np.full(8, 2.0)); bool(abs(K - K.T).max() < 1e-12)
True
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .elements import unit_mass, unit_stiffness
from .mesh import Mesh
from .voxels import VoxelMap


class ParametricModel:
    """Stiffness and mass of a mesh as linear functions of per-parameter material values.

    Parameters
    ----------
    mesh : the mesh.
    voxel_map : element -> parameter map; default: one parameter per element.
    nu : Poisson's ratio, scalar or per element (solids only).
    fixed_nodes : nodes whose every DOF is held at zero (removed from the system).
    """

    def __init__(
        self,
        mesh: Mesh,
        voxel_map: VoxelMap | None = None,
        nu: float | np.ndarray = 0.3,
        fixed_nodes: np.ndarray | None = None,
    ) -> None:
        self.mesh = mesh
        self.voxel_map = voxel_map if voxel_map is not None else VoxelMap.per_element(mesh)
        if len(self.voxel_map.element_param) != mesh.n_elements:
            raise ValueError(
                f"voxel map covers {len(self.voxel_map.element_param)} elements, "
                f"mesh has {mesh.n_elements}"
            )
        el = mesh.element_type
        coords = mesh.cell_coords
        self.Ke = unit_stiffness(el, coords, nu)
        self.Me = unit_mass(el, coords)
        d = el.dofs_per_node
        self.element_dofs = (mesh.cells[:, :, None] * d + np.arange(d)).reshape(len(mesh.cells), -1)
        fixed_nodes = np.zeros(0, np.int64) if fixed_nodes is None else np.asarray(fixed_nodes)
        self.nu = nu
        self.fixed_nodes = fixed_nodes.astype(np.int64)
        self.fixed_dofs = np.unique(mesh.dofs_of(fixed_nodes)) if fixed_nodes.size else fixed_nodes
        is_free = np.ones(mesh.n_dofs, dtype=bool)
        is_free[self.fixed_dofs] = False
        self.free_dofs = np.flatnonzero(is_free)
        self.free_index = np.full(mesh.n_dofs, -1, dtype=np.int64)
        self.free_index[self.free_dofs] = np.arange(len(self.free_dofs))
        self._build_pattern()

    @property
    def n_free(self) -> int:
        return len(self.free_dofs)

    @property
    def n_params(self) -> int:
        return self.voxel_map.n_params

    def _build_pattern(self) -> None:
        ne, nd = self.element_dofs.shape
        loc = self.free_index[self.element_dofs]
        rows = np.broadcast_to(loc[:, :, None], (ne, nd, nd))
        cols = np.broadcast_to(loc[:, None, :], (ne, nd, nd))
        keep = (rows >= 0) & (cols >= 0)
        n = self.n_free
        keys = rows[keep] * n + cols[keep]
        unique_keys, pos = np.unique(keys, return_inverse=True)
        self._rows = unique_keys // n
        self._indices = (unique_keys % n).astype(np.int32)
        self._indptr = np.searchsorted(self._rows, np.arange(n + 1)).astype(np.int32)
        param = np.broadcast_to(self.voxel_map.element_param[:, None, None], (ne, nd, nd))[keep]
        shape = (len(unique_keys), self.n_params)
        self.A_K = sp.csr_matrix((self.Ke[keep], (pos, param)), shape=shape)
        self.A_M = sp.csr_matrix((self.Me[keep], (pos, param)), shape=shape)

    def _matrix(self, data: np.ndarray) -> sp.csr_matrix:
        n = self.n_free
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))

    def _check(self, values: np.ndarray, what: str) -> np.ndarray:
        values = np.asarray(values, dtype=float)
        if values.shape == ():
            return np.full(self.n_params, float(values))
        if values.shape != (self.n_params,):
            raise ValueError(f"{what} needs shape ({self.n_params},), got {values.shape}")
        return values

    def K(self, w: np.ndarray | float) -> sp.csr_matrix:
        """Stiffness over the free DOFs for per-parameter Young's modulus (tension) ``w``."""
        return self._matrix(self.A_K @ self._check(w, "w"))

    def M(self, v: np.ndarray | float) -> sp.csr_matrix:
        """Mass over the free DOFs for per-parameter density (areal density) ``v``."""
        return self._matrix(self.A_M @ self._check(v, "v"))

    def _columns(self, unit: np.ndarray, u: np.ndarray) -> sp.csr_matrix:
        full = np.zeros(self.mesh.n_dofs)
        full[self.free_dofs] = u
        y = np.einsum("eij,ej->ei", unit, full[self.element_dofs])
        rows = self.free_index[self.element_dofs]
        keep = rows >= 0
        cols = np.broadcast_to(self.voxel_map.element_param[:, None], rows.shape)
        return sp.csr_matrix(
            (y[keep], (rows[keep], cols[keep])), shape=(self.n_free, self.n_params)
        )

    def stiffness_columns(self, u: np.ndarray) -> sp.csr_matrix:
        """(n_free, n_params) matrix G with G[:, e] = K_e u, so that K(w) u = G w."""
        return self._columns(self.Ke, self._vector(u))

    def mass_columns(self, u: np.ndarray) -> sp.csr_matrix:
        """(n_free, n_params) matrix H with H[:, e] = M_e u, so that M(v) u = H v."""
        return self._columns(self.Me, self._vector(u))

    def _vector(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        if u.shape != (self.n_free,):
            raise ValueError(f"u needs shape ({self.n_free},) (free DOFs), got {u.shape}")
        return u

    def expand(self, u: np.ndarray) -> np.ndarray:
        """Free-DOF vector(s) (n_free, ...) -> all DOFs (n_dofs, ...), fixed DOFs zero."""
        u = np.asarray(u)
        out = np.zeros((self.mesh.n_dofs,) + u.shape[1:], dtype=u.dtype)
        out[self.free_dofs] = u
        return out

    def restrict(self, u: np.ndarray) -> np.ndarray:
        """All-DOF vector(s) -> the free DOFs."""
        return np.asarray(u)[self.free_dofs]

    def nodal(self, u: np.ndarray) -> np.ndarray:
        """Free-DOF vector(s) (n_free, k) -> per-node displacements (k, n_nodes, dofs_per_node)."""
        full = self.expand(np.asarray(u).reshape(self.n_free, -1))
        return np.moveaxis(full.reshape(self.mesh.n_nodes, self.mesh.dofs_per_node, -1), -1, 0)
