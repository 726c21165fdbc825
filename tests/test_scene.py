"""Scene files: shipped scenes load, bad files give clear errors, scenes simulate."""

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.scene import SCENES_DIR, Defect, SceneError, load_scene, parse_scene
from vvtbench.simulate import (
    build_mesh,
    build_model,
    fixed_nodes,
    load_nodes,
    material_fields,
    simulate,
)

SHIPPED = sorted(SCENES_DIR.glob("*.toml"))


def test_the_paper_scenes_ship():
    names = {p.stem for p in SHIPPED}
    for needed in ["jello_cube_homogeneous", "jello_cube_defect_top", "jello_cube_defect_bottom",
                   "jello_cube_damped_top_front", "jello_cube_damped_top_back", "bunny_defect",
                   "drum_homogeneous", "drum_gel_bar", "drum_gel_circle", "drum_acrylic_circle",
                   "drum_two_acrylic_circles"]:
        assert needed in names
    assert sum(n.startswith("jello_cube_defect") for n in names) >= 4


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_scene_is_valid(path):
    scene = load_scene(path)
    assert scene.name == path.stem
    if scene.geometry.kind != "mesh":
        mesh = build_mesh(scene)
        fields = material_fields(scene, mesh)
        n_defect = int(np.sum(fields.density != fields.density[0])) + int(
            np.sum(fields.density == fields.density[0]) < mesh.n_elements)
        assert (n_defect > 0) == bool(scene.material.defects)


def test_paper_jello_and_clay_values():
    scene = load_scene("jello_cube_damped_top_front")
    assert (scene.material.E, scene.material.rho, scene.material.nu) == (9000.0, 1270.0, 0.3)
    assert scene.material.defects[0].E == 5e6 and scene.material.defects[0].rho == 7620.0
    assert scene.damping.pairs == [(12.5, 0.01749), (15.5, 0.01999)]
    drum = load_scene("drum_gel_bar")
    sig = drum.excitation.signal
    assert (sig.f0, sig.f1, sig.duration) == (50.0, 1000.0, 3.5)


