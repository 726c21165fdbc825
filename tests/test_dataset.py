"""Tests for the dataset generator (vvtbench.samples.generate), loader (vvtbench.samples.reader)
and video
I/O (vvtbench.video.files).

Rendering needs headless EGL (Mesa llvmpipe is fine); see tests/test_render.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vvtbench.bench.resolve import resolve_scenes
from vvtbench.cli import generate as cli_generate
from vvtbench.render.camera import Camera
from vvtbench.samples import generate as gen
from vvtbench.samples import reader as ds
from vvtbench.scene.scene import SCENES_DIR, SceneError, load_scene, parse_scene, with_overrides
from vvtbench.video.files import VideoWriter, concat_videos, probe_video, read_frames

TINY = {
    "name": "tiny",
    "seed": 7,
    "geometry": {"kind": "box", "cells": [3, 3, 3]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.002},
    "simulation": {"n_modes": 8, "duration": 0.05, "fps": 2000.0},
    "camera": {"resolution": [64, 64], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 2},
}
SEGMENT = 40  # 100 frames -> 3 segments


def tiny_scene(**render) -> object:
    data = json.loads(json.dumps(TINY))
    data["render"].update(render)
    return parse_scene(data, "tiny")


def _png8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * 255.0), 0, 255)


def _tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes()
            for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return gen.generate(tiny_scene(), tmp_path_factory.mktemp("a"), progress=False,
                       segment_frames=SEGMENT)


@pytest.fixture(scope="module")
def sample(tiny):
    return ds.open_sample(tiny)


def test_sample_folder_and_manifest(tiny, sample):
    names = {p.name for p in tiny.iterdir()}
    assert names == {"scene.toml", "camera.json", "truth.json", "truth.zarr", "video.mkv",
                     "rest.png", "depth.png", "preview.mp4", "manifest.json"}
    assert not list(tiny.parent.glob(".*"))  # no partial or temporary folder left behind
    assert sample.verify() == []
    files = sample.manifest["files"]
    assert all(len(e["sha256"]) == 64 and e["description"] for e in files.values())
    # a changed byte is caught
    png = tiny / "rest.png"
    original = png.read_bytes()
    try:
        png.write_bytes(original[:-1] + bytes([original[-1] ^ 1]))
        assert sample.verify() == ["rest.png: sha256 mismatch"]
    finally:
        png.write_bytes(original)
    # the resolved scene loads as a scene and names the generator version
    text = (tiny / "scene.toml").read_text()
    assert text.startswith("# Resolved scene written by vvtbench")
    assert load_scene(tiny / "scene.toml").to_toml_dict() == tiny_scene().to_toml_dict()


def test_open_sample_shapes(sample):
    S = sample.info["mesh"]["n_surface_nodes"]
    V = sample.info["mesh"]["n_visible"]
    m = 8
    H, W = 64, 64
    assert sample.n_frames == 100 and sample.fps == 2000.0 and sample.shape == (H, W)
    assert isinstance(sample.camera, Camera) and sample.camera.width == W
    np.testing.assert_allclose(json.loads((sample.path / "camera.json").read_text())["P"],
                               sample.camera.P)
    expect = {
        "mesh/points": ((64, 3), np.float64),
        "mesh/cells": ((27, 8), np.int64),
        "mesh/surface_nodes": ((S,), np.int64),
        "mesh/fixed_nodes": ((16,), np.int64),
        "mesh/node_sets/bottom": ((16,), np.int64),
        "material/stiffness": ((27,), np.float64),
        "voxels/stiffness": ((8, 8, 8), np.float64),
        "voxels/density": ((8, 8, 8), np.float64),
        "modes/frequencies_hz": ((m,), np.float64),
        "modes/damping_ratios": ((m,), np.float64),
        "modes/surface": ((m, S, 3), np.float64),
        "observation/rest_uv": ((S, 2), np.float64),
        "observation/visible": ((S,), np.bool_),
        "observation/visible_index": ((V,), np.int64),
        "observation/jacobian": ((V, 2, 3), np.float64),
        "observation/image_modes": ((m, V, 2), np.float64),
        "image/rest": ((H, W), np.float32),
        "image/depth": ((H, W), np.float32),
        "image/triangle": ((H, W), np.int32),
        "image/barycentric": ((H, W, 3), np.float32),
        "image/modes": ((m, H, W, 2), np.float32),
        "transient/displacements": ((100, S, 3), np.float32),
        "transient/times": ((100,), np.float64),
    }
    for name, (shape, dtype) in expect.items():
        a = sample[name]
        assert a.shape == shape and a.dtype == dtype, (name, a.shape, a.dtype)
    # 3 x 3 x 3 cells on an 8^3 grid: every voxel overlaps the body (volume-weighted)
    assert np.isfinite(sample["voxels/stiffness"]).all()
    np.testing.assert_allclose(sample["voxels/stiffness"], 9000.0)
    np.testing.assert_allclose(sample["voxels/volume"].sum(), sample["mesh/element_volumes"].sum())
    assert 0 < V < S
    frames = sample.read_frames(5, 8)
    assert frames.shape == (3, H, W) and frames.dtype == np.uint16
    np.testing.assert_array_equal(frames, sample.read_frames()[5:8])
    norm = next(sample.frames(5, 6, normalize=True))
    np.testing.assert_allclose(norm, frames[0] / 65535.0, rtol=1e-6)
    np.testing.assert_allclose(sample.times, np.arange(100) / 2000.0)
    np.testing.assert_allclose(sample.frequencies_hz, sample.info["modes"]["frequencies_hz"])


@pytest.mark.parametrize("codec", ["ffvhuff", "ffv1"])
def test_lossless_roundtrip_is_bit_exact(tmp_path, codec):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 65536, size=(30, 24, 40), dtype=np.uint16)
    frames[3] = 0
    frames[4] = 65535
    frames[5] = np.arange(24 * 40).reshape(24, 40) * 68  # a smooth ramp: what prediction likes
    segs = []
    for i, part in enumerate((frames[:13], frames[13:])):
        with VideoWriter(tmp_path / f"s{i}.mkv", 24, 40, capture_fps=2000.0, codec=codec) as w:
            for f in part:
                w.write(f)
        segs.append(tmp_path / f"s{i}.mkv")
    concat_videos(segs, tmp_path / "v.mkv", capture_fps=2000.0)
    back = np.stack(list(read_frames(tmp_path / "v.mkv")))
    np.testing.assert_array_equal(back, frames)
    np.testing.assert_array_equal(np.stack(list(read_frames(tmp_path / "v.mkv", start=11,
                                                            stop=17))), frames[11:17])
    assert probe_video(tmp_path / "v.mkv").frame_rate == 2000
    assert probe_video(tmp_path / "v.mkv").codec == codec


def test_video_frames_are_the_rendered_frames(sample):
    """Decoded DN == 16-bit quantization of a fresh render of the stored displacements."""
    from vvtbench.simulation.simulate import build_mesh

    mesh = build_mesh(sample.scene)
    nodes, rest, tris = gen.surface_geometry(mesh)
    np.testing.assert_array_equal(nodes, sample["mesh/surface_nodes"])
    disp = sample.array("transient/displacements")
    frames = sample.read_frames()
    with gen.scene_renderer(sample.scene, rest, tris) as r:
        np.testing.assert_array_equal(r.render(), sample["image/rest"])
        for k in (0, 37, 99):
            img = r.render(disp[k])
            want = gen.sensor_dn(img[None], 16, 0.0, False, 1e4, None)
            np.testing.assert_array_equal(frames[k], want)
    assert np.abs(frames[0].astype(int) - frames[99]).max() > 0  # it moves


def test_image_modes_are_jacobian_times_3d_modes(sample):
    cam = sample.camera
    vis = sample["observation/visible_index"]
    X = sample["mesh/points"][sample["mesh/surface_nodes"][vis]]
    phi = sample["modes/surface"][:, vis]  # (m, V, 3)
    gam = sample["observation/image_modes"]
    J = sample["observation/jacobian"]
    np.testing.assert_allclose(gam, np.einsum("vij,mvj->mvi", J, phi), rtol=1e-12)
    h = 1e-7 / np.abs(phi).max()
    fd = (cam.project((X + h * phi).reshape(-1, 3)) - cam.project((X - h * phi).reshape(-1, 3)))
    fd = fd.reshape(gam.shape) / (2 * h)
    np.testing.assert_allclose(gam, fd, rtol=1e-5, atol=1e-6 * np.abs(gam).max())


def test_dense_mode_fields_interpolate_vertex_modes(sample):
    tri = sample["image/triangle"]
    bary = sample["image/barycentric"].astype(np.float64)
    dense = sample["image/modes"]
    mask = tri >= 0
    assert np.isnan(dense[:, ~mask]).all() and np.isfinite(dense[:, mask]).all()
    # triangles index the surface nodes; interpolate the surface image modes independently
    surf = sample["mesh/surface"]
    lut = {n: i for i, n in enumerate(sample["mesh/surface_nodes"])}
    local = np.vectorize(lut.get)(surf)
    g = sample["observation/image_modes_surface"]  # (m, S, 2)
    corners = local[tri[mask]]
    ref = np.einsum("pk,mpkc->mpc", bary[mask], g[:, corners])
    np.testing.assert_allclose(dense[:, mask], ref, rtol=1e-4, atol=1e-5 * np.abs(g).max())
    # the render-free raster agrees with the renderer's depth buffer inside the object
    d_r = sample["image/depth"]
    both = mask & np.isfinite(d_r)
    assert both.sum() > 0.9 * mask.sum()
    assert np.median(np.abs(d_r[both] - _raster_depth(sample)[both]) / d_r[both]) < 1e-3


def _raster_depth(sample):
    from vvtbench.render.raster import rasterize

    nodes = sample["mesh/surface_nodes"]
    lut = np.full(len(sample["mesh/points"]), -1)
    lut[nodes] = np.arange(len(nodes))
    return rasterize(sample.camera, sample["mesh/points"][nodes], lut[sample["mesh/surface"]]).depth


def test_rerun_is_byte_identical(tiny, tmp_path):
    again = gen.generate(tiny_scene(), tmp_path, progress=False, segment_frames=SEGMENT)
    assert _tree(again) == _tree(tiny)


def test_interrupted_run_resumes(tiny, tmp_path):
    class Stop(Exception):
        pass

    def interrupt(stage, done, total):
        if stage == "render video" and done == SEGMENT + 5:
            raise Stop

    with pytest.raises(Stop):
        gen.generate(tiny_scene(), tmp_path, progress=False, segment_frames=SEGMENT,
                    callback=interrupt)
    partial = tmp_path / ".tiny.partial"
    assert not (tmp_path / "tiny").exists()
    assert json.loads((partial / "checkpoint.json").read_text())["segments_done"] == 1
    starts = []

    def record(stage, done, total):
        if stage == "render video" and not starts:
            starts.append(done)

    out = gen.generate(tiny_scene(), tmp_path, progress=False, segment_frames=SEGMENT,
                      callback=record)
    assert starts == [SEGMENT]  # resumed after the finished segment
    assert not partial.exists()
    assert _tree(out) == _tree(tiny)


def noisy_scene():
    return tiny_scene(bit_depth=12, read_noise_dn=2.0, shot_noise=True, frame_average=2)


@pytest.fixture(scope="module")
def noisy(tmp_path_factory) -> Path:
    return gen.generate(noisy_scene(), tmp_path_factory.mktemp("noisy"), progress=False)


def test_camera_noise_bit_depth_and_frame_average(noisy):
    s = ds.open_sample(noisy)
    assert s.bit_depth == 12 and s.info["video"]["subframe_fps"] == 4000.0
    frames = s.read_frames()
    assert frames.max() <= 4095 and frames.max() > 3000
    # times are the exposure centres of the averaged sub-frame pairs
    np.testing.assert_allclose(s.times, (np.arange(100) + 0.25) / 2000.0)
    # the noise-free, quantized rest image differs from the video by sensor noise only
    from vvtbench.simulation.simulate import build_mesh

    _, rest, tris = gen.surface_geometry(build_mesh(s.scene))
    disp = s["transient/displacements"]
    with gen.scene_renderer(s.scene, rest, tris) as r:
        clean = r.render(disp[50]) * 4095.0
    diff = frames[50] - clean
    bg = s["image/triangle"] == -1
    # background (I = 0): read noise only, averaged over 2 sub-frames, clipped at 0
    assert 0.3 < np.sqrt(np.mean(np.clip(diff[bg], 0, None) ** 2) * 2) < 2.5
    bright = (clean > 3000) & ~bg
    # bright pixels: shot noise dominates; var ~ (I*4095^2/full_well + 4) / 2
    var = np.var(diff[bright])
    expect = np.mean(clean[bright] * 4095.0 / 1e4 + 4.0) / 2
    assert 0.5 * expect < var < 2.0 * expect


def test_rerun_with_sensor_noise_is_byte_identical(noisy, tmp_path):
    """Read and shot noise are drawn per frame from the scene seed: same bytes again."""
    again = gen.generate(noisy_scene(), tmp_path, progress=False)
    assert _tree(again) == _tree(noisy)


def _requantized(sample, ks, bits: int) -> list[np.ndarray]:
    """Noise-free DN of fresh renders of the stored displacements of frames ``ks``."""
    from vvtbench.simulation.simulate import build_mesh

    _, rest, tris = gen.surface_geometry(build_mesh(sample.scene))
    disp = sample.array("transient/displacements")
    scale = sample.info["video"]["motion_scale"]
    with gen.scene_renderer(sample.scene, rest, tris) as r:
        return [gen.sensor_dn(r.render(scale * disp[k])[None], bits, 0.0, False, 1e4, None)
                for k in ks]


def _stream_pix_fmt(path: Path) -> str:
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    try:
        return next(gen)["pix_fmt"].split("(")[0].strip()
    finally:
        gen.close()


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_lossless_video_holds_lsb_aligned_dn(bits, tmp_path):
    """Every lossless bit depth is gray16le with DN in [0, 2^bits - 1], decoded bit-exactly."""
    scene = with_overrides(tiny_scene(bit_depth=bits), frames=6)
    s = ds.open_sample(gen.generate(scene, tmp_path, progress=False))
    dn_max = 2**bits - 1
    assert s.info["video"]["pixel_format"] == "gray16le" == _stream_pix_fmt(s.video_path)
    assert s.info["video"]["dn_max"] == dn_max
    frames = s.read_frames()
    assert frames.dtype == np.uint16 and frames.shape == (6, 64, 64)
    assert 0.5 * dn_max < frames.max() <= dn_max
    for k, want in zip((0, 5), _requantized(s, (0, 5), bits), strict=True):
        np.testing.assert_array_equal(frames[k], want)
    norm = s.read_frames(normalize=True)
    assert norm.dtype == np.float32 and 0.0 <= norm.min() and norm.max() <= 1.0
    np.testing.assert_allclose(norm, frames / dn_max, rtol=1e-6)


def test_video_pixel_format_mismatch_is_an_error(tmp_path):
    scene = with_overrides(tiny_scene(), frames=2)
    path = gen.generate(scene, tmp_path, progress=False)
    with VideoWriter(path / "video.mkv", 64, 64, capture_fps=2000.0, pix_fmt="gray") as w:
        w.write(np.full((64, 64), 200, np.uint8))
    with pytest.raises(ds.DatasetError, match="video stream is gray, but truth.json"):
        ds.open_sample(path)  # checked on open
    with pytest.raises(ds.DatasetError, match="video stream is gray, but truth.json"):
        list(ds.open_sample(path, verify=False).frames())  # and on reading


def test_motion_scale_scales_image_motion_linearly(tmp_path):
    """Scales 0.02 and 0.04 (image motion <= ~0.02 px, the linear regime): the video's change
    from the rest frame inside the object doubles; the physical displacements do not change."""
    out = []
    for scale in (0.02, 0.04):
        scene = with_overrides(tiny_scene(motion_scale=scale), frames=4)
        out.append(ds.open_sample(gen.generate(scene, tmp_path / str(scale), progress=False)))
    a, b = out
    np.testing.assert_array_equal(a["transient/displacements"], b["transient/displacements"])
    assert b.info["peak_image_motion_px"] == pytest.approx(2 * a.info["peak_image_motion_px"])
    assert 0.005 < b.info["peak_image_motion_px"] < 0.05
    rest = gen.sensor_dn(a["image/rest"][None], 16, 0.0, False, 1e4, None).astype(np.float64)
    from vvtbench.render.raster import rasterize
    from vvtbench.simulation.simulate import build_mesh

    _, V, F = gen.surface_geometry(build_mesh(a.scene))
    inner = _smooth_pixels(rasterize(a.camera, V, F), V, F, 2)  # no edges: sub-samples flip
    assert inner.sum() > 300
    da = (a.read_frames().astype(np.float64) - rest)[:, inner]
    db = (b.read_frames().astype(np.float64) - rest)[:, inner]
    assert np.abs(da).max() > 50
    slope = np.sum(da * db) / np.sum(da * da)
    assert abs(slope - 2.0) < 0.05 * 2.0, slope
    np.testing.assert_array_equal(b.read_frames()[[0, 3]], np.stack(_requantized(b, (0, 3), 16)))


def test_preview_clip_magnifies_motion(tiny, sample):
    """preview.mp4: frames every ~1/10 of the lowest mode's period; the rest render warped
    by the image-space motion magnified to gen.PREVIEW_PEAK_PX (8 px) peak; even size."""
    from vvtbench.render import Camera
    from vvtbench.render.raster import interpolate, rasterize
    from vvtbench.simulation.simulate import build_mesh

    info = sample.info
    f1 = info["modes"]["frequencies_hz"][0]
    stride = max(1, int(info["video"]["fps"] / (10.0 * f1)))
    ks = np.arange(0, sample.n_frames, stride)[: info["generator"]["preview_frames"]]
    clip = np.stack(list(read_frames(tiny / "preview.mp4", bpp=1))).astype(float)
    assert clip.shape == (len(ks), 64, 64) and len(ks) > 1
    _, rest, tris = gen.surface_geometry(build_mesh(sample.scene))
    cam = Camera.from_spec(sample.scene.camera)
    J = cam.jacobian(rest)
    raster = rasterize(cam, rest, tris)
    disp = sample.array("transient/displacements")
    peak = max(np.abs(interpolate(raster, tris, np.einsum("sij,sj->si", J, disp[k]),
                                  fill=0.0)).max() for k in ks)
    assert peak < 2.0  # the video's own motion is small: the preview must magnify it
    with gen.scene_renderer(sample.scene, rest, tris) as r:
        rest_img = np.clip(np.rint(r.render() * 255), 0, 255)
    # the magnified motion is visible: frames differ from the rest render and each other
    assert np.abs(clip - rest_img).mean(axis=(1, 2)).max() > 5
    # no bright artefacts: no frame is brighter anywhere than the rest render's maximum
    assert clip.max() <= rest_img.max() + 20


def test_top_level_open_sample(tiny, tmp_path):
    import vvtbench

    s = vvtbench.open_sample(tiny)
    assert isinstance(s, ds.Sample) and s.info == json.loads((tiny / "truth.json").read_text())
    assert vvtbench.open_sample is ds.open_sample and s.verify() == []
    with pytest.raises(ds.DatasetError, match="not a vvtbench sample"):
        vvtbench.open_sample(tmp_path)


def test_consumer_camera_variant(tiny, tmp_path):
    s = ds.open_sample(gen.generate(tiny_scene(), tmp_path, progress=False, consumer_crf=18))
    assert (s.path / "video.mp4").is_file() and not (s.path / "video.mkv").exists()
    assert s.bit_depth == 8 and s.info["video"]["lossless"] is False
    lossy = s.read_frames(normalize=True)
    ref = ds.open_sample(tiny).read_frames(normalize=True)
    assert lossy.shape == ref.shape and lossy.dtype == np.float32
    err = np.abs(lossy - ref)
    assert 0 < err.mean() < 0.02


def test_cli_suite_with_overrides(tmp_path, capsys):
    scene_file = tmp_path / "tiny.toml"
    import tomli_w

    scene_file.write_text(tomli_w.dumps(tiny_scene().to_toml_dict()))
    suite = tmp_path / "suite.toml"
    suite.write_text('scenes = ["tiny.toml"]\n')
    out = tmp_path / "out"
    code = cli_generate.main([str(suite), "-o", str(out), "--frames", "6",
                             "--resolution", "32x48", "--no-progress"])
    assert code == 0
    s = ds.open_sample(out / "tiny")
    assert s.n_frames == 6 and s.shape == (32, 48)
    assert cli_generate.main([str(suite), "-o", str(out), "--frames", "6", "--no-progress"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert cli_generate.main([str(scene_file), "-o", str(out), "--frames", "6", "--overwrite",
                             "--no-progress"]) == 0


def test_bad_input_gives_clear_errors(tmp_path, capsys):
    with pytest.raises(SceneError, match="no such scene file"):
        resolve_scenes("no_such_scene_xyz")
    assert cli_generate.main(["no_such_scene_xyz", "-o", str(tmp_path), "--no-progress"]) == 2
    assert "no such scene file" in capsys.readouterr().err
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(ds.DatasetError, match="cannot write to output folder"):
        gen.generate(tiny_scene(), blocker / "sub", progress=False)
    bad_suite = tmp_path / "suite.toml"
    bad_suite.write_text("scenes = [1, 2]\n")
    with pytest.raises(SceneError, match="list of scene names"):
        resolve_scenes(bad_suite)


# --------------------------------------------------------------------------- shipped scenes
def _deriv(I: np.ndarray, axis: int) -> np.ndarray:
    """Eighth-order central difference. (The fourth-order one of tests/test_render.py
    attenuates the gradient of the default speckles -- sigma ~1.5 px, finer on foreshortened
    faces -- by up to 8 %, which would be the estimator's bias, not the renderer's.)"""
    out = np.zeros_like(I)
    for k, c in enumerate((4 / 5, -1 / 5, 4 / 105, -1 / 280), 1):
        out += c * (np.roll(I, -k, axis=axis) - np.roll(I, k, axis=axis))
    return out


def _erode(mask: np.ndarray, r: int) -> np.ndarray:
    out = mask.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out &= np.roll(np.roll(mask, dy, 0), dx, 1)
    return out


def _smooth_pixels(raster, V: np.ndarray, F: np.ndarray, r: int) -> np.ndarray:
    """Object pixels at least ``r`` px from silhouettes and triplanar texture seams (where
    the dominant normal axis changes): there image changes are linear in small motions."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    axis = np.where(raster.mask, np.argmax(np.abs(n), axis=1)[raster.triangle], -1)
    smooth = np.zeros_like(raster.mask)
    for a in range(3):
        smooth |= _erode(axis == a, r)
    return _erode(raster.mask, r) & smooth


