"""Declared dependencies match the imported ones: what msctl imports is declared, what is
declared is imported, and what only the tests use is in the test extra."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

from components.pysource import parse_source

REPO = Path(__file__).resolve().parents[1]
OURS = {"msctl", "components", "assemblies", "calibration", "bench", "conftest", "examples"}
#: ROS 2 packages: installed by the ``ros`` extra, each module ``x_y`` from distribution
#: ``ros-x-y`` (the ros-python-wheels names), whether or not they are installed here.
ROS = {"rclpy", "std_msgs", "sensor_msgs", "geometry_msgs", "diagnostic_msgs", "std_srvs"}
OPTIONAL = ROS
#: Modules their distribution's metadata does not list (cmeel wheels install under a prefix).
INSTALLED_BY = {"pinocchio": ["pin"]}
#: Test-extra tools used as programs or plugins rather than imported.
TOOLS = {"pytest-timeout", "pytest-xdist", "ruff", "pytest-textual-snapshot"}
#: colcon and the extensions `msctl build` relies on, run as the ``colcon`` program.
TOOLS |= {
    "colcon-core",
    "colcon-ros",
    "colcon-python-setup-py",
    "colcon-package-selection",
    "colcon-parallel-executor",
    "colcon-recursive-crawl",
}


def _imports(*folders: str) -> set[str]:
    found: set[str] = set()
    for folder in folders:
        for path in (REPO / folder).rglob("*.py"):
            for node in ast.walk(parse_source(path.read_text(encoding="utf-8"), str(path))):
                if isinstance(node, ast.Import):
                    found |= {alias.name.split(".")[0] for alias in node.names}
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    found.add(node.module.split(".")[0])
    local = {path.stem for folder in folders for path in (REPO / folder).glob("*.py")}
    return {m for m in found if m not in sys.stdlib_module_names and m not in OURS | local}


def _name(requirement: str) -> str:
    return re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def _distributions(modules: set[str]) -> dict[str, set[str]]:
    """Module -> the distributions that may have installed it."""
    owners = {**INSTALLED_BY, **packages_distributions()}
    missing = sorted(m for m in modules if m not in owners)
    assert not missing, f"imported but installed by no distribution: {missing}"
    return {m: {d.lower().replace("_", "-") for d in owners[m]} for m in modules}


def _undeclared(imported: dict[str, set[str]], declared: set[str]) -> list[str]:
    return sorted(m for m, dists in imported.items() if not dists & declared)


def _unused(declared: set[str], imported: dict[str, set[str]]) -> list[str]:
    return sorted(declared - set().union(*imported.values()))


def _project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def test_what_msctl_imports_is_declared_and_nothing_else() -> None:
    declared = {_name(r) for r in _project()["dependencies"]}
    # `msctl view` imports its own extra's packages when it runs (and says the pip install
    # without them).
    view = {_name(r) for r in _project()["optional-dependencies"]["view"]}
    imported = _distributions(_imports("msctl", "components") - OPTIONAL)
    assert _undeclared(imported, declared | view) == [], "imported, not declared"
    assert _unused(declared | view, imported) == [], "declared, never imported"


def test_what_only_the_tests_import_is_in_the_test_extra() -> None:
    runtime = {_name(r) for r in _project()["dependencies"]}
    extra = {_name(r) for r in _project()["optional-dependencies"]["test"]}
    imported = _distributions(_imports("tests") - OPTIONAL)
    assert _undeclared(imported, runtime | extra) == [], "tests import these, undeclared"
    # The view extra is in the test extra for msctl view's own tests, imported or not.
    view = {_name(r) for r in _project()["optional-dependencies"]["view"]}
    assert _unused(extra - TOOLS - view, imported) == [], "in the test extra, never imported"
    assert not extra & runtime


def _ros_distribution(module: str) -> str:
    return "ros-" + module.replace("_", "-")


def test_what_is_imported_from_ros_is_the_ros_extra_and_nothing_else() -> None:
    """Every ROS 2 package msctl, its tests or its benchmarks import is in the ``ros`` extra,
    and the extra holds nothing they do not import."""
    extra = {_name(r) for r in _project()["optional-dependencies"]["ros"]}
    imported = _imports("msctl", "components", "tests", "bench") & ROS
    assert "rclpy" in imported
    assert {_ros_distribution(m) for m in imported} == extra
    everything = _imports("msctl", "components", "tests", "bench")
    unknown = sorted(m for m in everything if m.endswith(("_msgs", "_srvs")) and m not in ROS)
    assert unknown == [], "ROS message packages imported but missing from ROS (and the extra)"
