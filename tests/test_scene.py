"""Scene files: shipped scenes load, bad files give clear errors, scenes simulate."""

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.scene.families import draw
from vvtbench.scene.scene import SCENES_DIR, Defect, SceneError, load_scene, parse_scene
from vvtbench.simulation.simulate import (
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
     ["material.E", "got -5; allowed: a finite number >= 0.001"]),
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


@pytest.mark.parametrize("scene_of", [lambda: load_scene("bunny_defect"),
                                      lambda: draw("bunny_defects", "test", 5)],
                         ids=["paper", "family"])
def test_shipped_bunny_mesh_is_used_on_every_machine(tmp_path, monkeypatch, scene_of):
    """pytetwild's output differs from run to run, so the shipped scenes' bunny mesh is
    shipped (scenes/meshes): an empty cache and no mesher give the same mesh."""
    import pytetwild

    from vvtbench.fem.mesh import shipped_mesh_dir
    from vvtbench.simulation.simulate import build_mesh

    monkeypatch.setenv("VVTBENCH_CACHE", str(tmp_path / "cache"))

    def no_mesher(*a, **k):
        raise AssertionError("pytetwild called for a shipped mesh")

    monkeypatch.setattr(pytetwild, "tetrahedralize", no_mesher)
    mesh = build_mesh(scene_of())
    (shipped,) = shipped_mesh_dir().glob("tetwild-*.npz")
    with np.load(shipped) as z:
        np.testing.assert_array_equal(mesh.points, z["points"])
        assert mesh.n_elements == len(z["tets"])
    assert not (tmp_path / "cache").exists()


# ---------------------------------------------------------------- validation
_BOX = ('name = "x"\n[geometry]\nkind = "box"\ncells = [3, 3, 3]\n'
        '[excitation]\nkind = "pluck"\nat = [0.05, 0.0, 0.05]\n'
        '[simulation]\nn_modes = 4\nfps = 1000.0\nduration = 0.01\n')
_DRUM = ('name = "x"\n[geometry]\nkind = "drum"\ncells = 6\n'
         '[excitation]\nkind = "force"\nat = [0.05, 0.05, 0.0]\nradius = 0.02\n'
         'direction = [0.0, 0.0, 1.0]\n[simulation]\nn_modes = 4\nfps = 1000.0\n'
         'duration = 0.01\n')


def _one_line_error(message, path, key):
    assert "\n" not in message and "Traceback" not in message
    assert message.startswith(f"{path}: ") and f"key '{key}'" in message
    assert any(w in message for w in ("allowed", "should be", "reduce"))


@pytest.mark.parametrize("extra, key", [
    ("[material]\nE = inf\n", "material.E"),
    ("[material]\nE = nan\n", "material.E"),
    ("[material]\nrho = inf\n", "material.rho"),
    ("[material]\nE = 1e300\n", "material.E"),
    ("[damping]\nalpha = inf\n", "damping.alpha"),
    ("[damping]\npairs = [[12.5, inf], [15.5, 0.02]]\n", "damping.pairs[0][1]"),
    ("[damping]\npairs = [[12.5, 0.01], [inf, 0.02]]\n", "damping.pairs[1][0]"),
    ("[[material.defects]]\nshape = 'sphere'\ncenter = [nan, 0.02, 0.02]\nsize = [0.01]\n"
     "E = 5e5\n", "material.defects[0].center[0]"),
    ("[[material.defects]]\nshape = 'sphere'\ncenter = [0.02, 0.02, 0.02]\nsize = [inf]\n"
     "E = 5e5\n", "material.defects[0].size[0]"),
    ("[[material.defects]]\nshape = 'sphere'\ncenter = [0.02, 0.02, 0.02]\nsize = [0.01]\n"
     "E = inf\n", "material.defects[0].E"),
    ("[camera]\nposition = [nan, 0.0, 0.1]\n", "camera.position[0]"),
    ("[camera]\nposition = [0.1, 0.1, 0.1]\nlook_at = [0.1, 0.1, 0.1]\n", "camera"),
    ("[camera]\nposition = [0.0, 0.0, 1.0]\nlook_at = [0.0, 0.0, 0.0]\nup = [0.0, 0.0, 2.0]\n",
     "camera"),
    ("[camera]\nup = [0.0, 0.0, 0.0]\n", "camera.up"),
    ("[camera]\nfx = inf\n", "camera.fx"),
    ("[camera]\nresolution = [100000, 256]\n", "camera.resolution[0]"),
    ("[render]\nmotion_scale = inf\n", "render.motion_scale"),
    ("[render]\nfull_well_electrons = inf\n", "render.full_well_electrons"),
    ("[render]\nframe_average = 1000000000\n", "render.frame_average"),
    ("[render]\ntexture_seed = -1\n", "render.texture_seed"),
    ("[render]\nbit_depth = true\n", "render.bit_depth"),
    ("[boundary]\nfixed = ['c']\n[boundary.node_sets.c]\nbox_min = [1, 1, 1]\n"
     "box_max = [0, 0, 0]\n", "boundary.node_sets.c"),
    ("[boundary.node_sets.c]\nbox_min = [nan, 0, 0]\nbox_max = [1, 1, 1]\n",
     "boundary.node_sets.c.box_min[0]"),
])
def test_non_finite_and_out_of_range_values_are_one_line_errors(tmp_path, extra, key):
    path = _write(tmp_path, _BOX + extra)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    _one_line_error(str(info.value), path, key)