def _shipped_views():
    """One shipped scene per distinct (surface geometry, camera, render settings)."""
    seen, out = set(), []
    for path in sorted(SCENES_DIR.glob("*.toml")):
        s = load_scene(path)
        g = s.geometry.model_dump()
        g.pop("order", None)
        key = json.dumps([g, s.camera.model_dump(), s.render.model_dump()], sort_keys=True)
        if key not in seen:
            seen.add(key)
            out.append(path.stem)
    return out


def _rendered_surface(scene):
    """(vertices, triangles) ``generate`` renders: the simulation mesh's boundary (for meshes
    the tetrahedralization's, cached on disk after the first build)."""
    from vvtbench.simulation.simulate import build_mesh

    return gen.surface_geometry(build_mesh(scene))[1:]


@pytest.mark.parametrize("name", _shipped_views())
def test_rigid_subpixel_shift_with_shipped_scene_defaults(name):
    """A rigid 0.01 px shift is recovered as a 2-D shift within 5 % with each shipped scene's
    surface, camera, resolution, texture, supersampling, lighting and bit depth.

    The surface is the one ``generate`` renders (``gen.surface_geometry`` of the simulation
    mesh). The object moves parallel to the image plane (camera x, then camera y) by 0.01 px
    at the look-at depth ``z0``; a surface point at camera depth ``z`` then moves by exactly
    ``0.01 px * z0 / z`` along that image axis and not at all along the other. Both renders
    are quantized to the scene's bit depth as in the video (sensor noise off: the shipped
    scenes have none). ``(dx, dy)`` is the least-squares solution of
    ``I1 - I0 = -(dx Ix + dy Iy) z0 / z`` over textured pixels away from silhouettes and
    triplanar texture seams; the commanded component must be within 5 % of 0.01 px, the
    other below 5 % of it (cross-axis leakage).
    """
    from vvtbench.render.raster import rasterize

    scene = load_scene(name)
    rs = scene.render
    bits = 8 if rs.consumer_crf is not None else rs.bit_depth
    V, F = _rendered_surface(scene)
    cam = Camera.from_spec(scene.camera)
    uv = cam.project(V)
    assert np.all((uv > 0.05 * np.array([cam.width, cam.height]))
                  & (uv < 0.95 * np.array([cam.width, cam.height]))), "object leaves the frame"
    raster = rasterize(cam, V, F)
    mask = _smooth_pixels(raster, V, F, 4)
    assert mask.sum() > 2000
    look = np.asarray(scene.camera.look_at)
    w = np.where(raster.mask, cam.depth(look) / raster.depth.astype(np.float64), 0.0)

    def quantize(img: np.ndarray) -> np.ndarray:
        return gen.sensor_dn(img[None], bits, 0.0, False, 1.0, None).astype(np.float64)

    with gen.scene_renderer(scene, V, F) as r:
        I0 = quantize(r.render())
        for c, direction in enumerate((cam.R[0], cam.R[1])):  # image right, image down
            d = direction * 0.01 / np.linalg.norm(cam.jacobian(look) @ direction)
            I1 = quantize(r.render(np.tile(d, (len(V), 1))))
            Im = 0.5 * (I0 + I1)
            A = np.stack([(w * _deriv(Im, 1))[mask], (w * _deriv(Im, 0))[mask]], axis=1)
            est = np.linalg.lstsq(A, -(I1 - I0)[mask], rcond=None)[0]
            assert abs(est[c] / 0.01 - 1.0) < 0.05, (c, est)
            assert abs(est[1 - c]) < 0.05 * 0.01, (c, est)


