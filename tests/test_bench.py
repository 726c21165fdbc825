"""The benchmark runner: suites, cache, failures, results schema, Dask (export: test_export)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

pd = pytest.importorskip("pandas")
pytest.importorskip("pyarrow")

from vvtbench.bench import (  # noqa: E402
    COLUMNS,
    check_results,
    load_suite,
    read_results,
    run_suite,
)
from vvtbench.cli.run import main_check_results  # noqa: E402

MICRO = """
name = "micro"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous", "vvt"]
seeds = [0]
observations = ["true", "extracted"]

[defaults]
"geometry.cells" = [5, 5, 5]
"simulation.n_modes" = 12
"simulation.fps" = 400.0
"simulation.duration" = 1.0
"camera.resolution" = [96, 96]
"render.supersample" = 2
"excitation.displacement" = 0.0006
n_modes = 5
inference_shape = [3, 3, 3]

[extract]
max_modes = 8
fmax = 150.0

[solver.vvt]
max_iter = 3
"""

CRASH = '''
from dataclasses import dataclass


@dataclass
class Config:
    pass


class Crash:
    name = "crash"
    version = "0.0.1"
    description = "always fails"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        raise RuntimeError("boom: this solver always fails")
'''


PEEK = '''
import json
import types
from dataclasses import dataclass
from pathlib import Path

import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))  # its package folder: what the sandbox shows
from truth_search import leaves, truth_in
from vvtbench.api import Estimate

TARGETS = Path(__file__).with_name("peek_targets.npz")


@dataclass
class Config:
    pass


def search(problem):
    """Every path reachable from the problem that holds a true material, a true 3-D mode
    or a secret string; the targets sit beside this file in its package (the test wrote
    them there)."""
    found = list(leaves(problem))
    hits = []
    with np.load(TARGETS) as z:
        secrets = json.loads(str(z["secrets"]))
        for k in sorted({n.split("_")[0] for n in z.files if n != "secrets"}):
            truth = types.SimpleNamespace(w=z[k + "_w"], v=z[k + "_v"], modes_3d=z[k + "_u"])
            hits += truth_in(found, truth, secrets)
    return {"hits": json.dumps(sorted(set(hits))), "n_leaves": len(found)}


class Peek:
    """Searches everything it can reach in the problem it gets for the truth, and reports
    what it found in its estimate (it can write nowhere else)."""

    name = "peek"
    version = "0.0.1"
    description = "records what a solver can see"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        """Search and return the prior."""
        m = problem.n_params
        return Estimate(w=np.full(m, problem.w_mean), v=np.full(m, problem.v0),
                        extra=search(problem))


class PeekReference(Peek):
    name = "peekref"
    uses_truth = True

    def solve(self, problem, truth):
        """Search the problem; a reference solver receives the truth explicitly."""
        assert truth.modes_3d.shape[1] == problem.n_modes
        return super().solve(problem)
'''


def _computed(df) -> dict:
    return {s: v["computed"] for s, v in df.attrs["stats"].items()}


@pytest.fixture(scope="module")
def micro(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    suite_file = root / "micro.toml"
    suite_file.write_text(MICRO)
    out = root / "run"
    df = run_suite(str(suite_file), None, out, progress=False)
    return suite_file, out, df


def test_micro_suite_end_to_end(micro):
    _, out, df = micro
    assert list(df.columns) == list(COLUMNS)
    assert len(df) == 4
    assert set(df["observation"]) == {"true", "extracted"}
    assert (df["status"] == "ok").all(), df[["solver", "observation", "error"]]
    assert df["n_modes_observed"].min() >= 3
    vvt_true = df[(df.solver == "vvt") & (df.observation == "true")].iloc[0]
    assert np.isfinite(vvt_true.nc_w) and -1 <= vvt_true.nc_w <= 1
    assert (df[df.solver == "homogeneous"].nc_w == 0).all()
    # the first stage is scored too: extraction against the true modes, on extracted rows only
    ext = df[df.observation == "extracted"]
    assert ext.extraction_precision.between(0, 1).all() and ext.extraction_recall.gt(0).all()
    assert df[df.observation == "true"].extraction_precision.isna().all()
    assert df.mode_mac_true.between(0, 1).all()
    assert _computed(df) == {"generate": 1, "extract": 1, "observe": 2, "solve": 4,
                             "evaluate": 4}
    for p in df["estimate_path"]:
        assert (out / p).is_file()
    assert (out / "results.parquet").is_file() and (out / "results.csv").is_file()
    assert check_results(out / "results.parquet") == []
    assert check_results(out / "results.csv") == []
    # nothing half-written is left behind
    assert not list((out / "cache").rglob("*.tmp-*"))


def test_rerun_hits_cache_and_changed_option_recomputes_dependants(micro):
    suite_file, out, df0 = micro
    df1 = run_suite(str(suite_file), None, out, progress=False)
    assert _computed(df1) == {s: 0 for s in _computed(df1)}
    assert all(v["cached"] == v["tasks"] for v in df1.attrs["stats"].values())
    pd.testing.assert_frame_equal(df0.drop(columns="runtime_s"), df1.drop(columns="runtime_s"))
    df2 = run_suite(str(suite_file), None, out, progress=False,
                    solver_config={"vvt": {"max_iter": 2}})
    assert _computed(df2) == {"generate": 0, "extract": 0, "observe": 0, "solve": 2,
                              "evaluate": 2}
    changed = df2.solver == "vvt"
    assert (df2[changed].config_hash.values != df0[changed].config_hash.values).all()
    assert (df2[~changed].config_hash.values == df0[~changed].config_hash.values).all()


def test_crashing_solver_is_an_error_row(micro, tmp_path):
    suite_file, out, _ = micro
    plugin = tmp_path / "crash_solver.py"
    plugin.write_text(CRASH)
    df = run_suite(str(suite_file), ["homogeneous", f"{plugin}:Crash"], out, progress=False)
    bad = df[df.solver == "crash"]
    assert len(bad) == 2 and (bad.status == "error").all()
    assert bad.error.str.contains("boom: this solver always fails").all()
    assert bad.error.str.startswith("solve: RuntimeError").all()
    for p in bad.traceback_path:
        assert "boom" in (out / p).read_text()
    assert (df[df.solver == "homogeneous"].status == "ok").all()
    assert check_results(df) == []


def test_no_truth_reaches_a_solver_through_run_or_solve(micro, tmp_path):
    """A plug-in that searches everything reachable from its problem (attributes, __dict__,
    nested dicts and arrays) finds no material, no true 3-D mode, no scene name or sample
    path, through `vvtbench run` and through `vvtbench solve`; a reference solver gets the
    truth as an argument and its rows are marked as references."""
    import json
    from pathlib import Path

    from vvtbench.bench import load_observation
    from vvtbench.cli.solve import main_solve
    from vvtbench.observe import observe

    suite_file, out, _ = micro
    truths = [load_observation(out / "cache", f"observe/{d.name}", truth=True)[1]
              for d in (out / "cache" / "observe").iterdir() if (d / "truth.npz").is_file()]
    truths.append(observe("jello_cube_defect_top", inference_shape=(3, 3, 3), n_modes=4)[1])
    sample = next((out / "cache" / "generate").glob("*/sample"))
    secrets = ["jello_cube_defect_top", str(sample), str(out)]
    targets = {"secrets": np.array(json.dumps(secrets))}
    for i, t in enumerate(truths):
        targets |= {f"t{i}_w": t.w, f"t{i}_v": t.v, f"t{i}_u": t.modes_3d}
    package = tmp_path / "peek"  # a plug-in shown with its package: its helper and data
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "truth_search.py").write_text(
        (Path(__file__).with_name("truth_search.py")).read_text())
    np.savez(package / "peek_targets.npz", **targets)
    plugin = package / "peek_solver.py"
    plugin.write_text(PEEK)
    df = run_suite(str(suite_file), [f"{plugin}:Peek", f"{plugin}:PeekReference"], out,
                   progress=False)
    df = df[df.solver.isin(["peek", "peekref"])]  # the table keeps the other solvers' rows
    assert len(df) == 4 and (df.status == "ok").all(), df[["solver", "observation", "error"]]
    assert df.set_index("solver").reference.to_dict() == {"peek": False, "peekref": True}
    reports = [json.loads((out / Path(p).parent / "task.json").read_text())["deps"][0]
               for p in df.estimate_path]
    reports = [json.loads((out / "cache" / k / "estimate.json").read_text())["extra"]
               for k in reports]
    # vvtbench solve on the sample (extracted and true modes) and on the scene
    for i, argv in enumerate([[str(sample)], [str(sample), "--observation", "true"],
                              ["jello_cube_defect_top", "--grid", "3", "3", "3"]]):
        assert main_solve([f"{plugin}:Peek", *argv, "--modes", "4", "--no-mode-match",
                           "-o", str(tmp_path / f"solve{i}")]) == 0
        reports.append(json.loads((tmp_path / f"solve{i}" / "estimate.json").read_text())
                       ["extra"])
    assert len(reports) == 4 + 3  # run: 2 observations x 2 solvers; solve: 3
    for r in reports:
        assert r["n_leaves"] > 20 and json.loads(r["hits"]) == [], r


def test_check_results_rejects_broken_tables(micro, tmp_path, capsys):
    _, out, _ = micro
    df = read_results(out / "results.parquet")
    broken = df.copy()
    broken.loc[1, "status"] = "maybe"
    broken.loc[0, "nc_w"] = 1.7
    broken = broken.drop(columns=["dataset_revision"])
    path = tmp_path / "broken.csv"
    broken.to_csv(path, index=False)
    problems = check_results(path)
    text = "\n".join(problems)
    assert "missing column(s): dataset_revision" in text
    assert "column 'status', row 1: 'maybe' not allowed; allowed values: ok, error" in text
    assert "column 'nc_w', row 0: 1.7 outside the allowed range [-1.0, 1.0]" in text
    assert main_check_results([str(path)]) == 1
    assert "nc_w" in capsys.readouterr().err
    assert main_check_results([str(out / "results.parquet")]) == 0


def test_dask_local_cluster_gives_the_same_table(micro, tmp_path):
    distributed = pytest.importorskip("distributed")
    suite_file, out, df0 = micro
    out2 = tmp_path / "dask"
    # reuse the rendered video and extracted modes; observe/solve/evaluate run on Dask
    for stage in ("generate", "extract"):
        shutil.copytree(out / "cache" / stage, out2 / "cache" / stage)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            df = run_suite(str(suite_file), None, out2, scheduler=client, progress=False)
    assert _computed(df)["solve"] == 4 and _computed(df)["generate"] == 0
    # the scores agree; the bytes of a recomputed observation or estimate need not (rounding)
    cols = [c for c in df.columns if c not in ("runtime_s", "estimate_sha256",
                                               "observation_sha256")]
    pd.testing.assert_frame_equal(df0[cols], df[cols], check_exact=False, atol=1e-6)


def test_shipped_suites_parse():
    from vvtbench.bench import build_graph

    smoke = load_suite("smoke")
    tasks, runs = build_graph(smoke, smoke.solvers)
    assert {r.observation for r in runs} == {"true", "extracted"}
    paper = load_suite("paper")
    names = {t.name for t in paper.tracks}
    assert {"modes", "damping", "bunny", "geometry", "poisson", "element_order",
            "regularization", "drums"} <= names
    tasks, runs = build_graph(paper, paper.solvers)
    damping = [r for r in runs if r.track == "damping"]
    assert damping and all("+" in r.scene for r in damping)
    reg = {r.variation for r in runs if r.track == "regularization"}
    assert len(reg) == 5 and all(r.startswith("vvt.alpha_v=") for r in reg)


def test_leaderboard(micro, tmp_path):
    from vvtbench.cli.leaderboard import main_leaderboard

    _, out, _ = micro
    lb = tmp_path / "lb"
    assert main_leaderboard([str(out / "results.parquet"), "-o", str(lb)]) == 0
    text = (lb / "README.md").read_text()
    assert "## main — true modes" in text and "| 1 |" in text
    page = (lb / "index.html").read_text()
    assert "<table>" in page and "figures/main_slices.png" in page
    assert (lb / "figures" / "main_slices.png").is_file()
    assert (lb / "figures" / "main_intrinsic_resolution.png").is_file()


def test_line_fit_revision_changes_only_the_line_fit_extraction_keys(monkeypatch):
    import dataclasses

    from vvtbench.bench import build_graph

    smoke = load_suite("smoke")
    fitted = dataclasses.replace(smoke, extract={**smoke.extract, "line_fit": True})

    def keys(suite):
        tasks, _ = build_graph(suite, ["homogeneous"])
        return {(t.stage, t.label, t.key) for t in tasks.values()}

    before = keys(smoke), keys(fitted)
    from vvtbench.modes import revision

    monkeypatch.setattr(revision, "LINE_FIT_REVISION", revision.LINE_FIT_REVISION + 1)
    after = keys(smoke), keys(fitted)
    assert after[0] == before[0]  # suites without the line fit keep their cache
    changed = {s for s, _, _ in before[1] ^ after[1]}
    assert {"extract", "observe"} <= changed and "generate" not in changed


def test_pole_revision_changes_only_the_keys_of_pole_identifiers(monkeypatch):
    import dataclasses

    from vvtbench.bench import build_graph

    smoke = load_suite("smoke")
    poles = dataclasses.replace(smoke, extract={**smoke.extract, "identifier": "auto"})

    def keys(suite):
        tasks, _ = build_graph(suite, ["homogeneous"])
        return {(t.stage, t.label, t.key) for t in tasks.values()}

    before = keys(smoke), keys(poles)
    assert before[0] != before[1]
    from vvtbench.modes import revision

    monkeypatch.setattr(revision, "POLE_REVISION", revision.POLE_REVISION + 1)
    after = keys(smoke), keys(poles)
    assert after[0] == before[0]  # peak-picked suites keep their cache
    changed = {s for s, _, _ in before[1] ^ after[1]}
    assert {"extract", "observe"} <= changed and "generate" not in changed


def test_extractors_are_ranked_on_the_same_videos(micro, tmp_path):
    """An ``extracted:NAME`` source runs another extractor on the cached videos; the default
    source keeps its cache; the leaderboard ranks the extractors."""
    from vvtbench.reporting.leaderboard import build, extraction_table, extractor_ranking

    suite_file, out, _ = micro
    two = tmp_path / "two.toml"
    two.write_text(suite_file.read_text()
                   .replace('observations = ["true", "extracted"]',
                            'observations = ["extracted", "extracted:farneback"]')
                   .replace("[solver.vvt]", "[extract.extractor.farneback]\nwinsize = 11\n\n"
                            "[solver.vvt]"))
    df = run_suite(str(two), ["homogeneous"], out, progress=False)
    assert _computed(df) == {"generate": 0, "extract": 1, "observe": 1, "solve": 1,
                             "evaluate": 1}
    assert list(df.observation) == ["extracted", "extracted:farneback"]
    assert (df.status == "ok").all() and check_results(df) == []
    assert df.extraction_recall.between(0, 1).all() and df.extraction_recall.notna().all()
    ranked = extractor_ranking(df, "main")
    assert set(ranked.observation) == {"extracted", "extracted:farneback"}
    assert ranked.videos.tolist() == [1, 1] and list(ranked.columns)[:4] == [
        "observation", "extractor", "videos", "F1"]
    assert set(ranked.extractor) == {"phase (default)", "farneback"}
    table = extraction_table(df, "main")
    assert table.observation.tolist() == ["extracted", "extracted:farneback"]
    lb = build(out / "results.parquet", tmp_path / "lb")
    page = (lb / "index.html").read_text()
    assert "extractors ranked on the same videos" in page
    assert "how far an extractor is from what the video physically allows" in page
    assert "The Cramér–Rao ruler" in (lb / "README.md").read_text()
    one = extraction_table(df[df.observation == "extracted"], "main")
    assert "observation" not in one.columns and extractor_ranking(
        df[df.observation == "extracted"], "main") is None


def test_default_extractor_configured_changes_only_extracted_keys():
    import dataclasses

    from vvtbench.bench import build_graph
    from vvtbench.bench.graph import extract_options

    smoke = load_suite("smoke")
    phase = {"spec": "phase", "name": "phase", "version": "x", "config": {}}
    plain = dataclasses.replace(smoke, extractors={"phase": phase})
    tuned = dataclasses.replace(smoke, extractors={"phase": {**phase, "config": {"sigma": 3.0}}})
    assert extract_options(plain, "extracted") == (smoke.extract, smoke.extract)
    opts, key = extract_options(tuned, "extracted")
    assert opts["extractor_config"] == {"sigma": 3.0} and key["extractor"] == "phase x"
    assert extract_options(tuned, "true") == (smoke.extract, smoke.extract)

    def keys(suite):
        tasks, _ = build_graph(suite, ["homogeneous"])
        return {(t.stage, t.key) for t in tasks.values()}

    assert keys(plain) == keys(smoke)
    changed = {s for s, _ in keys(tuned) ^ keys(smoke)}
    assert changed == {"extract", "observe", "solve", "evaluate"}


def test_extraction_variant_runs_on_the_same_video_and_pairs_with_its_base(micro, tmp_path):
    """An ``extracted@NAME`` source extracts the cached video again with the variant's options:
    no second render, its own extraction and ranking table, rows paired with the base's; the
    leaderboard shows both sources and the paired difference."""
    from vvtbench.reporting.leaderboard import (
        build,
        extraction_sources,
        extraction_variants,
        extractor_ranking,
    )

    suite_file, out, _ = micro
    run = tmp_path / "run"
    shutil.copytree(out, run)  # the micro run's cache: its video is rendered already
    two = tmp_path / "two.toml"
    two.write_text(suite_file.read_text()
                   .replace('observations = ["true", "extracted"]',
                            'observations = ["extracted", "extracted@few"]')
                   .replace("[solver.vvt]", "[extract.variants.few]\nmax_modes = 3\n\n"
                            "[solver.vvt]"))
    df = run_suite(str(two), ["homogeneous", "vvt"], run, progress=False)
    assert _computed(df) == {"generate": 0, "extract": 1, "observe": 1, "solve": 2,
                             "evaluate": 2}
    assert (df.status == "ok").all() and check_results(df) == []
    assert set(df.observation) == {"extracted", "extracted@few"}
    base, few = (df[df.observation == o].set_index(["solver", "scene", "variation", "seed"])
                 for o in ("extracted", "extracted@few"))
    assert sorted(base.index) == sorted(few.index)  # the same instances
    assert (few.n_modes_observed <= 3).all()
    assert set(df.dataset_revision) == {df.dataset_revision.iloc[0]}  # one video
    # undamped truth: the damping error is undefined, never a number
    assert df.extraction_median_rel_damping_error.isna().all()

    sources = extraction_sources(df, "main")
    assert sources.observation.tolist() == ["extracted", "extracted@few"]
    assert {"precision", "recall (detectable)", "damping error", "NC w vvt",
            "NC w homogeneous"} <= set(sources.columns)
    assert (sources["damping error"] == "–").all()
    paired = extraction_variants(df, "main")
    assert paired.observation.tolist() == ["extracted@few"]
    assert paired.against.tolist() == ["extracted"] and paired.videos.tolist() == [1]
    assert paired["Δ NC w homogeneous"].iloc[0] == "+0.000 (n=1)"
    assert paired["Δ damping error"].iloc[0] == "–"
    assert paired["Δ precision"].iloc[0].endswith("(n=1)")
    ranked = extractor_ranking(df, "main")
    assert set(ranked.extractor) == {"phase (default)", "phase (default), variant few"}
    assert extraction_variants(df[df.observation == "extracted"], "main") is None

    lb = build(run / "results.parquet", tmp_path / "lb")
    text = (lb / "README.md").read_text()
    assert "main — extracted@few modes: ranking by mean NC w" in text
    assert "main — extraction and NC w from each source" in text
    assert "main — extraction variants against their base (paired, same videos)" in text
    assert "+0.000 (n=1)" in text


def test_an_unknown_extraction_variant_is_a_one_line_error(tmp_path):
    from vvtbench.bench import SuiteError

    bad = tmp_path / "bad.toml"
    bad.write_text(MICRO.replace('observations = ["true", "extracted"]',
                                 'observations = ["extracted", "extracted@nope"]'))
    with pytest.raises(SuiteError) as error:
        load_suite(bad)
    msg = str(error.value)
    assert "\n" not in msg and str(bad) in msg and "key 'observations[1]'" in msg
    assert "'nope'" in msg and "[extract.variants.NAME]" in msg
