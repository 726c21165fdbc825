"""Dataset generator and loader: a scene becomes one sample folder (video + ground truth).

``generate(scene, out_dir)`` simulates the scene, renders every frame through the scene's
camera, streams the frames to a lossless 16-bit FFV1 video chunk by chunk, and writes the ground
truth a solver or a metric could need. ``open_sample(path)`` reads it back. The folder layout,
every array's shape, dtype and unit, and the conventions are in ``docs/dataset.md``.

Properties
----------
* Memory: frames are rendered and encoded in segments of ``segment_frames`` video frames; the
  simulation keeps only modal coordinates, so peak memory does not grow with video length.
* Atomic: everything is written into ``out_dir/.NAME.partial/`` and renamed to ``out_dir/NAME``
  at the end; an existing sample is replaced only with ``overwrite=True``.
* Resumable: each finished video segment is recorded in ``.NAME.partial/checkpoint.json``; a
  rerun with the same scene and options continues after the last finished segment.
* Reproducible: the same scene (and seed) gives byte-identical files (ffmpeg bit-exact flags,
  no timestamps, per-frame seeded noise).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .scene import SCENES_DIR, Scene, SceneError, find_scene, load_scene, parse_scene

__all__ = [
    "DatasetError",
    "FORMAT_VERSION",
    "Sample",
    "generate",
    "main_generate",
    "open_sample",
    "resolve_scenes",
]

FORMAT_VERSION = 1
#: Nominal playback rate stored in the video containers. Matroska time stamps have 1 ms
#: resolution, so capture rates above 1000 FPS cannot be stored; the capture rate is in
#: ``truth.json`` (``video.fps``) and in the stream tag ``CAPTURE_FPS``.
PLAYBACK_FPS = 30
#: Default full-well capacity (electrons) of the simulated sensor, used by shot noise.
FULL_WELL_ELECTRONS = 10000.0
_NOISE_STREAM = 0x5EED_0001
_BITEXACT = ["-fflags", "+bitexact", "-flags:v", "+bitexact", "-map_metadata", "-1"]
_FFV1 = ["-level", "3", "-g", "1", "-slices", "4", "-slicecrc", "1", "-threads", "2"]


class DatasetError(RuntimeError):
    """Generation or loading failed for a reason the user can fix (message says how)."""


ProgressCallback = Callable[[str, int, int], None]


# --------------------------------------------------------------------------- small helpers
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


def _ffmpeg() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def default_voxel_shape(scene: Scene) -> tuple[int, ...]:
    """The paper's inference grids: 20 x 20 for drums, 8 x 8 x 8 for solids."""
    return (20, 20) if scene.geometry.kind == "drum" else (8, 8, 8)


def _as_scene(scene: Scene | str | Path) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene)


def with_overrides(
    scene: Scene,
    *,
    frames: int | None = None,
    duration: float | None = None,
    resolution: tuple[int, int] | None = None,
) -> Scene:
    """The scene with a different length (frames or seconds) or resolution (height, width)."""
    if frames is not None and duration is not None:
        raise SceneError("give either frames or duration, not both")
    data = scene.to_toml_dict()
    if frames is not None:
        if frames < 1:
            raise SceneError(f"frames must be >= 1, got {frames}")
        data["simulation"]["duration"] = frames / scene.simulation.fps
    if duration is not None:
        data["simulation"]["duration"] = float(duration)
    if resolution is not None:
        data["camera"]["resolution"] = [int(resolution[0]), int(resolution[1])]
    return parse_scene(data, scene.source or scene.name)


# --------------------------------------------------------------------------- progress
class _Progress:
    """Per-stage progress bars (rich) plus an optional callback(stage, done, total)."""

    def __init__(self, enabled: bool, callback: ProgressCallback | None, label: str) -> None:
        self.callback = callback
        self.bar = None
        self.label = label
        if enabled:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self.bar = Progress(
                TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), TimeRemainingColumn(), transient=False,
            )
            self.bar.start()
        self._task = None
        self._stage = ""
        self._total = 0
        self._done = 0

    def stage(self, name: str, total: int, done: int = 0) -> None:
        self._stage, self._total, self._done = name, max(int(total), 1), int(done)
        if self.bar is not None:
            self._task = self.bar.add_task(f"{self.label} {name}", total=self._total,
                                           completed=self._done)
        self._report()

    def advance(self, n: int = 1) -> None:
        self._done += n
        if self.bar is not None and self._task is not None:
            self.bar.update(self._task, completed=self._done)
        self._report()

    def _report(self) -> None:
        if self.callback is not None:
            self.callback(self._stage, self._done, self._total)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