# --------------------------------------------------------------------------- format 2
def test_sample_is_self_sufficient(sample):
    """Boundary, node sets and element name are in the truth: no simulation needed."""
    from vvtbench.simulation.simulate import build_mesh, fixed_nodes

    mesh = build_mesh(sample.scene)
    np.testing.assert_array_equal(sample.require("mesh/fixed_nodes"),
                                  fixed_nodes(sample.scene, mesh))
    for name, ids in mesh.node_sets.items():
        np.testing.assert_array_equal(sample.require(f"mesh/node_sets/{name}"), ids)
    assert sample.truth["mesh"].attrs["element"] == mesh.element == sample.element
    assert sample.format == ds.FORMAT_VERSION == 2 and sample.has_video
    # free DOFs are exactly the DOFs of the nodes that are not fixed
    d = sample.info["mesh"]["dofs_per_node"]
    fixed = np.zeros(sample.info["mesh"]["n_nodes"] * d, bool)
    fixed[(sample["mesh/fixed_nodes"][:, None] * d + np.arange(d)).ravel()] = True
    np.testing.assert_array_equal(np.flatnonzero(~fixed), sample["modes/free_dofs"])


def test_require_names_file_and_array_of_old_samples(tiny, tmp_path):
    import shutil

    import zarr

    old = tmp_path / "old"
    shutil.copytree(tiny, old)
    info = json.loads((old / "truth.json").read_text())
    info["format"] = 1
    (old / "truth.json").write_text(json.dumps(info))
    g = zarr.open_group(str(old / "truth.zarr"), mode="a")
    del g["mesh/fixed_nodes"]
    with pytest.raises(ds.DatasetError, match="truth.json"):
        ds.open_sample(old)  # no longer matches its manifest
    s = ds.open_sample(old, verify=False)
    assert s["mesh/points"].shape == (64, 3)  # what is there still reads
    with pytest.raises(ds.DatasetError, match=r"truth\.zarr: no array 'mesh/fixed_nodes'.*"
                                              r"format 1.*regenerate"):
        s.require("mesh/fixed_nodes")


