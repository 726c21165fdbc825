"""The package's shape: imports point down the pipeline, never up, never in a circle.

Every ``import`` of a vvtbench module is read from the source (at the top of a module or
inside a function: a deferred import is still an import), and checked against
:data:`LAYERS`, the order of the stages that docs/explanation/design.md draws. A module may
import its own layer or one below; two modules of a layer may not import each other in a
circle. A new module must be placed in a layer here (and in design.md) before it lands.
"""

from __future__ import annotations

import ast
import fnmatch
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "vvtbench"

#: lowest first; a module belongs to the first layer with a pattern that matches its name
LAYERS: list[tuple[str, list[str]]] = [
    ("base", ["vvtbench._version", "vvtbench._aliases", "vvtbench.io", "vvtbench.io.*"]),
    ("scene data", ["vvtbench.scene", "vvtbench.scene.scene"]),
    ("finite elements", ["vvtbench.fem", "vvtbench.fem.*"]),
    ("contracts and plug-in discovery", ["vvtbench.solving", "vvtbench.solving.problem",
                                         "vvtbench.solving.truth", "vvtbench.solving.plugins",
                                         "vvtbench.solving.extractors"]),
    ("simulation", ["vvtbench.simulation", "vvtbench.simulation.*"]),
    ("families", ["vvtbench.scene.families"]),
    ("render", ["vvtbench.render", "vvtbench.render.*"]),
    ("video", ["vvtbench.video", "vvtbench.video.*"]),
    ("samples", ["vvtbench.samples", "vvtbench.samples.*"]),
    ("motion", ["vvtbench.motion", "vvtbench.motion.*"]),
    ("modes", ["vvtbench.modes", "vvtbench.modes.*"]),
    ("sealed execution", ["vvtbench.solving.sealed"]),
    ("observe", ["vvtbench.observe"]),
    ("scoring", ["vvtbench.scoring", "vvtbench.scoring.*"]),
    ("datasets", ["vvtbench.datasets", "vvtbench.datasets.*"]),
    ("figures", ["vvtbench.reporting", "vvtbench.reporting.plots"]),
    ("field path", ["vvtbench.field", "vvtbench.field.*"]),
    ("bench", ["vvtbench.bench", "vvtbench.bench.*"]),
    ("learning", ["vvtbench.learning", "vvtbench.learning.*"]),
    ("leaderboard", ["vvtbench.reporting.leaderboard", "vvtbench.reporting.headroom"]),
    ("doors", ["vvtbench", "vvtbench.api", "vvtbench.cli", "vvtbench.cli.*"]),
]


def _modules(root: Path = PACKAGE) -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _targets(module: str, is_pkg: bool, node: ast.AST, known: set[str]) -> list[str]:
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        base = node.module or ""
        if node.level:
            parts = module.split(".") if is_pkg else module.split(".")[:-1]
            parts = parts[: len(parts) - (node.level - 1)]
            base = ".".join(parts + ([node.module] if node.module else []))
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                 for a in node.names]
    out = []
    for name in names:
        while name and name not in known:
            name = name.rpartition(".")[0]
        if name and name != module:
            out.append(name)
    return out


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """``{module: modules of vvtbench it imports}``, deferred imports included."""
    mods = _modules(root)
    known = set(mods)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for module, (path, is_pkg) in mods.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                graph[module].update(_targets(module, is_pkg, node, known))
    return graph


def layer_of(module: str) -> int | None:
    for i, (_, patterns) in enumerate(LAYERS):
        if any(fnmatch.fnmatchcase(module, p) for p in patterns):
            return i
    return None


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{m} ({LAYERS[layer_of(m)][0]}) imports {t} ({LAYERS[layer_of(t)][0]})"
                  for m, targets in graph.items() for t in targets
                  if layer_of(m) is not None and layer_of(t) is not None
                  and layer_of(t) > layer_of(m))


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


GRAPH = import_graph()


def test_every_module_has_a_layer():
    assert [m for m in GRAPH if layer_of(m) is None] == []


def test_no_module_imports_one_above_its_own_layer():
    assert upward_imports(GRAPH) == []


def test_no_import_circle():
    assert circles(GRAPH) == []


