"""The packages of a workspace and their dependency graph (what ``msctl build`` builds).

A directory is a package when it holds one of these manifests (the first found wins):

- ``msctl-build.toml``: anything else (firmware, say), built by the commands it declares;
- ``package.xml``: a ROS 2 package (built by colcon);
- ``pyproject.toml`` with a ``[project]`` table: a Python package (built by pip).

The search does not enter a package's own subdirectories, hidden directories, colcon's
``build``/``install``/``log`` or a directory holding ``COLCON_IGNORE``.

Dependencies between packages come from their manifests: a Python package's
``[project].dependencies`` naming another workspace package, a ROS package's ``depend``,
``build_depend``, ``buildtool_depend``, ``exec_depend`` (and older ``run_depend``), a
command package's ``depends``. Names match after PEP 503 normalisation, so ``limb_msgs``
in a package.xml and ``limb-msgs`` in a pyproject are the same package. Everything else a
Python package requires is external (from the package index, or a wheelhouse offline).

``msctl-build.toml``::

    name = "limb_firmware"
    depends = ["limb_msgs"]              # other workspace packages (optional)
    commands = [["make", "-j4"], ["make", "install"]]   # argument lists, never a shell
    sources = ["src/**", "Makefile"]     # what a change is looked for in (default: all)
"""

from __future__ import annotations

import heapq
import os
import re
import tomllib
import xml.etree.ElementTree as ElementTree
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from packaging.requirements import InvalidRequirement, Requirement

from msctl.errors import InputError, NotFoundError, did_you_mean

#: Manifests, in the order one directory's are preferred.
MANIFESTS = {"msctl-build.toml": "command", "package.xml": "ros", "pyproject.toml": "python"}
#: Directories never searched (colcon's output, caches, environments).
SKIPPED_DIRS = {"build", "install", "log", "node_modules", "__pycache__", "dist", "venv"}
#: A directory holding one of these is not searched.
IGNORE_MARKERS = ("COLCON_IGNORE", "AMENT_IGNORE")
#: package.xml tags whose packages must be built first.
ROS_DEPENDS = (
    "depend",
    "build_depend",
    "buildtool_depend",
    "build_export_depend",
    "exec_depend",
    "run_depend",
)
_COMMAND_KEYS = ("name", "depends", "commands", "sources")
_PLAIN_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def canonical(name: str) -> str:
    """A package name as compared (PEP 503): lower case, runs of ``-_.`` as one ``-``."""
    return re.sub(r"[-_.]+", "-", name).lower()


@dataclass(frozen=True)
class Package:
    """One package of the workspace.

    Attributes:
        name: Its name as its manifest writes it.
        type: ``python``, ``ros`` or ``command``.
        path: Its directory.
        manifest: The manifest file it was found by.
        depends: The names its manifest depends on (workspace packages or not).
        requires: A Python package's requirement strings (all of them).
        build_requires: A Python package's ``[build-system].requires``.
        commands: A command package's commands (argument lists).
        sources: A command package's source globs (empty: every file).
        build_type: A ROS package's build type (``ament_cmake``, ``ament_python`` ...).
    """

    name: str
    type: str
    path: Path
    manifest: Path
    depends: tuple[str, ...] = ()
    requires: tuple[str, ...] = ()
    build_requires: tuple[str, ...] = ()
    commands: tuple[tuple[str, ...], ...] = ()
    sources: tuple[str, ...] = ()
    build_type: str = ""

    @property
    def key(self) -> str:
        """Its name as compared (:func:`canonical`)."""
        return canonical(self.name)