def _write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, expected", [
    ('name = "x"\n[geometry]\nkind = "boxx"\n', ["geometry", "'box', 'mesh', 'drum'"]),
    ('name = "x"\n[geometry]\nkind = "box"\ncolour = 1\n', ["geometry.colour", "cells"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[material]\nE = -5\n',
     ["material.E", "got -5; allowed: a finite number > 0"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[damping]\npairs = [[1.0, 0.1]]\n',
     ["damping", "exactly two"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[excitation]\nkind = "pluck"\n',
     ["excitation", "needs 'at'"]),
    ('name = "x"\n[geometry]\nkind = "drum"\n[[material.defects]]\nshape = "sphere"\n'
     'center = [0, 0, 0]\nsize = [0.01]\nE = 5.0\n', ["defects[0]", "tension"]),
    ('name = "x"\n[geometry\n', ["not valid TOML"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[excitation]\nkind = "kick"\nat = [0, 0, 0]\n',
     ["excitation.kind", "'pluck'"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[damping]\npairs = [[12.5, 0.1], [15.5, 0.001]]\n',
     ["key 'damping.pairs'", "negative Rayleigh", "zeta at 15.5 Hz from 0.08065 to 0.124"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[damping]\npairs = [[10.0, 0.01], [50.0, 0.2]]\n',
     ["key 'damping.pairs'", "alpha=-", "from 0.002 to 0.05"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[[material.defects]]\nshape = "cylinder"\n'
     'center = [0, 0, 0]\nsize = [0.01]\nE = 5.0\n',
     ["key 'material.defects[0].size'", "cylinder defect needs 2 value(s), got 1",
      "sphere 1 (radius)"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[boundary.node_sets.clamp]\nbox_min = [0, 0, 0]\n',
     ["key 'boundary.node_sets.clamp'", "missing box_max"]),
])
def test_bad_scene_gives_clear_error(tmp_path, text, expected):
    path = _write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in expected:
        assert fragment in message


@pytest.mark.parametrize("signal, key", [
    ('kind = "chirp"\nf0 = -1.0\n', "excitation.signal.f0"),
    ('kind = "impulse"\nwidht = 0.01\n', "excitation.signal.widht"),
    ('f0 = 10.0\n', "excitation.signal.kind"),
])
def test_error_keys_have_no_union_tag(tmp_path, signal, key):
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "box"\n[excitation]\nkind = "force"\n'
                            f'at = [0, 0, 0]\n[excitation.signal]\n{signal}')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert f"key '{key}'" in message
    assert ".chirp." not in message and ".impulse." not in message


def test_error_key_of_a_geometry_field_lists_that_kinds_keys(tmp_path):
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "drum"\ncells = 1\norder = 2\n')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert "key 'geometry.cells'" in message and "key 'geometry.order'" in message
    assert "allowed keys here: kind, shape, size, cells" in message and ".drum." not in message


def _box_scene(tmp_path, extra, cells=2):
    return load_scene(_write(
        tmp_path, f'name = "x"\n[geometry]\nkind = "box"\ncells = [{cells}, {cells}, {cells}]\n'
        + extra))


def test_named_node_sets_by_box_and_indices_fix_those_nodes(tmp_path):
    scene = _box_scene(tmp_path, '[boundary]\nfixed = ["floor", "pin"]\n'
                                 '[boundary.node_sets.floor]\nbox_min = [-1, -1, -1e-6]\n'
                                 'box_max = [1, 1, 1e-6]\n'
                                 '[boundary.node_sets.pin]\nindices = [26, 13]\n')
    mesh = build_mesh(scene)
    np.testing.assert_array_equal(mesh.node_sets["floor"], mesh.node_sets["bottom"])
    np.testing.assert_array_equal(mesh.node_sets["pin"], [13, 26])
    fixed = fixed_nodes(scene, mesh)
    np.testing.assert_array_equal(fixed, np.union1d(mesh.node_sets["bottom"], [13, 26]))
    model = build_model(scene, mesh, material_fields(scene, mesh))
    assert model.n_free == 3 * (27 - 9 - 2)
    np.testing.assert_array_equal(model.fixed_dofs, mesh.dofs_of(fixed))


def test_node_set_index_out_of_range_names_file_and_key(tmp_path):
    scene = _box_scene(tmp_path, '[boundary]\nfixed = ["pin"]\n'
                                 '[boundary.node_sets.pin]\nindices = [3, 27]\n')
    with pytest.raises(SceneError) as info:
        build_mesh(scene)
    message = str(info.value)
    assert scene.source in message and "boundary.node_sets.pin.indices" in message
    assert "27 out of range" in message and "27 nodes" in message


@pytest.mark.parametrize("radius, direction", [(0.0, [1.0, 0.0, 1.0]), (0.02, [0.0, -2.0, 1.0])])
def test_pluck_moves_the_loaded_nodes_by_the_displacement_on_average(tmp_path, radius, direction):
    scene = _box_scene(tmp_path, f'[excitation]\nkind = "pluck"\nat = [0.05, 0.0, 0.05]\n'
                                 f"radius = {radius}\ndirection = {direction}\n"
                                 'displacement = 0.002\n[simulation]\nn_modes = 4\n'
                                 'fps = 1000.0\nduration = 0.002\nmethod = "newmark"\n', cells=3)
    result = simulate(scene)
    nodes = load_nodes(scene, result.mesh)
    assert len(nodes) == (1 if radius == 0 else 4)
    d = np.asarray(direction) / np.linalg.norm(direction)
    at_nodes = np.searchsorted(result.surface_nodes, nodes)
    np.testing.assert_array_equal(result.surface_nodes[at_nodes], nodes)
    u0 = result.displacements[0, at_nodes].astype(float)
    assert np.mean(u0 @ d) == pytest.approx(0.002, rel=1e-5)


def test_velocity_excitation_starts_the_loaded_node_at_that_velocity(tmp_path):
    scene = _box_scene(tmp_path, '[excitation]\nkind = "velocity"\nat = [0.05, 0.05, 0.05]\n'
                                 "velocity = [0.01, 0.0, -0.02]\n"
                                 "[simulation]\nn_modes = 54\nfps = 1e6\nduration = 3e-6\n")
    result = simulate(scene)
    assert result.model.n_free == 54
    u = result.displacements.astype(float)
    np.testing.assert_array_equal(u[0], 0.0)
    velocity = u[1] * scene.simulation.fps
    corner = np.flatnonzero(result.surface_nodes == load_nodes(scene, result.mesh)[0])[0]
    np.testing.assert_allclose(velocity[corner], [0.01, 0.0, -0.02], rtol=0, atol=1e-5)
    others = np.delete(velocity, corner, axis=0)
    assert np.abs(others).max() < 1e-3 * 0.02


def test_defect_contains_for_sphere_cylinder_and_ellipsoid():
    pts = np.array([[0.0, 0.0, 0.0], [0.009, 0.0, 0.0], [0.011, 0.0, 0.0], [0.0, 0.0, 0.019],
                    [0.0, 0.006, 0.006], [0.0, 0.0, 0.021]])
    sphere = Defect(shape="sphere", center=(0.0, 0.0, 0.0), size=(0.01,), E=1.0)
    assert sphere.contains(pts).tolist() == [True, True, False, False, True, False]
    cylinder = Defect(shape="cylinder", center=(0.0, 0.0, 0.0), size=(0.01, 0.04), axis="x",
                      E=1.0)
    along_x = [[0.019, 0.0, 0.0], [-0.021, 0.0, 0.0], [0.019, 0.007, 0.007], [0.0, 0.0, 0.011]]
    assert cylinder.contains(pts).tolist() == [True, True, True, False, True, False]
    assert cylinder.contains(along_x).tolist() == [True, False, True, False]
    ellipsoid = Defect(shape="ellipsoid", center=(0.0, 0.0, 0.0), size=(0.01, 0.02, 0.02),
                       E=1.0)
    assert ellipsoid.contains(pts).tolist() == [True, True, False, True, True, False]
    shifted = Defect(shape="sphere", center=(1.0, 2.0, 3.0), size=(0.5,), E=1.0)
    assert shifted.contains([[1.0, 2.0, 3.4], [1.0, 2.0, 2.4]]).tolist() == [True, False]


def test_voxel_map_from_a_tet_mesh():
    from vvtbench.fem.mesh import box_mesh, tets_to_mesh
    from vvtbench.fem.voxels import VoxelMap

    hexes = box_mesh((4, 4, 4), (0.04, 0.04, 0.04))
    kuhn = [[0, a, a + b, 7] for a in (1, 2, 4) for b in (1, 2, 4) if a != b]
    mesh = tets_to_mesh(hexes.points, hexes.cells[:, kuhn].reshape(-1, 4))
    vm = VoxelMap.from_mesh(mesh, (2, 2, 2))
    assert mesh.element == "tet4" and mesh.n_elements == 6 * 64
    assert vm.n_params == 8 and vm.grid.shape == (2, 2, 2)
    np.testing.assert_allclose(vm.grid.spacing, [0.02, 0.02, 0.02])
    ijk = np.floor(mesh.centroids / 0.02).astype(int)
    np.testing.assert_array_equal(vm.element_voxel, (ijk[:, 0] * 2 + ijk[:, 1]) * 2 + ijk[:, 2])
    np.testing.assert_array_equal(vm.active[vm.element_param], vm.element_voxel)
    np.testing.assert_array_equal(np.bincount(vm.element_param), np.full(8, 48))
    np.testing.assert_allclose(vm.average(np.full(mesh.n_elements, 3.0)), 3.0)


def test_voxel_map_from_a_membrane_mesh():
    from vvtbench.fem.mesh import drum_mesh
    from vvtbench.fem.voxels import VoxelMap

    mesh = drum_mesh("circle", 0.1, 6)
    vm = VoxelMap.from_mesh(mesh, (8, 8))
    assert vm.grid.shape == (8, 8, 1)
    lo = mesh.bounds[0]
    ij = np.clip(np.floor((mesh.centroids[:, :2] - lo[:2]) / 0.0125).astype(int), 0, 7)
    np.testing.assert_array_equal(vm.element_voxel, ij[:, 0] * 8 + ij[:, 1])
    grid = vm.to_grid(np.ones(vm.n_params))[:, :, 0]
    assert np.isnan(grid[[0, 0, 7, 7], [0, 7, 0, 7]]).all()
    assert vm.n_params == np.isfinite(grid).sum() < 64
    assert np.isfinite(grid[2:6, 2:6]).all()


def test_missing_mesh_file_names_file_and_key(tmp_path):
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "mesh"\npath = "nope.obj"\n')
    scene = load_scene(path)
    with pytest.raises(SceneError) as info:
        simulate(scene, transient=False)
    message = str(info.value)
    assert str(path) in message and "key 'geometry.path'" in message
    assert str(tmp_path / "nope.obj") in message and "not found" in message


def test_unknown_node_set_and_cli_exit_code(tmp_path, capsys):
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "box"\ncells = [2, 2, 2]\n'
                            '[boundary]\nfixed = ["floor"]\n')
    assert main(["simulate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "boundary.fixed" in err and "bottom" in err and "Traceback" not in err


def test_field_file_errors_name_file_and_key(tmp_path):
    np.savez(tmp_path / "fields.npz", E=np.full(7, 9000.0), rho=np.full(8, 1270.0))
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "box"\ncells = [2, 2, 2]\n'
                            '[material]\nfield_file = "fields.npz"\n')
    scene = load_scene(path)
    with pytest.raises(SceneError, match=r"fields.npz.*array 'E' has 7 values; the mesh has 8"):
        material_fields(scene, build_mesh(scene))


def test_field_file_sets_per_element_values(tmp_path):
    e = np.linspace(1e3, 2e4, 8)
    np.savez(tmp_path / "fields.npz", E=e, rho=np.full(8, 1000.0))
    path = _write(tmp_path, 'name = "x"\n[geometry]\nkind = "box"\ncells = [2, 2, 2]\n'
                            '[material]\nfield_file = "fields.npz"\n')
    scene = load_scene(path)
    np.testing.assert_array_equal(material_fields(scene, build_mesh(scene)).stiffness, e)


def test_defect_shapes_select_the_right_elements():
    scene = parse_scene({
        "name": "d", "geometry": {"kind": "box", "cells": [10, 10, 10]},
        "material": {"defects": [{"shape": "box", "center": [0.03, 0.02, 0.035],
                                  "size": [0.02, 0.02, 0.01], "E": 5e6, "rho": 7620.0}]},
    })
    fields = material_fields(scene, build_mesh(scene))
    assert np.sum(fields.stiffness == 5e6) == 4 * 4 * 2


def test_default_cli_prints_frequency_table(capsys):
    assert main(["simulate", "jello_cube_homogeneous", "--modes", "6"]) == 0
    out = capsys.readouterr().out
    assert "f (Hz)" in out and "zeta" in out


def test_drum_chirp_transient_runs_and_moves_out_of_plane():
    scene = load_scene("drum_homogeneous")
    scene = scene.model_copy(update={
        "geometry": scene.geometry.model_copy(update={"cells": 12}),
        "simulation": scene.simulation.model_copy(update={"n_modes": 20, "duration": 0.2}),
    })
    result = simulate(scene)
    assert result.displacements.shape == (600, len(result.surface_nodes), 1)
    assert np.abs(result.displacements).max() > 0
    rim = np.isin(result.surface_nodes, result.mesh.node_sets["rim"])
    assert np.abs(result.displacements[:, rim]).max() == 0


def test_bunny_tetrahedralizes_and_vibrates():
    scene = load_scene("bunny_defect")
    scene = scene.model_copy(update={
        "geometry": scene.geometry.model_copy(update={"edge_length_fac": 0.1, "epsilon": 0.01}),
        "simulation": scene.simulation.model_copy(update={"n_modes": 6}),
    })
    result = simulate(scene, transient=False)
    assert result.mesh.element == "tet4" and result.mesh.n_elements > 500
    assert len(result.mesh.node_sets["bottom"]) >= 3
    assert np.all(result.frequencies_hz > 0.5)
    assert np.sum(result.fields.stiffness == 5e6) > 0


def test_tetrahedralization_is_cached_so_meshes_repeat(tmp_path, monkeypatch):
    from vvtbench.fem.mesh import load_surface, tet_mesh

    monkeypatch.setenv("VVTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    v, f = load_surface("bunny", "y", 0.08, 500)
    first = tet_mesh(v, f, edge_length_fac=0.15, epsilon=0.02)
    assert len(list((tmp_path / "cache" / "meshes").glob("tetwild-*.npz"))) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache"]
    second = tet_mesh(v, f, edge_length_fac=0.15, epsilon=0.02)
    np.testing.assert_array_equal(first.cells, second.cells)
    np.testing.assert_array_equal(first.points, second.points)
