"""Dataset generator: a scene becomes one sample folder (video + ground truth + manifest).

``generate(scene, out_dir)`` simulates the scene, renders every frame through the scene's
camera, streams the frames to a lossless 16-bit FFVHUFF video chunk by chunk, and writes the ground
truth a solver or a metric could need; a scene with several cameras (``[[camera.views]]`` or
``[camera.rig]``) is simulated once and every view rendered from the same motion, view 0 where
a single-view sample has its files and view ``i`` under ``views/<i>/``;
``generate(scene, out_dir, video=False)`` writes a *modes-only* sample (the truth without
the video and the transient response) in about a second.
:func:`vvtbench.samples.reader.open_sample` reads either back. The folder layout, every array's
shape, dtype and unit, and the conventions are in ``docs/dataset.md``.

Properties
----------
* Memory: frames are rendered and encoded in segments of ``segment_frames`` video frames; the
  simulation keeps only modal coordinates, so peak memory does not grow with video length.
* Atomic: everything is written into ``out_dir/.NAME.partial/`` and renamed to ``out_dir/NAME``
  at the end; an existing sample is replaced only with ``overwrite=True``.
* Resumable: each finished video segment is recorded in ``.NAME.partial/checkpoint.json``; a
  rerun with the same scene and options continues after the last finished segment.
* Reproducible: the same scene (and seed) gives byte-identical files on one machine (ffmpeg
  bit-exact flags, no timestamps, per-frame seeded noise, BLAS on one thread, canonical sign
  and order of modes); on another CPU or with other library versions the values agree to the
  tolerances of :mod:`vvtbench.samples.compare`, not byte for byte.

Scene specs and overrides: :func:`vvtbench.scene.scene.with_overrides`; worker jobs:
:mod:`vvtbench.samples.jobs`; progress: :mod:`vvtbench.samples.progress`; the sensor noise model:
:mod:`vvtbench.render.sensor`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..fem.modal import single_threaded
from ..fem.voxels import default_voxel_shape
from ..io.files import open_new, write_json
from ..render.sensor import FULL_WELL_ELECTRONS, noise_rng, sensor_dn
from ..scene.scene import Scene, load_scene
from ..video.files import LOSSLESS_CODEC, PLAYBACK_FPS, VideoWriter, concat_videos
from .progress import ProgressCallback, StageProgress
from .reader import FORMAT_VERSION, DatasetError, sha256_file

__all__ = [
    "FULL_WELL_ELECTRONS",
    "generate",
    "mode_vectors_3d",
    "n_video_frames",
    "scene_renderer",
    "sensor_dn",
    "surface_geometry",
]


# --------------------------------------------------------------------------- small helpers
def _write_json_sorted(path: Path, data: Any) -> None:
    write_json(path, data, indent=2, sort_keys=True)


def _as_scene(scene: Scene | str | Path) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


# --------------------------------------------------------------------------- truth helpers
def surface_geometry(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(surface node ids, their rest points, triangles indexing the surface nodes)."""
    nodes = mesh.surface_nodes
    lut = np.full(mesh.n_nodes, -1, dtype=np.int64)
    lut[nodes] = np.arange(len(nodes))
    return nodes, mesh.points[nodes], lut[mesh.surface]


def mode_vectors_3d(result, nodes: np.ndarray) -> np.ndarray:
    """(n_modes, n_nodes, 3) 3-D mode shapes at ``nodes`` (drums: (0, 0, w)); fixed DOFs 0."""
    mesh, model, modes = result.mesh, result.model, result.modes
    d = mesh.dofs_per_node
    rows = model.free_index[mesh.dofs_of(nodes)]
    phi = np.zeros((len(rows), len(modes)))
    ok = rows >= 0
    phi[ok] = modes.vectors[rows[ok]]
    phi = phi.reshape(len(nodes), d, len(modes)).transpose(2, 0, 1)
    if d == 3:
        return phi
    out = np.zeros((len(modes), len(nodes), 3))
    out[:, :, 2] = phi[:, :, 0]
    return out


def _as_3d(u: np.ndarray) -> np.ndarray:
    """(..., n, d) displacements to (..., n, 3): membranes move along z."""
    if u.shape[-1] == 3:
        return u
    out = np.zeros(u.shape[:-1] + (3,), dtype=u.dtype)
    out[..., 2] = u[..., 0]
    return out


def _fine_scene(scene: Scene) -> Scene:
    """The scene simulated at fps * frame_average (sub-frames of the averaged video)."""
    a = scene.render.frame_average
    if a == 1:
        return scene
    sim = scene.simulation.model_copy(update={"fps": scene.simulation.fps * a})
    return scene.model_copy(update={"simulation": sim})


def n_video_frames(scene: Scene) -> int:
    """Number of video frames of ``scene``: round(duration * fps)."""
    return int(round(scene.simulation.duration * scene.simulation.fps))


def _to_png8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _depth_png(depth: np.ndarray) -> np.ndarray:
    """16-bit depth image: near = bright, 0 = background."""
    finite = np.isfinite(depth)
    out = np.zeros(depth.shape, dtype=np.uint16)
    if finite.any():
        lo, hi = float(depth[finite].min()), float(depth[finite].max())
        span = hi - lo if hi > lo else 1.0
        out[finite] = np.rint(1000 + 64535 * (hi - depth[finite]) / span).astype(np.uint16)
    return out


