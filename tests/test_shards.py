"""A suite in shards: ``vvtbench run SUITE --shard K/N`` and ``vvtbench merge-shards``.

Two shards of a tiny suite merge into the table of the unsharded run (run times aside), every
score recomputed; a complete shard is not run again; an interrupted one resumes from its shard
folder on a machine without its cache; shards that do not make one run are refused, saying
which; a run of one more solver adds its rows to the table it finds."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pd = pytest.importorskip("pandas")
pytest.importorskip("pyarrow")

from vvtbench.bench import build_graph, load_suite, read_results, run_suite  # noqa: E402
from vvtbench.bench.graph import Task  # noqa: E402
from vvtbench.bench.merge import merge_shards  # noqa: E402
from vvtbench.bench.rescore import TOLERANCE  # noqa: E402
from vvtbench.bench.results import METRIC_COLUMNS  # noqa: E402
from vvtbench.bench.shards import (  # noqa: E402
    ShardError,
    ShardSpec,
    partition,
    read_shard,
    units,
)
from vvtbench.cli import main  # noqa: E402

# true modes only (modes-only samples, nothing rendered); two instances: one per shard
TINY = """
name = "tiny"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous"]
seeds = [0, 1]
observations = ["true"]

[defaults]
"geometry.cells" = [5, 5, 5]
"simulation.n_modes" = 8
"simulation.fps" = 400.0
"simulation.duration" = 0.5
"camera.resolution" = [64, 64]
n_modes = 4
inference_shape = [3, 3, 3]
"""

RUN_TIMES = ("runtime_s",)


def _same_table(a, b, exact: bool = True) -> None:
    cols = [c for c in a.columns if c not in RUN_TIMES]
    if exact:
        pd.testing.assert_frame_equal(a[cols].reset_index(drop=True),
                                      b[cols].reset_index(drop=True), check_dtype=False)
        return
    text = [c for c in cols if c not in METRIC_COLUMNS
            and c not in ("estimate_sha256", "observation_sha256")]
    pd.testing.assert_frame_equal(a[text].reset_index(drop=True),
                                  b[text].reset_index(drop=True), check_dtype=False)
    for c in METRIC_COLUMNS:
        x, y = a[c].to_numpy(float), b[c].to_numpy(float)
        assert ((abs(x - y) <= TOLERANCE) | (pd.isna(x) & pd.isna(y))).all(), c


@pytest.fixture(scope="module")
def flow(tmp_path_factory):
    """The whole suite, its two shards (in process) and their merge."""
    root = tmp_path_factory.mktemp("shards")
    suite = root / "tiny.toml"
    suite.write_text(TINY)
    whole = run_suite(str(suite), None, root / "whole", progress=False)
    shards = root / "shards"
    for k in (1, 2):
        df = run_suite(str(suite), None, root / f"run{k}", progress=False, shard=f"{k}/2",
                       shard_dir=shards / f"{k}-of-2")
        assert len(df) == 1 and not df.attrs["shard"]["nothing_to_do"]
    merged = merge_shards([shards], root / "merged", progress=False)
    return {"root": root, "suite": suite, "whole": whole, "shards": shards, "merged": merged}


def test_two_shards_merge_into_the_unsharded_table(flow):
    whole, merged, root = flow["whole"], flow["merged"], flow["root"]
    assert len(whole) == 2
    _same_table(read_results(root / "whole"), read_results(root / "merged"))
    assert merged.attrs["differences"] == []
    truth = merged.attrs["truth"]
    assert truth["samples_same"] == truth["samples"] == 2
    assert truth["observations_same"] == truth["observations"] == 2
    stats = merged.attrs["stats"]  # nothing solved at the merge: every score recomputed
    assert stats["solve"]["computed"] == 0 and stats["solve"]["cached"] == 2
    assert stats["evaluate"]["computed"] == 2 and stats["observe"]["computed"] == 2
    run = json.loads((root / "merged" / "run.json").read_text())
    assert [m["shard"] for m in run["merged_from"]] == ["1/2", "2/2"]
    assert main(["check-results", str(root / "merged")]) == 0


def test_a_shard_folder_holds_rows_estimates_and_hashes_only(flow):
    folder = flow["shards"] / "1-of-2"
    shard = read_shard(folder)
    meta = shard.meta
    assert meta["complete"] and meta["shard"]["k"] == 1 and meta["shard"]["n"] == 2
    assert meta["suite"]["name"] == "tiny" and len(meta["suite"]["sha256"]) == 64
    assert [s["name"] for s in meta["solvers"]] == ["homogeneous"]
    assert meta["solvers"][0]["version"] and meta["limits"]["timeout_s"] > 0
    on_disk = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                     if p.is_file())
    assert on_disk == sorted([*meta["files"], "shard.json"])
    for name in meta["files"]:
        assert name == "results.csv" or name.startswith("solve/"), name
        assert Path(name).name in ("results.csv", "estimate.npz", "estimate.json",
                                   "task.json")
    assert len(shard.rows) == 1 and shard.rows.loc[0, "status"] == "ok"
    # each task of the shard is recorded, and the rows name their estimate's sha256
    stages = sorted(r["stage"] for r in meta["tasks"].values())
    assert stages == ["evaluate", "generate", "observe", "solve"]
    solve = next(k for k, r in meta["tasks"].items() if r["stage"] == "solve")
    assert meta["files"][f"{solve}/estimate.npz"] == shard.rows.loc[0, "estimate_sha256"]
    assert sum((folder / n).stat().st_size for n in meta["files"]) < 100_000


def test_a_complete_shard_is_not_run_again(flow, tmp_path):
    # another machine: the shard folder from git, no run folder
    copy = tmp_path / "1-of-2"
    shutil.copytree(flow["shards"] / "1-of-2", copy)
    before = (copy / "shard.json").read_text()
    df = run_suite(str(flow["suite"]), None, tmp_path / "fresh", progress=False, shard="1/2",
                   shard_dir=copy)
    assert df.attrs["shard"]["nothing_to_do"]
    assert len(df) == 1 and not (tmp_path / "fresh" / "cache").exists()
    assert (copy / "shard.json").read_text() == before


def test_an_interrupted_shard_resumes_from_its_folder(flow, tmp_path, monkeypatch):
    """Ctrl-C after the solve: the shard folder keeps the estimate; the next sitting, on a
    machine without the run folder, solves nothing again."""
    from vvtbench.bench import runner
    from vvtbench.bench.executors import Interrupted

    real = runner.execute_graph

    def stopped(tasks, cache, *args, **kwargs):  # Ctrl-C once all but the evaluation ran
        real({k: t for k, t in tasks.items() if t.stage != "evaluate"}, cache, *args,
             **kwargs)
        raise Interrupted(3, len(tasks))

    folder = tmp_path / "2-of-2"
    monkeypatch.setattr(runner, "execute_graph", stopped)
    with pytest.raises(Interrupted):
        run_suite(str(flow["suite"]), None, tmp_path / "old", progress=False, shard="2/2",
                  shard_dir=folder)
    monkeypatch.undo()
    partial = read_shard(folder)
    assert not partial.complete and partial.meta["counts"]["tasks_pending"] == 1
    assert [r["stage"] for r in partial.tasks.values() if r["status"] == "pending"] == [
        "evaluate"]
    assert list(folder.glob("solve/*/estimate.npz"))
    df = run_suite(str(flow["suite"]), None, tmp_path / "fresh", progress=False,
                   shard="2/2", shard_dir=folder)
    stats = df.attrs["stats"]
    assert stats["solve"]["computed"] == 0 and stats["solve"]["cached"] == 1
    assert stats["evaluate"]["computed"] == 1
    assert df.attrs["shard"]["seeded"]["solve"] == 1
    assert read_shard(folder).complete
    _same_table(df, read_shard(flow["shards"] / "2-of-2").rows)


def _shard_copies(flow, tmp_path) -> tuple[Path, Path]:
    a, b = tmp_path / "a" / "1-of-2", tmp_path / "b" / "2-of-2"
    shutil.copytree(flow["shards"] / "1-of-2", a)
    shutil.copytree(flow["shards"] / "2-of-2", b)
    return a, b


def _edit(folder: Path, **changes) -> None:
    doc = json.loads((folder / "shard.json").read_text())
    for path, value in changes.items():
        node = doc
        *head, last = path.split("__")
        for key in head:
            node = node[key]
        node[last] = value
    (folder / "shard.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("case, message", [
    ("missing", r"shard\(s\) 2/2 missing \(have 1/2\)"),
    ("twice", r"shard 1/2 given 2 times"),
    ("version", r"vvtbench version '0\.0\.0'"),
    ("suite", r"suite file sha256"),
    ("n", r"number of shards N"),
    ("incomplete", r"is not complete"),
    ("tampered", r"estimate\.npz: sha256 mismatch"),
    ("overlap", r"shards 1/2 \(.*\) and 2/2 \(.*\) both hold task"),
    ("foreign", r"holds 5 tasks, this suite gives it 4 \(1 not its own, 0 lacking"),
])
def test_shards_that_do_not_make_one_run_are_refused(flow, tmp_path, capsys, case, message):
    a, b = _shard_copies(flow, tmp_path)
    given = [a, b]
    if case == "missing":
        given = [a]
    elif case == "twice":
        given = [a, a, b]
    elif case == "version":
        _edit(b, vvtbench="0.0.0")
    elif case == "suite":
        _edit(b, suite__sha256="0" * 64)
    elif case == "n":
        _edit(b, shard__n=3)
    elif case == "incomplete":
        _edit(b, complete=False)
    elif case == "tampered":
        est = next(b.glob("solve/*/estimate.npz"))
        est.write_bytes(est.read_bytes()[:-10])
    elif case == "overlap":  # the other shard's tasks under this shard's name
        doc = json.loads((a / "shard.json").read_text())
        _edit(b, tasks=doc["tasks"])
    elif case == "foreign":  # a task of another suite (or solver, or version)
        doc = json.loads((b / "shard.json").read_text())
        _edit(b, tasks={**doc["tasks"], "solve/0123456789abcdef": {"stage": "solve",
                                                                   "status": "ok"}})
    with pytest.raises(ShardError, match=message):
        merge_shards(given, tmp_path / "out", progress=False)
    assert not (tmp_path / "out" / "results.parquet").exists()
    code = main(["merge-shards", *map(str, given), "-o", str(tmp_path / "out2")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("error: ") and "\n" not in err
    assert "Traceback" not in err


def test_shards_do_not_depend_on_the_executor(flow, tmp_path):
    """Shard 2 on a local pool of two processes holds the tasks the in-process run chose, and
    merges with shard 1 into the unsharded table (scores within the check-results tolerance:
    one BLAS thread per task changes the eigen-solves' last bits)."""
    pooled = tmp_path / "2-of-2"
    df = run_suite(str(flow["suite"]), None, tmp_path / "run", workers=2, progress=False,
                   shard="2/2", shard_dir=pooled)
    assert set(read_shard(pooled).tasks) == set(read_shard(flow["shards"] / "2-of-2").tasks)
    assert len(df) == 1
    merged = merge_shards([flow["shards"] / "1-of-2", pooled], tmp_path / "merged",
                          progress=False)
    assert merged.attrs["differences"] == []
    _same_table(read_results(flow["root"] / "whole"), read_results(tmp_path / "merged"),
                exact=False)


def test_the_partition_keeps_instances_whole_and_is_stable():
    suite = load_suite("smoke")
    tasks, runs = build_graph(suite, ["homogeneous"])
    for n in (1, 2, 3):
        parts = partition(tasks, runs, n)
        keys = [k for p in parts for u in p for k in u.tasks]
        assert sorted(keys) == sorted(tasks)  # every task once
        shard_of = {k: i for i, p in enumerate(parts) for u in p for k in u.tasks}
        for k, t in tasks.items():  # a video's generate, extract, observe... in one shard
            assert all(shard_of[d] == shard_of[k] for d in t.deps)
        assert sorted(i for p in parts for u in p for i in u.runs) == list(range(len(runs)))
    # the same with other solvers: the shards hold the same instances
    tasks2, runs2 = build_graph(suite, ["homogeneous", "oracle"])
    assert [[u.id for u in p] for p in partition(tasks, runs, 2)] == \
        [[u.id for u in p] for p in partition(tasks2, runs2, 2)]
    assert {u.id for u in units(tasks, runs)} == {u.id for u in units(tasks2, runs2)}


def test_the_partition_balances_the_estimated_cost():
    def unit(i: int, frames: float) -> dict[str, Task]:
        scene = {"simulation": {"fps": frames, "duration": 1.0},
                 "camera": {"resolution": [1000, 1000]}, "render": {"supersample": 1}}
        g = Task("generate", f"generate/{i}", [], {"scene": scene, "video": True}, f"s{i}")
        return {g.key: g, f"extract/{i}": Task("extract", f"extract/{i}", [g.key], {}, "")}

    tasks: dict[str, Task] = {}
    for i, frames in enumerate([10000, 100, 100, 100, 9900]):
        tasks.update(unit(i, frames))
    parts = partition(tasks, [], 2)
    costs = [sum(u.cost for u in p) for p in parts]
    assert sorted(len(p) for p in parts) == [2, 3]
    assert max(costs) / min(costs) < 1.1
    with pytest.raises(ShardError, match="allowed: K/N"):
        ShardSpec.parse("3/2")
    with pytest.raises(ShardError, match="allowed: K/N"):
        ShardSpec.parse("two")


def test_run_shard_cli_errors_are_one_line(flow, tmp_path, capsys):
    for argv, needle in (
            (["run", str(flow["suite"]), "--shard", "0/2"], "--shard '0/2': not allowed"),
            (["run", str(flow["suite"]), "--shard-dir", str(tmp_path)], "needs --shard"),
            (["run", str(flow["suite"]), "--shard", "3/3", "-o", str(tmp_path / "r3")],
             "the suite has 2 instance(s) to deal out"),
    ):
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code == 2 and needle in err and "\n" not in err, err
    other = tmp_path / "taken"
    shutil.copytree(flow["shards"] / "1-of-2", other)
    code = main(["run", str(flow["suite"]), "--shard", "2/2", "--shard-dir", str(other),
                 "-o", str(tmp_path / "r"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "holds shard 1/2 of suite 'tiny', not shard 2/2" in err


def test_a_run_of_one_more_solver_adds_its_rows(flow, tmp_path, capsys):
    out = tmp_path / "run"
    shutil.copytree(flow["root"] / "whole", out)
    code = main(["run", str(flow["suite"]), "--solvers", "oracle", "-o", str(out),
                 "--no-progress"])
    text = capsys.readouterr().out
    assert code == 0
    assert "kept 2 row(s) of homogeneous" in text
    df = read_results(out)
    assert list(df["solver"]) == ["homogeneous", "oracle", "homogeneous", "oracle"]
    assert list(df["seed"]) == [0, 0, 1, 1]
    _same_table(df[df.solver == "homogeneous"], read_results(flow["root"] / "whole"))
    assert main(["check-results", str(out)]) == 0
    # an evaluation gone from the cache: that row of the other solver is not current
    gone = df.loc[(df.solver == "homogeneous") & (df.seed == 1), "estimate_path"].item()
    shutil.rmtree(out / Path(gone).parent)
    code = main(["run", str(flow["suite"]), "--solvers", "oracle", "-o", str(out),
                 "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0
    assert "dropped 1 row(s) of homogeneous" in captured.err
    assert "--solvers homogeneous" in captured.err
    df = read_results(out)
    assert list(df["solver"]) == ["homogeneous", "oracle", "oracle"]
    assert list(df["seed"]) == [0, 0, 1]
    # the table of another suite file is replaced, as it always was
    other = tmp_path / "other.toml"
    other.write_text(TINY)
    assert main(["run", str(other), "--solvers", "oracle", "-o", str(out),
                 "--no-progress"]) == 0
    assert list(read_results(out)["solver"]) == ["oracle", "oracle"]

def test_a_score_a_shard_states_is_recomputed_not_copied(flow, tmp_path, capsys):
    a, b = _shard_copies(flow, tmp_path)
    rows = pd.read_csv(b / "results.csv", dtype=str, keep_default_na=False)
    true = float(rows.loc[0, "mode_mac"])
    rows.loc[0, "mode_mac"] = "0.5"
    rows.to_csv(b / "results.csv", index=False)
    from vvtbench.samples.reader import sha256_file

    doc = json.loads((b / "shard.json").read_text())
    _edit(b, files={**doc["files"], "results.csv": sha256_file(b / "results.csv")})
    out = tmp_path / "merged"
    code = main(["merge-shards", str(a), str(b), "-o", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "1 row(s) recomputed differently" in err
    assert "mode_mac" in err and "0.5 in the shard" in err
    df = read_results(out)
    assert abs(df.loc[df.seed == int(rows.loc[0, "seed"]), "mode_mac"].item() - true) < 1e-9


# --------------------------------------------------------------------------- video tracks

# a cube filmed by one camera (observed alone and through the field path) and by a rig of
# two (one view, and both joined): two instances, one per shard
TINY_VIDEO = """
name = "tiny_video"
solvers = ["homogeneous"]
seeds = [2]
observations = ["extracted"]

[defaults]
"geometry.cells" = [4, 4, 4]
"simulation.n_modes" = 6
"simulation.fps" = 200.0
"simulation.duration" = 0.8
"camera.resolution" = [64, 64]
"excitation.displacement" = 0.002
"render.supersample" = 1
"render.read_noise_dn" = 8.0   # the background moves in the video: joined views read it
n_modes = 3
inference_shape = [2, 2, 2]

[extract]
max_modes = 6
fmax = 95.0

[[tracks]]
name = "video"
scenes = ["jello_cube_defect_top"]

[[tracks]]
name = "field"
scenes = ["jello_cube_defect_top"]
[tracks.field]
format = "tiff"
bit_depth = 12

[[tracks]]
name = "views"
scenes = ["jello_cube_defect_top"]
[tracks.defaults]
"camera.rig.views" = 2
[tracks.sweep]
views = [1, 2]
"""


@pytest.fixture(scope="module")
def video_flow(tmp_path_factory):
    """The video suite whole, its two shards (from the whole run's cache: nothing computed
    again) and their merge (in a folder of its own: every observation and score
    recomputed)."""
    root = tmp_path_factory.mktemp("video_shards")
    suite = root / "tiny_video.toml"
    suite.write_text(TINY_VIDEO)
    whole = run_suite(str(suite), None, root / "whole", progress=False)
    assert (whole["status"] == "ok").all(), whole[["track", "variation", "error"]]
    shards = root / "shards"
    for k in (1, 2):
        run_suite(str(suite), None, root / "whole", progress=False, shard=f"{k}/2",
                  shard_dir=shards / f"{k}-of-2")
    merged = merge_shards([shards], root / "merged", progress=False)
    return {"root": root, "suite": suite, "whole": whole, "shards": shards, "merged": merged}


def _extractions(folder: Path) -> dict[str, dict]:
    """``{extract key: its record in shard.json}`` of a shard folder."""
    tasks = json.loads((folder / "shard.json").read_text())["tasks"]
    return {k: r for k, r in tasks.items() if r["stage"] == "extract"}


def test_video_shards_merge_into_the_unsharded_table(video_flow):
    """Every score of the merge equals the unsharded run's, byte for byte, and every
    observation made from the compact modes is the very bytes the whole frame gave."""
    root, merged = video_flow["root"], video_flow["merged"]
    assert len(video_flow["whole"]) == 4
    _same_table(read_results(root / "whole"), read_results(root / "merged"))
    assert merged.attrs["differences"] == []
    truth = merged.attrs["truth"]
    assert truth["observations_same"] == truth["observations"] == 4
    stats = merged.attrs["stats"]
    assert stats["extract"]["computed"] == 0 and stats["extract"]["cached"] == 4
    assert main(["check-results", str(root / "merged")]) == 0


def test_extracted_modes_are_kept_where_their_readers_read(video_flow):
    """One observation of one extraction: the shapes inside the box of what it samples and the
    scores read; joined views read every pixel: the whole frame. Written back, the modes
    equal the extraction's inside the box and are NaN outside."""
    from vvtbench.bench.compact import COMPACT_NAME
    from vvtbench.modes import ModeSet

    root = video_flow["root"]
    boxed = whole_frame = 0
    for folder in sorted(video_flow["shards"].iterdir()):
        for key, rec in _extractions(folder).items():
            assert not (folder / key / "modes.npz").exists()
            with np.load(folder / key / COMPACT_NAME) as z:
                shapes, box = z["shapes"], [int(x) for x in z["box"]]
            original = ModeSet.load(root / "whole" / "cache" / key)
            height, width = original.image_shape
            assert rec["modes"]["image_shape"] == [height, width]
            if rec["modes"]["box"] is None:
                whole_frame += 1
                assert "joins views" in rec["modes"]["why"]
                assert box == [0, height, 0, width]
            else:
                boxed += 1
                assert box == rec["modes"]["box"]
                assert (box[1] - box[0]) * (box[3] - box[2]) < 0.7 * height * width
            r0, r1, c0, c1 = box
            assert np.array_equal(shapes, original.shapes[:, r0:r1, c0:c1])
            restored = ModeSet.load(root / "merged" / "cache" / key)
            inside = restored.shapes[:, r0:r1, c0:c1]
            assert np.array_equal(inside, original.shapes[:, r0:r1, c0:c1])
            outside = restored.shapes.copy()
            outside[:, r0:r1, c0:c1] = np.nan
            assert np.isnan(outside).all()
            assert np.array_equal(restored.power, original.power)
            assert (root / "merged" / "cache" / key / "modes.json").read_bytes() == (
                root / "whole" / "cache" / key / "modes.json").read_bytes()
    assert (boxed, whole_frame) == (2, 2)  # one camera, its field video; the rig's two views


def test_a_box_that_leaves_out_read_pixels_is_caught(video_flow, tmp_path):
    """The check behind 'lossless': shapes cut into the object (past the box's margin, two
    pixels more on every side) change the observation the merge recomputes (it no longer has
    the bytes the shard recorded)."""
    from vvtbench.bench.compact import COMPACT_NAME, MARGIN_PX, compact_arrays, expand_arrays
    from vvtbench.io.files import write_npz
    from vvtbench.samples.reader import sha256_file

    copies = tmp_path / "shards"
    shutil.copytree(video_flow["shards"], copies)
    folder = next(f for f in sorted(copies.iterdir())
                  if any(r["modes"]["box"] for r in _extractions(f).values()))
    doc = json.loads((folder / "shard.json").read_text())
    for key, rec in _extractions(folder).items():
        if rec["modes"]["box"] is None:
            continue
        path = folder / key / COMPACT_NAME
        with np.load(path) as z:
            full = expand_arrays({k: z[k] for k in z.files})
        r0, r1, c0, c1 = rec["modes"]["box"]
        cut = MARGIN_PX + 2
        write_npz(path, compact_arrays(full, (r0 + cut, r1 - cut, c0 + cut, c1 - cut)))
        doc["files"][f"{key}/{COMPACT_NAME}"] = sha256_file(path)
    (folder / "shard.json").write_text(json.dumps(doc))
    merged = merge_shards([copies], tmp_path / "merged", progress=False)
    truth = merged.attrs["truth"]
    assert truth["observations_same"] < truth["observations"]


def test_an_interrupted_video_shard_resumes_from_its_compact_modes(video_flow, tmp_path):
    """On a machine without the run folder: the extractions come from the shard folder (none
    computed again), the observations of them are recomputed to the same bytes, and the
    shard folder is written again with the same boxes and shapes."""
    from vvtbench.bench.compact import COMPACT_NAME

    source = next(f for f in sorted(video_flow["shards"].iterdir())
                  if any(r["modes"]["box"] for r in _extractions(f).values()))
    copy = tmp_path / source.name
    shutil.copytree(source, copy)
    _edit(copy, complete=False)
    spec = f"{source.name.split('-')[0]}/2"
    df = run_suite(str(video_flow["suite"]), None, tmp_path / "fresh", progress=False,
                   shard=spec, shard_dir=copy)
    stats = df.attrs["stats"]
    assert stats["extract"]["computed"] == 0 and df.attrs["shard"]["seeded"]["extract"] == 2
    assert df.attrs["shard"]["seeded"]["without_frames"] == 1
    _same_table(df, read_shard(source).rows)
    after = read_shard(copy)
    assert after.complete
    for key, rec in _extractions(copy).items():
        assert rec["modes"] == {**_extractions(source)[key]["modes"],
                                "why": "as the shard folder it came from"}
        with np.load(copy / key / COMPACT_NAME) as a, np.load(source / key / COMPACT_NAME) as b:
            assert sorted(a.files) == sorted(b.files)
            for name in a.files:
                assert np.array_equal(a[name], b[name], equal_nan=True), name
    tasks = after.tasks
    before = read_shard(source).tasks
    for k, rec in tasks.items():
        if rec["stage"] == "observe":
            assert rec["observation_sha256"] == before[k]["observation_sha256"]


def test_footprint_modes_cut_joined_views_too(video_flow, tmp_path):
    """``shard_modes="footprint"``: the joined views' extractions are cut to their object's
    box as well; the merge recomputes their observations from less than the whole frame
    (lossy: those bytes differ) and the scores agree within the check-results tolerance."""
    root = video_flow["root"]
    shards = tmp_path / "shards"
    for k in (1, 2):
        run_suite(str(video_flow["suite"]), None, root / "whole", progress=False,
                  shard=f"{k}/2", shard_dir=shards / f"{k}-of-2", shard_modes="footprint")
    records = [r for f in sorted(shards.iterdir()) for r in _extractions(f).values()]
    assert all(r["modes"]["box"] is not None for r in records) and len(records) == 4
    assert sum("lossy" in r["modes"]["why"] for r in records) == 2
    sizes = {m: sum(p.stat().st_size for p in d.rglob("modes.box.npz"))
             for m, d in (("exact", video_flow["shards"]), ("footprint", shards))}
    assert sizes["footprint"] < sizes["exact"]
    merged = merge_shards([shards], tmp_path / "merged", progress=False)
    assert merged.attrs["differences"] == []
    _same_table(read_results(root / "whole"), read_results(tmp_path / "merged"), exact=False)
    with pytest.raises(ShardError, match="shard_modes='box' is not allowed"):
        run_suite(str(video_flow["suite"]), None, root / "whole", progress=False,
                  shard="1/2", shard_dir=tmp_path / "x", shard_modes="box")


def test_a_large_shard_says_so_naming_its_largest_files(video_flow, tmp_path, capsys,
                                                       monkeypatch):
    from vvtbench.bench import shards as shard_module
    from vvtbench.bench.compact import COMPACT_NAME

    folder = video_flow["shards"] / "1-of-2"
    doc = json.loads((folder / "shard.json").read_text())
    assert shard_module.size_warning(folder, doc) is None  # under 50 MB
    text = shard_module.size_warning(folder, doc, limit=1000, show=2)
    largest = shard_module.file_sizes(folder, doc["files"])[0][0]
    assert text.startswith(f"warning: shard folder {folder} holds ")
    assert largest.endswith(COMPACT_NAME) and largest in text and "\n" not in text
    monkeypatch.setattr(shard_module, "SIZE_WARNING_BYTES", 1000)
    code = main(["run", str(video_flow["suite"]), "--shard", "1/2", "--shard-dir",
                 str(tmp_path / "1-of-2"), "-o", str(video_flow["root"] / "whole"),
                 "--no-progress"])
    err = capsys.readouterr().err
    assert code == 0 and "warning: shard folder" in err and COMPACT_NAME in err


def _committed_shards() -> list[Path]:
    root = Path(__file__).resolve().parent.parent / "shards"
    return sorted(p.parent for p in root.glob("*/*-of-*/shard.json")) if root.exists() else []


@pytest.mark.parametrize("folder", _committed_shards(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_a_committed_shard_is_intact(folder):
    """A shard folder committed to the repository reads back: every file it lists has its
    sha256, it is complete, it is the shard its folder names, its rows are valid, and the
    suite file is still the one it was run on (a merge needs all of them on one file)."""
    from vvtbench.bench.results import check_results

    shard = read_shard(folder)
    assert shard.complete, f"{folder}: incomplete"
    assert folder.name == shard.spec.name and folder.parent.name == shard.meta["suite"]["name"]
    assert len(shard.rows) > 0 and check_results(shard.rows) == []
    from vvtbench.bench.shards import suite_sha256

    suite = load_suite(shard.meta["suite"]["ref"])
    assert suite_sha256(suite) == shard.meta["suite"]["sha256"], (
        f"{folder}: {suite.source} is not the file this shard was run on, so the committed "
        "shards no longer merge: restore the file, or remove the suite's shards and run them "
        "again")
