"""Volume-weighted voxel overlap (vvtbench.fem.voxels.overlap_matrix)."""

from __future__ import annotations

import numpy as np

from vvtbench.fem.elements import element_volumes, get_element
from vvtbench.fem.mesh import box_mesh, drum_mesh
from vvtbench.fem.voxels import VoxelGrid, VoxelMap, overlap_matrix, voxel_average

SIZE = (0.05, 0.05, 0.05)


def _box_grid(shape=(8, 8, 8)) -> VoxelGrid:
    return VoxelGrid((0.0, 0.0, 0.0), SIZE, shape)


def _hex_to_tets(mesh) -> np.ndarray:
    """Each hex8 of a box mesh split into 6 tets (Kuhn split of its corner cube)."""
    c = mesh.cells  # lexicographic corners: index = i + 2 j + 4 k
    split = [[0, a, a + b, 7] for a in (1, 2, 4) for b in (1, 2, 4) if a != b]
    X = mesh.points[c[:, split].reshape(-1, 4)]
    neg = np.linalg.det(X[:, 1:] - X[:, :1]) < 0
    X[neg] = X[neg][:, [0, 2, 1, 3]]  # positive orientation
    return X


def test_hex_overlap_is_exact():
    mesh = box_mesh((6, 6, 6), SIZE)
    grid = _box_grid()
    A = overlap_matrix(mesh, grid)
    assert A.shape == (512, mesh.n_elements)
    vols = element_volumes(mesh.element_type, mesh.cell_coords)
    np.testing.assert_allclose(np.asarray(A.sum(axis=0)).ravel(), vols, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), np.prod(grid.spacing),
                               rtol=1e-12)  # the body fills the grid
    # 6^3 mesh under an 8^3 grid: no NaN voxel (centroid voxelization leaves 296 empty)
    values = np.linspace(1.0, 2.0, mesh.n_elements)
    avg = voxel_average(A, values)
    assert np.isfinite(avg).all()
    centroid = VoxelMap.from_mesh(mesh, (8, 8, 8))
    assert centroid.n_params == 216  # 512 - 296
    # a grid larger than the body: voxels outside are NaN, the rest hold the body's volume
    big = VoxelGrid((-0.01, 0.0, 0.0), (0.07, 0.05, 0.05), (7, 5, 5))
    B = overlap_matrix(mesh, big)
    col = np.asarray(B.sum(axis=1)).ravel().reshape(7, 5, 5)
    assert np.all(col[0] == 0) and np.all(col[-1] == 0)
    np.testing.assert_allclose(col[1:-1], 1e-3 ** 3 * 1e3, rtol=1e-12)
    assert np.isnan(voxel_average(B, values).reshape(7, 5, 5)[0]).all()
    # hex27 boxes are axis-aligned too
    m27 = box_mesh((3, 3, 3), SIZE, order=2)
    C = overlap_matrix(m27, grid)
    np.testing.assert_allclose(np.asarray(C.sum(axis=1)).ravel(), np.prod(grid.spacing),
                               rtol=1e-12)


def test_tet_overlap_matches_the_hex_answer():
    mesh = box_mesh((6, 6, 6), SIZE)
    grid = _box_grid()
    exact = overlap_matrix(mesh, grid)
    tets = _hex_to_tets(mesh)
    T = overlap_matrix(tets, grid, element="tet4")
    vt = element_volumes(get_element("tet4"), tets)
    np.testing.assert_allclose(np.asarray(T.sum(axis=0)).ravel(), vt, rtol=1e-12)
    # per voxel (row) and per (voxel, hex) pair, summing the 6 tets of each hex
    parent = np.repeat(np.arange(mesh.n_elements), 6)
    import scipy.sparse as sp

    agg = T @ sp.csr_matrix((np.ones(len(parent)), (np.arange(len(parent)), parent)))
    rows = np.asarray(T.sum(axis=1)).ravel()
    np.testing.assert_allclose(rows, np.asarray(exact.sum(axis=1)).ravel(), rtol=1e-9)
    voxel = np.prod(grid.spacing)
    assert np.abs(agg - exact).max() < 1e-9 * voxel


def test_tri3_drum_overlap_matches_exact_areas():
    mesh = drum_mesh("square", 0.1, 12)
    vm = VoxelMap.from_mesh(mesh, (10, 10))
    A = overlap_matrix(mesh, vm.grid)
    areas = element_volumes(mesh.element_type, mesh.cell_coords)
    np.testing.assert_allclose(np.asarray(A.sum(axis=0)).ravel(), areas, rtol=1e-12)
    cell = np.prod(vm.grid.spacing[:2])
    np.testing.assert_allclose(np.asarray(A.sum(axis=1)).ravel(), cell, rtol=1e-9)
    assert np.isfinite(voxel_average(A, np.ones(mesh.n_elements))).all()


def test_scale_scales_volumes():
    mesh = box_mesh((2, 2, 2), SIZE)
    grid = VoxelGrid((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), (2, 2, 2))
    A = overlap_matrix(mesh, grid, scale=2.0)
    np.testing.assert_allclose(A.sum(), 0.1**3, rtol=1e-12)


def test_warped_hexes_and_tet10_are_cut_exactly():
    """A sheared box (not axis-aligned) is split into tets and cut: columns and rows exact."""
    mesh = box_mesh((3, 3, 3), SIZE)
    shear = mesh.cell_coords.copy()
    shear[..., 0] += 0.3 * shear[..., 2]  # parallelepipeds, planar faces
    grid = VoxelGrid((0.0, 0.0, 0.0), (0.05 + 0.015, 0.05, 0.05), (5, 4, 4))
    A = overlap_matrix(shear, grid, element="hex8")
    np.testing.assert_allclose(np.asarray(A.sum(axis=0)).ravel(), (0.05 / 3) ** 3, rtol=1e-9)
    # rows: slice volume of the sheared body in each voxel column along z, checked by sum
    np.testing.assert_allclose(A.sum(), 0.05**3, rtol=1e-12)
    m10 = box_mesh((2, 2, 2), SIZE)  # tet10 from the hex corners' tets, mid-side nodes
    from vvtbench.fem.elements import TET10_EDGES

    tets = _hex_to_tets(m10)
    mids = (tets[:, TET10_EDGES[:, 0]] + tets[:, TET10_EDGES[:, 1]]) / 2
    B = overlap_matrix(np.concatenate([tets, mids], axis=1), _box_grid((3, 3, 3)),
                       element="tet10")
    np.testing.assert_allclose(np.asarray(B.sum(axis=1)).ravel(), (0.05 / 3) ** 3, rtol=1e-9)
