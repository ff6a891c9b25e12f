"""The layering of docs/architecture.md, checked on the source: every import of an fgjax module points to the same
or a lower layer, no import cycle between modules, no private name imported across modules, imports at module top
(except in the command-line dispatcher and the package's lazy `__getattr__`)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2] / "fgjax"

# module prefix -> layer (docs/architecture.md, "Layers"); the longest matching prefix wins
LAYERS = {
    "fgjax.geometry": 0, "fgjax.version": 0, "fgjax.io": 0, "fgjax.metrics": 0, "fgjax.xla_env": 0, "fgjax.config": 0,
    "fgjax.viz": 0,
    "fgjax.gaussians": 1, "fgjax.ply": 1, "fgjax.cluster": 1, "fgjax.data": 1, "fgjax.provenance": 1,
    "fgjax.render": 2,
    "fgjax.flow": 3, "fgjax.models": 3, "fgjax.train": 3,
    "fgjax.synth": 4,
    "fgjax.method": 5,
    "fgjax.articulate": 6,
    "fgjax.pipeline": 7,
    "fgjax.apps": 8, "fgjax.bench": 8,
    "fgjax.cli": 9, "fgjax": 9,
}
LAZY_OK = {"fgjax.cli", "fgjax"}  # the dispatcher and the package __init__ import lazily, for start-up time


def module_name(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer(mod: str) -> int:
    best = max((p for p in LAYERS if mod == p or mod.startswith(p + ".")), key=len)
    return LAYERS[best]


def fgjax_imports(tree: ast.Module, mod: str, is_pkg: bool, root: Path = ROOT):
    """(imported module, names, lineno, at module top) for every import of an fgjax module."""
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("fgjax"):
                    yield a.name, [], node.lineno, id(node) in top
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                pkg = mod.split(".") if is_pkg else mod.split(".")[:-1]
                base = ".".join(pkg[: len(pkg) - node.level + 1] + ([base] if base else []))
            if not base.startswith("fgjax"):
                continue
            names = [a.name for a in node.names]
            # `from fgjax.x import y` where y is a submodule imports the submodule
            for n in names:
                sub = f"{base}.{n}"
                if (root.parent / Path(*sub.split("."))).with_suffix(".py").exists() or \
                        (root.parent / Path(*sub.split("."))).is_dir():
                    yield sub, [], node.lineno, id(node) in top
                else:
                    yield base, [n], node.lineno, id(node) in top


def collect(root: Path = ROOT):
    graph, problems = {}, []
    for path in sorted(root.rglob("*.py")):
        mod = module_name(path, root)
        tree = ast.parse(path.read_text())
        deps = set()
        for target, names, line, at_top in fgjax_imports(tree, mod, path.name == "__init__.py", root):
            where = f"{path.relative_to(root.parent)}:{line}"
            if target == mod:
                continue
            if layer(target) > layer(mod):
                problems.append(f"{where}: {mod} (layer {layer(mod)}) imports {target} (layer {layer(target)})")
            for n in names:
                if n.startswith("_") and not n.startswith("__"):
                    problems.append(f"{where}: {mod} imports the private name {target}.{n}")
            if not at_top and mod not in LAZY_OK:
                problems.append(f"{where}: {mod} imports {target} inside a function (imports go at module top)")
            deps.add(target)
        graph[mod] = deps
    return graph, problems


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
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

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_imports_point_down_and_sit_at_module_top():
    _, problems = collect()
    assert not problems, "\n".join(problems)


def test_no_import_cycles():
    graph, _ = collect()
    found = cycles(graph)
    assert not found, f"import cycles: {found}"


def test_no_module_over_800_lines():
    long = [f"{p.relative_to(ROOT.parent)}: {len(p.read_text().splitlines())}" for p in ROOT.rglob("*.py")
            if len(p.read_text().splitlines()) > 800]
    assert not long, f"modules over 800 lines: {long}"


def test_checker_catches_an_upward_import_and_a_cycle(tmp_path):
    """The checker itself: an injected upward import, a lazy import and a private name are reported, and a cycle
    is found."""
    pkg = tmp_path / "fgjax"
    (pkg / "render").mkdir(parents=True)
    (pkg / "method").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "render" / "__init__.py").write_text("")
    (pkg / "method" / "__init__.py").write_text("")
    (pkg / "render" / "api.py").write_text("from fgjax.method.stage2 import run_stage2\n")
    (pkg / "method" / "stage2.py").write_text(
        "from fgjax.render.api import _private\n\ndef run_stage2():\n    from fgjax.render import api\n")
    graph, problems = collect(pkg)
    text = "\n".join(problems)
    assert "fgjax.render.api (layer 2) imports fgjax.method.stage2 (layer 5)" in text
    assert "private name fgjax.render.api._private" in text
    assert "inside a function" in text
    assert cycles(graph) == [["fgjax.method.stage2", "fgjax.render.api"]]


@pytest.mark.parametrize("mod", ["fgjax.method.stage2", "fgjax.articulate.pipeline", "fgjax.render.api",
                                 "fgjax.pipeline", "fgjax.data.prepare"])
def test_layers_cover_every_module(mod):
    assert layer(mod) in range(10)
