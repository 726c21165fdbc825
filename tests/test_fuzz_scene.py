"""Fuzzing scene validation: shipped scenes with random numeric leaves replaced by NaN, inf,
negative, huge, zero or wrongly typed values. ``parse_scene`` must either accept the scene,
and then every number in it is finite, or raise a one-line ``SceneError`` that names the file
and a key; never another exception. A second property places defects and load points anywhere
on a small mesh: each selects something or is a one-line SceneError, never silently nothing.
"""

from __future__ import annotations

import copy
import math
import re
from functools import cache

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from vvtbench.scene.scene import SceneError, load_scene, parse_scene  # noqa: E402
from vvtbench.simulation.simulate import build_mesh, load_nodes, material_fields  # noqa: E402

SOURCE = "fuzz/scene.toml"
SCENES = ["jello_cube_defect_top", "jello_cube_damped_top_front", "drum_gel_bar",
          "drum_two_acrylic_circles", "bunny_defect", "jello_cube_defect_cylinder"]
SETTINGS = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])

BAD_NUMBERS = [math.nan, math.inf, -math.inf, -1.0, -1, 0, 0.0, 1e-300, 1e300, -1e300, 10**30,
               2**63, 5e-324, 1e13, 1e6]
BAD_TYPES = [True, False, "x", "", "nan", None, [], [1.0], {}, {"a": 1}, [math.nan, 0.0, 0.0]]


@cache
def _base(name: str) -> dict:
    return load_scene(name).to_toml_dict()


