"""Hidden-truth scoring: a submission is scored from its estimates against truth it does not
hold; nothing it states is taken as a score, and nothing in it reaches outside itself."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from vvtbench.bench.submission import score_submission, write_challenge, write_submission
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
        assert row.nc_w == pytest.approx(ev["nc_w"]) and row.runtime_s == 1.5
    assert not df.reference.any()


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
