"""The runtime (``components``) never imports the operator's CLI (``msctl``): a component,
a backend or the data plane must ship and run without it. Every import counts, those inside
functions too (a lazy import is still a dependency when it runs)."""

from __future__ import annotations

import ast
from pathlib import Path

from components.pysource import parse_source

REPO = Path(__file__).resolve().parents[1]


def _msctl_imports(path: Path) -> set[str]:
    """Every ``msctl`` module ``path`` imports, at its top level or inside a function."""
    found: set[str] = set()
    for node in ast.walk(parse_source(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        found |= {name for name in names if name == "msctl" or name.startswith("msctl.")}
    return found


def runtime_imports_of_msctl() -> set[tuple[str, str]]:
    """(file, msctl module) for each import of ``msctl`` under ``components``."""
    return {
        (path.relative_to(REPO).as_posix(), module)
        for path in sorted((REPO / "components").rglob("*.py"))
        for module in _msctl_imports(path)
    }


def test_the_runtime_imports_nothing_from_msctl() -> None:
    # The last three (the supervisors' control contract, this_host) moved to
    # components.supervision with the typed protocol (cf48467): nothing is allowed now.
    assert runtime_imports_of_msctl() == set(), (
        "components must not import msctl (the runtime ships without the CLI): move what "
        "the component needs under components/"
    )


def test_imports_inside_functions_are_seen(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text(
        "import os\n"
        "def f():\n"
        "    from msctl.launcher.control import AGENT_SRV\n"
        "    import msctl.errors as e\n"
        "class C:\n"
        "    def g(self):\n"
        "        if True:\n"
        "            from msctl import quick\n"
    )
    assert _msctl_imports(module) == {"msctl.launcher.control", "msctl.errors", "msctl"}
