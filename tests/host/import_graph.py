"""The project's import graph, read from the source with ``ast`` (nothing is imported).

Nodes are the project's modules: every ``.py`` under a top-level package (a directory with an
``__init__.py``, e.g. ``host``) and the flat firmware modules in ``device/`` (named ``device/x``,
since on a segment they sit at the top of ``sys.path``). An edge ``a -> b`` means executing ``a``
imports ``b``: every ``import``/``from ... import`` in ``a`` counts, also inside functions (a lazy
import still closes a circle), except under ``if TYPE_CHECKING:``, and except a package's
``__init__`` importing its own submodule inside a function (a lazy driver registry such as
``device/servos``: it runs after the package is initialised, so it cannot close a circle).
Importing ``p.q.m`` also runs ``p/__init__`` and ``p/q/__init__``: edges to those packages are
added unless ``a`` lives inside them (a package's own ``__init__`` is already running).
"""

from __future__ import annotations

import ast
from pathlib import Path

FIRMWARE_DIR = "device"


def _modules(root: Path) -> dict[str, Path]:
    """Module name -> file, for every project package and the flat firmware directory."""
    mods: dict[str, Path] = {}
    for pkg in sorted(p.parent for p in root.glob("*/__init__.py")):
        for f in pkg.rglob("*.py"):
            rel = f.relative_to(root).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = f
    fw = root / FIRMWARE_DIR
    if fw.is_dir():
        for f in fw.rglob("*.py"):
            rel = f.relative_to(fw).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[f"{FIRMWARE_DIR}/" + ".".join(parts)] = f
    return mods


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", None)
            if name == "TYPE_CHECKING":
                for sub in node.body:
                    skip.update(id(n) for n in ast.walk(sub))
    return skip


def _function_nodes(tree: ast.AST) -> set[int]:
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            for sub in node.body:
                inside.update(id(n) for n in ast.walk(sub))
    return inside


def _imported_names(node: ast.AST, module: str, is_pkg: bool) -> list[str]:
    """Absolute dotted names an import statement may load (the module and, for ``from``, each
    imported name as a possible submodule)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    assert isinstance(node, ast.ImportFrom)
    if node.level:
        base = module.split(".")
        if not is_pkg:
            base = base[:-1]
        base = base[: len(base) - (node.level - 1)]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    return [prefix] + [f"{prefix}.{a.name}" for a in node.names if a.name != "*"]


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the project modules it imports (see the module docstring for the rules)."""
    mods = _modules(root)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        firmware = mod.startswith(FIRMWARE_DIR + "/")
        local = mod.split("/", 1)[1] if firmware else mod
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        skip = _type_checking_nodes(tree)
        lazy = _function_nodes(tree) if is_pkg else set()
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom) or id(node) in skip:
                continue
            for name in _imported_names(node, local, is_pkg):
                target = None
                if firmware and f"{FIRMWARE_DIR}/{name}" in mods:
                    target = f"{FIRMWARE_DIR}/{name}"
                elif name in mods:
                    target = name
                if target is None or target == mod:
                    continue
                if id(node) in lazy and target.startswith(mod + "."):
                    continue  # the package's own submodule, loaded after the package is ready
                graph[mod].add(target)
                if target.startswith(FIRMWARE_DIR + "/"):
                    continue
                parts = target.split(".")
                for i in range(1, len(parts)):
                    pkg = ".".join(parts[:i])
                    if pkg in mods and not (mod == pkg or mod.startswith(pkg + ".")):
                        graph[mod].add(pkg)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
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
