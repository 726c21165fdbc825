"""Suite files are validated by pydantic models: every error is a one-line SuiteError naming the
file, the key path and what is allowed."""

from __future__ import annotations

import tomllib

import pytest

from vvtbench.bench import SuiteError, load_suite, parse_suite

BASE = 'scenes = ["jello_cube_homogeneous"]\n'


def error_of(text: str) -> str:
    with pytest.raises(SuiteError) as info:
        parse_suite(tomllib.loads(BASE + text), "my_suite.toml")
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("my_suite.toml: key '")
    return msg


def test_unknown_keys_name_the_key_and_the_allowed_ones():
    msg = error_of("solverz = ['vvt']")
    assert "key 'solverz': unknown key" in msg and "solvers" in msg
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\nseed = [0]\n")
    assert "key 'tracks[0].seed': unknown key" in msg and "seeds" in msg
    msg = error_of("[extract]\nfmaxx = 10.0\n")
    assert "key 'extract.fmaxx': unknown key" in msg and "fmax" in msg
    msg = error_of("[defaults]\nn_mode = 5\n")
    assert "key 'defaults.n_mode': unknown key" in msg and "n_modes" in msg


def test_seeds_are_non_negative_integers():
    assert "key 'seeds[1]'" in (msg := error_of("seeds = [0, -1]")) and ">= 0" in msg
    assert "key 'seeds'" in error_of("seeds = -3")
    assert "key 'seeds[0]'" in error_of("seeds = [true]")  # no silent bool -> int
    assert "key 'seeds'" in error_of("seeds = []")
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\nseeds = [2, -5]\n")
    assert "key 'tracks[0].seeds[1]'" in msg


def test_numbers_are_finite_and_in_range():
    msg = error_of("[defaults]\nn_modes = nan\n")
    assert "key 'defaults.n_modes'" in msg and "not a finite number" in msg
    assert "key 'solver.vvt.alpha_v'" in error_of("[solver.vvt]\nalpha_v = inf\n")
    assert "key 'extract.fmax'" in error_of("[extract]\nfmax = -inf\n")
    msg = error_of("[defaults]\nn_modes = 0\n")
    assert "key 'defaults.n_modes'" in msg and "an integer >= 1" in msg
    msg = error_of("[defaults]\nnu = 0.5\n")
    assert "key 'defaults.nu'" in msg and "(-1, 0.5)" in msg
    msg = error_of("[sweep]\ngeometry_scale = [1.0, 0.0]\n")
    assert "key 'sweep.geometry_scale[1]'" in msg and "> 0" in msg
    msg = error_of("[[variations]]\ngeometry_scale = [1.0, -1.0, 1.0]\n")
    assert "key 'variations[0].geometry_scale[1]'" in msg
    assert "key 'extract.shake_threshold'" in error_of("[extract]\nshake_threshold = 1.5\n")
    assert "key 'extract.product_roughness'" in error_of("[extract]\nproduct_roughness = -0.1\n")
    assert "key 'extract.faint_product_ratio'" in error_of("[extract]\nfaint_product_ratio = 2\n")
    assert "key 'extract.product_scaling'" in error_of("[extract]\nproduct_scaling = 'cubic'\n")
    msg = error_of("[extract]\nroughness_weighting = 'noise'\n")
    assert "key 'extract.roughness_weighting'" in msg and "'spectrum'" in msg
    msg = error_of("[extract]\nmin_reliable_fraction = -1\n")
    assert "key 'extract.min_reliable_fraction'" in msg and ">= 0" in msg
    assert "key 'sweep.n_modes'" in error_of("[sweep]\nn_modes = []\n")


def test_bad_observation_and_scene_names():
    msg = error_of('observations = ["true", "video"]')
    assert "key 'observations[1]'" in msg and "'extracted'" in msg
    assert "key 'observations'" in error_of("observations = []")
    msg = error_of('observations = ["true", "extracted:farneback", "extracted:farneback"]')
    assert "key 'observations'" in msg and "duplicate" in msg
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\nobservations = ['true', "
                   "'true']\n")
    assert "key 'tracks[0].observations'" in msg
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\nobservations = ['x']\n")
    assert "key 'tracks[0].observations[0]'" in msg
    msg = error_of("[[tracks]]\nscenes = ['no_such_scene']\n")
    assert "key 'tracks[0].scenes[0]'" in msg and "jello_cube_homogeneous" in msg
    msg = error_of("[extract]\nweighting = 'snr'\n")
    assert "key 'extract.weighting'" in msg and "'confidence'" in msg


def test_extracted_observations_name_an_extractor_checked_at_load(tmp_path):
    suite = parse_suite(tomllib.loads(
        BASE + 'observations = ["extracted", "extracted:farneback"]\n'
        "[extract.extractor.farneback]\nwinsize = '9'\n"), "s.toml")
    assert suite.tracks[0].observations == ["extracted", "extracted:farneback"]
    assert suite.name == "s"  # not the extractor of the last observation
    fb = suite.extractors["farneback"]
    assert fb["name"] == "farneback" and fb["config"] == {"winsize": 9} and fb["version"]
    for text, key, words in (
            ('observations = ["extracted:no_such_flow"]', "observations[0]",
             ("farneback", "phase")),
            ('observations = ["extracted:"]', "observations[0]", ("'extracted:EXTRACTOR'",)),
            ("[extract.extractor.farneback]\nwinsiz = 9\n", "extract.extractor.farneback",
             ("winsize",)),
            ("[extract.extractor.farneback]\nwinsize = 'big'\n", "extract.extractor.farneback",
             ("int",)),
            ("[extract.extractor.no_such_flow]\nx = 1\n", "extract.extractor.no_such_flow",
             ("farneback",))):
        msg = error_of(text)
        assert f"key '{key}'" in msg and all(w in msg for w in words), msg
    plugin = tmp_path / "flow.py"  # a file extractor, named relative to the suite file
    plugin.write_text("from vvtbench.motion.extractors import FarnebackExtractor\n\n\n"
                      "class Flow(FarnebackExtractor):\n    name = 'flow'\n")
    suite = parse_suite(tomllib.loads(BASE + 'observations = ["extracted:flow.py:Flow"]\n'),
                        str(tmp_path / "s.toml"))
    assert suite.extractors["flow.py:Flow"]["spec"] == f"{plugin}:Flow"


