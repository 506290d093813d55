"""No import cycles among msctl's and components' modules at import time (imports inside
functions are lazy on purpose and do not count)."""

from __future__ import annotations

import ast
from pathlib import Path

from components.pysource import parse_source

REPO = Path(__file__).resolve().parents[1]


def _modules() -> dict[str, Path]:
    found = {}
    for root in ("msctl", "components"):
        for path in (REPO / root).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            found[name.removesuffix(".__init__")] = path
    return found


def _imported_at_import_time(path: Path, modules: dict[str, Path]) -> set[str]:
    """Modules of ours a module's top level imports (not under ``if TYPE_CHECKING``)."""
    out: set[str] = set()
    for node in parse_source(path.read_text(encoding="utf-8"), str(path)).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                out.add(full if full in modules else node.module)
        elif isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
    return {m for m in out if m in modules}


def test_no_module_level_import_cycles() -> None:
    modules = _modules()
    graph = {
        name: _imported_at_import_time(path, modules) - {name} for name, path in modules.items()
    }
    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append([*path[path.index(nxt) :], nxt])
            elif nxt not in state:
                visit(nxt)
        path.pop()
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name)
    assert cycles == []


#: Cycles in the runtime that imports inside functions close, each on purpose: the role
#: table checks interfaces (InterfaceSpec) and the interfaces and robots declare roles (Role).
LAZY_CYCLES_KEPT = [
    {"components.executor.interface", "components.robots", "components.roles"},
]


def _imported_when_run(path: Path, modules: dict[str, Path]) -> set[str]:
    """Modules of ours a module imports anywhere, inside functions too (not for typing)."""
    tree = parse_source(path.read_text(encoding="utf-8"), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = []
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                out.add(full if full in modules else node.module)
        elif isinstance(node, ast.Import):
            out |= {alias.name for alias in node.names}
    return {m for m in out if m in modules}


def _strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Groups of modules that reach each other (Tarjan's algorithm), two or more each."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(graph[node]):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = set()
            while True:
                member = stack.pop()
                group.add(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(group)

    for name in sorted(graph):
        if name not in index:
            visit(name)
    return groups


def test_no_runtime_cycles_even_through_imports_inside_functions() -> None:
    # The builder runs components in an executor, whose claim guard enforces claims: the
    # claims module must not reach back up to the builder or the kind registry (the rule of
    # a module's command inputs is made by components.roles.command_rule).
    modules = {n: p for n, p in _modules().items() if n.startswith("components")}
    graph = {name: _imported_when_run(path, modules) - {name} for name, path in modules.items()}
    groups = _strongly_connected(graph)
    assert [g for g in groups if g not in LAZY_CYCLES_KEPT] == []
    assert not graph["components.claims"] & {"components.build", "components.kinds"}
