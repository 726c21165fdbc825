"""Challenges of record: instances drawn from a secret the host keeps cannot be regenerated
from the repository; a participant who regenerates the public split gains nothing."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from vvtbench.bench.submission import (
    SubmissionError,
    challenge_of_record,
    score_submission,
    write_challenge,
    write_submission,
)
from vvtbench.cli import main
from vvtbench.observe import observe
from vvtbench.scene.families import draw, draw_secret
from vvtbench.solving.problem import Estimate, InverseProblem

pytest.importorskip("pyarrow")

BASE = """name = "tiny_base"
[geometry]
kind = "box"
size = [0.05, 0.05, 0.05]
cells = [6, 6, 6]
[material]
E = 9000.0
rho = 1270.0
nu = 0.3
[boundary]
fixed = ["bottom"]
[simulation]
n_modes = 12
[camera]
position = [0.16, -0.13, 0.13]
look_at = [0.025, 0.025, 0.022]
fov_y_deg = 30.0
resolution = [128, 128]
"""
FAMILY = """name = "tinycubes"
base = "tiny_base.toml"
attempts = 50
[defects]
count = 1
shape = { choice = ["box", "sphere"] }
position = [{ uniform = [0.1, 0.9] }, { uniform = [0.1, 0.9] }, { uniform = [0.3, 0.9] }]
size = { loguniform = [0.2, 0.35] }
E_ratio = { loguniform = [5.0, 50.0] }
[camera]
cone_deg = 10.0
"""
OBSERVE = {"n_modes": 6, "inference_shape": (3, 3, 3)}
SECRET = bytes(range(32))  # fixed here so that the test is the same on every run


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    root = tmp_path_factory.mktemp("family")
    (root / "tiny_base.toml").write_text(BASE)
    (root / "tinycubes.toml").write_text(FAMILY)
    return root / "tinycubes.toml"


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def test_the_secret_stays_in_the_truth_and_nothing_handed_out_names_the_draw(family,
                                                                            tmp_path, capsys):
    out = tmp_path / "ch"
    assert main(["challenge", str(family), "--n", "2", "--modes", "4", "-o", str(out)]) == 0
    problems, truth = out / "problems", out / "truth"
    secret = bytes.fromhex((truth / "secret.key").read_text())
    assert len(secret) == 32
    assert stat.S_IMODE((truth / "secret.key").stat().st_mode) == 0o600
    assert stat.S_IMODE(truth.stat().st_mode) == 0o700
    man = json.loads((problems / "manifest.json").read_text())
    assert man["split_kind"] == "challenge" and len(man["instances"]) == 2
    for instance in man["instances"]:  # opaque: 16 hex digits, no family, split or index
        assert len(instance) == 16 and int(instance, 16) >= 0
        assert _files(problems / instance) == ["problem.json", "problem.npz"]
        meta = json.loads((problems / instance / "problem.json").read_text())["meta"]
        text = json.dumps(meta)
        assert "scene" not in meta and "seed" not in meta and "tinycubes" not in text
    handed_out = b"".join(p.read_bytes() for p in problems.rglob("*") if p.is_file())
    assert secret not in handed_out and secret.hex().encode() not in handed_out
    assert "secret" not in " ".join(_files(problems)) and "truth" not in " ".join(_files(problems))
    # the host redraws every instance from the kept secret
    record = json.loads((truth / "manifest.json").read_text())
    for instance, index in record["draw"].items():
        scene = draw_secret(family, secret, index, instance)
        import tomllib

        kept = tomllib.loads((truth / instance / "scene.toml").read_text())
        assert kept == tomllib.loads(__import__("tomli_w").dumps(scene.to_toml_dict()))
    # a second challenge has another secret, other ids
    other = tmp_path / "ch2"
    assert main(["challenge", str(family), "--n", "2", "--modes", "4", "-o", str(other)]) == 0
    assert (other / "truth" / "secret.key").read_text() != (truth / "secret.key").read_text()
    assert not set(json.loads((other / "problems" / "manifest.json").read_text())["instances"]) \
        & set(man["instances"])


def _attack(problems_dir, public):
    """What a participant with the repository can do: for each handed-out problem, the public
    instance with the same problem sha256, or else the one whose eigenvalues are nearest, and
    submit that instance's truth."""
    man = json.loads((problems_dir / "manifest.json").read_text())
    by_sha = {sha: truth for sha, (_, truth) in public.items()}
    estimates = {}
    for instance, info in man["instances"].items():
        truth = by_sha.get(info["problem_sha256"])
        if truth is None:
            lam = np.log(InverseProblem.load(problems_dir / instance).eigenvalues)
            nearest = min(public.values(),
                          key=lambda pt: float(np.linalg.norm(np.log(pt[0].eigenvalues) - lam)))
            truth = nearest[1]
        estimates[instance] = Estimate(w=truth.w, v=truth.v)
    return estimates


