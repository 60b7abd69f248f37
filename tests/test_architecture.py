"""The rules of docs/architecture.md, checked on the package's own imports.

- **Stages to the left.** Every module belongs to a layer (:data:`LAYERS`, the
  data flow of the map: load -> simplify -> progressive -> packets -> service ->
  api); a module imports only modules of its own layer or of layers before it.
- **No cycle.** No two modules import each other, directly or through others,
  deferred imports inside functions included (a deferred import hides a cycle
  from Python, not from the reader).
- **No private names across modules.** ``from .x import _name`` only within
  one module's own file; another module's ``_name`` is its business.
- **The map is whole.** Every module of ``lodserver/`` and every viewer module
  of ``static/`` is named in ``docs/architecture.md``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "lodserver"

# The package's layers, in data-flow order: the first name that a module's dotted
# name starts with gives its layer. A module may import its own layer and those before.
LAYERS = [
    ("lodserver.mesh", "lodserver.overlap", "lodserver.numba_cache", "lodserver.heap"),
    ("lodserver.io",),
    ("lodserver.simplify", "lodserver.metrics", "lodserver.bake"),
    ("lodserver.options",),
    ("lodserver.progressive",),
    ("lodserver.build", "lodserver.packets"),
    ("lodserver.scene", "lodserver.chains"),
    ("lodserver.folders", "lodserver.schedulers"),
    ("lodserver.service",),
    ("lodserver.pipeline",),
    ("lodserver.api",),
    ("lodserver.cli", "lodserver.first_run"),
]
# The package's own __init__ is its public face: it may import from any layer, and
# only the last layer (the command line) may import it.
TOP = "lodserver"


def _modules() -> dict[str, Path]:
    """Dotted name -> file, for every module of the package (a package by its __init__)."""
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


MODULES = _modules()


def _imports(name: str, path: Path):
    """(imported module, imported name or None, line) for each lodserver import of a module."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target == TOP or target.startswith(TOP + "."):
                for alias in node.names:
                    submodule = f"{target}.{alias.name}"
                    if submodule in MODULES:
                        yield submodule, None, node.lineno
                    else:
                        yield target, alias.name, node.lineno
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == TOP or alias.name.startswith(TOP + "."):
                    yield alias.name, None, node.lineno


def _layer(name: str) -> int:
    for rank, prefixes in enumerate(LAYERS):
        if any(name == p or name.startswith(p + ".") for p in prefixes):
            return rank
    raise AssertionError(f"{name} is in no layer of LAYERS: add it where the data flow puts it")


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name, path in MODULES.items():
        graph[name] = {target for target, _, _ in _imports(name, path)
                       if target in MODULES and target != name}
    return graph


def test_every_module_imports_only_its_own_stage_and_those_to_its_left():
    wrong = []
    for name, path in MODULES.items():
        if name == TOP:
            continue
        for target, _, line in _imports(name, path):
            if target != TOP and _layer(target) > _layer(name):
                wrong.append(f"{path.relative_to(REPO)}:{line} imports {target}")
            elif target == TOP and _layer(name) < len(LAYERS) - 1:
                wrong.append(f"{path.relative_to(REPO)}:{line} imports the package's public face")
    assert wrong == []


def test_no_module_imports_a_private_name_of_another():
    wrong = [f"{path.relative_to(REPO)}:{line} imports {target}.{imported}"
             for name, path in MODULES.items()
             for target, imported, line in _imports(name, path)
             if imported and imported.startswith("_") and not imported.startswith("__")]
    assert wrong == []


def test_no_import_cycle():
    graph = _graph()
    # the package __init__ files re-export their stage: a cycle through one of
    # them is still a cycle, so they stay in the graph
    state, cycles = {}, []

    def visit(node, trail):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                cycles.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    # a package importing its own submodules is how it re-exports them; a
    # submodule importing its package's __init__ back is the cycle to refuse
    real = [c for c in cycles
            if not all(a.startswith(b + ".") or b.startswith(a + ".") for a, b in zip(c, c[1:]))]
    assert real == []


def test_the_map_names_every_module_and_viewer_file():
    text = (REPO / "docs" / "architecture.md").read_text()
    named = set(re.findall(r"`([\w/-]+\.(?:py|js))`", text))
    missing = sorted(str(path.relative_to(PACKAGE)) for path in PACKAGE.rglob("*.py")
                     if path.name != "__init__.py" and path.name not in named
                     and str(path.relative_to(PACKAGE)) not in named)
    missing += sorted(path.name for path in (REPO / "static").glob("*.js")
                      if path.name not in named)
    assert missing == [], f"docs/architecture.md does not name {missing}"
