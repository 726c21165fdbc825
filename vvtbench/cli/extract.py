"""``vvtbench extract``: image-space modes of a video (motion, spectrum, peaks, plots).

Also ``python -m vvtbench.cli.extract ...``; in Python, :func:`vvtbench.modes.extract_modes`.
"""

from __future__ import annotations

import argparse
import json
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..modes.modeset import ModeSet
from ..modes.record import ordinal
from ..video.files import VIDEO_SUFFIXES, open_video
from .args import bounded, nonnegative_float, positive_float, positive_int


def _parse_roi(s: str) -> tuple[int, int, int, int]:
    try:
        parts = tuple(int(v) for v in s.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 4:
        raise argparse.ArgumentTypeError("roi must be y0,y1,x0,x1 (integers)")
    return parts  # type: ignore[return-value]


def _parse_frames(s: str) -> tuple[int, int | None]:
    start, sep, stop = s.partition(":")
    try:
        a = int(start) if start.strip() else 0
        b = int(stop) if stop.strip() else None
    except ValueError:
        a, b, sep = -1, None, ""
    if not sep or a < 0 or (b is not None and b <= a):
        raise argparse.ArgumentTypeError("frames must be START:STOP with 0 <= START < STOP "
                                         "(either may be left out: 100: or :500)")
    return a, b


def _sample_fps(path: Path) -> float | None:
    """The capture frame rate recorded in a vvtbench sample folder (its container says less:
    Matroska timestamps cannot hold 2000 fps), or None."""
    truth = path / "truth.json" if path.is_dir() else path.parent / "truth.json"
    if not truth.is_file():
        return None
    try:
        return float(json.loads(truth.read_text())["video"]["fps"])
    except (KeyError, TypeError, ValueError):
        return None


def _sample_excitation(path: Path) -> str | None:
    """The excitation kind of a vvtbench sample's scene (``scene.toml``), or None."""
    import tomllib

    scene = path / "scene.toml" if path.is_dir() else path.parent / "scene.toml"
    if not scene.is_file() or not (scene.parent / "truth.json").is_file():
        return None
    try:
        kind = tomllib.loads(scene.read_text()).get("excitation", {}).get("kind")
    except (OSError, ValueError, AttributeError):
        return None
    return kind if isinstance(kind, str) else None


def _sample_of(path: Path) -> Path | None:
    """The sample folder ``path`` is, or whose video it is, else None."""
    if path.is_dir() and (path / "manifest.json").is_file():
        return path
    if path.is_file() and (path.parent / "manifest.json").is_file() \
            and (path.parent / "truth.json").is_file():
        return path.parent
    return None


def _resolve_source(path: Path) -> Path:
    """The video file to read; a sample (folder or its video) is verified first
    (:func:`vvtbench.samples.reader.open_sample`: truth and video against the manifest)."""
    from ..samples.reader import DatasetError, open_sample
    from ..video.cameras import IMAGE_SUFFIXES, is_camera_source

    if not path.exists():
        if is_camera_source(path):  # a glob or printf pattern of an image sequence
            return path
        raise FileNotFoundError(2, "no such file or folder", str(path))
    sample = _sample_of(path)
    if sample is not None:
        s = open_sample(sample)
        if path.is_dir() or path.resolve() == s.video_path.resolve():
            return s.video_path
        return path
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
        if not found and any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
            return path  # a folder of images: an image sequence
        if len(found) != 1:
            raise DatasetError(
                f"{path}: a folder with {len(found)} video files "
                f"({', '.join(p.name for p in found) or 'none'}); give the file"
            )
        return found[0]
    return path


def _check_output(out: Path, video: Path) -> None:
    """The output folder may not be a file, nor inside a sample folder."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(17, "-o must be a folder, and this is a file", str(out))
    sample = _sample_of(video)
    if sample is not None:
        o, s = out.resolve(), sample.resolve()
        if o == s or s in o.parents:
            raise ValueError(f"-o {out}: inside the sample {sample} (it would change the "
                             "sample and break its manifest); give another folder")


def _note_fps(given: Path, src: Path, fps: float | None,
              read: dict | None = None) -> None:
    """Tell on stderr which frame rate is used when ``--fps`` is not given."""
    if fps is not None:
        truth = given / "truth.json" if given.is_dir() else given.parent / "truth.json"
        print(f"note: --fps not given: using {fps:g} fps from {truth}", file=sys.stderr)
        return
    try:
        stream = open_video(src, **(read or {}))
    except (OSError, ValueError):
        return  # extract_modes reports the error
    fps = stream.fps
    step = int(stream.meta.get("decimation") or 1)
    if fps is not None and stream.meta.get("frame_rate_source") == "file header":
        saved = (f" (recorded at {float(Fraction(stream.meta['record_fps'])):g} fps, every "
                 f"{ordinal(step)} frame stored: {stream.meta.get('decimation_key')} {step})"
                 if step > 1 and stream.meta.get("record_fps") else "")
        print(f"note: --fps not given: using {fps:g} fps from the header of {src}{saved}",
              file=sys.stderr)
    elif fps is not None:
        print(
            f"note: --fps not given: using the container's frame rate, {fps:g} fps, of {src} "
            "(high-speed footage often stores a wrong one: pass --fps)",
            file=sys.stderr,
        )


def build_parser(prog: str = "vvtbench extract") -> argparse.ArgumentParser:
    """Argument parser of :func:`main_extract`."""
    ap = argparse.ArgumentParser(
        prog=prog,
        description="Extract image-space modes from a video (writes modes.npz, modes.json "
        "and PNG plots; format in docs/modes.md).",
    )
    ap.add_argument(
        "video", type=Path, help="video file (avi/mp4/mkv/.npy), camera file (Photron "
        ".cih/.cihx/.mraw, Phantom .cine), image sequence (a folder, a glob 'frames/*.tif' or "
        "a pattern img_%%05d.png) or a folder holding a video (docs/reference/camera-files.md)"
    )
    ap.add_argument(
        "--fps",
        type=positive_float,
        default=None,
        help="recording frame rate (Hz, > 0); default: a sample's truth.json, else the "
        "container's",
    )
    ap.add_argument("-o", "--out", type=Path, required=True, help="output directory")
    ap.add_argument("--fmin", type=nonnegative_float, default=None,
                    help="lowest mode frequency (Hz, >= 0)")
    ap.add_argument("--fmax", type=positive_float, default=None,
                    help="highest (Hz, > fmin, <= fps/2)")
    ap.add_argument("--prominence", type=nonnegative_float, default=0.5,
                    help="peak prominence (decades, >= 0)")
    ap.add_argument("--min-sep", type=positive_float, default=None,
                    help="min peak separation (Hz, > 0)")
    ap.add_argument("--max-modes", type=positive_int, default=None,
                    help="keep at most this many (the most prominent; default: no cap)")
    ap.add_argument("--min-power-ratio", type=bounded(float, ge=0, le=1), default=1e-6,
                    help="vs the strongest peak in band (0..1)")
    ap.add_argument("--extractor", default="phase", metavar="NAME",
                    help="motion extractor: a registered name (`vvtbench extractors`), "
                    "module:Class or path/to/file.py:Class (default: phase)")
    ap.add_argument("--set", dest="extractor_set", action="append", default=[],
                    metavar="KEY=VALUE", help="extractor config override (repeatable; "
                    "`vvtbench extractors -v` lists the keys)")
    ap.add_argument("--scales", type=bounded(int, ge=1, le=8), default=3)
    ap.add_argument("--orientations", type=bounded(int, ge=1, le=16), default=4)
    ap.add_argument("--sigma", type=nonnegative_float, default=2.0,
                    help="smoothing sigma (px, >= 0)")
    ap.add_argument("--batch", type=positive_int, default=32)
    ap.add_argument("--workers", type=bounded(int, ge=1, also=(-1,)), default=1,
                    help="threads (-1 = all CPUs)")
    ap.add_argument("--average", type=positive_int, default=1,
                    help="average N consecutive frames")
    ap.add_argument("--roi", type=_parse_roi, default=None,
                    help="crop y0,y1,x0,x1 (rows y0:y1, columns x0:x1; camera files read only "
                    "these rows)")
    ap.add_argument("--frames", type=_parse_frames, default=None, metavar="START:STOP",
                    help="frame range read (STOP excluded; either may be left out)")
    ap.add_argument("--bit-depth", type=bounded(int, ge=1, le=16), default=None,
                    help="significant bits per sample of an image sequence, .npy or camera "
                    "file (default: the file's header; e.g. 12 for 12-bit data in 16-bit TIFFs)")
    ap.add_argument("--max-frames", type=positive_int, default=None)
    ap.add_argument("--weighting", choices=("confidence", "none", "noise"), default="noise",
                    help="pixel weights of the spectrum the peaks are picked from (default: noise; "
                    "docs/modes.md)")
    ap.add_argument(
        "--window", choices=("hann", "none"), default="hann", help="temporal taper of the FFT"
    )
    ap.add_argument("--reference", choices=("mean", "first"), default="mean",
                    help="what motion is measured against: the temporal mean of the record "
                         "(read in a first pass) or its first frame (noisier: amplitudes read "
                         "low)")
    ap.add_argument("--keep-shake", action="store_true", help="keep camera-shake peaks")
    ap.add_argument(
        "--keep-distortion",
        action="store_true",
        help="keep peaks that are harmonics / intermodulation products of stronger ones",
    )
    ap.add_argument("--product-roughness", type=bounded(float, ge=0, le=1), default=0.15,
                    help="a distortion product (f_i +- f_j, 2 f_i of stronger peaks) rougher "
                    "than this is rejected (default 0.15; docs/modes.md)")
    ap.add_argument("--faint-product-ratio", type=bounded(float, ge=0, le=1), default=0.01,
                    help="a distortion product with less than this fraction of its weaker "
                    "parent's power is rejected whatever its roughness (default 0.01; 0: off; "
                    "docs/modes.md)")
    ap.add_argument("--product-scaling", choices=("product", "weaker"), default="product",
                    help="a faint product is measured against P_i P_j / P_max (product) or "
                    "its weaker parent's power (default: product; docs/modes.md)")
    ap.add_argument("--shape-attenuation", action="store_true",
                    help="attenuate the noisiest pixels of the mode shapes (opt-in; "
                    "docs/modes.md)")
    ap.add_argument("--line-fit", action="store_true",
                    help="fit the peaks as lines across all pixels (close modes resolved) and "
                    "add significant lines of the residual (docs/modes.md, 'Line fit')")
    ap.add_argument("--identifier", choices=("auto", "peaks", "era", "plscf"), default="auto",
                    help="how modes are identified: auto (ERA for a free decay, the peak "
                    "picker for a driven record, read from --excitation, a sample's scene, "
                    "else the motion's envelope), peaks (the peak picker), era (poles of the "
                    "free decay) or plscf (poles of the power spectra); docs/modes.md")
    ap.add_argument("--excitation", default=None, metavar="KIND",
                    help="how the object was set moving (pluck, velocity, force, sweep, ...), "
                    "for --identifier auto; default: a sample's scene, else the envelope")
    ap.add_argument("--reject-products", action="store_true",
                    help="also reject harmonics and intermodulation products of stronger modes "
                    "judged by phase and shape (opt-in; docs/modes.md, 'False modes of the "
                    "extractor's own making')")
    ap.add_argument("--shape-fill", action="store_true",
                    help="fill the noisiest pixels of the mode shapes in from their reliable "
                    "neighbours (opt-in; docs/modes.md, 'Reliable pixels')")
    ap.add_argument("--roughness-weighting", choices=("shape", "spectrum"), default="shape",
                    help="pixel weights of the roughness tests: the shapes' (confidence) or the "
                    "spectrum's (noise weights: occlusion edges and seams left out; default: "
                    "shape; docs/modes.md, 'Reliable pixels')")
    ap.add_argument("--min-reliable-fraction", type=nonnegative_float, default=None,
                    help="reject a peak whose energy on the reliable pixels (noise weights) is "
                    "below this fraction of its energy on all pixels (default: off; "
                    "docs/modes.md, 'Reliable pixels')")
    ap.add_argument("--memory-budget-mb", type=positive_float, default=1024.0)
    ap.add_argument("--tmpdir", default=None, help="where the extraction's scratch space is "
                    "made (displacements spill there; default: the system's temporary folder)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--quiet", action="store_true", help="no progress line")
    ap.add_argument("--timeout", type=positive_float, default=3600.0,
                    help="seconds the extraction may run (default 3600); it runs sealed: the "
                    "extractor sees the video and nothing else of yours")
    return ap


_USER_ERRORS = ("ValueError", "VideoError", "FileNotFoundError", "DatasetError",
                "PluginError", "NotADirectoryError", "IsADirectoryError", "PermissionError")


def _extract_sealed(args, src: Path, fps, options: dict) -> int:
    """The one extraction of ``extract``: :func:`vvtbench.modes.extract_modes` in a sealed
    child (:func:`vvtbench.solving.sealed.extract_sealed`) that sees the video (or the camera's
    folder) and the output only; 0, or the exit status after one line."""
    from ..solving.sealed import SealedError, extract_sealed

    sample = _sample_of(Path(args.video))
    secrets = [args.out, *([sample] if sample is not None else [])]
    if not args.quiet and sys.stderr.isatty():
        print(f"extracting modes from {src} ...", file=sys.stderr, flush=True)
    try:
        extract_sealed(src, fps, options, args.out, secrets=secrets,
                       folder=sample is None, timeout=args.timeout, scratch=args.tmpdir)
    except SealedError as error:
        from .args import explain

        text = str(error)
        kind = text.partition(":")[0]
        if error.kind == "error" and kind in _USER_ERRORS:
            msg = explain(text.partition(": ")[2])
            print(f"error: {msg if str(src) in msg else f'{src}: {msg}'}", file=sys.stderr)
            return 2
        print(f"error: {src}: the extraction failed: {text}", file=sys.stderr)
        return 1
    return 0


def main_extract(argv: list[str] | None = None) -> int:
    """``vvtbench extract VIDEO --fps F -o DIR [...]``; returns the exit status."""
    args = build_parser().parse_args(argv)
    if args.fmin is not None and args.fmax is not None and args.fmin >= args.fmax:
        raise ValueError(f"--fmin {args.fmin:g} must be below --fmax {args.fmax:g}")
    if args.roi is not None:
        y0, y1, x0, x1 = args.roi
        if not (0 <= y0 < y1 and 0 <= x0 < x1):
            raise ValueError(f"--roi {y0},{y1},{x0},{x1}: need 0 <= y0 < y1 and 0 <= x0 < x1")
    from ..solving.extractors import load_extractor
    from ..solving.plugins import parse_overrides

    # checked before any frame is read; passed on as overrides, so that for phase --scales,
    # --sigma ... still apply where --set is silent
    checked = parse_overrides(args.extractor_set, load_extractor(args.extractor).Config)
    extractor_config = {key: getattr(checked, key) for key in
                        (item.partition("=")[0].strip() for item in args.extractor_set)}
    _check_output(args.out, args.video)
    src = _resolve_source(args.video)
    start, stop = args.frames if args.frames is not None else (0, None)
    read = {"start": start, "stop": stop, "bit_depth": args.bit_depth}
    fps = args.fps if args.fps is not None else _sample_fps(args.video)
    if args.fps is None:
        _note_fps(args.video, src, fps, read)
    options = dict(
        fmin=args.fmin, fmax=args.fmax, prominence=args.prominence,
        min_separation_hz=args.min_sep, max_modes=args.max_modes,
        min_power_ratio=args.min_power_ratio, n_scales=args.scales,
        n_orientations=args.orientations, sigma=args.sigma, batch=args.batch,
        workers=args.workers, average=args.average, roi=args.roi, max_frames=args.max_frames,
        weighting=args.weighting, window=args.window, reference=args.reference,
        keep_camera_shake=args.keep_shake,
        reject_distortion=not args.keep_distortion,
        memory_budget=int(args.memory_budget_mb * (1 << 20)), progress=False,
        line_fit=args.line_fit, stability=not args.no_plots,
        reject_products=args.reject_products,
        product_roughness=args.product_roughness,
        faint_product_ratio=args.faint_product_ratio, product_scaling=args.product_scaling,
        shape_attenuation=args.shape_attenuation, shape_fill=args.shape_fill,
        roughness_weighting=args.roughness_weighting,
        min_reliable_fraction=args.min_reliable_fraction, extractor=args.extractor,
        extractor_config=extractor_config, identifier=args.identifier,
        excitation=args.excitation if args.excitation is not None
        else _sample_excitation(args.video), **read)
    code = _extract_sealed(args, src, fps, options)
    if code:
        return code
    ms = ModeSet.load(args.out)
    if ms.lossy is not None:
        from ..video.files import describe_lossy

        print(f"warning: {describe_lossy(ms.lossy, ms.metadata.get('fps_input'))}",
              file=sys.stderr)
    for note in ms.metadata.get("record_notes") or []:
        print(f"warning: {note['message']}", file=sys.stderr)
    ms.save(args.out)
    if not args.no_plots:
        from ..modes.plots import plot_modes

        plot_modes(ms, args.out)
    print(f"{len(ms)} modes, T = {ms.n_frames} frames at {ms.fps:g} fps -> {args.out}")
    if not len(ms) and ms.metadata.get("no_modes"):
        print(f"  no mode: {ms.metadata['no_modes']}")
    ident = ms.identifier
    print(f"identifier: {ident['used']}"
          + (f" ({ident['requested']}: {ident['reason']})" if ident["requested"] == "auto"
             else ""))
    peak, resolved = ms.peak_displacement_px, ms.damping_resolved()
    start = ms.initial_displacement_px
    sf, (zlo, zhi) = ms.frequency_std_hz(), ms.damping_interval()
    biased = ms.close_mode_bias()
    for i, row in enumerate(ms.summary()):
        z = row["damping"]
        print(
            f"  #{row['index']:2d} {row['frequencies_hz']:10.4f}"
            + (f" +- {sf[i]:.2g}" if np.isfinite(sf[i]) else "")
            + " Hz  zeta "
            + (f"{z:.4f}" if z is not None and resolved[i] else "  -   ")
            + (f" [{zlo[i]:.3g}, {zhi[i]:.3g}]" if np.isfinite(zlo[i]) else "")
            + ("  ! close mode bias" if biased[i] else "")
            + f"  peak {peak[i]:.3g} px"
            + (f" (at onset {start[i]:.3g} px)" if start[i] > 1.05 * peak[i] else "")
            + (f"  prominence {row['prominences']:.2f}" if row["prominences"] is not None
               else "")
            + (f"  roughness {row['roughness']:.2f}" if row.get("roughness") is not None else "")
        )
    for r in ms.metadata.get("rejected", []):
        if r["reason"] == "camera_shake":
            why = f"MAC {r['shake_mac']:.2f}"
        elif r["reason"] == "distortion":
            why = f"{r['kind']} of {r['parents_hz'][0]:.3f} and {r['parents_hz'][1]:.3f} Hz"
        elif r["reason"] == "keyframe":
            why = (f"harmonic {r['harmonic']} of the keyframe rate {r['comb_hz']:.3f} Hz, "
                   f"a keyframe every {r['gop']} frames")
        elif r["reason"] == "product":
            why = f"{r['product']} ({r['test']})"
        elif r["reason"] == "unreliable":
            why = f"reliable fraction {r['reliable_fraction']:.3f}"
        elif r["reason"] == "faint":
            why = f"power {r['power_ratio']:.2g} of the strongest mode's"
        elif r["reason"] == "unstable":
            why = f"frequency spread {r['frequency_std_hz']:.3g} Hz over the model orders"
        else:
            why = f"roughness {r['roughness']:.2f}"
        print(f"  rejected {r['frequency_hz']:.4f} Hz: {r['reason']} ({why})")
    return 0

