"""Tests for vvtbench.render: camera model, textures and the float pyrender backend.

Rendering tests need headless EGL (Mesa llvmpipe is fine).  They FAIL, never
skip, when EGL is missing, naming the Debian packages to install.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from vvtbench.render.camera import Camera
from vvtbench.render.texture import speckle_texture, triplanar_mapping
from vvtbench.scene.scene import SCENES_DIR, load_scene

# --------------------------------------------------------------------------- helpers


def _grid_plane(n: int, half: float, jitter: float = 0.0, seed: int = 0):
    """Square plane z=0 in [-half, half]^2 as an n x n vertex grid (interior jittered)."""
    g = np.linspace(-half, half, n)
    X, Y = np.meshgrid(g, g)
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(n * n)], axis=1)
    if jitter:
        interior = np.all(np.abs(V[:, :2]) < half * (1 - 1e-9), axis=1)
        V[interior, :2] += np.random.default_rng(seed).uniform(-jitter, jitter, (interior.sum(), 2))
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            F += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return V, np.array(F)


def _cube(levels: int = 2, size: float = 1.0):
    import trimesh

    m = trimesh.creation.box(extents=(size, size, size))
    for _ in range(levels):
        m = m.subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


def _polygon_area_centroid(P: np.ndarray):
    x, y = P[:, 0], P[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    c = x * y1 - x1 * y
    A = c.sum() / 2.0
    return abs(A), np.array([((x + x1) * c).sum(), ((y + y1) * c).sum()]) / (6.0 * A)


def _deriv(I: np.ndarray, axis: int) -> np.ndarray:
    """Fourth-order central difference (accurate for speckles of a few px)."""

    def f(k):
        return np.roll(I, -k, axis=axis)

    return (-f(2) + 8.0 * f(1) - 8.0 * f(-1) + f(-2)) / 12.0


def _linearised_shift(I0: np.ndarray, I1: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Least-squares (du, dv) with I1 - I0 = -grad(I) . d over ``mask``."""
    I0 = I0.astype(np.float64)
    I1 = I1.astype(np.float64)
    Im = 0.5 * (I0 + I1)
    A = np.stack([_deriv(Im, 1)[mask], _deriv(Im, 0)[mask]], axis=1)
    b = -(I1 - I0)[mask]
    return np.linalg.lstsq(A, b, rcond=None)[0]


@pytest.fixture(scope="module")
def gl():
    """The EGL backend; fails (not skips) with install instructions if unavailable."""
    from vvtbench.render import pyrender_backend as pb

    try:
        info = pb.gl_info()
    except pb.EGLUnavailableError as exc:
        pytest.fail(str(exc), pytrace=False)
    assert info["version"]
    return pb


# --------------------------------------------------------------------------- camera


def _random_camera(seed: int = 0) -> Camera:
    rng = np.random.default_rng(seed)
    base = Camera.look_at(
        rng.normal(size=3) + [0, -4, 1],
        rng.normal(scale=0.2, size=3),
        fx=300.0,
        width=320,
        height=240,
    )
    return Camera.from_intrinsics(
        310.0, 290.0, 170.3, 110.8, width=320, height=240, R=base.R, t=base.t, skew=2.5
    )


