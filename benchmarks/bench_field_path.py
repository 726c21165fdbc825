"""The field path against the benchmark's own: one rendered sample scored through ``run`` with
the true camera and the lossless video, then handed over as a field user hands it over (a
12-bit TIFF sequence, or H.264; an STL of the object; N clicks with Gaussian pixel noise) and
scored again, same solver, same extraction options. Prints NC of w and v per row and the
difference to the true-camera row.

    .venv/bin/python benchmarks/bench_field_path.py --out runs/field/run \\
        --sample runs/field/jello_cube_defect_top --duration 1.0 \
        [--formats tiff mraw h264] [--crf 18 23] [--bitrate-mbps 50] [--click-seeds 0 1 2]

Measured on 2 cores (2026-11-27; ``jello_cube_defect_top``, 1 s at 2000 FPS, the paper
suite's extraction, vvt, 10 modes, 8^3 voxels): lossless video and true camera NC w 0.595;
12-bit TIFF + STL + 10 clicks at 0.5 px NC w 0.564-0.581 over 5 click seeds (mean difference
-0.026, worst -0.032; -0.022 with noise-free clicks); MRAW identical to TIFF; H.264 crf 12
-0.050, 100 Mbit/s -0.040, crf 18 -0.139, crf 23 -0.180; the STL tetrahedralized
(``--mesh tet``) -0.446. Table in docs/suites.md ("Field tracks").

``--sample``: an already generated sample of the scene (``vvtbench generate
jello_cube_defect_top --duration 1.0 --out DIR``; a paper cube takes minutes to render on
2 cores); it is
linked into the run's cache as the generate task's output after its resolved scene is checked
to be the one the suite asks for. Without it the run renders the scene itself.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tomllib
from pathlib import Path

from vvtbench.bench import run_suite
from vvtbench.bench.graph import build_graph
from vvtbench.bench.stages import file_hashes
from vvtbench.bench.suite import SUITES_DIR, parse_suite
from vvtbench.io.files import write_json
from vvtbench.scene.scene import load_scene


def field_suite(scene: str, formats: list[str], crfs: list[int], clicks: int, noise: float,
                seeds: list[int], n_modes: int, duration: float | None = None,
                click_seeds: list[int] | None = None,
                bitrates: list[float] | None = None, mesh: str = "auto") -> dict:
    """The comparison as a suite: the paper suite's extraction (its ``modes`` track's) and
    vvt settings; one true-camera track, one field track per format (per H.264 ``crf``) and
    click seed (None: the row's seed)."""
    paper = tomllib.loads((SUITES_DIR / "paper.toml").read_text())
    modes_track = next(t for t in paper["tracks"] if t["name"] == "modes")
    common = {"scenes": [scene], "observations": ["extracted"],
              "extract": dict(modes_track.get("extract", {}))}
    tracks = [{"name": "true_camera", **common}]
    encodings = [(f"h264_crf{c}", {"format": "h264", "crf": c}) if fmt == "h264" else
                 (fmt, {"format": fmt, "bit_depth": 12})
                 for fmt in formats for c in (crfs if fmt == "h264" else [None])]
    encodings += [(f"h264_{b:g}mbps", {"format": "h264", "bitrate_mbps": b})
                  for b in bitrates or []]
    for label, encoding in encodings:
        for cs in click_seeds or [None]:
            field = {**encoding, "clicks": clicks, "click_noise_px": noise, "mesh": mesh,
                     **({} if cs is None else {"click_seed": cs})}
            name = f"{label}" + ("" if mesh == "auto" else f"_{mesh}") + (
                "" if cs is None else f"_c{cs}")
            tracks.append({"name": name, **common, "field": field})
    return {"name": "field_bench", "solvers": ["vvt"], "seeds": seeds,
            "defaults": {**paper["defaults"], "n_modes": n_modes,
                         **({} if duration is None else {"simulation.duration": duration})},
            "extract": paper["extract"], "solver": paper["solver"], "tracks": tracks}


def seed_cache(suite, out: Path, sample: Path) -> int:
    """Link ``sample`` into the cache as the output of every generate task of its scene."""
    tasks, _ = build_graph(suite, ["vvt"], until="generate")
    have = load_scene(sample / "scene.toml").to_toml_dict()
    n = 0
    for key, task in tasks.items():
        want = {k: v for k, v in task.payload["scene"].items()}
        if want != have:
            raise SystemExit(f"{sample}: its scene differs from the suite's "
                             f"{task.payload['scene']['name']!r} (seed or settings)")
        final = out / "cache" / key
        if (final / "task.json").is_file():
            continue
        tmp = final.with_name(final.name + ".tmp-seed")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(sample, tmp / "sample", copy_function=os.link)
        write_json(tmp / "task.json", {"stage": "generate", "key": key, "deps": [],
                                       "payload": task.payload,
                                       "result": {"sample": "sample", "video": True},
                                       "seconds": 0.0, "vvtbench": "seeded",
                                       "files": file_hashes(tmp)})
        os.replace(tmp, final)
        n += 1
    return n


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="jello_cube_defect_top")
    p.add_argument("--sample", type=Path, default=None)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--formats", nargs="+", default=["tiff", "h264"],
                   choices=["tiff", "mraw", "h264"])
    p.add_argument("--crf", type=int, nargs="+", default=[23])
    p.add_argument("--bitrate-mbps", type=float, nargs="+", default=None,
                   help="H.264 tracks at these bit rates (Mbit per second of recording)")
    p.add_argument("--clicks", type=int, default=10)
    p.add_argument("--noise", type=float, default=0.5)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--click-seeds", type=int, nargs="+", default=None,
                   help="one field track per click-noise seed (default: the row's seed)")
    p.add_argument("--n-modes", type=int, default=10)
    p.add_argument("--mesh", choices=["auto", "tet"], default="auto",
                   help="how the STL is meshed (auto: a block as its voxel grid)")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds (default: the scene's; 1.0 renders 6x faster)")
    a = p.parse_args()
    suite = parse_suite(field_suite(a.scene, a.formats, a.crf, a.clicks, a.noise, a.seeds,
                                    a.n_modes, a.duration, a.click_seeds, a.bitrate_mbps,
                                    a.mesh),
                        "bench_field_path")
    a.out.mkdir(parents=True, exist_ok=True)
    if a.sample is not None:
        print(f"seeded {seed_cache(suite, a.out, a.sample)} generate task(s) from {a.sample}")
    df = run_suite(suite, ["vvt"], out_dir=a.out, progress=False)
    ref = df[df.track == "true_camera"].set_index("seed")
    print(f"{'track':<16} {'seed':>4} {'status':<7} {'nc_w':>7} {'nc_v':>7} {'d nc_w':>7} "
          f"{'d nc_v':>7} {'modes':>5} {'cam err px':>10}")
    cache = a.out / "cache"
    for _, row in df.sort_values(["track", "seed"]).iterrows():
        base = ref.loc[row.seed]
        cam = ""
        calib = _calibration(cache, df, row)
        if calib:
            cam = f"{calib['camera_error_px']['rms_px']:.3f}"
        print(f"{row.track:<16} {row.seed:>4} {row.status:<7} {row.nc_w:7.3f} {row.nc_v:7.3f} "
              f"{row.nc_w - base.nc_w:+7.3f} {row.nc_v - base.nc_v:+7.3f} "
              f"{row.n_modes_observed:>5} {cam:>10}")
        if row.status != "ok":
            print(f"    {row.error}")
    field = df[df.track != "true_camera"].copy()
    if len(field):
        field["encoding"] = field.track.str.replace(r"_c\d+$", "", regex=True)
        for enc, g in field.groupby("encoding"):
            d = g.nc_w.to_numpy() - ref.loc[g.seed].nc_w.to_numpy()
            print(f"{enc}: d nc_w mean {d.mean():+.3f}, worst {d.min():+.3f} over {len(d)} "
                  f"row(s)")


def _calibration(cache: Path, df, row) -> dict | None:
    """The ``calibration.json`` of a field row's observe task (by its evaluate task)."""
    est = row.get("estimate_path")
    if not isinstance(est, str) or not est:
        return None
    stage, key = Path(est).parts[-3:-1]
    info = cache / stage / key / "task.json"
    if not info.is_file():
        return None
    obs = json.loads(info.read_text())["deps"][1]
    f = cache / obs / "calibration.json"
    return json.loads(f.read_text()) if f.is_file() else None


if __name__ == "__main__":
    main()
