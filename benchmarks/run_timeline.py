"""Where a run's time went: worker-seconds and wall span per stage, solver and family.

    .venv/bin/python benchmarks/run_timeline.py runs/standard_clean

Reads every ``cache/STAGE/KEY/task.json`` of a run folder (``seconds``: the task's own time,
measured by the worker; the file's modification time: when it finished) and ``run.json``
(the run's wall time). Prints, per stage, the number of tasks, their summed seconds
(worker-seconds), the median and maximum task, and the wall span from the first task's start
to the last one's end; solve tasks are split by solver and by family (the scene name's
prefix), video and modes-only samples apart. Tasks cached from an earlier run keep their old
times: measure a clean run (a new folder).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def _family(label: str) -> str:
    name = label.split(":", 1)[-1]
    return name.split("-", 1)[0] if "-test-" in name or "-val-" in name else name


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
    groups: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    spans: dict[str, list[float]] = defaultdict(list)
    scene_of: dict[str, str] = {}  # observe key -> scene name (one read per observation)
    for f in sorted((args.run / "cache").glob("*/*/task.json")):
        t = json.loads(f.read_text())
        sec, end = float(t.get("seconds", 0.0)), f.stat().st_mtime
        stage, payload = t["stage"], t.get("payload", {})
        if stage == "generate":
            scene = payload.get("scene", {})
            kind = "video" if t.get("result", {}).get("video") else "modes-only"
            sub = f"{_family(scene.get('name', ''))} {kind}"
        elif stage == "solve":
            dep = t["deps"][0]
            if dep not in scene_of:
                obs = json.loads((args.run / "cache" / dep / "task.json").read_text())
                scene_of[dep] = obs.get("payload", {}).get("scene", {}).get("name", "")
            scene = scene_of[dep]
            sub = f"{payload.get('solver', '?')} on {_family(scene)}"
        else:
            sub = ""
        groups[(stage, sub)].append((sec, end))
        spans[stage] += [end - sec, end]
    run = json.loads((args.run / "run.json").read_text()) if (args.run / "run.json").is_file() \
        else {}
    t0 = min(min(v) for v in spans.values()) if spans else 0.0
    total = 0.0
    print(f"{'stage / part':46s} {'tasks':>6s} {'worker-s':>9s} {'median s':>9s} {'max s':>8s} "
          f"{'wall span (min)':>18s}")
    for stage in ("generate", "extract", "observe", "solve", "evaluate"):
        if stage not in spans:
            continue
        rows = [(sub, v) for (st, sub), v in sorted(groups.items()) if st == stage]
        secs = np.array([s for _, v in rows for s, _ in v])
        total += secs.sum()
        a, b = (min(spans[stage]) - t0) / 60, (max(spans[stage]) - t0) / 60
        print(f"{stage:46s} {len(secs):6d} {secs.sum():9.0f} {np.median(secs):9.1f} "
              f"{secs.max():8.1f} {a:8.1f} - {b:6.1f}")
        if len(rows) > 1:
            for sub, v in rows:
                s = np.array([x for x, _ in v])
                print(f"  {sub:44s} {len(s):6d} {s.sum():9.0f} {np.median(s):9.1f} "
                      f"{s.max():8.1f}")
    print(f"{'all tasks':46s} {'':6s} {total:9.0f} worker-s = {total / 3600:.2f} worker-h")
    if run:
        print(f"run.json: wall {run.get('wall_s', float('nan')) / 60:.1f} min, workers "
              f"{run.get('workers')}, {run.get('n_runs')} result rows")


if __name__ == "__main__":
    main()