@pytest.mark.parametrize("line, key", [
    ("direction = [nan, 0.0, 1.0]", "excitation.direction[0]"),
    ("direction = [inf, 0.0, 0.0]", "excitation.direction[0]"),
    ("direction = [0.0, 0.0, 0.0]", "excitation.direction"),
    ("radius = inf", "excitation.radius"),
    ("displacement = inf", "excitation.displacement"),
    ("velocity = [nan, 0.0, 0.0]", "excitation.velocity[0]"),
])
def test_excitation_vectors_must_be_finite_and_directions_non_zero(tmp_path, line, key):
    path = _write(tmp_path, _BOX.replace('kind = "pluck"\n', f'kind = "pluck"\n{line}\n'))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    _one_line_error(str(info.value), path, key)


def test_excitation_point_must_be_finite(tmp_path):
    path = _write(tmp_path, _BOX.replace("at = [0.05, 0.0, 0.05]", "at = [0.05, nan, 0.05]"))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    _one_line_error(str(info.value), path, "excitation.at[1]")


@pytest.mark.parametrize("signal, key", [
    ("kind = 'chirp'\nf1 = inf\n", "excitation.signal.f1"),
    ("kind = 'chirp'\namplitude = inf\n", "excitation.signal.amplitude"),
    ("kind = 'chirp'\nduration = nan\n", "excitation.signal.duration"),
    ("kind = 'impulse'\nwidth = nan\n", "excitation.signal.width"),
])
def test_force_signal_values_must_be_finite(tmp_path, signal, key):
    path = _write(tmp_path, _DRUM + "[excitation.signal]\n" + signal)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    _one_line_error(str(info.value), path, key)


@pytest.mark.parametrize("rows, fragment", [
    ([[0, 0.0], [0.001, np.nan], [0.002, 1.0]], "the first nan in row 1 (force)"),
    ([[0, 0.0], [0.001, np.inf], [0.002, 1.0]], "the first inf in row 1 (force)"),
    ([[0, 0.0], [0.001, 1.0], [np.inf, 1.0]], "the first inf in row 2 (time)"),
])
def test_force_file_samples_must_be_finite(tmp_path, rows, fragment):
    np.save(tmp_path / "force.npy", np.array(rows))
    scene = load_scene(_write(tmp_path, _DRUM + "[excitation.signal]\nkind = 'file'\n"
                                             "path = 'force.npy'\n"))
    with pytest.raises(SceneError) as info:
        simulate(scene)
    message = str(info.value)
    assert "\n" not in message and str(tmp_path / "force.npy") in message
    assert "excitation.signal.path" in message and fragment in message and "allowed" in message


