"""``python -m tools import-graph``: the engine's import graph, checked.

Builds the graph of ``engine/`` from the source (``ast``; every ``import`` statement,
including the lazy ones inside functions) and fails when

* a module imports ``bpy`` (the engine runs outside Blender),
* an arrow points up the layer order below (a package may import only packages of a lower
  layer, and modules of its own package),
* modules import each other in a circle,
* a module is longer than ``--max-lines`` (numba kernel modules excepted).

Layers, lowest first (docs/architecture.md explains each)::

    foundations (engine.errors, engine.cameras, engine.colour) < io < raster < spike
    < scene < geometry < evaluate < export < train < cluster < cli

and inside ``engine.train`` the same rule over its parts::

    config < frames < losses < motion < guidance < skipping < loop
"""
from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

HELP = "check the engine's import graph: no cycles, no upward arrows, no bpy, module size"

LAYERS = ("foundations", "io", "raster", "spike", "scene", "geometry", "evaluate", "export", "train", "cluster",
          "cli")
FOUNDATIONS = {"engine", "engine.errors", "engine.cameras", "engine.colour", "engine.numba_cache"}
# `python -m engine` is the command line's front door: it sits with engine.cli, at the top
ENTRY_POINTS = {"engine.__main__": "cli"}
# engine.train's parts, lowest first; a module of engine.train outside them (the package itself) is "config"
TRAIN_PARTS = ("config", "frames", "losses", "motion", "guidance", "skipping", "loop")
MAX_LINES = 500  # "no module over ~500 lines": lint and the test suite check the same bound
KERNEL_MODULES = {"engine.raster._kernels"}  # numba kernels: exempt from the size limit
ENGINE = Path(__file__).resolve().parents[1] / "engine"


def module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> str:
    if module in ENTRY_POINTS:
        return ENTRY_POINTS[module]
    if module in FOUNDATIONS:
        return "foundations"
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else "foundations"


def train_part_of(module: str) -> str | None:
    """The part of ``engine.train`` that ``module`` belongs to (None outside training)."""
    parts = module.split(".")
    if parts[:2] != ["engine", "train"]:
        return None
    return parts[2] if len(parts) > 2 and parts[2] in TRAIN_PARTS else "config"


def _resolve(module: str, is_package: bool, level: int, name: str | None) -> str:
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([name] if name else []))


def imports_of(path: Path, module: str, known: set[str]) -> list[tuple[str, int]]:
    """(imported engine module, line) for every import in ``path``; ``from X import name``
    counts ``X.name`` when that is a module, else ``X``."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out.append((a.name, node.lineno))
        elif isinstance(node, ast.ImportFrom):
            src = _resolve(module, is_package, node.level, node.module) if node.level else (node.module or "")
            for a in node.names:
                sub = f"{src}.{a.name}"
                out.append((sub if sub in known else src, node.lineno))
    return out


def build_graph(root: Path = ENGINE) -> tuple[dict[str, list[tuple[str, int]]], dict[str, Path]]:
    files = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    known = set(files)
    graph = {}
    for mod, path in files.items():
        graph[mod] = imports_of(path, mod, known)
    return graph, files


def find_cycles(graph: dict[str, list[tuple[str, int]]]) -> list[list[str]]:
    """Strongly connected components with more than one module (or a self-import), by
    Tarjan's algorithm over the engine-internal edges. A package's ``__init__`` importing
    its own modules is not an edge back (``engine.train`` -> ``engine.train.loop.run`` is how a
    package exports; the module importing a sibling goes through the sibling, not the package)."""
    edges = {m: sorted({d for d, _ in deps if d in graph and not d == m and not m.startswith(d + ".")})
             for m, deps in graph.items()}
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
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

    sys.setrecursionlimit(max(1000, 10 * len(edges)))
    for v in edges:
        if v not in index:
            visit(v)
    return out


def check(root: Path = ENGINE, max_lines: int = MAX_LINES) -> list[str]:
    """Every problem found, as ``file:line: message`` strings (empty: all good)."""
    graph, files = build_graph(root)
    problems = []
    rank = {name: i for i, name in enumerate(LAYERS)}
    for mod, deps in graph.items():
        rel = files[mod].relative_to(root.parent)
        for dep, line in deps:
            if dep == "bpy" or dep.startswith("bpy."):
                problems.append(f"{rel}:{line}: imports bpy (the engine never imports Blender)")
            if dep.startswith("tools"):
                problems.append(f"{rel}:{line}: imports {dep} (development tools are not shipped)")
            if dep not in graph or dep == mod:
                continue
            a, b = layer_of(mod), layer_of(dep)
            if rank[b] > rank[a]:
                problems.append(f"{rel}:{line}: {mod} ({a}) imports {dep} ({b}): an arrow pointing up")
            ta, tb = train_part_of(mod), train_part_of(dep)
            if ta and tb and mod != "engine.train" and TRAIN_PARTS.index(tb) > TRAIN_PARTS.index(ta):
                problems.append(f"{rel}:{line}: {mod} (train.{ta}) imports {dep} (train.{tb}): an arrow pointing up")
        n = len(files[mod].read_text().splitlines())
        if n > max_lines and mod not in KERNEL_MODULES:
            problems.append(f"{rel}:1: {n} lines (more than {max_lines})")
    for comp in find_cycles(graph):
        problems.append(f"{files[comp[0]].relative_to(root.parent)}:1: import cycle: {' -> '.join(comp)}")
    return problems


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, default=ENGINE, help="the engine package folder")
    parser.add_argument("--max-lines", type=int, default=MAX_LINES,
                        help=f"longest module allowed (default {MAX_LINES}, as the test suite checks)")
    parser.add_argument("--edges", action="store_true", help="print the package-level edges too")


def main(args) -> int:
    problems = check(args.root, args.max_lines)
    graph, _ = build_graph(args.root)
    if args.edges:
        pkg_edges = sorted({(layer_of(m), layer_of(d)) for m, deps in graph.items() for d, _ in deps
                            if d in graph and layer_of(m) != layer_of(d)}, key=lambda e: (LAYERS.index(e[0]), e[1]))
        for a, b in pkg_edges:
            print(f"{a} -> {b}")
    n_edges = sum(1 for deps in graph.values() for d, _ in deps if d in graph)
    for p in problems:
        print(p)
    print(f"{len(graph)} modules, {n_edges} internal imports: "
          + ("OK (no cycles, no upward arrows, no bpy)" if not problems else f"{len(problems)} problem(s)"))
    return 1 if problems else 0