_DESCRIPTIONS = {
    "scene.toml": "resolved scene (every default filled in), generating vvtbench version "
                  "in the header comment",
    "camera.json": "pinhole camera (model, convention): K (3x3 px), R (3x3), t (3, m), "
                   "P = K[R|t] (3x4), width, height (px), fov_y_deg",
    "truth.json": "small ground truth: modal frequencies (Hz), damping ratios, Rayleigh "
                  "coefficients, video/camera-model settings, voxel grid, array index",
    "video.mkv": "lossless video, FFVHUFF gray16le, DN stored LSB-aligned in "
                 "[0, 2^bit_depth - 1] (truth.json video.bit_depth)",
    "video.mp4": "consumer-camera video, 8-bit gray H.264 (lossy, CRF in truth.json)",
    "rest.png": "rest-pose frame, noise-free, 8-bit (for viewing)",
    "depth.png": "rest-pose depth, 16-bit, near = bright, 0 = background (for viewing)",
    "preview.mp4": "small H.264 preview with magnified motion (for viewing)",
    "family.json": "scene family instance: family, split, index, seed, family file sha256, "
                   "vvtbench version (docs/families.md)",
}


def _describe(rel: str) -> str:
    parts = rel.split("/", 2)
    if parts[0] == "views" and len(parts) == 3 and parts[1].isdigit():
        return f"view {parts[1]}: {_describe(parts[2])}"
    if rel in _DESCRIPTIONS:
        return _DESCRIPTIONS[rel]
    if rel.startswith("truth.zarr/"):
        parts = rel.split("/")
        name = "/".join(parts[1:-1]) if parts[-1] in ("zarr.json",) else "/".join(parts[1:])
        if parts[-1] == "zarr.json":
            return f"Zarr metadata of {name or 'the root group'}"
        arr = "/".join(p for p in parts[1:] if p != "c" and not p.isdigit())
        return f"Zarr chunk of array {arr}"
    return ""


# --------------------------------------------------------------------------- generate
@dataclass
class _Options:
    consumer_crf: int | None
    full_well: float
    voxel_shape: tuple[int, ...]
    segment_frames: int
    preview_frames: int
    video: bool = True
    #: render the video's frames (False: the filmed truth without the video files)
    frames: bool = True

    def to_dict(self) -> dict:
        return {
            "consumer_crf": self.consumer_crf,
            "full_well_electrons": self.full_well,
            "voxel_shape": list(self.voxel_shape),
            "segment_frames": self.segment_frames,
            "preview_frames": self.preview_frames,
            "video": self.video,
        }