def test_modes_only_sample(tmp_path):
    import time

    from vvtbench.scene.scene import load_scene

    t0 = time.process_time()  # CPU time (every thread of this process): load does not count
    path = gen.generate(load_scene("jello_cube_defect_top"), tmp_path, video=False,
                        progress=False)
    cpu = time.process_time() - t0
    s = ds.open_sample(path)
    names = {p.name for p in path.iterdir()}
    assert names == {"scene.toml", "camera.json", "truth.json", "truth.zarr", "rest.png",
                     "depth.png", "manifest.json"}
    assert s.verify() == [] and not s.has_video
    assert s.info["video"]["file"] is None and s.n_frames == 0
    assert s.info["peak_image_motion_px"] is None
    with pytest.raises(ds.DatasetError, match="modes-only"):
        next(s.frames())
    with pytest.raises(ds.DatasetError, match="modes-only"):
        s.require("transient/displacements")
    assert "image/modes" not in s
    for name in ("mesh/points", "mesh/cells", "mesh/surface", "mesh/fixed_nodes",
                 "material/stiffness", "modes/eigenvalues", "modes/vectors", "modes/free_dofs",
                 "image/depth", "observation/visible", "observation/jacobian"):
        assert s.require(name).size > 0
    assert np.isfinite(s["voxels/stiffness"]).all()
    assert s["observation/visible"].sum() > 0
    # no transient, no video: about 2 s of CPU (the speed itself: benchmarks/bench_generate.py)
    assert cpu < 60


