"""Scene files: shipped scenes load, bad files give clear errors, scenes simulate."""

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.scene import SCENES_DIR, SceneError, load_scene, parse_scene
from vvtbench.simulate import build_mesh, material_fields, simulate

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
    ('name = "x"\n[geometry]\nkind = "box"\n[material]\nE = -5\n', ["material.E", "greater"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[damping]\npairs = [[1.0, 0.1]]\n',
     ["damping", "exactly two"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[excitation]\nkind = "pluck"\n',
     ["excitation", "needs 'at'"]),
    ('name = "x"\n[geometry]\nkind = "drum"\n[[material.defects]]\nshape = "sphere"\n'
     'center = [0, 0, 0]\nsize = [0.01]\nE = 5.0\n', ["defects[0]", "tension"]),
    ('name = "x"\n[geometry\n', ["not valid TOML"]),
    ('name = "x"\n[geometry]\nkind = "box"\n[excitation]\nkind = "kick"\nat = [0, 0, 0]\n',
     ["excitation.kind", "'pluck'"]),
])
def test_bad_scene_gives_clear_error(tmp_path, text, expected):
    path = _write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in expected:
        assert fragment in message


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