def test_a_defect_outside_the_body_is_an_error_a_partly_overlapping_one_is_not(tmp_path):
    inside = "[[material.defects]]\nshape = 'sphere'\ncenter = [0.025, 0.025, 0.025]\n" \
             "size = [0.01]\nE = 5e5\n"
    outside = inside.replace("[0.025, 0.025, 0.025]", "[1.0, 1.0, 1.0]")
    partly = inside.replace("[0.025, 0.025, 0.025]", "[0.05, 0.05, 0.05]").replace(
        "[0.01]", "[0.02]")
    scene = load_scene(_write(tmp_path, _BOX + inside + outside))
    mesh = build_mesh(scene)
    with pytest.raises(SceneError) as info:
        material_fields(scene, mesh)
    message = str(info.value)
    _one_line_error(message, scene.source, "material.defects[1]")
    assert "lies entirely outside the body" in message and "x 0..0.05" in message
    fields = material_fields(load_scene(_write(tmp_path, _BOX + partly)), mesh)
    assert 0 < np.sum(fields.stiffness == 5e5) < mesh.n_elements


def test_a_defect_between_element_centroids_is_an_error(tmp_path):
    tiny = "[[material.defects]]\nshape = 'sphere'\ncenter = [0.0, 0.0, 0.0]\n" \
           "size = [0.001]\nE = 5e5\n"
    scene = load_scene(_write(tmp_path, _BOX + tiny))
    with pytest.raises(SceneError, match=r"defects\[0\]'.*contains no element centroid"):
        material_fields(scene, build_mesh(scene))


@pytest.mark.parametrize("at, radius, ok", [
    ([17.0, 0.0, 0.05], 0.0, False),           # 17 m away: was snapped to the nearest node
    ([0.05, 0.0, 0.2], 0.0, False),            # 15 cm above a 5 cm cube
    ([0.05, 0.0, 0.2], 0.16, True),            # ... but within the patch radius of a node
    ([0.051, -0.001, 0.051], 0.0, True),       # 1 mm off the corner: within one element
    ([0.025, 0.025, 0.025], 0.0, True),        # inside, between nodes
])
def test_a_load_point_off_the_body_is_an_error(tmp_path, at, radius, ok):
    text = _BOX.replace("at = [0.05, 0.0, 0.05]", f"at = {at}\nradius = {radius}")
    scene = load_scene(_write(tmp_path, text))
    mesh = build_mesh(scene)
    if ok:
        assert len(load_nodes(scene, mesh)) >= 1
        return
    with pytest.raises(SceneError) as info:
        load_nodes(scene, mesh)
    message = str(info.value)
    _one_line_error(message, scene.source, "excitation.at")
    assert "from the body" in message and "one element size" in message


def test_a_node_set_box_holding_no_node_is_an_error(tmp_path):
    scene = load_scene(_write(tmp_path, _BOX + "[boundary]\nfixed = ['bottom', 'c']\n"
                                               "[boundary.node_sets.c]\nbox_min = [1, 1, 1]\n"
                                               "box_max = [2, 2, 2]\n"))
    with pytest.raises(SceneError, match=r"node_sets.c'.*holds no mesh node"):
        build_mesh(scene)