def test_jacobian_matches_finite_differences():
    cam = _random_camera(1)
    X = np.random.default_rng(2).normal(scale=0.5, size=(20, 3))
    J = cam.jacobian(X)
    assert J.shape == (20, 2, 3)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (cam.project(X + e) - cam.project(X - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-6)
    # single point API
    np.testing.assert_allclose(cam.jacobian(X[0]), J[0])


def test_look_at_target_projects_to_image_center():
    cam = Camera.look_at((1.0, -3.0, 2.0), (0.2, 0.1, -0.3), fov_y_deg=40.0, width=101, height=60)
    np.testing.assert_allclose(cam.project([0.2, 0.1, -0.3]), [50.0, 29.5], atol=1e-9)
    assert cam.depth([0.2, 0.1, -0.3]) == pytest.approx(np.linalg.norm([0.8, -3.1, 2.3]))
    np.testing.assert_allclose(cam.center, [1.0, -3.0, 2.0], atol=1e-12)
    # fov: the top edge of the image (v = -0.5) is fov/2 above the axis
    assert cam.fy == pytest.approx(30.0 / np.tan(np.radians(20.0)))
    # world up is image up, world "right" is image right
    c = np.array([0.2, 0.1, -0.3])
    assert cam.project(c + [0, 0, 0.1])[1] < 29.5
    right = np.cross(c - cam.center, [0, 0, 1])
    assert cam.project(c + 0.1 * right / np.linalg.norm(right))[0] > 50.0
    # P agrees with project
    X = np.array([[0.3, 0.4, 0.5]])
    p = cam.P @ np.append(X[0], 1.0)
    np.testing.assert_allclose(p[:2] / p[2], cam.project(X)[0])


def test_camera_dict_roundtrip_and_validation():
    cam = _random_camera(3)
    d = json.loads(json.dumps(cam.to_dict()))
    assert Camera.from_dict(d) == cam
    with pytest.raises(ValueError):
        Camera.look_at((0, 0, 1), (0, 0, 0), fov_y_deg=30.0, width=8, height=8)  # up || view
    with pytest.raises(ValueError):
        Camera.look_at((0, 1, 0), (0, 0, 0), width=8, height=8)  # neither fov nor fx
    with pytest.raises(ValueError):
        Camera(K=np.eye(3), R=2 * np.eye(3), t=np.zeros(3), width=4, height=4)


def test_scaled_camera_uses_pixel_centre_convention():
    cam = _random_camera(4)
    X = np.random.default_rng(5).normal(scale=0.3, size=(10, 3))
    s4 = cam.scaled(4)
    assert (s4.width, s4.height) == (4 * cam.width, 4 * cam.height)
    # pixel edges scale: u' + 0.5 = 4 (u + 0.5)
    np.testing.assert_allclose(s4.project(X) + 0.5, 4.0 * (cam.project(X) + 0.5), atol=1e-9)


def _camera_scene(**camera):
    from vvtbench.scene.scene import parse_scene

    cam = {"resolution": [48, 64], "position": [0.16, -0.13, 0.13],
           "look_at": [0.025, 0.025, 0.022], **camera}
    return parse_scene({"name": "cam", "geometry": {"kind": "box", "cells": [2, 2, 2]},
                        "camera": cam, "render": {"supersample": 2}}, "cam.toml")


def test_camera_spec_focal_lengths_and_principal_point():
    base = Camera.from_spec(_camera_scene(fx=80.0).camera)
    assert (base.fx, base.fy, base.cx, base.cy) == (80.0, 80.0, 31.5, 23.5)
    cam = Camera.from_spec(_camera_scene(fx=80.0, fy=88.0, cx=36.5, cy=20.5).camera)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (80.0, 88.0, 36.5, 20.5)
    np.testing.assert_array_equal(cam.R, base.R)
    X = np.random.default_rng(0).uniform(0.0, 0.05, size=(20, 3))
    uv0, uv = base.project(X), cam.project(X)
    np.testing.assert_allclose(uv[:, 0], uv0[:, 0] + 5.0, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1] - 20.5, 1.1 * (uv0[:, 1] - 23.5), atol=1e-9)
    np.testing.assert_allclose(cam.project([0.025, 0.025, 0.022]), [36.5, 20.5], atol=1e-9)
    fov = Camera.from_spec(_camera_scene(fov_y_deg=30.0, cx=10.0).camera)
    assert fov.cx == 10.0 and fov.cy == 23.5 and fov.fx == fov.fy
    from vvtbench.scene.scene import SceneError

    with pytest.raises(SceneError, match=r"(?s)cam.toml.*key 'camera': fy \(px\) needs fx"):
        _camera_scene(fy=90.0)
    with pytest.raises(SceneError, match="(?s)cam.toml.*key 'camera.cx': Input should be a finite"):
        _camera_scene(fx=80.0, cx=float("inf"))


def test_shifted_principal_point_shifts_the_rendered_rest_pose(gl):
    """cx + 5, cy - 3 (px) moves the rest-pose render by 5 columns right and 3 rows up."""
    from vvtbench.samples import generate as gen
    from vvtbench.simulation.simulate import build_mesh

    imgs = []
    for pp in ({}, {"cx": 36.5, "cy": 20.5}):
        scene = _camera_scene(fx=80.0, **pp)
        _, V, F = gen.surface_geometry(build_mesh(scene))
        with gen.scene_renderer(scene, V, F) as r:
            imgs.append(r.render().astype(np.float64))
    base, moved = imgs
    assert base[3:, :-5].sum() > 0.9 * base.sum()  # the object stays inside both frames
    np.testing.assert_allclose(moved[:-3, 5:], base[3:, :-5], atol=1e-5)


# --------------------------------------------------------------------------- texture