@dataclass
class Graph:
    """A workspace's packages and the dependencies between them.

    Attributes:
        root: The workspace directory.
        packages: Every package, by :attr:`Package.key`.
        edges: Each package's workspace dependencies (keys), in its manifest's order.
        notes: Manifests found but not taken as packages, and why.
    """

    root: Path
    packages: dict[str, Package]
    edges: dict[str, tuple[str, ...]]
    notes: list[str] = field(default_factory=list)

    def names(self) -> list[str]:
        """Every package's name."""
        return [p.name for p in self.packages.values()]

    def key_of(self, name: str) -> str:
        """The key of the package named ``name``.

        Raises:
            NotFoundError: Naming the nearest package names.
        """
        key = canonical(name)
        if key not in self.packages:
            hint = did_you_mean(name, self.names())
            raise NotFoundError(
                f"no package {name!r} in {self.root}",
                hint=hint or f"its packages: {', '.join(sorted(self.names())) or 'none'}",
            )
        return key

    def up_to(self, names: Iterable[str]) -> list[str]:
        """The named packages and everything they depend on (colcon's ``--packages-up-to``),
        in build order."""
        wanted: set[str] = set()
        stack = [self.key_of(n) for n in names]
        while stack:
            key = stack.pop()
            if key not in wanted:
                wanted.add(key)
                stack.extend(self.edges[key])
        return [k for k in self.order() if k in wanted]

    def order(self) -> list[str]:
        """Every package, each after its dependencies (ties by name, so it is stable)."""
        waiting = {k: set(deps) for k, deps in self.edges.items()}
        users: dict[str, list[str]] = {k: [] for k in self.edges}
        for key, deps in self.edges.items():
            for dep in deps:
                users[dep].append(key)
        ready = [k for k, deps in waiting.items() if not deps]
        heapq.heapify(ready)
        ordered = []
        while ready:
            key = heapq.heappop(ready)
            ordered.append(key)
            for user in users[key]:
                waiting[user].discard(key)
                if not waiting[user]:
                    heapq.heappush(ready, user)
        return ordered

    def external_requirements(self, key: str) -> list[str]:
        """A Python package's requirements that no workspace package satisfies."""
        package = self.packages[key]
        return [r for r in package.requires if canonical(Requirement(r).name) not in self.packages]

    def to_dict(self) -> dict[str, Any]:
        """The graph as ``msctl build --list --json`` prints it."""
        return {
            "workspace": str(self.root),
            "packages": [
                {
                    "name": self.packages[k].name,
                    "type": self.packages[k].type,
                    "path": str(self.packages[k].path),
                    "depends": [self.packages[d].name for d in self.edges[k]],
                    "external": self.external_requirements(k)
                    if self.packages[k].type == "python"
                    else [],
                }
                for k in self.order()
            ],
            "notes": self.notes,
        }


# --------------------------------------------------------------------------- discovery
def find_packages(root: Path) -> Graph:
    """Find every package under ``root`` and link their dependencies.

    Raises:
        InputError: For a malformed manifest (naming the file and the field), two packages
            of one name, or a dependency cycle.
    """
    found: list[Package] = []
    notes: list[str] = []
    for directory, subdirs, files in os.walk(root):
        here = Path(directory)
        if any(marker in files for marker in IGNORE_MARKERS):
            subdirs[:] = []
            continue
        package = None
        for manifest, package_type in MANIFESTS.items():
            if manifest in files:
                package = _read(here / manifest, package_type, notes)
                if package is not None:
                    break
        if package is not None:
            found.append(package)
            subdirs[:] = []
            continue
        subdirs[:] = sorted(
            d
            for d in subdirs
            if not d.startswith(".") and d not in SKIPPED_DIRS and not d.endswith(".egg-info")
        )
    return link(root, found, notes)


