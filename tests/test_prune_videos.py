"""`vvtbench run --prune-videos`: a sample's videos leave the cache once every task reading
them is done; the table is the one an unpruned run gives; a rerun renders nothing; a rerun
that needs a video renders it again, checked against the recorded sha256; the cache stays
honest about every other missing file."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import pytest

pd = pytest.importorskip("pandas")
pytest.importorskip("pyarrow")

from vvtbench.bench import SuiteError, build_graph, load_suite, read_results, run_suite  # noqa: E402
from vvtbench.bench import prune as prune_module  # noqa: E402
from vvtbench.bench.prune import (  # noqa: E402
    VideoPlan,
    dependants,
    pruned_absent,
    pruned_files,
    video_readers,
)
from vvtbench.bench.stages import execute_task, verify_cached  # noqa: E402
from vvtbench.cli.run import main_check_results, main_run  # noqa: E402
from vvtbench.samples.reader import sha256_file  # noqa: E402

# one cube seen by a rig of two cameras; one row from view 0 alone, one from both views
SUITE = """
name = "prune_micro"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous"]
seeds = [2]
observations = ["extracted"]

[defaults]
"geometry.cells" = [4, 4, 4]
"simulation.n_modes" = 6
"simulation.fps" = 200.0
"simulation.duration" = 0.8
"camera.resolution" = [64, 64]
"camera.rig.views" = 2
"excitation.displacement" = 0.002
"render.supersample" = 1
n_modes = 3
inference_shape = [2, 2, 2]

[extract]
max_modes = 6
fmax = 95.0

[[tracks]]
name = "views"
scenes = ["jello_cube_defect_top"]
[tracks.sweep]
views = [1, 2]
"""

# the same suite with one more extraction source on the same sample
FLOW = SUITE + """
[[tracks]]
name = "flow"
scenes = ["jello_cube_defect_top"]
observations = ["extracted:farneback"]
"""

VIDEOS = ("sample/video.mkv", "sample/views/1/video.mkv")


def _quiet_main(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main_run(argv)
    return code, out.getvalue(), err.getvalue()


def _gen(run: Path) -> Path:
    (folder,) = [p for p in (run / "cache" / "generate").iterdir() if p.name != "_work"]
    return folder


def _table(run: Path):
    return read_results(run / "results.parquet").drop(columns="runtime_s")


def _same_scores(a, b) -> None:
    """Every column but the runtime agrees; the bytes of an observation computed again in
    another process (another BLAS thread count) may differ in the last bit, so their sha256
    is left out and the scores are compared to 1e-9."""
    cols = [c for c in a.columns if c not in ("runtime_s", "estimate_sha256",
                                              "observation_sha256")]
    pd.testing.assert_frame_equal(a[cols].reset_index(drop=True),
                                  b[cols].reset_index(drop=True), check_dtype=False,
                                  check_exact=False, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The suite run without pruning (``plain``), then with ``--prune-videos --workers 2``
    (``pruned``) on a copy of the plain run's rendered sample and extracted modes: the
    observations, solves and scores run again and the videos are pruned after them. Records,
    at each prune, which of the sample's readers had finished."""
    root = tmp_path_factory.mktemp("prune")
    suite = root / "prune.toml"
    suite.write_text(SUITE)
    plain = root / "plain"
    df = run_suite(str(suite), None, plain, progress=False)
    assert (df.status == "ok").all(), df.error.tolist()
    pruned = root / "pruned"
    for stage in ("generate", "extract"):
        shutil.copytree(plain / "cache" / stage, pruned / "cache" / stage)
    tasks, _ = build_graph(load_suite(str(suite)), ["homogeneous"])
    readers = video_readers(tasks)
    seen = []
    real = prune_module.prune_sample

    def spy(cache, gen_key):
        seen.append((gen_key, {r: (Path(cache) / r / "task.json").is_file()
                               for r in readers[gen_key]}))
        return real(cache, gen_key)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(prune_module, "prune_sample", spy)
        code, out, err = _quiet_main([str(suite), "-o", str(pruned), "--prune-videos",
                                      "--workers", "2", "--no-progress"])
    assert code == 0, err
    return {"suite": suite, "plain": plain, "pruned": pruned, "out": out, "err": err,
            "seen": seen, "tasks": tasks, "readers": readers}