@pytest.mark.parametrize("low,high", [
    ("vvtbench.solving.sealed", "vvtbench.bench"),
    ("vvtbench.video", "vvtbench.field"),
    ("vvtbench.fem", "vvtbench.simulation"),
    ("vvtbench.render", "vvtbench.samples"),
    ("vvtbench.motion", "vvtbench.modes"),
])
def test_named_directions_hold(low, high):
    """The sandbox never imports the runner; camera readers and video files never import the
    field path; fem, render and motion import nothing above them."""
    bad = [(m, t) for m, targets in GRAPH.items() if m == low or m.startswith(low + ".")
           for t in targets if t == high or t.startswith(high + ".")]
    assert bad == []


def test_problem_imports_only_fem_and_io():
    allowed = ("vvtbench.fem", "vvtbench.io")
    assert {t for t in GRAPH["vvtbench.solving.problem"]
            if not t.startswith(allowed)} == set()


def test_the_checks_can_fail(tmp_path):
    """A new circle and an upward import in a copy of a small tree are both found."""
    pkg = tmp_path / "vvtbench"
    for sub in ("fem", "bench", "solving"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "fem" / "mesh.py").write_text("from ..bench import runner\n")
    (pkg / "bench" / "runner.py").write_text("def f():\n    from ..fem import mesh\n")
    (pkg / "solving" / "sealed.py").write_text("from vvtbench.bench.runner import f\n")
    graph = import_graph(pkg)
    assert circles(graph) == [["vvtbench.bench.runner", "vvtbench.fem.mesh"]]
    up = upward_imports(graph)
    assert any(u.startswith("vvtbench.fem.mesh (finite elements) imports vvtbench.bench.runner")
               for u in up)
    assert any(u.startswith("vvtbench.solving.sealed") for u in up)


FORWARDING = ("vvtbench.io", "vvtbench.scene", "vvtbench.video")


def test_no_module_takes_a_name_from_a_forwarding_package():
    """``vvtbench.io``, ``.scene`` and ``.video`` forward the names of the modules they
    replaced, with a warning: the package itself must use the modules that define them."""
    mods = _modules()
    bad = []
    for module, (path, is_pkg) in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = module.split(".") if is_pkg else module.split(".")[:-1]
                    parts = parts[: len(parts) - (node.level - 1)]
                    base = ".".join(parts + ([node.module] if node.module else []))
                if base in FORWARDING:
                    bad += [f"{module}: from {base} import {a.name}" for a in node.names
                            if f"{base}.{a.name}" not in mods]
    assert bad == []


def test_the_public_surface_resolves_and_is_what_shipped_solvers_import():
    import importlib
    import re

    api = importlib.import_module("vvtbench.api")
    for name in api.__all__:
        assert getattr(api, name).__module__ == api.NAMES[name] or name in ("observe",)
    shipped = Path(__file__).resolve().parent.parent / "solvers"
    other = [f"{p.name}: {m}" for p in sorted(shipped.glob("*.py"))
             for m in re.findall(r"^\s*(?:from|import) (vvtbench[\w.]*)", p.read_text(), re.M)
             if m != "vvtbench.api"]
    assert other == []


@pytest.mark.parametrize("old,new,name", [
    ("vvtbench.problem", "vvtbench.solving.problem", "Estimate"),
    ("vvtbench.loaders", "vvtbench.datasets.loaders", "InstanceDataset"),
    ("vvtbench.field.readers", "vvtbench.video.cameras", "open_camera_file"),
    ("vvtbench.scene", "vvtbench.scene.scene", "load_scene"),
    ("vvtbench.video", "vvtbench.video.files", "open_video"),
])
def test_an_old_import_path_still_works_with_a_warning(old, new, name):
    import importlib

    module = importlib.import_module(old)
    vars(module).pop(name, None)  # a name already served is kept: serve it afresh
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        value = getattr(module, name)
    assert value is getattr(importlib.import_module(new), name)


def test_every_import_of_vvtbench_names_a_module_that_exists():
    """A deferred import of a module that moved or went fails only when its function runs;
    here it fails at once, wherever it is."""
    mods = _modules()
    bad = []
    for module, (path, is_pkg) in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = module.split(".") if is_pkg else module.split(".")[:-1]
                    parts = parts[: len(parts) - (node.level - 1)]
                    base = ".".join(parts + ([node.module] if node.module else []))
                if base.split(".")[0] == "vvtbench" and base not in mods:
                    bad.append(f"{module}: from {base} import ...")
            elif isinstance(node, ast.Import):
                bad += [f"{module}: import {a.name}" for a in node.names
                        if a.name.split(".")[0] == "vvtbench" and a.name not in mods]
    assert bad == []