def test_speckle_texture_seeded_periodic_float():
    a = speckle_texture(128, grain=3.0, density=0.5, seed=7)
    assert a.dtype == np.float32 and a.shape == (128, 128)
    assert a.min() >= 0.0 and a.max() <= 1.0 and a.std() > 0.2
    assert np.array_equal(a, speckle_texture(128, grain=3.0, density=0.5, seed=7))
    assert not np.array_equal(a, speckle_texture(128, grain=3.0, density=0.5, seed=8))
    # tileable: the jump across the wrap-around seam is like any other neighbour step
    inner = np.abs(np.diff(a, axis=1)).mean()
    seam = np.abs(a[:, 0] - a[:, -1]).mean()
    assert seam < 2.0 * inner
    assert speckle_texture(64, contrast=0.5, seed=1).max() <= 0.75 + 1e-6


def test_triplanar_mapping_textures_every_face_without_large_stretch():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    tm = triplanar_mapping(V, F, tile_size=0.5)
    np.testing.assert_array_equal(tm.vertices, V[tm.source_index])
    np.testing.assert_array_equal(tm.source_index[tm.triangles], F)  # same faces
    assert len(tm.vertices) < 3 * len(V)
    # every face has non-degenerate uv, stretched by at most sqrt(3) (area ratio)
    e1 = tm.vertices[tm.triangles[:, 1]] - tm.vertices[tm.triangles[:, 0]]
    e2 = tm.vertices[tm.triangles[:, 2]] - tm.vertices[tm.triangles[:, 0]]
    area3 = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    t1 = tm.uv[tm.triangles[:, 1]] - tm.uv[tm.triangles[:, 0]]
    t2 = tm.uv[tm.triangles[:, 2]] - tm.uv[tm.triangles[:, 0]]
    area_uv = 0.5 * np.abs(t1[:, 0] * t2[:, 1] - t1[:, 1] * t2[:, 0]) * 0.5**2
    ratio = area_uv / area3
    assert ratio.min() > 1 / np.sqrt(3) - 1e-9 and ratio.max() <= 1.0 + 1e-9
    # displacements map through source_index
    d = np.arange(len(V) * 3, dtype=float).reshape(-1, 3)
    np.testing.assert_array_equal(tm.expand(d), d[tm.source_index])


# --------------------------------------------------------------------------- backend


def test_egl_error_names_debian_packages():
    from vvtbench.render import pyrender_backend as pb

    msg = str(pb.egl_error(OSError("libEGL.so.1: cannot open shared object file")))
    for pkg in ("libegl1", "libegl-mesa0", "libgl1-mesa-dri", "libgles2"):
        assert pkg in msg
    assert "PYOPENGL_PLATFORM=egl" in msg


def test_projection_matrix_matches_pyrender_intrinsics(gl):
    cam = Camera.from_intrinsics(210.0, 190.0, 60.2, 41.7, width=128, height=96)
    ours = gl._gl().OpenCVCamera(cam, znear=0.1, zfar=10.0)
    ref = gl._gl().pyrender.IntrinsicsCamera(210.0, 190.0, 60.7, 42.2, znear=0.1, zfar=10.0)
    np.testing.assert_allclose(
        ours.get_projection_matrix(128, 96), ref.get_projection_matrix(128, 96), atol=1e-12
    )
    # resolution independent (supersampling)
    np.testing.assert_allclose(
        ours.get_projection_matrix(512, 384), ref.get_projection_matrix(128, 96), atol=1e-12
    )


@pytest.mark.parametrize("skew,pp", [(0.0, None), (3.0, (40.3, 27.9))])
def test_rendered_geometry_matches_camera_project(gl, skew, pp):
    """A uniformly white tilted quad: its intensity centroid and area equal the
    centroid and area of the polygon given by Camera.project of its corners."""
    base = Camera.look_at((0.3, -2.0, 0.5), (0.1, 0.05, 0.02), fx=90.0, width=80, height=60)
    cx, cy = pp if pp else (None, None)
    cam = Camera.from_intrinsics(
        90.0, 95.0, cx, cy, width=80, height=60, R=base.R, t=base.t, skew=skew
    )
    c = np.array([0.12, 0.03, 0.05])
    a = np.array([0.25, 0.05, 0.1])
    b = np.array([-0.04, 0.02, 0.23])
    V = np.array([c - a - b, c + a - b, c + a + b, c - a + b])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    with gl.Renderer(V, F, cam, texture=np.ones((8, 8)), supersample=4) as r:
        img = r.render().astype(np.float64)
    assert img.shape == (60, 80)
    vv, uu = np.mgrid[:60, :80]
    area = img.sum()
    centroid = np.array([(img * uu).sum(), (img * vv).sum()]) / area
    area_ref, centroid_ref = _polygon_area_centroid(cam.project(V))
    assert abs(area - area_ref) < 0.01 * area_ref
    assert np.abs(centroid - centroid_ref).max() < 0.05, centroid - centroid_ref