@pytest.mark.parametrize("rate", ["2000", "1200", "30000/1001"])
def test_frame_rate_is_read_exactly_from_the_container(rate, tmp_path):
    """ffmpeg prints 2000 FPS as "2k fps"; the rate comes back as an exact fraction."""
    from fractions import Fraction

    from vvtbench.video.files import open_video

    path = tmp_path / "v.mkv"
    with VideoWriter(path, 8, 8, playback_fps=Fraction(rate)) as w:
        for k in range(5):
            w.write(np.full((8, 8), 1000 * k, np.uint16))
    info = probe_video(path)
    assert info.container_rate == Fraction(rate) and info.frame_rate == Fraction(rate)
    vs = open_video(path)
    assert vs.rate == Fraction(rate) and vs.fps == float(Fraction(rate))
    assert len(list(vs.frames)) == 5
    # the capture-rate tag of vvtbench's own videos wins over the nominal playback rate
    tagged = tmp_path / "t.mkv"
    with VideoWriter(tagged, 8, 8, capture_fps=Fraction(rate)) as w:
        w.write(np.zeros((8, 8), np.uint16))
    assert probe_video(tagged).frame_rate == Fraction(rate)
    assert probe_video(tagged).container_rate == 30


def test_a_bare_stream_has_no_frame_rate(tmp_path):
    """A raw H.264 stream has no time stamps: ffmpeg's 25 fps is its demuxer's default, so
    the rate is unknown (extract then asks for --fps) rather than silently 25."""
    import subprocess

    from vvtbench.video.files import ffmpeg_exe

    mp4, raw = tmp_path / "v.mp4", tmp_path / "v.h264"
    for out in (mp4, raw):
        subprocess.run([ffmpeg_exe(), "-v", "error", "-y", "-f", "lavfi", "-i",
                        "testsrc2=size=32x32:rate=2000", "-frames:v", "4", "-c:v", "libx264",
                        "-pix_fmt", "yuv420p", str(out)], check=True)
    assert probe_video(mp4).container_rate == 2000
    info = probe_video(raw)
    assert info.container_rate is None and info.frame_rate is None and info.codec == "h264"


def test_high_rate_frame_count_from_the_container_is_not_called_truncated(tmp_path):
    """At 2000 fps the container duration (printed to 10 ms) misses a frame or so: a paper
    sample (12,000 frames) read as 11,999 failed to open. The cheap check allows that slack;
    counting decodes exactly."""
    from vvtbench.video.files import VideoWriter, count_frames, probe_video

    path = tmp_path / "v.mkv"
    w = VideoWriter(path, 8, 8, capture_fps=2000)
    for i in range(221):
        w.write(np.full((8, 8), i, dtype=np.uint16))
    w.close()
    estimate = probe_video(path).n_frames
    assert count_frames(path) == 221 and abs(estimate - 221) <= 21
