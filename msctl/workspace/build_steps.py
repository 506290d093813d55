"""What building a package runs: how to build (the options) and each package type's steps.

- Python: ``pip install --no-deps`` (``-e`` when editable), or ``pip wheel --no-deps``;
- ROS 2: ``colcon build --packages-select``, shown the directories of the ROS packages it
  depends on;
- command: the commands of its ``msctl-build.toml``, in its directory, no shell.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from msctl.workspace.packages import Graph, Package
from msctl.workspace.wheelhouse import pip, target_python


@dataclass(frozen=True)
class BuildOptions:
    """How to build.

    Attributes:
        jobs: Packages built at once.
        offline: No network: pip uses only the wheelhouse (``--no-index``).
        wheelhouse: A wheelhouse to fill (online) or install from (offline).
        platform: Download wheels for this platform (e.g. ``manylinux2014_aarch64``):
            download only, nothing is built here.
        python_version: Download wheels for this Python (e.g. ``3.11``): download only.
        editable: Install Python packages editable (``pip install -e``).
        wheels: Build Python packages' wheels into this directory instead of installing.
        force: Build every selected package, changed or not.
        keep_going: Build the independent packages after a failure.
        timeout: Seconds one package's build may take (``None``: no bound); a package
            over it is stopped, with every process it started, and fails naming it.
        python: The interpreter of the environment to install into.
        colcon: The colcon program (``None``: not available).
    """

    jobs: int = field(default_factory=lambda: os.cpu_count() or 2)
    offline: bool = False
    wheelhouse: Path | None = None
    platform: str | None = None
    python_version: str | None = None
    editable: bool = False
    wheels: Path | None = None
    force: bool = False
    keep_going: bool = True
    timeout: float | None = None
    python: str = field(default_factory=target_python)
    colcon: str | None = field(default_factory=lambda: shutil.which("colcon"))

    @property
    def download_only(self) -> bool:
        """Filling a wheelhouse for another platform or Python: nothing to build here."""
        return bool(self.wheelhouse and (self.platform or self.python_version))


@dataclass(frozen=True)
class Step:
    """One command of a package's build.

    Attributes:
        label: What it is, in the messages (``dependencies``, ``install``, ``colcon`` ...).
        argv: The command (no shell).
        cwd: Where it runs.
        serial: Run under the builder's lock (pip installing shared dependencies).
        expect: Text its output must hold for a success (a tool that exits 0 having done
            nothing, as colcon does for a package it did not find, has failed).
        unmet: What to say when ``expect`` is missing.
    """

    label: str
    argv: tuple[str, ...]
    cwd: Path
    serial: bool = False
    expect: str = ""
    unmet: str = ""


def package_steps(package: Package, graph: Graph, options: BuildOptions) -> list[Step]:
    """The commands building ``package`` (its external requirements' install aside,
    which is decided when it runs)."""
    if package.type == "python":
        return _python_steps(package, options)
    if package.type == "ros":
        return _ros_steps(package, graph, options)
    return _command_steps(package)


def _python_steps(package: Package, options: BuildOptions) -> list[Step]:
    if options.wheels is not None:
        args = ["wheel", "--no-deps", *pip_index(options), "-w", str(options.wheels)]
        argv = pip(options.python, *args, str(package.path))
        return [Step("wheel", tuple(argv), package.path)]
    args = ["install", "--no-deps", *pip_index(options), *_isolation(options)]
    args += ["-e", str(package.path)] if options.editable else [str(package.path)]
    return [Step("install", tuple(pip(options.python, *args)), package.path)]


def _ros_steps(package: Package, graph: Graph, options: BuildOptions) -> list[Step]:
    root = graph.root
    # colcon builds a package in the environment of the installs of the dependencies it
    # discovers: it must be shown their directories too (selecting only this one), or a
    # dependent builds without them (an ament_cmake find_package fails).
    base_paths = [str(package.path)]
    base_paths += [str(graph.packages[k].path) for k in _ros_dependencies(package, graph)]
    argv = (
        options.colcon or "colcon",
        "build",
        "--base-paths",
        *base_paths,
        "--packages-select",
        package.name,
        "--build-base",
        str(root / "build"),
        "--install-base",
        str(root / "install"),
    )
    unmet = (
        f"colcon exited 0 without building {package.name}: it did not take "
        f"{package.manifest} for a ROS package (see `colcon --log-level info list "
        f"--base-paths {package.path}`: a malformed package.xml, e.g. a maintainer's "
        "email, makes colcon ignore it)"
    )
    return [Step("colcon", argv, root, expect=f"Finished <<< {package.name}", unmet=unmet)]


def _ros_dependencies(package: Package, graph: Graph) -> list[str]:
    """Every ROS package ``package`` depends on, directly or not, in build order."""
    wanted: set[str] = set()
    stack = list(graph.edges[package.key])
    while stack:
        key = stack.pop()
        if key not in wanted:
            wanted.add(key)
            stack.extend(graph.edges[key])
    return [k for k in graph.order() if k in wanted and graph.packages[k].type == "ros"]


def _command_steps(package: Package) -> list[Step]:
    return [
        Step(f"command {i + 1} ({argv[0]})", tuple(argv), package.path)
        for i, argv in enumerate(package.commands)
    ]


def pip_index(options: BuildOptions) -> list[str]:
    """pip's index arguments: none offline, the wheelhouse's wheels when there is one."""
    links = ["--find-links", str(options.wheelhouse)] if options.wheelhouse else []
    return (["--no-index"] if options.offline else []) + links


def _isolation(options: BuildOptions) -> list[str]:
    # Offline with no wheelhouse, an isolated build could not get its backend: use the
    # environment's own (setuptools ...), as colcon does.
    return ["--no-build-isolation"] if options.offline and not options.wheelhouse else []