def generate(
    scene: Scene | str | Path,
    out_dir: str | Path,
    *,
    video: bool = True,
    frames: bool = True,
    progress: bool = True,
    overwrite: bool = False,
    consumer_crf: int | None = None,
    full_well: float | None = None,
    voxel_shape: tuple[int, ...] | None = None,
    segment_frames: int = 500,
    preview_frames: int = 240,
    callback: ProgressCallback | None = None,
    extra_json: dict[str, Any] | None = None,
) -> Path:
    """Generate the sample of ``scene`` as the folder ``out_dir / scene.name``; return its path.

    Parameters
    ----------
    scene : a Scene, a scene file path, or a shipped scene name.
    out_dir : parent folder (created if missing).
    video : render the video (default). False writes a *modes-only* sample: the truth
        without ``video.*``, ``preview.mp4``, ``transient/*`` and ``image/modes``, and without
        running the transient simulation (docs/dataset.md, "Modes-only samples").
    frames : with ``video``, render the frames (default). False writes the truth of the filmed
        sample, every array and file as rendering would write it (transient, image-space
        modes, the Cramér-Rao ruler from the rest render), without the video files and
        ``preview.mp4``: the manifest lists them under ``withheld``. What a merge of run
        shards regenerates to score estimates against (docs/suites.md, "Running a suite in
        shards"); minutes of rendering saved per sample.
    progress : show progress bars per stage.
    overwrite : replace an existing sample folder (otherwise an error).
    consumer_crf : if given (default: the scene's ``render.consumer_crf``), the video is 8-bit
        gray H.264 at this CRF (``video.mp4``, lossy: the "consumer camera" track) instead of
        the lossless 16-bit ``video.mkv``.
    full_well : sensor full-well capacity in electrons, the shot-noise scale (default: the
        scene's ``render.full_well_electrons``).
    voxel_shape : grid of the voxel material fields (default 8^3, drums 20x20).
    segment_frames : video frames per checkpointed segment (resume granularity).
    preview_frames : number of frames in ``preview.mp4``.
    callback : called as ``callback(stage, done, total)`` on every progress step.
    extra_json : more JSON files for the sample folder, ``{file name: data}`` (e.g.
        ``family.json`` of a family instance); listed in the manifest like every file.
    """
    scene = _as_scene(scene)
    for file_name in extra_json or {}:
        if Path(file_name).name != file_name or file_name in _DESCRIPTIONS and (
                file_name != "family.json") or not file_name.endswith(".json"):
            raise DatasetError(f"extra_json: {file_name!r} is not allowed (allowed: a plain "
                               "*.json file name that is not one of the sample's own files)")
    if consumer_crf is None:
        consumer_crf = scene.render.consumer_crf
    if full_well is None:
        full_well = scene.render.full_well_electrons
    if consumer_crf is not None and not 0 <= consumer_crf <= 51:
        raise DatasetError(f"consumer_crf must be in 0..51 (H.264 CRF), got {consumer_crf}")
    opts = _Options(
        consumer_crf, float(full_well),
        tuple(int(n) for n in (voxel_shape or default_voxel_shape(scene))),
        int(segment_frames), int(preview_frames), bool(video), bool(frames) or not video,
    )
    out_dir = Path(out_dir)
    final = out_dir / scene.name
    if final.exists() and not overwrite:
        raise DatasetError(f"{final} already exists; pass overwrite=True (--overwrite) to "
                           "replace it")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".{scene.name}.write-test-{os.getpid()}"
        with open_new(probe):  # O_EXCL|O_NOFOLLOW: never through a planted link
            pass
        probe.unlink()
    except OSError as error:
        raise DatasetError(f"cannot write to output folder {out_dir}: {error.strerror or error}"
                           ) from None
    partial = out_dir / f".{scene.name}.partial"
    if partial.is_symlink() or (partial.exists() and not partial.is_dir()):
        raise DatasetError(f"{partial}: a link or a file where generate keeps its unfinished "
                           "sample; remove it")
    scene_text = _scene_toml(scene)
    fingerprint = hashlib.sha256(
        json.dumps({"scene": scene_text, "options": opts.to_dict(), "vvtbench": __version__,
                    "format": FORMAT_VERSION, "extra": extra_json or {},
                    **({} if opts.frames else {"frames": False})},
                   sort_keys=True).encode()
    ).hexdigest()
    checkpoint = partial / "checkpoint.json"
    state = _load_checkpoint(checkpoint, fingerprint)
    if state is None:
        shutil.rmtree(partial, ignore_errors=True)
        (partial / "segments").mkdir(parents=True)
        state = {"fingerprint": fingerprint, "segments_done": 0}
        _write_json_sorted(checkpoint, state)
    bar = StageProgress(progress, callback, scene.name)
    try:
        with single_threaded():  # the same sums on 2 cores and on 64 (docs/dataset.md)
            _generate_into(scene, scene_text, partial, opts, state, checkpoint, bar)
    finally:
        bar.close()
    shutil.rmtree(partial / "segments", ignore_errors=True)
    checkpoint.unlink()
    for file_name, data in sorted((extra_json or {}).items()):
        if (partial / file_name).exists():
            raise DatasetError(f"extra_json: {file_name!r} is not allowed (allowed: a file "
                               "name that is not one of the sample's own files)")
        _write_json_sorted(partial / file_name, data)
    _write_manifest(partial, scene, withheld=[] if opts.frames else _withheld(partial))
    if final.exists():
        trash = out_dir / f".{scene.name}.old"
        shutil.rmtree(trash, ignore_errors=True)
        final.rename(trash)
        partial.rename(final)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        partial.rename(final)
    return final




def _load_checkpoint(checkpoint: Path, fingerprint: str) -> dict | None:
    if not checkpoint.is_file():
        return None
    try:
        state = json.loads(checkpoint.read_text())
    except (OSError, ValueError):
        return None
    return state if state and state.get("fingerprint") == fingerprint else None


def _scene_toml(scene: Scene) -> str:
    import tomli_w

    header = (f"# Resolved scene written by vvtbench {__version__} "
              f"(dataset format {FORMAT_VERSION}); seed = {scene.seed}\n")
    return header + tomli_w.dumps(scene.to_toml_dict())


@functools.lru_cache(maxsize=4)
def _texture(density: float, contrast: float, seed: int) -> np.ndarray:
    """The speckle texture of a scene, computed once per process (0.2-0.4 s each: 1024^2
    FFT filtering) and shared read-only by every sample that uses it."""
    from ..render.texture import speckle_texture

    tex = np.asarray(speckle_texture(1024, grain=4.0, density=density, contrast=contrast,
                                     seed=seed), dtype=np.float32)
    tex.setflags(write=False)
    return tex


def scene_renderer(scene: Scene, vertices: np.ndarray, triangles: np.ndarray, camera=None):
    """The :class:`Renderer` a sample of ``scene`` is filmed with (texture, settings; the
    scene's camera, view 0, unless ``camera`` is given)."""
    from ..render import Camera
    from ..render.pyrender_backend import Renderer

    rs = scene.render
    texture = _texture(rs.texture_density, rs.texture_contrast, rs.texture_seed)
    try:
        camera = Camera.from_spec(scene.camera) if camera is None else camera
        return Renderer(vertices, triangles, camera, texture=texture,
                        supersample=rs.supersample, lighting=rs.lighting)
    except ValueError as error:
        raise DatasetError(f"scene {scene.name}: cannot render with key 'camera': {error}"
                           ) from None