def link(root: Path, packages: Sequence[Package], notes: Sequence[str] = ()) -> Graph:
    """The graph of ``packages``: workspace dependencies resolved, names unique, no cycle.

    Raises:
        InputError: For two packages of one name, or a dependency cycle.
    """
    by_key: dict[str, Package] = {}
    for package in packages:
        other = by_key.get(package.key)
        if other is not None:
            raise InputError(
                f"two packages are named {package.name!r}: {other.manifest} and {package.manifest}",
                hint="rename one, or put COLCON_IGNORE in the directory of the one not meant",
            )
        by_key[package.key] = package
    for package in by_key.values():
        _refuse_unknown_depends(package, by_key)
    edges = {
        key: tuple(
            dict.fromkeys(
                canonical(d) for d in p.depends if canonical(d) in by_key and canonical(d) != key
            )
        )
        for key, p in by_key.items()
    }
    graph = Graph(root, dict(sorted(by_key.items())), edges, list(notes))
    _refuse_cycles(graph)
    return graph


def _refuse_unknown_depends(package: Package, by_key: dict[str, Package]) -> None:
    """A command package's ``depends`` names workspace packages only (unlike a Python or
    ROS package's, which name external ones too): a name that is not one is a typo, and
    building without it would build the package before what it needs.

    Raises:
        InputError: Naming the package, the unknown dependency and the file.
    """
    if package.type != "command":
        return
    for name in package.depends:
        if canonical(name) not in by_key:
            known = [p.name for p in by_key.values() if p.key != package.key]
            raise InputError(
                f"{package.manifest}: package {package.name!r} depends on {name!r}, "
                "which is no package of the workspace",
                hint=did_you_mean(name, known)
                or "fix the name in 'depends', or clone the repository holding it (`msctl update`)",
            )


def _refuse_cycles(graph: Graph) -> None:
    if len(graph.order()) == len(graph.packages):
        return
    # Walk from a package left out of the order until a package repeats: that is a cycle.
    ordered = set(graph.order())
    start = next(k for k in graph.packages if k not in ordered)
    path = [start]
    while True:
        nxt = next(d for d in graph.edges[path[-1]] if d not in ordered)
        if nxt in path:
            cycle = [*path[path.index(nxt) :], nxt]
            break
        path.append(nxt)
    names = " -> ".join(graph.packages[k].name for k in cycle)
    files = ", ".join(str(graph.packages[k].manifest) for k in cycle[:-1])
    raise InputError(
        f"dependency cycle: {names}",
        hint=f"remove one of these dependencies ({files})",
    )


def _read(manifest: Path, package_type: str, notes: list[str]) -> Package | None:
    return _READERS[package_type](manifest, notes)