@pytest.mark.parametrize("name", ["smoke", "paper", "standard", "standard_val"])
def test_shipped_suites_keep_their_names(name):
    """The run folder is runs/<name>: an extracted observation must not rename the suite."""
    assert load_suite(name).name == name


def test_values_are_kept_as_written():
    """Validation coerces nothing: the runner hashes and records the file's own values."""
    suite = parse_suite(tomllib.loads(BASE + "[sweep]\ngeometry_scale = [1, 1.5]\n"), "s.toml")
    scales = [v.inference["geometry_scale"] for v in suite.tracks[0].variations]
    assert scales == [1, 1.5] and type(scales[0]) is int


def test_shipped_suites_validate():
    for name in ("smoke", "paper"):
        suite = load_suite(name)
        assert suite.tracks and all(t.variations for t in suite.tracks)


def test_family_tracks_draw_their_instances(tmp_path):
    from vvtbench.bench import build_graph
    from vvtbench.scene.families import draw

    suite = load_suite("standard")
    track = next(t for t in suite.tracks if t.name == "cube_true")
    assert len(track.scenes) == 50
    tasks, runs = build_graph(suite, ["homogeneous"], until="generate")
    names = {t.payload["scene"]["name"] for t in tasks.values() if t.stage == "generate"}
    assert "cube_defects-test-00049" in names and not any("-train-" in n for n in names)
    gen = next(t for t in tasks.values() if t.payload["scene"]["name"] ==
               "cube_defects-test-00003")
    assert gen.payload["scene"]["seed"] == draw("cube_defects", "test", 3).seed
    bad = {"name": "x", "solvers": ["homogeneous"],
           "tracks": [{"name": "t", "family": "cube_defects", "scenes": ["jello_cube"]}]}
    with pytest.raises(SuiteError, match="family"):
        parse_suite(bad, "x.toml")
    bad["tracks"][0] = {"name": "t", "family": "no_such_family", "count": 2}
    with pytest.raises(SuiteError, match="family"):
        parse_suite(bad, "x.toml")


def test_doctests():
    import doctest

    from vvtbench.bench import suite

    result = doctest.testmod(suite)
    assert result.attempted > 0 and result.failed == 0


def test_track_extraction_options_override_the_suite_and_only_that_track_s_keys():
    from vvtbench.bench import build_graph
    from vvtbench.bench.graph import extract_options

    text = ("[extract]\nline_fit = true\nfmax = 100.0\n"
            "[[tracks]]\nname = 'a'\nscenes = ['jello_cube_homogeneous']\n"
            "observations = ['extracted']\n"
            "[[tracks]]\nname = 'b'\nscenes = ['jello_cube_homogeneous']\n"
            "observations = ['extracted']\n[tracks.extract]\nline_fit = false\n")
    suite = parse_suite(tomllib.loads(text), "s.toml")
    a, b = suite.tracks
    assert a.extract == {} and b.extract == {"line_fit": False}
    assert extract_options(suite, "extracted", a.extract)[0] == {"line_fit": True, "fmax": 100.0}
    assert extract_options(suite, "extracted", b.extract)[0] == {"line_fit": False,
                                                                 "fmax": 100.0}
    tasks, _ = build_graph(suite, ["homogeneous"])
    extracts = [t for t in tasks.values() if t.stage == "extract"]
    assert sorted(t.payload["options"]["line_fit"] for t in extracts) == [False, True]
    # bad values and a motion extractor table are one-line errors naming the key
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\n[tracks.extract]\n"
                   "line_fit = 'yes'\n")
    assert "key 'tracks[0].extract.line_fit'" in msg and "true or false" in msg
    msg = error_of("[[tracks]]\nscenes = ['jello_cube_homogeneous']\n"
                   "[tracks.extract.extractor.phase]\nsigma = 3.0\n")
    assert "key 'tracks[0].extract.extractor'" in msg and "[extract.extractor.NAME]" in msg


def test_the_quick_suite_is_the_standard_suite_on_fewer_instances():
    """Every task of `quick` (generation, extraction, observation, solve, evaluation) has the
    cache key of a task of `standard`: the same instance, options and solver config, so the
    quick ranking is read on a subset of the standard one's rows."""
    import dataclasses

    from vvtbench.bench import build_graph

    solvers = ["homogeneous", "learned", "oracle", "sensitivity", "vvt"]
    q = load_suite("quick")
    s = load_suite("standard")
    kept = {t.name for t in q.tracks}
    assert kept <= {t.name for t in s.tracks}
    quick, _ = build_graph(q, solvers)
    standard, _ = build_graph(dataclasses.replace(
        s, tracks=[t for t in s.tracks if t.name in kept]), solvers)
    assert {t.stage for t in quick.values()} >= {"generate", "extract", "solve", "evaluate"}
    assert set(quick) <= set(standard), sorted(set(quick) - set(standard))[:3]