def test_depth_matches_ray_plane_intersection(gl):
    cam = Camera.look_at((0.4, -1.5, 1.2), (0.0, 0.0, 0.0), fx=70.0, width=48, height=40)
    V, F = _grid_plane(3, 0.6)
    with gl.Renderer(V, F, cam, supersample=4) as r:
        depth = r.depth()
    assert depth.shape == (40, 48) and depth.dtype == np.float32
    # analytic depth of plane z=0 along each pixel-centre ray
    vv, uu = np.mgrid[:40, :48]
    rays_cam = np.linalg.solve(cam.K, np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)]))
    rays = cam.R.T @ rays_cam  # world direction for unit camera-z
    lam = -cam.center[2] / rays[2]  # camera-z depth of the intersection
    hit = cam.center[:, None] + lam * rays
    inside = (np.abs(hit[0]) < 0.6 - 0.02) & (np.abs(hit[1]) < 0.6 - 0.02)
    outside = (np.abs(hit[0]) > 0.6 + 0.02) | (np.abs(hit[1]) > 0.6 + 0.02) | (lam < 0)
    d = depth.ravel()
    assert inside.sum() > 300 and outside.sum() > 100
    np.testing.assert_allclose(d[inside], lam[inside], rtol=2e-4)
    assert np.all(np.isinf(d[outside]))


def test_supersampling_equals_box_filtered_highres_render(gl):
    """supersample=4 (GPU box filter) == native render with Camera.scaled(4), box-averaged."""
    cam = Camera.look_at((0.5, -2.0, 1.0), (0, 0, 0), fx=60.0, width=40, height=32)
    V, F = _cube(1, 0.8)
    tex = speckle_texture(256, grain=3.0, seed=2)
    with gl.Renderer(V, F, cam, texture=tex, texture_tile=0.5, supersample=4) as r:
        lo = r.render()
    with gl.Renderer(V, F, cam.scaled(4), texture=tex, texture_tile=0.5, supersample=1) as r:
        hi = r.render()
    ref = hi.reshape(32, 4, 40, 4).mean(axis=(1, 3))
    assert lo.shape == (32, 40)
    np.testing.assert_allclose(lo, ref, atol=1e-4)


@pytest.fixture(scope="module")
def speckle_plane_renders(gl):
    """Fronto-parallel speckle plane, rest and rigidly shifted renders (supersample=4)."""
    W = H = 96
    cam = Camera.look_at((0.02, -0.01, 2.0), (0, 0, 0), up=(0, 1, 0), fx=120.0, width=W, height=H)
    V, F = _grid_plane(6, 0.6, jitter=0.04, seed=1)
    # speckle sigma = 4 texels = 2 px
    tile = 512 * 0.5 * 2.0 / 120.0
    tex = speckle_texture(512, grain=4.0, seed=3)
    J = cam.jacobian(V.mean(axis=0))  # uniform over a fronto-parallel plane
    out = {}
    with gl.Renderer(V, F, cam, texture=tex, texture_tile=tile, supersample=4) as r:
        out["rest"] = r.render()
        for px in (0.01, 0.001):
            want = px * np.array([0.8, -0.6])
            d = np.linalg.lstsq(J, want, rcond=None)[0]
            np.testing.assert_allclose(J @ d, want, atol=1e-12)
            out[px] = (want, r.render(np.tile(d, (len(V), 1))))
        out["rest_again"] = r.render()
    mask = np.zeros((H, W), bool)
    mask[14:-14, 14:-14] = True  # textured interior, away from the plane's edges
    out["mask"] = mask
    return out


@pytest.mark.parametrize("px", [0.01, 0.001])
def test_subpixel_rigid_shift_is_recovered(speckle_plane_renders, px):
    want, I1 = speckle_plane_renders[px]
    est = _linearised_shift(speckle_plane_renders["rest"], I1, speckle_plane_renders["mask"])
    err = np.linalg.norm(est - want) / np.linalg.norm(want)
    assert err < 0.05, (est, want)


def test_rest_pose_is_restored_after_displaced_frames(speckle_plane_renders):
    np.testing.assert_array_equal(
        speckle_plane_renders["rest"], speckle_plane_renders["rest_again"]
    )