def test_videos_go_after_their_last_reader_and_the_table_is_the_unpruned_one(runs):
    plain, pruned = runs["plain"], runs["pruned"]
    gen = _gen(pruned)
    for rel in VIDEOS:
        assert (_gen(plain) / rel).is_file() and not (gen / rel).exists()
    for kept in ("sample/preview.mp4", "sample/truth.json", "sample/manifest.json",
                 "sample/views/1/camera.json"):
        assert (gen / kept).is_file()
    # the joint observation of both views read both videos before they went
    readers = runs["readers"][f"generate/{gen.name}"]
    stages = sorted(runs["tasks"][r].stage for r in readers)
    assert stages == ["extract", "extract", "observe", "observe"]
    assert runs["seen"] == [(f"generate/{gen.name}", dict.fromkeys(readers, True))]
    info = json.loads((gen / "task.json").read_text())
    record = info["pruned"]
    assert record["at"].endswith("Z") and sorted(e["name"] for e in record["files"]) == list(
        VIDEOS)
    sizes = 0
    for e in record["files"]:
        assert e["sha256"] == sha256_file(_gen(plain) / e["name"]) == info["files"][e["name"]]
        assert e["bytes"] == (_gen(plain) / e["name"]).stat().st_size > 0
        sizes += e["bytes"]
    assert verify_cached(gen, info) is None
    summary = [line for line in runs["out"].splitlines() if " rows in " in line][0]
    assert f"videos of 1 sample(s) pruned, {sizes / 1e9:.3g} GB freed" in summary
    run_json = json.loads((pruned / "run.json").read_text())
    assert run_json["pruned"] == {"samples": 1, "files": 2, "bytes": sizes}
    assert run_json["stats"]["observe"]["computed"] == 2  # the readers really ran
    # every score of every row is the unpruned run's
    _same_scores(_table(plain), _table(pruned))
    assert main_check_results([str(pruned)]) == 0


def test_leaderboard_reads_a_pruned_run(runs, tmp_path):
    from vvtbench.cli.leaderboard import main_leaderboard

    board = tmp_path / "board"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main_leaderboard([str(runs["pruned"] / "results.parquet"), "-o",
                                 str(board)]) == 0
    assert "views" in (board / "README.md").read_text()


def test_verify_counts_a_pruned_video_as_absent_on_purpose_and_nothing_else(runs, tmp_path):
    from vvtbench.cli.verify import verify_run

    run = tmp_path / "run"
    shutil.copytree(runs["pruned"], run)
    assert list(verify_run(run, full=False)) == []
    (_gen(run) / "sample" / "preview.mp4").unlink()
    problems = list(verify_run(run, full=False))
    assert problems and all("preview.mp4" in p for p in problems), problems


def test_rerun_renders_nothing(runs):
    pruned = runs["pruned"]
    before = _table(pruned)
    df = run_suite(str(runs["suite"]), None, pruned, progress=False, prune_videos=True)
    assert all(v["computed"] == 0 and v["cached"] == v["tasks"]
               for v in df.attrs["stats"].values()), df.attrs["stats"]
    assert df.attrs["rerendered"] == [] and df.attrs["pruned"]["bytes"] == 0
    pd.testing.assert_frame_equal(before, read_results(pruned).drop(columns="runtime_s"))
    _same_scores(before, df)


def test_a_cached_run_is_pruned_on_a_dask_cluster(runs, tmp_path):
    """The scheduler prunes whichever executor runs the tasks: an unpruned run's folder rerun
    on Dask with pruning computes nothing and deletes the videos."""
    distributed = pytest.importorskip("distributed")
    run = tmp_path / "run"
    shutil.copytree(runs["plain"], run, ignore=shutil.ignore_patterns(".lock"))
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            df = run_suite(str(runs["suite"]), None, run, scheduler=client, progress=False,
                           prune_videos=True)
    assert all(v["computed"] == 0 for v in df.attrs["stats"].values())
    assert df.attrs["pruned"]["samples"] == 1 and df.attrs["pruned"]["files"] == 2
    assert not any((_gen(run) / rel).exists() for rel in VIDEOS)
    _same_scores(_table(runs["plain"]), df)


def test_a_new_extractor_renders_the_sample_again_once(runs, tmp_path):
    """A source added to the suite reads the video: the sample is rendered again (seeded: the
    same bytes as the pruned video, said in one line), the old rows keep their scores, the
    new row is scored, and the videos are pruned again."""
    run = tmp_path / "run"
    shutil.copytree(runs["pruned"], run, ignore=shutil.ignore_patterns(".lock"))
    flow = tmp_path / "flow.toml"
    flow.write_text(FLOW)
    code, out, err = _quiet_main([str(flow), "-o", str(run), "--prune-videos", "--no-progress"])
    assert code == 0, err
    stats = json.loads((run / "run.json").read_text())["stats"]
    assert stats["generate"]["computed"] == 1 and stats["extract"]["computed"] == 1
    assert stats["observe"]["computed"] == 1 and stats["evaluate"]["computed"] == 1
    lines = [x for x in err.splitlines() if x.startswith("re-rendered ")]
    assert len(lines) == 1 and "needed again by 2 task(s)" in lines[0]
    assert "the new video's sha256 is the recorded one" in lines[0]
    df = _table(run)
    pd.testing.assert_frame_equal(df[df.track == "views"].reset_index(drop=True),
                                  _table(runs["pruned"]))
    new = df[df.track == "flow"]
    assert len(new) == 1 and (new.status == "ok").all() and new.observation.tolist() == [
        "extracted:farneback"]
    assert new.extraction_recall.between(0, 1).all() and new.n_modes_observed.ge(1).all()
    gen = _gen(run)
    assert not any((gen / rel).exists() for rel in VIDEOS)
    assert sorted(pruned_files(json.loads((gen / "task.json").read_text()))) == list(VIDEOS)