def _toml(manifest: Path) -> dict[str, Any]:
    try:
        return tomllib.loads(manifest.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{manifest}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{manifest}: cannot read it: {exc}") from None


def _read_pyproject(manifest: Path, notes: list[str]) -> Package | None:
    data = _toml(manifest)
    project = data.get("project")
    if not isinstance(project, dict) or not isinstance(project.get("name"), str):
        notes.append(
            f"{manifest}: no [project] name, so not built (add one, or a msctl-build.toml)"
        )
        return None
    name = project["name"]
    if "dependencies" in project.get("dynamic", []):
        notes.append(f"{manifest}: its dependencies are dynamic, so none is known to msctl")
    requires = project.get("dependencies", [])
    if not isinstance(requires, list) or not all(isinstance(r, str) for r in requires):
        raise InputError(f"{manifest}: [project].dependencies must be a list of strings")
    system = data.get("build-system", {})
    build_requires = system.get("requires", ["setuptools>=40.8.0"])
    if not isinstance(build_requires, list) or not all(isinstance(r, str) for r in build_requires):
        raise InputError(f"{manifest}: [build-system].requires must be a list of strings")
    depends = []
    for text in [*requires, *build_requires]:
        try:
            requirement = Requirement(text)
        except InvalidRequirement as exc:
            raise InputError(f"{manifest}: requirement {text!r} is not valid: {exc}") from None
        if text in requires:
            depends.append(requirement.name)
    return Package(
        name=name,
        type="python",
        path=manifest.parent,
        manifest=manifest,
        depends=tuple(depends),
        requires=tuple(requires),
        build_requires=tuple(build_requires),
    )


def _read_package_xml(manifest: Path, notes: list[str]) -> Package:
    try:
        root = ElementTree.parse(manifest).getroot()
    except ElementTree.ParseError as exc:
        raise InputError(f"{manifest}: not valid XML: {exc}") from None
    except OSError as exc:
        raise InputError(f"{manifest}: cannot read it: {exc}") from None
    name = (root.findtext("name") or "").strip()
    if root.tag != "package" or not name:
        raise InputError(
            f"{manifest}: not a ROS package manifest (a <package> with a <name>)",
            hint="or put COLCON_IGNORE beside it if it is not a package",
        )
    depends = [
        (element.text or "").strip()
        for tag in ROS_DEPENDS
        for element in root.findall(tag)
        if (element.text or "").strip()
    ]
    build_type = (root.findtext("export/build_type") or "ament_cmake").strip()
    return Package(
        name=name,
        type="ros",
        path=manifest.parent,
        manifest=manifest,
        depends=tuple(dict.fromkeys(depends)),
        build_type=build_type,
    )


def _read_command(manifest: Path, notes: list[str]) -> Package:
    data = _toml(manifest)
    for key in data:
        if key not in _COMMAND_KEYS:
            raise InputError(
                f"{manifest}: unknown field {key!r}",
                hint=did_you_mean(key, _COMMAND_KEYS) or f"its fields: {', '.join(_COMMAND_KEYS)}",
            )
    name = data.get("name")
    if not isinstance(name, str) or not _PLAIN_NAME.match(name):
        raise InputError(
            f"{manifest}: field 'name' must be a plain package name",
            hint='e.g. name = "limb_firmware"',
        )
    depends = data.get("depends", [])
    if not isinstance(depends, list) or not all(isinstance(d, str) for d in depends):
        raise InputError(f"{manifest}: field 'depends' must be a list of package names")
    commands = data.get("commands")
    if (
        not isinstance(commands, list)
        or not commands
        or not all(
            isinstance(c, list) and c and all(isinstance(a, str) for a in c) for c in commands
        )
    ):
        raise InputError(
            f"{manifest}: field 'commands' must be a list of commands, each a list of "
            "arguments (no shell)",
            hint='e.g. commands = [["make", "-j4"], ["make", "install"]]',
        )
    sources = data.get("sources", [])
    if not isinstance(sources, list) or not all(isinstance(s, str) for s in sources):
        raise InputError(f"{manifest}: field 'sources' must be a list of globs")
    for pattern in sources:
        if pattern.startswith("/") or ".." in Path(pattern).parts:
            raise InputError(f"{manifest}: source glob {pattern!r} leaves the package directory")
    return Package(
        name=name,
        type="command",
        path=manifest.parent,
        manifest=manifest,
        depends=tuple(depends),
        commands=tuple(tuple(c) for c in commands),
        sources=tuple(sources),
    )


#: How each type of manifest is read.
_READERS = {"python": _read_pyproject, "ros": _read_package_xml, "command": _read_command}


# --------------------------------------------------------------------------- sources
#: Never sources: VCS data, caches and build output inside a package directory.
_NOT_SOURCES = {".git", "__pycache__", "build", "dist", ".msctl", ".pytest_cache", ".tox"}


def source_files(package: Package) -> list[Path]:
    """The files whose content decides whether ``package`` must be built again."""
    if package.sources:
        found: set[Path] = set()
        for pattern in package.sources:
            for path in package.path.glob(pattern):
                if path.is_file():
                    found.add(path)
        found.add(package.manifest)
        return sorted(found)
    files = []
    for directory, subdirs, names in os.walk(package.path):
        subdirs[:] = sorted(
            d
            for d in subdirs
            if d not in _NOT_SOURCES and not d.startswith(".") and not d.endswith(".egg-info")
        )
        for name in sorted(names):
            if not name.endswith((".pyc", ".pyo", "~")):
                files.append(Path(directory) / name)
    return files
