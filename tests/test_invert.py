"""vvtbench invert: stages, caching, the invalid-estimate path, on a small synthetic clip."""

from __future__ import annotations

import hashlib
import json
import textwrap

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.field.invert import source_sha256
from vvtbench.field.objects import resolve_object
from vvtbench.render.camera import Camera

FPS, T, SIZE = 200.0, 256, 64
FREQS = (23.0, 41.0)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A textured 64x64 image of a plate whose texture moves in two standing patterns (23 and
    41 Hz), saved as .npy, with a clicks CSV of the plate's corners and edge midpoints."""
    import cv2

    root = tmp_path_factory.mktemp("clip")
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((SIZE, SIZE)), (0, 0), 1.5)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    shape1 = np.sin(np.pi * xx / SIZE) * np.sin(np.pi * yy / SIZE)
    shape2 = np.sin(2 * np.pi * xx / SIZE) * np.sin(np.pi * yy / SIZE)
    t = np.arange(T) / FPS
    frames = np.empty((T, SIZE, SIZE), np.float32)
    for i, ti in enumerate(t):
        d = 0.4 * shape1 * np.sin(2 * np.pi * FREQS[0] * ti) \
            + 0.3 * shape2 * np.sin(2 * np.pi * FREQS[1] * ti)
        frames[i] = cv2.remap(texture.astype(np.float32), xx, (yy + d).astype(np.float32),
                              cv2.INTER_CUBIC,
                              borderMode=cv2.BORDER_REFLECT)
    video = root / "plate.npy"
    np.save(video, frames)
    plate = resolve_object("plate:0.1x0.1")
    camera = Camera.look_at((0.05, -0.12, 0.25), (0.05, 0.05, 0.0), fx=150.0, width=SIZE,
                            height=SIZE)
    pts = plate.mesh.points
    ids = [0, 10, 20, 210, 230, 420, 430, 440]
    uv = camera.project(pts[ids])
    clicks = root / "clicks.csv"
    clicks.write_text("vertex,u,v\n" + "".join(
        f"{i},{u:.3f},{v:.3f}\n" for i, (u, v) in zip(ids, uv, strict=True)))
    return root, video, clicks


def _invert(root, video, clicks, out, *extra):
    return main(["invert", str(video), "--object", "plate:0.1x0.1", "--clicks", str(clicks),
                 "--fps", str(FPS), "--fmin", "15", "--solver", "homogeneous", "--modes", "2",
                 "-o", str(out),
                 *extra])


def test_invert_report_and_stage_reuse(clip, capsys):
    root, video, clicks = clip
    out = root / "out"
    assert _invert(root, video, clicks, out) == 0
    report = (out / "report.md").read_text()
    assert report.startswith("# Material map")
    assert "reprojection error | RMS 0.0" in report
    used = json.loads((out / "modes.json").read_text())
    assert used["n_modes_used"] == 2
    assert np.allclose(sorted(used["frequencies_hz"]), FREQS, atol=1.0)
    with np.load(out / "fields.npz") as z:
        assert z["w"].shape == (400,) and np.all(z["w"] > 0) and np.all(z["v"] > 0)
    assert (out / "fields.png").stat().st_size > 0
    stages = json.loads((out / "stages.json").read_text())
    digest = hashlib.sha256()
    data = video.read_bytes()
    digest.update(f"{video.name}\0{len(data)}\0".encode() + data)
    assert stages["extract"]["inputs"]["video_sha256"] == digest.hexdigest()
    capsys.readouterr()
    assert _invert(root, video, clicks, out) == 0
    assert "reused finished stages: calibrate, extract, solve" in capsys.readouterr().out
    moved = root / "clicks2.csv"
    lines = clicks.read_text().splitlines()
    moved.write_text("\n".join(lines[:-1]) + "\n")  # one click fewer: a new camera
    assert _invert(root, video, moved, out) == 0
    assert "reused finished stages: extract\n" in capsys.readouterr().out


def test_invalid_estimate_is_never_a_result(clip, capsys):
    root, video, clicks = clip
    solver = root / "negative.py"
    solver.write_text(textwrap.dedent('''
        from dataclasses import dataclass
        import numpy as np
        from vvtbench.solving.problem import Estimate

        class Negative:
            name = "negative"
            version = "1.0"
            description = "returns a negative stiffness"

            @dataclass
            class Config:
                pass

            def __init__(self, config=None):
                self.config = config

            def solve(self, problem):
                w = np.full(problem.n_params, -1.0)
                return Estimate(w=w, v=np.ones(problem.n_params), solver=self.name)
    '''))
    out = root / "bad"
    code = main(["invert", str(video), "--object", "plate:0.1x0.1", "--clicks", str(clicks),
                 "--fps", str(FPS), "--fmin", "15", "--solver", f"{solver}:Negative",
                 "--modes", "2", "-o", str(out)])
    assert code == 1
    assert "NO RESULT" in capsys.readouterr().err
    assert (out / "report.md").read_text().startswith("# NO RESULT: the estimate is invalid: "
                                                      "w is not positive in 400 of 400 voxels")
    assert not (out / "fields.npz").exists()


def test_bad_input_is_one_line(clip, capsys, tmp_path):
    root, video, clicks = clip
    few = tmp_path / "few.csv"
    few.write_text("vertex,u,v\n0,1,1\n20,5,5\n")
    assert _invert(root, video, few, tmp_path / "o") == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "at least 4" in err
    assert _invert(root, video, clicks, tmp_path / "o2", "--object", "plate:zero") == 2


def test_source_sha256_of_folder_and_pattern(tmp_path):
    for i in (2, 10):
        (tmp_path / f"img_{i}.png").write_bytes(bytes([i]) * 5)
    assert source_sha256(tmp_path) == source_sha256(tmp_path / "img_*.png")
    assert source_sha256(tmp_path / "img_%d.png") == source_sha256(tmp_path)
    before = source_sha256(tmp_path)
    (tmp_path / "img_10.png").write_bytes(b"\x00" * 5)
    assert source_sha256(tmp_path) != before


def test_a_folder_of_the_users_is_never_written_into(clip, capsys, tmp_path):
    root, video, clicks = clip
    mine = tmp_path / "mine"
    (mine / "extract").mkdir(parents=True)
    (mine / "report.md").write_text("my own notes\n")
    (mine / "extract" / "keep.txt").write_text("mine")
    capsys.readouterr()
    assert _invert(root, video, clicks, mine) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(mine) in err[0] and "report.md" in err[0]
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == [
        "extract", "extract/keep.txt", "report.md"]
    assert (mine / "report.md").read_text() == "my own notes\n"