# --------------------------------------------------------------------------- camera model
def _noise_rng(seed: int, frame: int) -> np.random.Generator:
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _NOISE_STREAM, int(frame)])


def sensor_dn(
    subframes: np.ndarray, bit_depth: int, read_noise_dn: float, shot_noise: bool,
    full_well: float, rng: np.random.Generator | None,
) -> np.ndarray:
    """Average sub-frame intensities in [0, 1] (each with its own noise) into one frame of DN.

    Per sub-frame: electrons = I * full_well, Poisson when ``shot_noise``; DN = electrons *
    (2^bits - 1) / full_well + N(0, read_noise_dn^2). The sub-frames are averaged, then rounded
    and clipped to [0, 2^bits - 1].
    """
    dn_max = float(2**bit_depth - 1)
    x = np.asarray(subframes, dtype=np.float64)
    if shot_noise:
        x = rng.poisson(np.clip(x, 0.0, None) * full_well) / full_well
    x = x * dn_max
    if read_noise_dn > 0:
        x = x + rng.normal(0.0, read_noise_dn, size=x.shape)
    frame = x.mean(axis=0)
    return np.clip(np.rint(frame), 0, dn_max).astype(np.uint16)


# --------------------------------------------------------------------------- video I/O
class _VideoWriter:
    """Lossless FFV1 Matroska writer of frames of DN.

    Parameters
    ----------
    path : output ``.mkv`` file.
    height, width : frame size (px).
    fps : capture rate, stored in the stream tag ``CAPTURE_FPS``.
    pix_fmt : ``"gray16le"`` (default: DN of any bit depth stored LSB-aligned in 16 bits, the
        lossless track) or ``"gray"`` (8-bit; the segments re-encoded into the consumer track).
    """

    def __init__(self, path: Path, height: int, width: int, fps: float,
                 pix_fmt: str = "gray16le") -> None:
        import imageio_ffmpeg

        if pix_fmt not in ("gray16le", "gray"):
            raise ValueError(f"pix_fmt must be 'gray16le' or 'gray', got {pix_fmt!r}")
        params = _FFV1 + _BITEXACT + ["-metadata:s:v:0", f"CAPTURE_FPS={fps:g}"]
        self._dtype = "<u2" if pix_fmt == "gray16le" else np.uint8
        self._gen = imageio_ffmpeg.write_frames(
            str(path), (width, height), pix_fmt_in=pix_fmt, pix_fmt_out=pix_fmt,
            codec="ffv1", quality=None, fps=PLAYBACK_FPS, macro_block_size=1,
            output_params=params, ffmpeg_log_level="error",
        )
        self._gen.send(None)

    def write(self, frame: np.ndarray) -> None:
        self._gen.send(np.ascontiguousarray(frame, dtype=self._dtype))

    def close(self) -> None:
        self._gen.close()


def _concat(segments: list[Path], out: Path, work: Path, encode: list[str] | None,
            fps: float) -> None:
    """Join video segments into ``out``: stream copy, or re-encode with ``encode`` args."""
    listing = work / "segments.txt"
    listing.write_text("".join(f"file '{p.resolve()}'\n" for p in segments))
    codec = ["-c", "copy"] if encode is None else encode
    cmd = [
        _ffmpeg(), "-y", "-loglevel", "error", "-f", "concat", "-safe", "0", "-i", str(listing),
        *codec, *_BITEXACT, "-metadata:s:v:0", f"CAPTURE_FPS={fps:g}", str(out),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise DatasetError(f"ffmpeg failed joining the video segments: {proc.stderr.strip()}")
    listing.unlink()


def read_video(path: Path, height: int, width: int, *, bpp: int = 2, start: int = 0,
               stop: int | None = None, stored_pix_fmt: str | None = None
               ) -> Iterator[np.ndarray]:
    """Decode frames ``start:stop`` of a gray video as (H, W) uint16 (bpp 2) or uint8 arrays.

    With ``stored_pix_fmt`` (e.g. ``"gray16le"``), a video stream in another pixel format is a
    :class:`DatasetError` instead of being silently converted (8-bit gray read as 16-bit
    comes back multiplied by 257).
    """
    import imageio_ffmpeg

    pix = "gray16le" if bpp == 2 else "gray"
    inp = ["-ss", f"{start / PLAYBACK_FPS:.6f}"] if start > 0 else None
    out = ["-frames:v", str(stop - start)] if stop is not None else None
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt=pix, bpp=bpp, input_params=inp,
                                     output_params=out)
    meta = next(gen)
    found = str(meta.get("pix_fmt", "")).split("(")[0].strip()
    if stored_pix_fmt is not None and found != stored_pix_fmt:
        gen.close()
        raise DatasetError(f"{path}: video stream is {found or 'of unknown pixel format'}, "
                           f"but truth.json (video.pixel_format) says {stored_pix_fmt}; "
                           "regenerate the sample with this vvtbench")
    dtype = "<u2" if bpp == 2 else np.uint8
    try:
        for raw in gen:
            yield np.frombuffer(raw, dtype=dtype).reshape(height, width)
    finally:
        gen.close()