def _numeric_paths(value, path=()) -> list[tuple]:
    """Paths to every int/float leaf (booleans excluded) of nested dicts and lists."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _numeric_paths(v, path + (k,))]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _numeric_paths(v, path + (i,))]
    if isinstance(value, int | float) and not isinstance(value, bool):
        return [path]
    return []


def _set(data, path, value):
    cur = data
    for p in path[:-1]:
        cur = cur[p]
    cur[path[-1]] = value


def _all_finite(value) -> bool:
    if isinstance(value, dict):
        return all(_all_finite(v) for v in value.values())
    if isinstance(value, list | tuple):
        return all(_all_finite(v) for v in value)
    if isinstance(value, float):
        return math.isfinite(value)
    return True


def _check_message(message: str) -> None:
    assert "\n" not in message, message
    head = message.removeprefix(f"{SOURCE}: ")
    assert head != message and re.match(r"(\d+ problems: )?key '", head), message
    assert "Traceback" not in message and "pydantic" not in message.lower(), message
    assert len(message) < 4000


def _parse_or_clear_error(data: dict) -> None:
    try:
        scene = parse_scene(data, SOURCE)
    except SceneError as error:
        _check_message(str(error))
        return
    assert _all_finite(scene.model_dump(mode="python")), scene


any_value = st.one_of(
    st.sampled_from(BAD_NUMBERS),
    st.sampled_from(BAD_TYPES),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
)


@SETTINGS
@given(name=st.sampled_from(SCENES), data=st.data())
def test_mutated_numeric_leaves_are_accepted_finite_or_a_one_line_error(name, data):
    scene = copy.deepcopy(_base(name))
    paths = _numeric_paths(scene)
    chosen = data.draw(st.lists(st.sampled_from(paths), min_size=1, max_size=3, unique=True))
    for path in chosen:
        _set(scene, path, data.draw(any_value))
    _parse_or_clear_error(scene)


@SETTINGS
@given(name=st.sampled_from(SCENES), data=st.data())
def test_mutated_tables_and_keys_give_a_one_line_error(name, data):
    """Whole tables replaced by scalars or lists, keys removed or misspelt."""
    scene = copy.deepcopy(_base(name))
    table = data.draw(st.sampled_from(sorted(k for k, v in scene.items() if isinstance(v, dict))))
    action = data.draw(st.sampled_from(["replace", "drop", "extra", "drop_inner"]))
    if action == "replace":
        scene[table] = data.draw(st.sampled_from(BAD_TYPES + BAD_NUMBERS))
    elif action == "drop":
        del scene[table]
    elif action == "extra":
        scene[table][data.draw(st.text(min_size=1, max_size=8))] = 1.0
    elif scene[table]:
        del scene[table][data.draw(st.sampled_from(sorted(scene[table])))]
    _parse_or_clear_error(scene)


_SMALL = {"name": "fuzz", "geometry": {"kind": "box", "cells": [3, 3, 3]},
          "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05]}}
coordinate = st.floats(min_value=-0.5, max_value=0.5, allow_nan=False)


@cache
def _small_mesh():
    return build_mesh(parse_scene(_SMALL, SOURCE))


@SETTINGS
@given(center=st.tuples(coordinate, coordinate, coordinate),
       radius=st.floats(min_value=1e-4, max_value=0.2))
def test_a_defect_anywhere_selects_elements_or_is_a_one_line_error(center, radius):
    data = copy.deepcopy(_SMALL)
    data["material"] = {"defects": [{"shape": "sphere", "center": list(center),
                                     "size": [radius], "E": 5e5}]}
    scene = parse_scene(data, SOURCE)
    mesh = _small_mesh()
    try:
        fields = material_fields(scene, mesh)
    except SceneError as error:
        _check_message(str(error))
        assert "material.defects[0]" in str(error)
        assert not scene.material.defects[0].contains(mesh.centroids).any()
        return
    assert np.any(fields.stiffness == 5e5)


@SETTINGS
@given(at=st.tuples(coordinate, coordinate, coordinate),
       radius=st.sampled_from([0.0, 0.001, 0.02, 0.3]))
def test_a_load_point_anywhere_is_on_the_body_or_a_one_line_error(at, radius):
    data = copy.deepcopy(_SMALL)
    data["excitation"] = {"kind": "pluck", "at": list(at), "radius": radius}
    scene = parse_scene(data, SOURCE)
    mesh = _small_mesh()
    dist = np.linalg.norm(mesh.points - np.asarray(at), axis=1).min()
    try:
        nodes = load_nodes(scene, mesh)
    except SceneError as error:
        _check_message(str(error))
        assert dist > radius + 0.05 / 3  # farther than radius + one element from every node
        return
    assert nodes.size >= 1
    h = np.sqrt(3) * 0.05 / 3
    assert dist <= radius + h + 1e-12


def _log_uniform(lo: float, hi: float):
    return st.floats(min_value=math.log10(lo), max_value=math.log10(hi)).map(lambda x: 10**x)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(E=_log_uniform(1e-3, 1e13), rho=_log_uniform(1e-2, 1e5), side=_log_uniform(1e-6, 1e3),
       alpha=_log_uniform(1e-6, 1e9), beta=_log_uniform(1e-9, 1e3),
       kind=st.sampled_from(["pluck", "velocity", "force"]))
def test_values_anywhere_in_their_ranges_simulate_to_finite_numbers_or_a_clear_error(
    E, rho, side, alpha, beta, kind
):
    """The ranges are wide; their extremes together must not give NaN silently."""
    from vvtbench.simulation.simulate import simulate

    data = {"name": "fuzz", "geometry": {"kind": "box", "cells": [2, 2, 2],
                                         "size": [side, side, side]},
            "material": {"E": E, "rho": rho}, "damping": {"alpha": alpha, "beta": beta},
            "excitation": {"kind": kind, "at": [side, 0.0, side], "radius": 0.0,
                           "signal": {"kind": "impulse"}} if kind == "force" else
            {"kind": kind, "at": [side, 0.0, side]},
            "simulation": {"n_modes": 4, "fps": 1000.0, "duration": 0.005}}
    scene = parse_scene(data, SOURCE)
    try:
        result = simulate(scene)
    except SceneError as error:
        assert "\n" not in str(error) and str(error).startswith(SOURCE)
        return
    assert np.all(np.isfinite(result.frequencies_hz))
    assert np.all(np.isfinite(result.displacements))