def test_too_large_problems_are_rejected_before_meshing(tmp_path, monkeypatch):
    from vvtbench.simulation import simulate as sim

    monkeypatch.setattr(sim, "available_memory", lambda: 24 * 2.0**30)
    meshed = []
    monkeypatch.setattr(sim, "build_mesh", lambda scene: meshed.append(scene))
    scene = load_scene(_write(tmp_path, _BOX.replace("[3, 3, 3]", "[100, 100, 100]")))
    with pytest.raises(SceneError) as info:
        simulate(scene)
    assert meshed == []  # refused from the geometry alone, before a mesh is built
    message = str(info.value)
    _one_line_error(message, scene.source, "geometry.cells")
    assert "100x100x100 hex8" in message and "this machine has 24 GiB available" in message
    need = float(message.split("needs about ")[1].split(" GiB")[0])
    assert 40 < need < 200
    drum = load_scene(_write(tmp_path, _DRUM.replace("cells = 6", "cells = 100000")
                              + "[excitation.signal]\nkind = 'chirp'\n"))
    with pytest.raises(SceneError, match=r"key 'geometry.cells'.*needs about .* GiB"):
        simulate(drum)
    frames = load_scene(_write(tmp_path, _BOX.replace("duration = 0.01", "duration = 1e6")
                               .replace("fps = 1000.0", "fps = 1e6")))
    with pytest.raises(SceneError, match=r"key 'simulation.duration'.*needs about"):
        simulate(frames)
    np.save(tmp_path / "f.npy", np.array([[0.0, 0.0], [1e-15, 1.0], [0.002, 1.0]]))
    fine = load_scene(_write(tmp_path, _DRUM + "[excitation.signal]\nkind = 'file'\n"
                                               "path = 'f.npy'\n"))
    with pytest.raises(SceneError, match=r"key 'excitation.signal'.*needs about"):
        simulate(fine)


def test_memory_estimate_of_shipped_scenes_is_modest_and_unknown_memory_skips_the_check():
    from vvtbench.simulation.simulate import GIB, check_problem_size

    for path in SHIPPED:
        scene = load_scene(path)
        if scene.geometry.kind != "mesh":
            assert check_problem_size(scene) < 1.5 * GIB
    big = load_scene("jello_cube_homogeneous")
    big = big.model_copy(update={"geometry": big.geometry.model_copy(
        update={"cells": (200, 200, 200)})})
    assert check_problem_size(big, available=float("inf")) > 100 * GIB


def test_values_at_the_ends_of_their_ranges_cannot_overflow_and_a_guard_remains(
    tmp_path, monkeypatch
):
    from vvtbench.fem.modal import Modes
    from vvtbench.simulation import simulate as sim

    path = _write(tmp_path, _BOX + "[material]\nE = 1e13\nrho = 1e-300\n")
    with pytest.raises(SceneError, match=r"key 'material.rho': got 1e-300; allowed: .*>= 0.01"):
        load_scene(path)
    stiff = _BOX.replace("cells = [3, 3, 3]", "cells = [3, 3, 3]\nsize = [1e-6, 1e-6, 1e-6]")
    stiff = stiff.replace("at = [0.05, 0.0, 0.05]", "at = [1e-6, 0.0, 1e-6]")
    scene = load_scene(_write(tmp_path, stiff + "[material]\nE = 1e13\nrho = 0.01\n"))
    result = simulate(scene)
    assert np.all(np.isfinite(result.frequencies_hz)) and np.all(np.isfinite(result.displacements))
    monkeypatch.setattr(sim, "eigenmodes", lambda K, M, k, seed: Modes(
        np.full(k, np.nan), np.zeros((K.shape[0], k))))
    with pytest.raises(SceneError, match=r"non-finite frequencies"):
        simulate(scene)


@pytest.mark.parametrize("extra, key", [
    ("[material]\nE = inf\n", "material.E"),
    ("[excitation.x]\n", "excitation.at"),
    ("[[material.defects]]\nshape = 'box'\ncenter = [5.0, 5.0, 5.0]\nsize = [0.01, 0.01, 0.01]\n"
     "E = 5e5\n", "material.defects[0]"),
    ("[camera]\nlook_at = [0.15, -0.2, 0.15]\n", "camera"),
    ("[geometry.x]\n", "geometry.cells"),
])
def test_cli_simulate_on_a_bad_scene_exits_2_with_one_line(tmp_path, capsys, extra, key):
    text = _BOX + extra
    if extra == "[excitation.x]\n":
        text = _BOX.replace("at = [0.05, 0.0, 0.05]", "at = [17.0, 0.0, 0.05]")
    if extra == "[geometry.x]\n":
        text = _BOX.replace("[3, 3, 3]", "[3000, 3000, 3000]")
    path = _write(tmp_path, text)
    assert main(["simulate", str(path), "--transient"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {path}: ")
    assert f"key '{key}'" in err and "Traceback" not in err