def test_intensities_are_not_quantised(speckle_plane_renders):
    img = speckle_plane_renders["rest"]
    assert img.dtype == np.float32
    v = img[speckle_plane_renders["mask"]].astype(np.float64)
    assert len(np.unique(v)) > 0.9 * v.size
    off_grid = np.abs(v * 255.0 - np.round(v * 255.0)) > 1e-3
    assert off_grid.mean() > 0.9
    # a 0.001 px motion changes pixels by far less than one 8-bit step, yet visibly
    diff = np.abs(speckle_plane_renders[0.001][1] - img)[speckle_plane_renders["mask"]]
    assert diff.max() < 0.5 / 255 and (diff > 0).mean() > 0.5


def test_visibility_of_cube_from_corner(gl):
    V, F = _cube(2, 1.0)  # 5 x 5 vertices per face
    cam = Camera.look_at((2.5, -2.2, 2.0), (0, 0, 0), fov_y_deg=35.0, width=96, height=96)
    with gl.Renderer(V, F, cam, supersample=4) as r:
        vis = r.visible_vertices()
    assert vis.shape == (len(V),) and vis.dtype == bool
    on_visible_face = (
        np.isclose(V[:, 0], 0.5) | np.isclose(V[:, 1], -0.5) | np.isclose(V[:, 2], 0.5)
    )
    assert on_visible_face.sum() == 61
    assert vis[on_visible_face].all()
    assert not vis[~on_visible_face].any()
    # a camera that sees only part of the cube: off-frame vertices are invisible
    narrow = Camera.look_at((2.5, -2.2, 2.0), (0.5, -0.5, 0.5), fov_y_deg=8.0, width=32, height=32)
    with gl.Renderer(V, F, narrow, supersample=2) as r:
        vis2 = r.visible_vertices()
    uv = narrow.project(V)
    in_frame = np.all((uv >= -0.5) & (uv < 31.5), axis=1)
    assert 0 < vis2.sum() < on_visible_face.sum()
    assert not vis2[~in_frame].any()


@pytest.mark.parametrize("lighting", ["lit", "lambert"])
def test_shaded_modes_are_linear_in_albedo(gl, lighting):
    cam = Camera.look_at((0, 0, 2.0), (0, 0, 0), up=(0, 1, 0), fx=40.0, width=24, height=24)
    V, F = _grid_plane(2, 0.5)
    kw = dict(supersample=1, lighting=lighting, light_direction=(0, 0, -1.0), ambient=0.2)
    with gl.Renderer(V, F, cam, texture=np.full((4, 4), 1.0), **kw) as r:
        white = r.render()[8:16, 8:16]
    with gl.Renderer(V, F, cam, texture=np.full((4, 4), 0.5), **kw) as r:
        grey = r.render()[8:16, 8:16]
    # diffuse + ambient = 0.9 for a white surface facing the light; small specular on top
    assert 0.9 - 1e-6 <= white.mean() < 0.95
    # linear (no gamma): half the albedo gives about half the intensity
    assert abs(grey.mean() / white.mean() - 0.5) < 0.03
    # two-sided: reversed winding (normal pointing away from the camera) shades the same
    with gl.Renderer(V, F[:, ::-1], cam, texture=np.full((4, 4), 1.0), **kw) as r:
        flipped = r.render()[8:16, 8:16]
    np.testing.assert_allclose(flipped, white, atol=1e-5)
    # light at 60 degrees from the normal: ambient + 0.7 * cos(60) = 0.55 (+ specular)
    tilted = dict(kw, light_direction=(np.sin(np.pi / 3), 0, -np.cos(np.pi / 3)))
    with gl.Renderer(V, F, cam, texture=np.full((4, 4), 1.0), **tilted) as r:
        oblique = r.render()[8:16, 8:16]
    assert 0.55 - 1e-3 < oblique.mean() < 0.58


@pytest.mark.parametrize("name", sorted(p.stem for p in SCENES_DIR.glob("*.toml")))
def test_shipped_viewpoints(name):
    """Drums are seen obliquely (out-of-plane motion moves the image); box scenes show three
    faces (front y = 0, right x = max, top), as in the paper's cube figures."""
    scene = load_scene(name)
    cam = np.asarray(scene.camera.position, float)
    axis = np.asarray(scene.camera.look_at, float) - cam
    axis /= np.linalg.norm(axis)
    if scene.geometry.kind == "drum":
        tilt = np.degrees(np.arccos(abs(axis[2])))
        assert 20.0 <= tilt <= 70.0, f"{name}: camera {tilt:.0f} deg off the drum normal"
    elif scene.geometry.kind == "box":
        size = np.asarray(scene.geometry.size, float)
        assert cam[1] < 0.0 and cam[0] > size[0] and cam[2] > size[2], (
            f"{name}: camera at {cam} does not see the front, right and top faces")
