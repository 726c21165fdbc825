"""Resolution of a scene specification to scenes: :func:`resolve_scenes`.

A scene path or name, a folder of scene TOMLs, or a suite (its defaults, variation overrides
and seeds applied, as ``vvtbench run`` does) becomes a list of scenes. A scene with a
different length or resolution: :func:`vvtbench.scene.scene.with_overrides`.
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path

from ..scene.scene import SCENES_DIR, Scene, SceneError, find_scene, load_scene, parse_scene

__all__ = ["resolve_scenes"]


def resolve_scenes(spec: str | Path) -> list[Scene]:
    """Scenes named by a scene path or name, a folder of scene TOMLs, or a suite (a TOML with
    ``scenes = ["name", ...]`` or ``[[tracks]]``, or a shipped suite name).

    A suite's scenes come with its ``[defaults]`` and variation scene overrides applied and
    its seeds set, as ``vvtbench run`` generates them (``vvtbench.bench.apply_overrides``).
    When one scene resolves to several different scenes (variations, seeds), each gets a
    ``-`` and an 8-digit content hash after its name."""
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
        if ("scenes" in data or "tracks" in data) and "geometry" not in data:
            names = data.get("scenes", [])
            if not isinstance(names, list) or not all(isinstance(n, str) for n in _flat(names)):
                raise SceneError(f"{p}: key 'scenes' must be a list of scene names or paths")
            return _suite_scenes(p)
        return [load_scene(p)]
    return [load_scene(find_scene(spec))]


def _flat(items: list) -> list:
    """Scene references of a suite's ``scenes`` (a nested list is one object's videos)."""
    return [x for item in items for x in (item if isinstance(item, list) else [item])]


def _suite_scenes(path: Path) -> list[Scene]:
    """The distinct scenes a suite generates: its defaults, variation overrides and seeds
    applied (the runner's ``_resolve_scene``, read-only use of the bench package)."""
    from .suite import SuiteError, apply_overrides, load_suite, scene_ref

    try:
        suite = load_suite(path)
    except SuiteError as error:
        raise SceneError(str(error)) from None
    resolved: dict[str, list[dict]] = {}
    for track in suite.tracks:
        for group in track.scenes:
            for ref in group:
                base = load_scene(scene_ref(ref, suite.source))
                for var in track.variations:
                    for seed in track.seeds:
                        data = apply_overrides(base.to_toml_dict(),
                                               {**var.scene_overrides, "seed": seed})
                        parsed = parse_scene(data, f"{base.source} (suite {suite.name} "
                                             "overrides)").to_toml_dict()
                        bucket = resolved.setdefault(parsed["name"], [])
                        if parsed not in bucket:
                            bucket.append(parsed)
    out = []
    for name, variants in resolved.items():
        for data in variants:
            if len(variants) > 1:
                tag = hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:8]
                data = {**data, "name": f"{name}-{tag}"}
            out.append(parse_scene(data, f"{name} (suite {suite.name})"))
    return out
