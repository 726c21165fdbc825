"""Hidden-truth scoring: a submission is scored from its estimates against truth it does not
hold; nothing it states is taken as a score, and nothing in it reaches outside itself."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from vvtbench.bench.results import check_results
from vvtbench.bench.submission import (
    SubmissionError,
    score_submission,
    write_challenge,
    write_submission,
)
from vvtbench.cli import main
from vvtbench.observe import observe
from vvtbench.scene.scene import load_scene
from vvtbench.scoring.metrics import evaluate
from vvtbench.solving.problem import Estimate

pytest.importorskip("pyarrow")


@pytest.fixture(scope="module")
def challenge(tmp_path_factory):
    root = tmp_path_factory.mktemp("challenge")
    items = []
    for scene in ("jello_cube_defect_top", "jello_cube_defect_bottom"):
        problem, truth = observe(load_scene(scene), observation="true", n_modes=5,
                                 inference_shape=(3, 3, 3))
        items.append((scene, problem, truth))
    write_challenge(items, root / "problems", root / "truth", "tiny")
    return root, {i: (p, t) for i, p, t in items}


def _estimates(items):
    return {instance: Estimate(w=truth.w + 100.0, v=truth.v, runtime_s=1.5)
            for instance, (_, truth) in items.items()}


def test_scores_are_computed_from_the_estimates(challenge, tmp_path):
    root, items = challenge
    write_submission(_estimates(items), root / "problems", tmp_path / "sub", "mine", "1.0")
    doc = json.loads((tmp_path / "sub" / "manifest.json").read_text())
    doc["scores"] = {"nc_w": 1.0}  # stated scores are ignored
    (tmp_path / "sub" / "manifest.json").write_text(json.dumps(doc))
    df = score_submission(tmp_path / "sub", root / "truth")
    assert (df.status == "ok").all(), df.error.tolist()
    for _, row in df.iterrows():
        problem, truth = items[row.scene]
        ev = evaluate(problem, truth, truth.w + 100.0, truth.v)["metrics"]
        assert row.nc_w == pytest.approx(ev["nc_w"])
    assert not df.reference.any()
    # a runtime the scorer did not measure is never shown; these instances are public
    assert df.runtime_s.isna().all() and (df.sandbox == "submitted").all()
    assert (df.split_kind == "public").all()
    assert check_results(df) == []


def test_the_public_folder_holds_no_truth(challenge):
    root, _ = challenge
    names = {p.name for p in (root / "problems").rglob("*")}
    assert not any("truth" in n for n in names)


def test_missing_foreign_linked_pickled_and_escaping_estimates_are_error_rows(challenge,
                                                                               tmp_path):
    root, items = challenge
    sub = tmp_path / "sub"
    write_submission(_estimates(items), root / "problems", sub, "mine", "1.0")
    doc = json.loads((sub / "manifest.json").read_text())
    top, bottom = "jello_cube_defect_top", "jello_cube_defect_bottom"
    linked = sub / top / "estimate.npz"
    linked.unlink()
    os.symlink(root / "truth" / top / "truth.npz", linked)
    doc["estimates"][bottom]["file"] = f"../../{root.name}/truth/{bottom}/truth.npz"
    (sub / "manifest.json").write_text(json.dumps(doc))
    df = score_submission(sub, root / "truth").set_index("scene")
    assert (df.status == "error").all()
    assert "links are refused" in df.loc[top, "error"]
    assert "inside the submission" in df.loc[bottom, "error"]
    doc["estimates"][bottom]["file"] = f"{bottom}/estimate.npz"
    doc["estimates"][bottom]["problem_sha256"] = "0" * 64
    del doc["estimates"][top]
    (sub / "manifest.json").write_text(json.dumps(doc))
    df = score_submission(sub, root / "truth").set_index("scene")
    assert df.loc[top, "error"] == "no estimate submitted"
    assert "another problem" in df.loc[bottom, "error"]
    doc["estimates"][bottom]["problem_sha256"] = json.loads(
        (root / "truth" / "manifest.json").read_text())["instances"][bottom]["problem_sha256"]
    (sub / "manifest.json").write_text(json.dumps(doc))
    np.save(sub / "obj.npy", np.array([object()], dtype=object))
    np.savez(sub / bottom / "estimate.npz", w_params=np.array([object()], dtype=object),
             v_params=np.ones(3))
    df = score_submission(sub, root / "truth").set_index("scene")
    assert df.loc[bottom, "status"] == "error"


def test_an_invalid_estimate_is_not_scored(challenge, tmp_path):
    root, items = challenge
    est = _estimates(items)
    est["jello_cube_defect_top"].w[0] = -1.0
    write_submission(est, root / "problems", tmp_path / "sub", "mine", "1.0")
    df = score_submission(tmp_path / "sub", root / "truth").set_index("scene")
    assert df.loc["jello_cube_defect_top", "status"] == "invalid"
    assert np.isnan(df.loc["jello_cube_defect_top", "nc_w"])


def test_the_command_writes_only_where_it_is_told(challenge, tmp_path, capsys):
    root, items = challenge
    write_submission(_estimates(items), root / "problems", tmp_path / "sub", "mine", "1.0")
    assert main(["score", str(tmp_path / "sub"), "--truth", str(root / "truth"), "-o",
                 str(root / "truth" / "scores")]) == 2
    assert not (root / "truth" / "scores").exists()
    assert main(["score", str(tmp_path / "sub"), "--truth", str(root / "truth"), "-o",
                 str(tmp_path / "scores")]) == 0
    assert (tmp_path / "scores" / "results.parquet").is_file()
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "manifest.json").write_text('{"format": "other"}')
    capsys.readouterr()
    assert main(["score", str(tmp_path / "bad"), "--truth", str(root / "truth"), "-o",
                 str(tmp_path / "s2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "manifest.json" in err[0] and "format" in err[0]


def _submitted(challenge, tmp_path, **stds):
    root, items = challenge
    est = _estimates(items)
    for e in est.values():
        e.extra.update({k: np.full_like(e.w, v) for k, v in stds.items()})
    sub = tmp_path / "sub"
    write_submission(est, root / "problems", sub, "mine", "1.0")
    return sub, json.loads((sub / "manifest.json").read_text())


TOP, BOTTOM = "jello_cube_defect_top", "jello_cube_defect_bottom"


def test_a_linked_instance_folder_is_refused_at_any_depth(challenge, tmp_path):
    root, _ = challenge
    sub, _ = _submitted(challenge, tmp_path)
    outside = tmp_path / "outside"
    (sub / TOP).rename(outside)  # a valid estimate, but reached through a link
    os.symlink(outside, sub / TOP)
    df = score_submission(sub, root / "truth").set_index("scene")
    assert df.loc[TOP, "status"] == "error" and "links are refused" in df.loc[TOP, "error"]
    assert df.loc[BOTTOM, "status"] == "ok"


def test_a_fifo_is_refused_without_waiting_for_a_writer(challenge, tmp_path):
    import signal

    root, _ = challenge
    sub, _ = _submitted(challenge, tmp_path)
    (sub / TOP / "estimate.npz").unlink()
    os.mkfifo(sub / TOP / "estimate.npz")

    def hung(*_):
        raise AssertionError("score waited on a FIFO")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(120)  # turns a hang into a failure; not a measure of speed
    try:
        df = score_submission(sub, root / "truth").set_index("scene")
        assert df.loc[TOP, "status"] == "error" and "FIFO" in df.loc[TOP, "error"]
        assert df.loc[BOTTOM, "status"] == "ok"
        (sub / "manifest.json").rename(sub / "manifest.real")
        os.mkfifo(sub / "manifest.json")
        with pytest.raises(SubmissionError, match="manifest.json"):
            score_submission(sub, root / "truth")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _header_only_npz(path, n_claimed: int, n_params: int) -> None:
    """An .npz whose w_params header claims ``n_claimed`` float64 values and holds none."""
    import io
    import zipfile

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False,
                                                "shape": (n_claimed,)})
    v = io.BytesIO()
    np.lib.format.write_array(v, np.ones(n_params))
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("w_params.npy", head.getvalue())
        z.writestr("v_params.npy", v.getvalue())


def test_an_array_header_claiming_a_trillion_values_is_one_invalid_row(challenge, tmp_path):
    root, items = challenge
    sub, _ = _submitted(challenge, tmp_path)
    n = items[TOP][0].n_params
    _header_only_npz(sub / TOP / "estimate.npz", 10**12, n)
    assert (sub / TOP / "estimate.npz").stat().st_size < 1000
    df = score_submission(sub, root / "truth").set_index("scene")
    assert df.loc[TOP, "status"] == "invalid"
    assert f"1000000000000 values, the problem has {n} parameters" in df.loc[TOP, "error"]
    assert df.loc[BOTTOM, "status"] == "ok"  # the other rows are scored
    _header_only_npz(sub / TOP / "estimate.npz", n, n)  # the size is right, the data absent
    df = score_submission(sub, root / "truth").set_index("scene")
    assert df.loc[TOP, "status"] == "error" and "not an estimate" in df.loc[TOP, "error"]


@pytest.mark.parametrize("std", [-1.0, float("nan"), float("inf")])
def test_negative_or_non_finite_uncertainties_are_invalid(challenge, tmp_path, std):
    root, _ = challenge
    sub, _ = _submitted(challenge, tmp_path, w_std=std)
    df = score_submission(sub, root / "truth")
    assert (df.status == "invalid").all() and df.interval_coverage_w.isna().all()
    assert df.error.str.contains("w_std is negative or not finite").all()
    sub2, _ = _submitted(challenge, tmp_path / "ok", w_std=50.0)
    df = score_submission(sub2, root / "truth")
    assert (df.status == "ok").all() and df.interval_coverage_w.notna().all()


def test_a_stated_runtime_is_never_put_on_the_board(challenge, tmp_path):
    root, _ = challenge
    sub, doc = _submitted(challenge, tmp_path)
    for entry in doc["estimates"].values():
        entry["runtime_s"] = 1e-12
    (sub / "manifest.json").write_text(json.dumps(doc))
    df = score_submission(sub, root / "truth")
    assert (df.status == "ok").all() and df.runtime_s.isna().all()
    assert check_results(df) == []


def test_score_never_replaces_a_file_it_did_not_write(challenge, tmp_path, capsys):
    from vvtbench.io.outputs import claim_output

    root, _ = challenge
    sub, _ = _submitted(challenge, tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "results.csv").write_text("my own table\n")
    capsys.readouterr()
    assert main(["score", str(sub), "--truth", str(root / "truth"), "-o", str(mine)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(mine) in err[0] and "results.csv" in err[0]
    assert sorted(os.listdir(mine)) == ["results.csv"]
    assert (mine / "results.csv").read_text() == "my own table\n"
    other = claim_output(tmp_path / "other", "invert")
    assert main(["score", str(sub), "--truth", str(root / "truth"), "-o", str(other)]) == 2
    assert not (other / "results.csv").exists()
    scores = tmp_path / "scores"
    assert main(["score", str(sub), "--truth", str(root / "truth"), "-o", str(scores)]) == 0
    (scores / "notes.txt").write_text("kept")
    first = (scores / "results.csv").read_text()
    assert main(["score", str(sub), "--truth", str(root / "truth"), "-o", str(scores)]) == 0
    assert (scores / "results.csv").read_text() == first  # its own folder: updated
    assert (scores / "notes.txt").read_text() == "kept"