# --------------------------------------------------------------------------- the stages
@dataclass
class _Context:
    """What the stages of one sample share."""

    scene: Scene
    work: Path
    opts: _Options
    result: Any  # SimulationResult
    nodes: np.ndarray  # surface node ids
    rest: np.ndarray  # their rest points
    tris: np.ndarray  # triangles indexing the surface nodes
    camera: Any
    n_frames: int
    cameras: list  # every view's camera; cameras[0] is ``camera``
    offset_steps: int = 0  # simulation steps between the start of view i and view i + 1

    @property
    def frame_average(self) -> int:
        return self.scene.render.frame_average

    @property
    def bit_depth(self) -> int:
        return 8 if self.opts.consumer_crf is not None else self.scene.render.bit_depth


def _generate_into(scene: Scene, scene_text: str, work: Path, opts: _Options, state: dict,
                   checkpoint: Path, bar: StageProgress) -> None:
    (work / "scene.toml").write_text(scene_text)
    ctx = _simulate(scene, work, opts, bar)
    views = []
    for v, camera in enumerate(ctx.cameras):
        with scene_renderer(scene, ctx.rest, ctx.tris, camera) as renderer:
            if opts.video and opts.frames:
                _render_video(ctx, renderer, state, checkpoint, bar, v)
            views.append(_rest_views(ctx, renderer, v))
            if opts.video and opts.frames and v == 0:
                _preview(ctx, renderer, work / "preview.mp4", 0.0, bar)
    bar.stage("ground truth", 4 + 2 * len(views))
    truth = _write_truth(ctx, views, bar)
    _write_info(ctx, truth)
    bar.advance()


def view_folder(view: int) -> str:
    """The folder of view ``view``'s files inside a sample ("" for view 0, whose files are
    where a single-view sample has them; ``views/<i>/`` for the others)."""
    return "" if view == 0 else f"views/{view}/"


def _offset_steps(scene: Scene) -> int:
    """Simulation steps (at fps * frame_average) between the start of consecutive views."""
    offset = scene.camera.time_offset_s
    if offset == 0:
        return 0
    step = 1.0 / (scene.simulation.fps * scene.render.frame_average)
    n = offset / step
    if abs(n - round(n)) > 1e-6 * max(1.0, n):
        raise DatasetError(f"scene {scene.name}: key 'camera.rig.time_offset_s' = {offset:g} s "
                           "is not a whole number of simulation steps; allowed: multiples of "
                           f"1 / (simulation.fps * render.frame_average) = {step:.9g} s")
    return int(round(n))


def _simulate(scene: Scene, work: Path, opts: _Options, bar: StageProgress) -> _Context:
    """Simulate (modes; the transient at fps * frame_average only when filming)."""
    from ..render import Camera
    from ..simulation.simulate import simulate

    A = scene.render.frame_average
    n_frames = n_video_frames(scene) if opts.video else 0
    if opts.video and n_frames < 1:
        raise DatasetError(f"scene {scene.name}: simulation.duration * fps gives no frame")
    bar.stage("simulate", 1)
    offset = _offset_steps(scene) if opts.video else 0
    fine = _fine_scene(scene)
    if offset:  # the later views film (n_views - 1) * offset steps beyond view 0
        extra = (scene.camera.n_views - 1) * offset / (scene.simulation.fps * A)
        fine = fine.model_copy(update={"simulation": fine.simulation.model_copy(
            update={"duration": fine.simulation.duration + extra})})
    result = simulate(fine, transient=opts.video)
    if opts.video:
        if not result.has_transient:
            raise DatasetError(f"scene {scene.name}: excitation kind 'none' gives no motion "
                               "to film (generate a modes-only sample with video=False, "
                               "--no-video)")
        n_frames = min(n_frames, len(result.times) // A)  # rounding of duration * fps * A
    bar.advance()
    nodes, rest, tris = surface_geometry(result.mesh)
    try:
        cameras = Camera.views_from_spec(scene.camera)
    except ValueError as error:
        raise DatasetError(f"scene {scene.name}: cannot render with key 'camera': {error}"
                           ) from None
    return _Context(scene, work, opts, result, nodes, rest, tris, cameras[0], n_frames,
                    cameras, offset)


def _render_video(ctx: _Context, renderer, state: dict, checkpoint: Path,
                  bar: StageProgress, view: int = 0) -> None:
    """Render, quantize and encode the video of one view in checkpointed segments, then join
    them. View ``i`` films ``i * offset_steps`` simulation steps after view 0; its sensor noise
    comes from its own generator (:func:`view_noise_rng`)."""
    scene, opts, result, A = ctx.scene, ctx.opts, ctx.result, ctx.frame_average
    rs = scene.render
    camera = ctx.cameras[view]
    H, W = camera.height, camera.width
    seg_len = max(1, opts.segment_frames)
    n_seg = math.ceil(ctx.n_frames / seg_len)
    seg_dir = ctx.work / "segments" / (f"view{view}" if view else "")
    seg_dir.mkdir(parents=True, exist_ok=True)
    key = "segments_done" if view == 0 else f"segments_done_view{view}"
    shift = view * ctx.offset_steps
    done = int(state.get(key, 0))
    bar.stage("render video" + (f" (view {view})" if view else ""), ctx.n_frames,
              min(done * seg_len, ctx.n_frames))
    seg_pix = "gray" if opts.consumer_crf is not None else "gray16le"
    noisy = rs.shot_noise or rs.read_noise_dn > 0
    for s in range(done, n_seg):
        a, b = s * seg_len, min((s + 1) * seg_len, ctx.n_frames)
        tmp = seg_dir / f"seg_{s:05d}.tmp.mkv"
        with VideoWriter(tmp, H, W, capture_fps=scene.simulation.fps, pix_fmt=seg_pix) as writer:
            for k0 in range(a, b, 64):
                k1 = min(k0 + 64, b)
                u = _as_3d(result.displacement_frames(k0 * A + shift, k1 * A + shift))
                for k in range(k0, k1):
                    subs = np.stack([renderer.render(rs.motion_scale * u[(k - k0) * A + j])
                                     for j in range(A)])
                    rng = view_noise_rng(scene.seed, k, view) if noisy else None
                    writer.write(sensor_dn(subs, ctx.bit_depth, rs.read_noise_dn,
                                           rs.shot_noise, opts.full_well, rng))
                    bar.advance()
        os.replace(tmp, seg_dir / f"seg_{s:05d}.mkv")
        state[key] = s + 1
        _write_json_sorted(checkpoint, state)
    segments = [seg_dir / f"seg_{s:05d}.mkv" for s in range(n_seg)]
    bar.stage("join video", 1)
    name = "video.mkv" if opts.consumer_crf is None else "video.mp4"
    folder = ctx.work / view_folder(view)
    folder.mkdir(parents=True, exist_ok=True)
    concat_videos(segments, folder / f"{name}.tmp{Path(name).suffix}",
                  capture_fps=scene.simulation.fps, crf=opts.consumer_crf)
    os.replace(folder / f"{name}.tmp{Path(name).suffix}", folder / name)
    bar.advance()


def view_noise_rng(seed: int, frame: int, view: int) -> np.random.Generator:
    """The sensor-noise generator of video frame ``frame`` of view ``view``: view 0's is
    :func:`vvtbench.render.sensor.noise_rng` (a single-view sample's), view ``i > 0`` draws from
    ``numpy.random.default_rng([seed & 0xFFFFFFFF, 0x5EED0001, frame, i])``, so no two views
    share noise."""
    if view == 0:
        return noise_rng(seed, frame)
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EED0001, int(frame), int(view)])


