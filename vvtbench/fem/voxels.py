"""Element -> voxel maps: the grid on which material unknowns live.

>>> from vvtbench.fem.mesh import box_mesh
>>> m = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
>>> vm = VoxelMap.from_mesh(m, (2, 2, 2))
>>> vm.n_params, np.bincount(vm.element_param).tolist()
(8, [8, 8, 8, 8, 8, 8, 8, 8])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import Mesh


@dataclass(frozen=True)
class VoxelGrid:
    """Axis-aligned grid: ``shape`` voxels spanning ``origin`` to ``origin + size``."""

    origin: tuple[float, float, float]
    size: tuple[float, float, float]
    shape: tuple[int, int, int]

    @property
    def spacing(self) -> np.ndarray:
        return np.asarray(self.size) / np.asarray(self.shape)

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """Flat (C-order, index = (i * ny + j) * nz + k) voxel index of each point."""
        ijk = np.floor((np.asarray(points) - self.origin) / self.spacing).astype(np.int64)
        ijk = np.clip(ijk, 0, np.asarray(self.shape) - 1)
        return np.ravel_multi_index(ijk.T, self.shape)

    def centers(self) -> np.ndarray:
        """(n_voxels, 3) voxel centres in flat order."""
        axes = [o + (np.arange(n) + 0.5) * h for o, n, h in zip(self.origin, self.shape,
                                                               self.spacing, strict=True)]
        g = np.meshgrid(*axes, indexing="ij")
        return np.column_stack([a.ravel() for a in g])

    def to_dict(self) -> dict:
        return {"origin": list(self.origin), "size": list(self.size), "shape": list(self.shape)}


@dataclass(frozen=True)
class VoxelMap:
    """Which voxel each element belongs to (by centroid), and which voxels hold elements.

    Attributes
    ----------
    grid : the voxel grid.
    element_voxel : (n_elements,) flat voxel index of each element.
    active : (n_params,) sorted flat indices of voxels that contain at least one element.
    element_param : (n_elements,) index into ``active`` (the unknown each element uses).
    """

    grid: VoxelGrid
    element_voxel: np.ndarray
    active: np.ndarray
    element_param: np.ndarray

    @property
    def n_params(self) -> int:
        return len(self.active)

    @classmethod
    def from_mesh(cls, mesh: Mesh, shape: tuple[int, ...], padding: float = 0.0) -> VoxelMap:
        """Voxelize the mesh's bounding box into ``shape`` (2-D shapes for membranes)."""
        lo, hi = mesh.bounds
        shape3 = tuple(int(s) for s in shape) + (1,) * (3 - len(shape))
        extent = hi - lo
        flat = extent <= 1e-12 * max(extent.max(), 1e-300)
        extent = np.where(flat, 1.0, extent) * (1 + 2 * padding)
        origin = np.where(flat, lo - 0.5, lo - padding * (hi - lo))
        grid = VoxelGrid(tuple(origin.tolist()), tuple(extent.tolist()), shape3)
        return cls.from_grid(mesh, grid)

    @classmethod
    def from_grid(cls, mesh: Mesh, grid: VoxelGrid) -> VoxelMap:
        voxel = grid.voxel_of(mesh.centroids)
        active, param = np.unique(voxel, return_inverse=True)
        return cls(grid, voxel, active, param.ravel())

    @classmethod
    def per_element(cls, mesh: Mesh) -> VoxelMap:
        """Every element its own unknown (the simulation's map)."""
        n = mesh.n_elements
        lo, hi = mesh.bounds
        grid = VoxelGrid(tuple(lo.tolist()), tuple((hi - lo).tolist()), (n, 1, 1))
        idx = np.arange(n)
        return cls(grid, idx, idx, idx)

    def to_grid(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Per-parameter ``values`` (n_params,) as a ``grid.shape`` array; empty voxels ``fill``."""
        out = np.full(self.grid.n_voxels, fill, dtype=float)
        out[self.active] = values
        return out.reshape(self.grid.shape)

    def average(self, element_values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Volume-weighted mean of per-element values in each active voxel: (n_params,)."""
        w = np.ones(len(self.element_param)) if weights is None else np.asarray(weights)
        num = np.bincount(self.element_param, w * element_values, minlength=self.n_params)
        den = np.bincount(self.element_param, w, minlength=self.n_params)
        return num / den