def test_a_deleted_file_that_was_not_pruned_is_damage(runs, tmp_path):
    gen = tmp_path / "gen"
    shutil.copytree(_gen(runs["pruned"]), gen)
    info = json.loads((gen / "task.json").read_text())
    assert verify_cached(gen, info) is None and pruned_absent(gen) == set(VIDEOS)
    (gen / "sample" / "preview.mp4").unlink()
    assert verify_cached(gen, info) == "sample/preview.mp4: deleted"
    shutil.copy2(_gen(runs["plain"]) / "sample" / "preview.mp4", gen / "sample" / "preview.mp4")
    # a pruned file brought back must be the recorded one
    (gen / VIDEOS[1]).write_bytes(b"not the video")
    assert verify_cached(gen, info) == f"{VIDEOS[1]}: sha256 mismatch (edited or truncated)"
    (gen / VIDEOS[1]).unlink()
    # a record that does not name the file's recorded sha256 does not excuse its absence
    info["pruned"]["files"][0]["sha256"] = "0" * 64
    assert verify_cached(gen, info) == f"{info['pruned']['files'][0]['name']}: deleted"


def test_a_different_render_recomputes_everything_downstream(runs, tmp_path):
    """When the re-rendered video's sha256 is not the recorded one, every task below the
    sample is forced; a forced task computes again and replaces its cached output."""
    run = tmp_path / "run"
    shutil.copytree(runs["pruned"], run, ignore=shutil.ignore_patterns(".lock"))
    cache = run / "cache"
    tasks = runs["tasks"]
    (g,) = [k for k in tasks if k.startswith("generate/")]
    plan = VideoPlan.build(tasks, cache)
    assert set(plan.records) == {g} and plan.forced == {}  # every reader is cached
    plan.records[g] = {**plan.records[g], VIDEOS[0]: {"bytes": 1, "sha256": "f" * 64}}
    plan.finished(g, {g: {"status": "ok", "computed": True}})
    below = dependants(tasks, g)
    assert set(plan.forced) == set(below) and len(below) == len(tasks) - 1
    assert "differs from the pruned one" in plan.forced[below[0]]
    (entry,) = plan.rerendered
    assert entry["same"] is False and entry["recomputed"] == len(below)
    evaluate = next(t for t in tasks.values() if t.stage == "evaluate")
    metrics = (cache / evaluate.key / "metrics.json").read_text()
    res = execute_task(str(cache), evaluate, force=plan.forced[evaluate.key])
    assert res["computed"] and res["status"] == "ok" and res["forced"] == plan.forced[
        evaluate.key]
    assert (cache / evaluate.key / "metrics.json").read_text() == metrics
    assert not [p for p in cache.glob("evaluate/*") if ".tmp-" in p.name]


def test_runs_that_need_the_samples_render_them_again(runs):
    """A run that stops at generate (``vvtbench export SUITE`` reusing the run folder) wants
    the samples themselves: a pruned one is rendered again."""
    suite = load_suite(str(runs["suite"]))
    tasks, _ = build_graph(suite, [], until="generate")
    plan = VideoPlan.build(tasks, runs["pruned"] / "cache")
    (g,) = tasks
    assert "samples are this run's output" in plan.forced[g]


def test_pruning_before_the_observations_is_refused(runs):
    with pytest.raises(SuiteError, match="prune_videos with until='generate' is not allowed"):
        run_suite(str(runs["suite"]), None, runs["pruned"], until="generate",
                  prune_videos=True, progress=False)


class _Recorder:
    """An executor that runs nothing: it records what it is handed, in order."""

    slots = 1

    def __init__(self):
        self.order: list[str] = []

    def submit(self, fn, cache, task, *args):
        self.order.append(task.key)
        outcome = {"key": task.key, "status": "ok", "computed": True, "seconds": 0.0}
        return type("Done", (), {"result": lambda self: outcome})()

    def wait_any(self, futures):
        return set(futures)


def _chain_graph(n: int) -> dict:
    from vvtbench.bench.graph import Task

    tasks = {}
    for i in range(n):
        tasks[f"g{i}"] = Task("generate", f"g{i}", [], {}, f"sample {i}")
        tasks[f"e{i}"] = Task("extract", f"e{i}", [f"g{i}"], {}, f"extract {i}")
    return tasks


@pytest.mark.parametrize("prune", [False, True])
def test_pruning_reads_each_sample_before_rendering_the_next(prune, tmp_path):
    from vvtbench.bench.executors import execute_graph

    tasks = _chain_graph(4)
    plan = VideoPlan(tasks, tmp_path, prune, {f"g{i}": [f"e{i}"] for i in range(4)})
    recorder = _Recorder()
    done = execute_graph(tasks, tmp_path, recorder, False, None, videos=plan)
    assert set(done) == set(tasks)
    if prune:  # one slot: a sample's reader runs before the next sample is rendered
        assert recorder.order == ["g0", "e0", "g1", "e1", "g2", "e2", "g3", "e3"]
    else:  # everything ready is handed out at once
        assert recorder.order == ["g0", "g1", "g2", "g3", "e0", "e1", "e2", "e3"]