# --------------------------------------------------------------------------- truth helpers
def _surface_geometry(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(surface node ids, their rest points, triangles indexing the surface nodes)."""
    nodes = mesh.surface_nodes
    lut = np.full(mesh.n_nodes, -1, dtype=np.int64)
    lut[nodes] = np.arange(len(nodes))
    return nodes, mesh.points[nodes], lut[mesh.surface]


def _mode_vectors_3d(result, nodes: np.ndarray) -> np.ndarray:
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
    "video.mkv": "lossless video, FFV1 gray16le, DN stored LSB-aligned in "
                 "[0, 2^bit_depth - 1] (truth.json video.bit_depth)",
    "video.mp4": "consumer-camera video, 8-bit gray H.264 (lossy, CRF in truth.json)",
    "rest.png": "rest-pose frame, noise-free, 8-bit (for viewing)",
    "depth.png": "rest-pose depth, 16-bit, near = bright, 0 = background (for viewing)",
    "preview.mp4": "small H.264 preview with magnified motion (for viewing)",
}


def _describe(rel: str) -> str:
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

    def to_dict(self) -> dict:
        return {
            "consumer_crf": self.consumer_crf,
            "full_well_electrons": self.full_well,
            "voxel_shape": list(self.voxel_shape),
            "segment_frames": self.segment_frames,
            "preview_frames": self.preview_frames,
        }


def generate(
    scene: Scene | str | Path,
    out_dir: str | Path,
    *,
    progress: bool = True,
    overwrite: bool = False,
    consumer_crf: int | None = None,
    full_well: float | None = None,
    voxel_shape: tuple[int, ...] | None = None,
    segment_frames: int = 500,
    preview_frames: int = 240,
    callback: ProgressCallback | None = None,
) -> Path:
    """Generate the sample of ``scene`` as the folder ``out_dir / scene.name``; return its path.

    Parameters
    ----------
    scene : a Scene, a scene file path, or a shipped scene name.
    out_dir : parent folder (created if missing).
    progress : show progress bars per stage.
    overwrite : replace an existing sample folder (otherwise an error).
    consumer_crf : if given (default: the scene's ``render.consumer_crf``), the video is 8-bit
        gray H.264 at this CRF (``video.mp4``, lossy: the "consumer camera" track) instead of
        the lossless 16-bit ``video.mkv``.
    full_well : sensor full-well capacity in electrons, the shot-noise scale (default: the
        scene's ``render.full_well_electrons``).
    voxel_shape : inference grid of the voxel material fields (default 8^3, drums 20x20).
    segment_frames : video frames per checkpointed segment (resume granularity).
    preview_frames : number of frames in ``preview.mp4``.
    callback : called as ``callback(stage, done, total)`` on every progress step.
    """
    scene = _as_scene(scene)
    if consumer_crf is None:
        consumer_crf = scene.render.consumer_crf
    if full_well is None:
        full_well = scene.render.full_well_electrons
    if consumer_crf is not None and not 0 <= consumer_crf <= 51:
        raise DatasetError(f"consumer_crf must be in 0..51 (H.264 CRF), got {consumer_crf}")
    opts = _Options(
        consumer_crf, float(full_well),
        tuple(int(n) for n in (voxel_shape or default_voxel_shape(scene))),
        int(segment_frames), int(preview_frames),
    )
    out_dir = Path(out_dir)
    final = out_dir / scene.name
    if final.exists() and not overwrite:
        raise DatasetError(f"{final} already exists; pass overwrite=True (--overwrite) to "
                           "replace it")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".{scene.name}.write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise DatasetError(f"cannot write to output folder {out_dir}: {error.strerror or error}"
                           ) from None
    partial = out_dir / f".{scene.name}.partial"
    scene_text = _scene_toml(scene)
    fingerprint = hashlib.sha256(
        json.dumps({"scene": scene_text, "options": opts.to_dict(), "vvtbench": __version__,
                    "format": FORMAT_VERSION}, sort_keys=True).encode()
    ).hexdigest()
    checkpoint = partial / "checkpoint.json"
    state = None
    if checkpoint.is_file():
        try:
            state = json.loads(checkpoint.read_text())
        except (OSError, ValueError):
            state = None
        if not state or state.get("fingerprint") != fingerprint:
            state = None
    if state is None:
        shutil.rmtree(partial, ignore_errors=True)
        (partial / "segments").mkdir(parents=True)
        state = {"fingerprint": fingerprint, "segments_done": 0}
        _write_json(checkpoint, state)
    bar = _Progress(progress, callback, scene.name)
    try:
        _generate_into(scene, scene_text, partial, opts, state, checkpoint, bar)
    finally:
        bar.close()
    shutil.rmtree(partial / "segments", ignore_errors=True)
    checkpoint.unlink()
    _write_manifest(partial, scene)
    if final.exists():
        trash = out_dir / f".{scene.name}.old"
        shutil.rmtree(trash, ignore_errors=True)
        final.rename(trash)
        partial.rename(final)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        partial.rename(final)
    return final


def _scene_toml(scene: Scene) -> str:
    import tomli_w

    header = (f"# Resolved scene written by vvtbench {__version__} "
              f"(dataset format {FORMAT_VERSION}); seed = {scene.seed}\n")
    return header + tomli_w.dumps(scene.to_toml_dict())


def scene_renderer(scene: Scene, vertices: np.ndarray, triangles: np.ndarray):
    """The :class:`Renderer` a sample of ``scene`` is filmed with (camera, texture, settings)."""
    from .render import Camera
    from .render.pyrender_backend import Renderer
    from .render.texture import speckle_texture

    rs = scene.render
    texture = speckle_texture(1024, grain=4.0, density=rs.texture_density,
                              contrast=rs.texture_contrast, seed=rs.texture_seed)
    try:
        return Renderer(vertices, triangles, Camera.from_spec(scene.camera), texture=texture,
                        supersample=rs.supersample, lighting=rs.lighting)
    except ValueError as error:
        raise DatasetError(f"scene {scene.name}: cannot render with key 'camera': {error}"
                           ) from None


def _generate_into(scene: Scene, scene_text: str, work: Path, opts: _Options, state: dict,
                   checkpoint: Path, bar: _Progress) -> None:
    from .fem.elements import element_volumes
    from .fem.voxels import VoxelMap
    from .render import Camera
    from .render.raster import interpolate, rasterize
    from .simulate import simulate

    (work / "scene.toml").write_text(scene_text)
    rs = scene.render
    A = rs.frame_average
    n_frames = n_video_frames(scene)
    if n_frames < 1:
        raise DatasetError(f"scene {scene.name}: simulation.duration * fps gives no frame")

    bar.stage("simulate", 1)
    result = simulate(_fine_scene(scene))
    if not result.has_transient:
        raise DatasetError(f"scene {scene.name}: excitation kind 'none' gives no motion to film")
    n_frames = min(n_frames, len(result.times) // A)  # rounding of duration * fps * A
    bar.advance()

    mesh = result.mesh
    nodes, rest, tris = _surface_geometry(mesh)
    camera = Camera.from_spec(scene.camera)
    H, W = camera.height, camera.width
    bit_depth = 8 if opts.consumer_crf is not None else rs.bit_depth
    renderer = scene_renderer(scene, rest, tris)
    with renderer:
        # ---------------------------------------------------------------- video segments
        seg_len = max(1, opts.segment_frames)
        n_seg = math.ceil(n_frames / seg_len)
        seg_dir = work / "segments"
        seg_dir.mkdir(exist_ok=True)
        done = int(state.get("segments_done", 0))
        bar.stage("render video", n_frames, min(done * seg_len, n_frames))
        scale = rs.motion_scale
        seg_pix = "gray" if opts.consumer_crf is not None else "gray16le"
        for s in range(done, n_seg):
            a, b = s * seg_len, min((s + 1) * seg_len, n_frames)
            tmp = seg_dir / f"seg_{s:05d}.tmp.mkv"
            writer = _VideoWriter(tmp, H, W, scene.simulation.fps, seg_pix)
            try:
                for k0 in range(a, b, 64):
                    k1 = min(k0 + 64, b)
                    u = _as_3d(result.displacement_frames(k0 * A, k1 * A))
                    for k in range(k0, k1):
                        subs = np.stack([renderer.render(scale * u[(k - k0) * A + j])
                                         for j in range(A)])
                        noisy = rs.shot_noise or rs.read_noise_dn > 0
                        rng = _noise_rng(scene.seed, k) if noisy else None
                        writer.write(sensor_dn(subs, bit_depth, rs.read_noise_dn, rs.shot_noise,
                                               opts.full_well, rng))
                        bar.advance()
            finally:
                writer.close()
            os.replace(tmp, seg_dir / f"seg_{s:05d}.mkv")
            state["segments_done"] = s + 1
            _write_json(checkpoint, state)
        segments = [seg_dir / f"seg_{s:05d}.mkv" for s in range(n_seg)]
        bar.stage("join video", 1)
        if opts.consumer_crf is None:
            _concat(segments, work / "video.mkv", work, None, scene.simulation.fps)
        else:
            enc = ["-c:v", "libx264", "-preset", "medium", "-crf", str(opts.consumer_crf),
                   "-pix_fmt", "gray", "-threads", "2", "-r", str(PLAYBACK_FPS)]
            _concat(segments, work / "video.mp4", work, enc, scene.simulation.fps)
        bar.advance()

        # ---------------------------------------------------------------- rest, depth, vis
        bar.stage("ground truth", 6)
        import imageio.v3 as iio

        rest_img = renderer.render()
        depth = renderer.depth()
        visible = renderer.visible_vertices()
        iio.imwrite(work / "rest.png", _to_png8(rest_img))
        iio.imwrite(work / "depth.png", _depth_png(depth))
        bar.advance()

        uv = camera.project(rest)
        zc = camera.depth(rest)
        J = camera.jacobian(rest)  # (S, 2, 3)
        phi3 = _mode_vectors_3d(result, nodes)  # (m, S, 3)
        img_modes = np.einsum("sij,msj->msi", J, phi3)  # (m, S, 2)
        raster = rasterize(camera, rest, tris)
        vis_idx = np.flatnonzero(visible)

        import zarr

        root = zarr.open_group(str(work / "truth.zarr"), mode="w", zarr_format=3)
        root.attrs.update({"vvtbench": __version__, "format": FORMAT_VERSION,
                           "scene": scene.name})

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
        put("mesh/surface", mesh.surface)
        put("mesh/surface_nodes", nodes)
        vols = element_volumes(mesh.element_type, mesh.cell_coords)
        put("mesh/element_volumes", vols)
        # material
        f = result.fields
        put("material/stiffness", f.stiffness)
        put("material/density", f.density)
        put("material/nu", f.nu)
        vmap = VoxelMap.from_mesh(mesh, opts.voxel_shape)
        grid_shape = tuple(opts.voxel_shape)
        for key, values in (("stiffness", f.stiffness), ("density", f.density), ("nu", f.nu)):
            put(f"voxels/{key}", vmap.to_grid(vmap.average(values, vols)).reshape(grid_shape))
        put("voxels/element_voxel", vmap.element_voxel)
        bar.advance()
        # modes
        modes = result.modes
        put("modes/eigenvalues", np.asarray(modes.eigenvalues, dtype=np.float64))
        put("modes/frequencies_hz", result.frequencies_hz)
        put("modes/damping_ratios", np.asarray(result.damping_ratios, dtype=np.float64))
        put("modes/vectors", modes.vectors)
        put("modes/free_dofs", result.model.free_dofs)
        put("modes/surface", phi3)
        # observation
        put("observation/rest_uv", uv)
        put("observation/rest_depth", zc)
        put("observation/visible", visible)
        put("observation/visible_index", vis_idx)
        put("observation/visible_nodes", nodes[vis_idx])
        put("observation/jacobian", J[vis_idx])
        put("observation/image_modes", img_modes[:, vis_idx])
        put("observation/image_modes_surface", img_modes)
        bar.advance()
        # image-space fields
        put("image/rest", rest_img)
        put("image/depth", depth)
        put("image/triangle", raster.triangle)
        put("image/barycentric", raster.barycentric)
        dense = root.create_array("image/modes", shape=(len(modes), H, W, 2), dtype=np.float32,
                                  chunks=(1, H, W, 2), fill_value=np.nan, overwrite=True)
        for m in range(len(modes)):
            dense[m] = interpolate(raster, tris, img_modes[m]).astype(np.float32)
        bar.advance()
        # transient (surface-node displacements at the video frame times, sub-frames averaged)
        S = len(nodes)
        tchunk = max(1, min(n_frames, (8 << 20) // (S * 12)))
        disp = root.create_array("transient/displacements", shape=(n_frames, S, 3),
                                 dtype=np.float32, chunks=(tchunk, S, 3), overwrite=True)
        fine_t = result.times
        times = fine_t[: n_frames * A].reshape(n_frames, A).mean(axis=1)
        put("transient/times", times)
        peak_px = 0.0
        for k0 in range(0, n_frames, tchunk):
            k1 = min(k0 + tchunk, n_frames)
            u = _as_3d(result.displacement_frames(k0 * A, k1 * A))
            u = u.reshape(k1 - k0, A, S, 3).mean(axis=1, dtype=np.float64)
            disp[k0:k1] = u.astype(np.float32)
            px = np.einsum("vij,tvj->tvi", J[vis_idx], u[:, vis_idx])
            peak_px = max(peak_px, float(np.abs(px).max(initial=0.0)))
        bar.advance()

        info = {
            "format": FORMAT_VERSION,
            "vvtbench": __version__,
            "scene": scene.name,
            "seed": scene.seed,
            "video": {
                "file": "video.mp4" if opts.consumer_crf is not None else "video.mkv",
                "codec": "h264" if opts.consumer_crf is not None else "ffv1",
                "lossless": opts.consumer_crf is None,
                "crf": opts.consumer_crf,
                "pixel_format": "gray" if opts.consumer_crf is not None else "gray16le",
                "frames": n_frames,
                "fps": scene.simulation.fps,
                "playback_fps": PLAYBACK_FPS,
                "height": H,
                "width": W,
                "bit_depth": bit_depth,
                "dn_max": 2**bit_depth - 1,
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
                     "n_surface_nodes": S, "n_surface_triangles": len(tris),
                     "n_visible": int(len(vis_idx))},
            "modes": {"n": len(modes), "frequencies_hz": result.frequencies_hz.tolist(),
                      "damping_ratios": [float(z) for z in result.damping_ratios],
                      "rayleigh_alpha": result.alpha, "rayleigh_beta": result.beta},
            "voxels": {**vmap.grid.to_dict(), "shape": list(grid_shape),
                       "n_active": int(vmap.n_params)},
            "peak_image_motion_px": peak_px * rs.motion_scale,
            "truncation_error": result.truncation_error,
            "generator": opts.to_dict(),
        }
        _write_json(work / "truth.json", info)
        cam = camera.to_dict()
        cam["P"] = camera.P.tolist()
        cam["fov_y_deg"] = float(np.degrees(2 * np.arctan((H / 2) / camera.fy)))
        _write_json(work / "camera.json", cam)
        bar.advance()

        # ---------------------------------------------------------------- preview
        _preview(scene, result, renderer, work / "preview.mp4", n_frames, A, peak_px,
                 opts.preview_frames, bar)


def _preview(scene, result, renderer, path: Path, n_frames: int, A: int, peak_px: float,
             n_preview: int, bar: _Progress) -> None:
    """A short H.264 clip with the motion magnified to ~3 px peak, for people to watch."""
    import imageio_ffmpeg

    fps = scene.simulation.fps
    f1 = float(result.frequencies_hz[0]) if len(result.frequencies_hz) else 1.0
    stride = max(1, int(fps / (10.0 * max(f1, 1e-6))))  # ~10 frames per lowest-mode period
    ks = np.arange(0, n_frames, stride)[: max(1, n_preview)]
    gain = 3.0 / peak_px if peak_px > 0 else 1.0
    gain = max(gain, 1.0)
    H, W = renderer.shape
    h2, w2 = H + H % 2, W + W % 2
    writer = imageio_ffmpeg.write_frames(
        str(path), (w2, h2), pix_fmt_in="gray", pix_fmt_out="yuv420p", codec="libx264",
        quality=None, fps=PLAYBACK_FPS, macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-crf", "23", "-preset", "medium", "-threads", "1", *_BITEXACT],
    )
    writer.send(None)
    bar.stage("preview", len(ks))
    try:
        for k in ks:
            u = _as_3d(result.displacement_frames(k * A, k * A + 1))[0]
            img = _to_png8(renderer.render(gain * u))
            if (h2, w2) != (H, W):
                img = np.pad(img, ((0, h2 - H), (0, w2 - W)))
            writer.send(np.ascontiguousarray(img))
            bar.advance()
    finally:
        writer.close()


def _write_manifest(work: Path, scene: Scene) -> None:
    files = {}
    for p in sorted(work.rglob("*")):
        if p.is_file():
            rel = p.relative_to(work).as_posix()
            if rel == "manifest.json":
                continue
            files[rel] = {"sha256": _sha256(p), "bytes": p.stat().st_size,
                          "description": _describe(rel)}
    _write_json(work / "manifest.json", {
        "format": "vvtbench-sample",
        "format_version": FORMAT_VERSION,
        "vvtbench": __version__,
        "scene": scene.name,
        "seed": scene.seed,
        "files": files,
    })


# --------------------------------------------------------------------------- loading
@dataclass
class Sample:
    """A generated sample, opened lazily (see docs/dataset.md).

    ``sample["observation/jacobian"]`` reads a ground-truth array from ``truth.zarr``;
    :meth:`frames` iterates over video frames without loading the whole video.
    """

    path: Path
    scene: Scene
    camera: Any
    info: dict
    manifest: dict
    truth: Any = field(repr=False)

    @property
    def n_frames(self) -> int:
        return int(self.info["video"]["frames"])

    @property
    def fps(self) -> float:
        return float(self.info["video"]["fps"])

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.info["video"]["height"]), int(self.info["video"]["width"]))

    @property
    def bit_depth(self) -> int:
        return int(self.info["video"]["bit_depth"])

    @property
    def video_path(self) -> Path:
        return self.path / self.info["video"]["file"]

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self["modes/frequencies_hz"]

    @property
    def damping_ratios(self) -> np.ndarray:
        return self["modes/damping_ratios"]

    @property
    def times(self) -> np.ndarray:
        return self["transient/times"]

    def __getitem__(self, name: str) -> np.ndarray:
        return np.asarray(self.truth[name][...])

    def array(self, name: str):
        """The lazy Zarr array ``name`` (slice it to read part of it)."""
        return self.truth[name]

    def frames(self, start: int = 0, stop: int | None = None, *,
               normalize: bool = False) -> Iterator[np.ndarray]:
        """Video frames ``start:stop`` one at a time: (H, W) uint16 DN, or float32 in [0, 1]
        (DN / (2^bit_depth - 1)) with ``normalize``."""
        n = self.n_frames
        stop = n if stop is None else min(stop, n)
        if not 0 <= start <= stop:
            raise IndexError(f"frames {start}:{stop} out of range 0:{n}")
        if start == stop:
            return
        pix = self.info["video"]["pixel_format"]
        bpp = 2 if pix == "gray16le" else 1
        check = pix if self.info["video"].get("lossless") else None
        scale = 1.0 / (2 ** self.bit_depth - 1)
        for frame in read_video(self.video_path, *self.shape, bpp=bpp, start=start, stop=stop,
                                stored_pix_fmt=check):
            yield (frame.astype(np.float32) * np.float32(scale)) if normalize \
                else frame.astype(np.uint16)

    def read_frames(self, start: int = 0, stop: int | None = None, *,
                    normalize: bool = False) -> np.ndarray:
        """Frames ``start:stop`` as one (T, H, W) array."""
        out = list(self.frames(start, stop, normalize=normalize))
        dtype = np.float32 if normalize else np.uint16
        return np.stack(out) if out else np.zeros((0, *self.shape), dtype)

    def verify(self) -> list[str]:
        """Files whose sha256 differs from the manifest, or are missing or not listed."""
        bad = []
        listed = self.manifest["files"]
        for rel, entry in listed.items():
            p = self.path / rel
            if not p.is_file():
                bad.append(f"{rel}: missing")
            elif _sha256(p) != entry["sha256"]:
                bad.append(f"{rel}: sha256 mismatch")
        for p in self.path.rglob("*"):
            rel = p.relative_to(self.path).as_posix()
            if p.is_file() and rel != "manifest.json" and rel not in listed:
                bad.append(f"{rel}: not in the manifest")
        return bad


def open_sample(path: str | Path) -> Sample:
    """Open a sample folder written by :func:`generate`."""
    import zarr

    from .render import Camera

    path = Path(path)
    needed = ("manifest.json", "truth.json", "camera.json", "scene.toml", "truth.zarr")
    missing = [n for n in needed if not (path / n).exists()]
    if missing:
        raise DatasetError(f"{path}: not a vvtbench sample (missing {', '.join(missing)})")
    manifest = json.loads((path / "manifest.json").read_text())
    info = json.loads((path / "truth.json").read_text())
    if info.get("format", 0) > FORMAT_VERSION:
        raise DatasetError(f"{path}: dataset format {info['format']} is newer than this "
                           f"vvtbench ({__version__}) reads ({FORMAT_VERSION}); upgrade vvtbench")
    scene = load_scene(path / "scene.toml")
    camera = Camera.from_dict(json.loads((path / "camera.json").read_text()))
    truth = zarr.open_group(str(path / "truth.zarr"), mode="r")
    return Sample(path, scene, camera, info, manifest, truth)


# --------------------------------------------------------------------------- CLI
def resolve_scenes(spec: str | Path) -> list[Scene]:
    """Scenes named by a scene path or name, a folder of scene TOMLs, or a suite TOML
    (``scenes = ["name", ...]``, names or paths relative to the suite file)."""
    p = Path(spec)
    if p.is_dir():
        files = sorted(p.glob("*.toml"))
        if not files:
            raise SceneError(f"{p}: folder holds no scene files (*.toml)")
        return [s for f in files for s in resolve_scenes(f)]
    if p.is_file() or (SCENES_DIR / "suites" / f"{spec}.toml").is_file():
        if not p.is_file():
            p = SCENES_DIR / "suites" / f"{spec}.toml"
        try:
            data = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
            raise SceneError(f"{p}: not valid TOML: {error}") from None
        if "scenes" in data and "geometry" not in data:
            names = data["scenes"]
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise SceneError(f"{p}: key 'scenes' must be a list of scene names or paths")
            out = []
            for name in names:
                q = p.parent / name
                out.append(load_scene(q if q.is_file() else name))
            return out
        return [load_scene(p)]
    return [load_scene(find_scene(spec))]


def _resolution(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be HxW, e.g. 256x256; got {text!r}"
                                         ) from None
    return h, w


def build_generate_parser(parser: argparse.ArgumentParser | None = None
                          ) -> argparse.ArgumentParser:
    p = parser or argparse.ArgumentParser(
        prog="vvtbench generate", description="Render scenes into sample folders "
        "(video + ground truth); see docs/dataset.md.")
    p.add_argument("scene", metavar="SCENE_OR_SUITE",
                   help="scene file or shipped scene name, a folder of scene TOMLs, or a suite "
                        "TOML with scenes = [...]")
    p.add_argument("-o", "--out", required=True, type=Path, help="output folder")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, help="number of video frames (overrides duration)")
    length.add_argument("--duration", type=float, help="video length in seconds")
    p.add_argument("--resolution", type=_resolution, help="HxW output size, e.g. 256x256")
    p.add_argument("--overwrite", action="store_true", help="replace existing sample folders")
    p.add_argument("--consumer-crf", type=int, default=None,
                   help="write an 8-bit H.264 video at this CRF instead of lossless 16-bit")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def main_generate(argv: list[str] | None = None) -> int:
    """``vvtbench generate``: returns the exit code (0 ok, 2 bad input, 1 failure)."""
    args = build_generate_parser().parse_args(argv)
    return run_generate(args)


def run_generate(args: argparse.Namespace) -> int:
    try:
        scenes = resolve_scenes(args.scene)
        scenes = [with_overrides(s, frames=args.frames, duration=args.duration,
                                 resolution=args.resolution) for s in scenes]
        for scene in scenes:
            path = generate(scene, args.out, progress=not args.no_progress,
                            overwrite=args.overwrite, consumer_crf=args.consumer_crf)
            print(f"{scene.name}: {path}")
    except (SceneError, DatasetError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0