def _rest_views(ctx: _Context, renderer, view: int = 0) -> dict:
    """Rest render, depth buffer and visibility (one frame) of one view, and its viewing
    PNGs."""
    import imageio.v3 as iio

    rest_img = renderer.render()
    depth = renderer.depth()
    visible = renderer.visible_vertices()
    folder = ctx.work / view_folder(view)
    folder.mkdir(parents=True, exist_ok=True)
    iio.imwrite(folder / "rest.png", _to_png8(rest_img))
    iio.imwrite(folder / "depth.png", _depth_png(depth))
    return {"rest": rest_img, "depth": depth, "visible": visible, "camera": ctx.cameras[view]}


def _write_truth(ctx: _Context, views: list[dict], bar: StageProgress) -> dict:
    """Write ``truth.zarr`` (view 0's arrays where a single-view sample has them, view ``i``'s
    under ``views/<i>/``); returns the numbers ``truth.json`` reports."""
    import zarr

    from ..fem.elements import element_volumes
    from ..fem.voxels import VoxelMap, overlap_matrix, voxel_average

    result, mesh, nodes = ctx.result, ctx.result.mesh, ctx.nodes
    root = zarr.open_group(str(ctx.work / "truth.zarr"), mode="w", zarr_format=3)
    root.attrs.update({"vvtbench": __version__, "format": FORMAT_VERSION,
                       "scene": ctx.scene.name, "video": ctx.opts.video})

    def put(name: str, data: np.ndarray, chunks=None) -> None:
        data = np.asarray(data)
        if chunks is None:  # small arrays: one chunk (one file); large: ~16 MB chunks
            chunks = data.shape if data.nbytes <= 16 << 20 else "auto"
        arr = root.create_array(name, shape=data.shape, dtype=data.dtype,
                                chunks=chunks, overwrite=True)
        arr[...] = data

    # mesh
    put("mesh/points", mesh.points)
    put("mesh/cells", mesh.cells)
    root["mesh"].attrs.update({"element": mesh.element, "dofs_per_node": mesh.dofs_per_node})
    put("mesh/surface", mesh.surface)
    put("mesh/surface_nodes", nodes)
    vols = element_volumes(mesh.element_type, mesh.cell_coords)
    put("mesh/element_volumes", vols)
    d = mesh.dofs_per_node
    put("mesh/fixed_nodes", np.unique(np.asarray(result.model.fixed_dofs, np.int64) // d))
    for set_name, ids in sorted(mesh.node_sets.items()):
        put(f"mesh/node_sets/{set_name}", np.asarray(ids, dtype=np.int64))
    # material, per element and on the voxel grid (volume-weighted overlap)
    f = result.fields
    put("material/stiffness", f.stiffness)
    put("material/density", f.density)
    put("material/nu", f.nu)
    vmap = VoxelMap.from_mesh(mesh, ctx.opts.voxel_shape)
    grid_shape = tuple(ctx.opts.voxel_shape)
    overlap = overlap_matrix(mesh, vmap.grid)
    for key, values in (("stiffness", f.stiffness), ("density", f.density), ("nu", f.nu)):
        put(f"voxels/{key}", voxel_average(overlap, values).reshape(grid_shape))
    voxel_volume = np.asarray(overlap.sum(axis=1)).ravel()
    put("voxels/volume", voxel_volume.reshape(grid_shape))
    put("voxels/element_voxel", vmap.element_voxel)
    bar.advance()
    # modes
    modes = result.modes
    phi3 = mode_vectors_3d(result, nodes)  # (m, S, 3)
    put("modes/eigenvalues", np.asarray(modes.eigenvalues, dtype=np.float64))
    put("modes/frequencies_hz", result.frequencies_hz)
    put("modes/damping_ratios", np.asarray(result.damping_ratios, dtype=np.float64))
    put("modes/vectors", modes.vectors)
    put("modes/free_dofs", result.model.free_dofs)
    put("modes/surface", phi3)
    per_view = [_write_view_truth(ctx, root, put, v, view, phi3) for v, view in
                enumerate(views)]
    for _ in per_view:
        bar.advance()
    peaks = (_write_transient(ctx, root, put, [(p["J_vis"], p["vis_idx"]) for p in per_view])
             if ctx.opts.video else [None] * len(views))
    rulers = [_write_crb(ctx, root, put, view["rest"], view_folder(v)) if ctx.opts.video
              else None for v, view in enumerate(views)]
    bar.advance()
    return {"vmap": vmap, "grid_shape": grid_shape, "n_visible": per_view[0]["n_visible"],
            "n_occupied": int((voxel_volume > 0).sum()), "peak_px": peaks[0], "crb": rulers[0],
            "views": [{"n_visible": p["n_visible"], "peak_px": peak, "crb": ruler}
                      for p, peak, ruler in zip(per_view, peaks, rulers, strict=True)]}


def _write_view_truth(ctx: _Context, root, put, v: int, view: dict, phi3: np.ndarray) -> dict:
    """The arrays of one view (``observation/*``, ``image/*``), under ``views/<v>/`` for
    ``v > 0``."""
    from ..render.raster import interpolate, rasterize

    camera, rest, tris, pre = view["camera"], ctx.rest, ctx.tris, view_folder(v)
    H, W = camera.height, camera.width
    nodes = ctx.nodes
    visible = view["visible"]
    vis_idx = np.flatnonzero(visible)
    J = camera.jacobian(rest)  # (S, 2, 3)
    img_modes = np.einsum("sij,msj->msi", J, phi3)  # (m, S, 2)
    put(pre + "observation/rest_uv", camera.project(rest))
    put(pre + "observation/rest_depth", camera.depth(rest))
    put(pre + "observation/visible", visible)
    put(pre + "observation/visible_index", vis_idx)
    put(pre + "observation/visible_nodes", nodes[vis_idx])
    put(pre + "observation/jacobian", J[vis_idx])
    put(pre + "observation/image_modes", img_modes[:, vis_idx])
    put(pre + "observation/image_modes_surface", img_modes)
    # image-space fields
    raster = rasterize(camera, rest, tris)
    put(pre + "image/rest", view["rest"])
    put(pre + "image/depth", view["depth"])
    put(pre + "image/triangle", raster.triangle)
    put(pre + "image/barycentric", raster.barycentric)
    if ctx.opts.video:
        m = len(phi3)
        dense = root.create_array(pre + "image/modes", shape=(m, H, W, 2), dtype=np.float32,
                                  chunks=(1, H, W, 2), fill_value=np.nan, overwrite=True)
        for i in range(m):
            dense[i] = interpolate(raster, tris, img_modes[i]).astype(np.float32)
    return {"J_vis": J[vis_idx], "vis_idx": vis_idx, "n_visible": int(len(vis_idx))}


def _write_crb(ctx: _Context, root, put, rest_img: np.ndarray, pre: str = "") -> dict:
    """The Cramér-Rao ruler (:mod:`vvtbench.render.crb`) of one view: ``crb/*`` block bounds
    of the rest render and ``modes/crb_*`` per mode (under ``pre``: ``views/<i>/`` for view
    ``i > 0``); returns the summary ``truth.json`` reports."""
    from ..render import crb

    rs = ctx.scene.render
    intensity = np.asarray(rest_img, dtype=np.float64)
    var = crb.noise_variance_dn2(intensity, ctx.bit_depth, rs.read_noise_dn, rs.shot_noise,
                                 ctx.opts.full_well, ctx.frame_average)
    fisher_px = crb.pixel_fisher(intensity * float(2**ctx.bit_depth - 1), var)
    blocks = crb.block_crb(fisher_px, crb.BLOCK_PX)
    put(pre + "crb/fisher", blocks["fisher"])
    put(pre + "crb/std_px", blocks["std_px"])
    put(pre + "crb/std_min_px", blocks["std_min_px"])
    dense = root[pre + "image/modes"]
    info, gain = crb.mode_information(fisher_px, (dense[m] for m in range(dense.shape[0])),
                                      rs.motion_scale)
    energy = crb.modal_energy(root["transient/displacements"], root["modes/surface"]) * gain**2
    snr = crb.mode_snr(info, energy)
    threshold = crb.detection_snr_threshold(ctx.n_frames)
    put(pre + "modes/crb_snr", snr)
    put(pre + "modes/crb_information", info)
    put(pre + "modes/crb_energy_px2", energy)
    summary = {"block_px": crb.BLOCK_PX, "detection_snr": threshold,
               "false_alarm": crb.EXTRACTOR_FALSE_ALARM, "n_bins": max(1, ctx.n_frames // 2),
               "n_detectable": int(np.count_nonzero(snr >= threshold)),
               "derivative_taps": crb.DERIVATIVE_TAPS.tolist(),
               "noise_model": "(I D^2/F [shot] + r^2)/A + 1/12 DN^2"}
    root[pre + "crb"].attrs.update(summary)
    return {**summary, "snr": snr}


def _write_transient(ctx: _Context, root, put, seen: list[tuple[np.ndarray, np.ndarray]]
                     ) -> list[float]:
    """Surface-node displacements at the video frame times (sub-frames averaged); returns the
    peak single-axis image motion (px, unscaled) of each view (``seen``: its Jacobians at its
    visible nodes and their indices), over these frames."""
    result, A, n_frames = ctx.result, ctx.frame_average, ctx.n_frames
    S = len(ctx.nodes)
    tchunk = max(1, min(n_frames, (8 << 20) // (S * 12)))
    disp = root.create_array("transient/displacements", shape=(n_frames, S, 3),
                             dtype=np.float32, chunks=(tchunk, S, 3), overwrite=True)
    times = result.times[: n_frames * A].reshape(n_frames, A).mean(axis=1)
    put("transient/times", times)
    peaks = [0.0] * len(seen)
    for k0 in range(0, n_frames, tchunk):
        k1 = min(k0 + tchunk, n_frames)
        u = _as_3d(result.displacement_frames(k0 * A, k1 * A))
        u = u.reshape(k1 - k0, A, S, 3).mean(axis=1, dtype=np.float64)
        disp[k0:k1] = u.astype(np.float32)
        for v, (J_vis, vis_idx) in enumerate(seen):
            px = np.einsum("vij,tvj->tvi", J_vis, u[:, vis_idx])
            peaks[v] = max(peaks[v], float(np.abs(px).max(initial=0.0)))
    return peaks


def _write_info(ctx: _Context, truth: dict) -> None:
    """Write ``truth.json`` and ``camera.json``."""
    scene, opts, result, camera = ctx.scene, ctx.opts, ctx.result, ctx.camera
    rs, mesh = scene.render, result.mesh
    A = ctx.frame_average
    H, W = camera.height, camera.width
    consumer = opts.consumer_crf is not None
    filmed = opts.video
    info = {
        "format": FORMAT_VERSION,
        "vvtbench": __version__,
        "scene": scene.name,
        "seed": scene.seed,
        "video": {
            "file": None if not filmed else ("video.mp4" if consumer else "video.mkv"),
            "codec": None if not filmed else ("h264" if consumer else LOSSLESS_CODEC),
            "lossless": not consumer,
            "crf": opts.consumer_crf,
            "pixel_format": "gray" if consumer else "gray16le",
            "frames": ctx.n_frames,
            "fps": scene.simulation.fps,
            "playback_fps": PLAYBACK_FPS,
            "height": H,
            "width": W,
            "bit_depth": ctx.bit_depth,
            "dn_max": 2**ctx.bit_depth - 1,
            "frame_average": A,
            "subframe_fps": scene.simulation.fps * A,
            "read_noise_dn": rs.read_noise_dn,
            "shot_noise": rs.shot_noise,
            "full_well_electrons": opts.full_well,
            "noise_seed": scene.seed,
            "noise_rng": "numpy default_rng([seed & 0xFFFFFFFF, 0x5EED0001, frame])",
            "motion_scale": rs.motion_scale,
            "supersample": rs.supersample,
            "lighting": rs.lighting,
        },
        "mesh": {"element": mesh.element, "n_nodes": mesh.n_nodes,
                 "n_elements": mesh.n_elements, "dofs_per_node": mesh.dofs_per_node,
                 "n_surface_nodes": len(ctx.nodes), "n_surface_triangles": len(ctx.tris),
                 "n_visible": truth["n_visible"],
                 "node_sets": sorted(mesh.node_sets)},
        "modes": {"n": len(result.modes), "frequencies_hz": result.frequencies_hz.tolist(),
                  "damping_ratios": [float(z) for z in result.damping_ratios],
                  "rayleigh_alpha": result.alpha, "rayleigh_beta": result.beta,
                  **({} if truth.get("crb") is None else
                     {"crb_snr": [float(x) for x in truth["crb"].pop("snr")]})},
        **({} if truth.get("crb") is None else {"crb": truth["crb"]}),
        "voxels": {**truth["vmap"].grid.to_dict(), "shape": list(truth["grid_shape"]),
                   "n_active": int(truth["vmap"].n_params), "n_occupied": truth["n_occupied"]},
        "peak_image_motion_px": (None if truth["peak_px"] is None
                                 else truth["peak_px"] * rs.motion_scale),
        "truncation_error": result.truncation_error,
        "generator": opts.to_dict(),
    }
    if len(ctx.cameras) > 1:
        info["views"] = _views_info(ctx, truth, info["video"]["file"],
                                    info["modes"].get("crb_snr"))
    _write_json_sorted(ctx.work / "truth.json", info)
    for v, cam_v in enumerate(ctx.cameras):
        cam = cam_v.to_dict()
        cam["P"] = cam_v.P.tolist()
        cam["fov_y_deg"] = float(np.degrees(2 * np.arctan((cam_v.height / 2) / cam_v.fy)))
        _write_json_sorted(ctx.work / view_folder(v) / "camera.json", cam)


def _views_info(ctx: _Context, truth: dict, video_file: str | None,
                first_snr: list | None) -> list[dict]:
    """``truth.json`` ``views``: what differs between the views of a multi-view sample."""
    scene = ctx.scene
    step = 1.0 / (scene.simulation.fps * ctx.frame_average)
    out = []
    for v, (camera, seen) in enumerate(zip(ctx.cameras, truth["views"], strict=True)):
        folder = view_folder(v)
        ruler = seen["crb"]
        out.append({
            "index": v,
            "folder": folder.rstrip("/"),
            "camera": folder + "camera.json",
            "video_file": None if video_file is None else folder + video_file,
            "height": camera.height,
            "width": camera.width,
            "time_offset_s": v * ctx.offset_steps * step,
            "n_visible": seen["n_visible"],
            "peak_image_motion_px": (None if seen["peak_px"] is None
                                     else seen["peak_px"] * scene.render.motion_scale),
            **({} if ruler is None else {
                "crb_snr": (first_snr if v == 0 else [float(x) for x in ruler["snr"]]),
                "crb_detectable": int(ruler["n_detectable"])}),
        })
    return out


def _preview(ctx: _Context, renderer, path: Path, peak_px: float, bar: StageProgress) -> None:
    """A short H.264 clip with the motion magnified to ``PREVIEW_PEAK_PX`` (8 px) peak.

    The rest render is warped by the magnified *image-space* displacement ``J u`` (the
    projection Jacobian at the rest pose times the vertex motion, interpolated over the
    object's visible triangles and extended into the background by the nearest object
    pixel's, so the silhouette moves too): no re-rendering of magnified 3-D motion, whose
    large vertex excursions flip faces and light the cube's front edge.  ``peak_px`` (the
    video's unmagnified peak) is not needed: the gain is set from the frames shown.
    """
    from scipy.ndimage import distance_transform_edt, map_coordinates

    from ..render.raster import interpolate, rasterize

    result, A = ctx.result, ctx.frame_average
    fps = ctx.scene.simulation.fps
    f1 = float(result.frequencies_hz[0]) if len(result.frequencies_hz) else 1.0
    stride = max(1, int(fps / (10.0 * max(f1, 1e-6))))  # ~10 frames per lowest-mode period
    ks = np.arange(0, ctx.n_frames, stride)[: max(1, ctx.opts.preview_frames)]
    camera = ctx.camera
    J = camera.jacobian(ctx.rest)  # (S, 2, 3)
    raster = rasterize(camera, ctx.rest, ctx.tris)
    inside = raster.mask
    # nearest object pixel of every background pixel
    _, (iy, ix) = distance_transform_edt(~inside, return_indices=True)
    rest = np.asarray(renderer.render(), dtype=np.float64)
    H, W = rest.shape
    fields = []
    for k in ks:
        u = _as_3d(result.displacement_frames(k * A, k * A + 1))[0]
        d = interpolate(raster, ctx.tris, np.einsum("sij,sj->si", J, u), fill=0.0)
        fields.append(d[iy, ix].astype(np.float32))
    peak = max((float(np.abs(d[inside]).max(initial=0.0)) for d in fields), default=0.0)
    gain = PREVIEW_PEAK_PX / peak if peak > 0 else 1.0
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    tmp = path.with_name(path.stem + ".tmp.mp4")
    bar.stage("preview", len(ks))
    with VideoWriter(tmp, H, W, pix_fmt="gray", codec="h264", crf=23) as writer:
        for d in fields:
            # backward warp: the content at x came from x - g d(x) (smooth d, small error)
            coords = (yy - gain * d[..., 1], xx - gain * d[..., 0])
            frame = map_coordinates(rest, coords, order=1, mode="nearest")
            writer.write(_to_png8(frame.astype(np.float32)))
            bar.advance()
    os.replace(tmp, path)


PREVIEW_PEAK_PX = 8.0  # magnified peak image motion of preview.mp4 (px)


def _withheld(work: Path) -> list[str]:
    """The files ``truth.json`` names that a sample generated without frames does not hold:
    every view's video and ``preview.mp4``."""
    info = json.loads((work / "truth.json").read_text())
    names = [info["video"]["file"], *(v.get("video_file") for v in info.get("views") or [])]
    return sorted({str(n) for n in names if n} | {"preview.mp4"})


def _write_manifest(work: Path, scene: Scene, withheld: list[str] | None = None) -> None:
    files = {}
    for p in sorted(work.rglob("*")):
        if p.is_file():
            rel = p.relative_to(work).as_posix()
            if rel == "manifest.json":
                continue
            files[rel] = {"sha256": sha256_file(p), "bytes": p.stat().st_size,
                          "description": _describe(rel)}
    _write_json_sorted(work / "manifest.json", {
        "format": "vvtbench-sample",
        "format_version": FORMAT_VERSION,
        "vvtbench": __version__,
        "scene": scene.name,
        "seed": scene.seed,
        "files": files,
        **({"withheld": list(withheld)} if withheld else {}),
    })