def _solve_honestly(problems_dir):
    from vvtbench.solving.plugins import load_solver

    solver = load_solver("sensitivity")()
    man = json.loads((problems_dir / "manifest.json").read_text())
    return {i: solver.solve(InverseProblem.load(problems_dir / i)) for i in man["instances"]}


def _mean_nc(estimates, root, tmp_path, label):
    sub = tmp_path / f"sub-{label}"
    write_submission(estimates, root / "problems", sub, label, "1")
    df = score_submission(sub, root / "truth")
    assert (df.status == "ok").all(), df.error.tolist()
    return float(df.nc_w.mean()), df


def test_regenerating_the_public_split_gives_nothing(family, tmp_path):
    # the participant: the whole repository, so every public test instance, observed alike
    public_dir = tmp_path / "regenerated"
    drawn = [draw(family, "test", i) for i in range(10)]
    observed = [observe(s, observation="true", **OBSERVE) for s in drawn]
    write_challenge(((s.name, p, t) for s, (p, t) in zip(drawn, observed, strict=True)),
                    public_dir / "problems", public_dir / "truth", "regenerated")
    shas = json.loads((public_dir / "problems" / "manifest.json").read_text())["instances"]
    public = {shas[s.name]["problem_sha256"]: pt for s, pt in zip(drawn, observed, strict=True)}

    # control: a challenge handed out from the public test split is answered exactly
    control = tmp_path / "control"
    write_challenge(((f"x{i}", *observed[i]) for i in range(3)),
                    control / "problems", control / "truth", "control")
    nc_control, _ = _mean_nc(_attack(control / "problems", public), control, tmp_path, "c")
    assert nc_control == pytest.approx(1.0)

    # a challenge of record: drawn from the host's secret
    record = tmp_path / "record"
    assert challenge_of_record(family, 3, record, secret=SECRET, observe_options=OBSERVE) == 3
    handed = json.loads((record / "problems" / "manifest.json").read_text())["instances"]
    assert not {info["problem_sha256"] for info in handed.values()} & set(public)
    nc_attack, attack = _mean_nc(_attack(record / "problems", public), record, tmp_path, "a")
    nc_honest, honest = _mean_nc(_solve_honestly(record / "problems"), record, tmp_path, "h")
    print(f"mean NC w: regenerated public truth {nc_attack:.3f} per instance "
          f"{attack.nc_w.round(3).tolist()}; sensitivity {nc_honest:.3f} "
          f"{honest.nc_w.round(3).tolist()}; control {nc_control:.3f}")
    assert nc_attack < nc_honest - 0.2  # regeneration gives no better than an honest solve
    assert (attack.split_kind == "challenge").all()


def test_a_family_whose_truth_is_public_is_refused(family, tmp_path, capsys):
    fixed = family.with_name("fixed.toml")
    fixed.write_text('name = "fixed"\nbase = "tiny_base.toml"\n[camera]\ncone_deg = 10.0\n')
    capsys.readouterr()
    assert main(["challenge", str(fixed), "--n", "2", "-o", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "defects" in err[0] and "public" in err[0]
    assert not (tmp_path / "c").exists()
    with pytest.raises(SubmissionError, match="defects"):
        challenge_of_record(fixed, 1, tmp_path / "c2", secret=SECRET)


def test_a_challenge_that_fails_midway_leaves_nothing(family, tmp_path, monkeypatch):
    import vvtbench.observe

    real, calls = vvtbench.observe.observe, []

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise vvtbench.observe.ObserveError("the second instance cannot be observed")
        return real(*a, **k)

    monkeypatch.setattr(vvtbench.observe, "observe", failing)
    out = tmp_path / "c"
    with pytest.raises(vvtbench.observe.ObserveError):
        challenge_of_record(family, 3, out, secret=SECRET, observe_options=OBSERVE)
    assert not out.exists() and os.listdir(tmp_path) == []
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(SubmissionError, match="not an empty folder"):
        challenge_of_record(family, 1, out, secret=SECRET, observe_options=OBSERVE)
    assert os.listdir(out) == ["notes.txt"]
