"""A wheelhouse: a directory of wheels that lets a robot with no network install the
workspace's external Python dependencies.

Online, ``msctl build --wheelhouse DIR`` fills it with ``pip download`` (for the robot's
platform and Python when ``--platform`` / ``--python-version`` say so); on the robot,
``msctl build --offline --wheelhouse DIR`` installs from it with ``pip install --no-index
--find-links DIR``. Before pip runs offline, :func:`missing` names every requirement that
neither the environment nor the wheelhouse satisfies, so the operator learns all of them
at once, not pip's first.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from packaging.requirements import Requirement
from packaging.tags import sys_tags
from packaging.utils import (
    InvalidSdistFilename,
    InvalidWheelFilename,
    canonicalize_name,
    parse_sdist_filename,
    parse_wheel_filename,
)
from packaging.version import Version

#: Written into a wheelhouse by a download: what it was filled for.
MANIFEST = "msctl-wheelhouse.json"
#: Options of every pip call: no questions, no version nag, plain output for the logs.
PIP_QUIET = ("--disable-pip-version-check", "--no-input", "--no-color", "--progress-bar", "off")


def target_python() -> str:
    """The interpreter of the environment packages install into: the active virtual
    environment's (``$VIRTUAL_ENV``), else the one running msctl."""
    venv = os.environ.get("VIRTUAL_ENV")
    if venv:
        candidate = Path(venv) / "bin" / "python"
        if candidate.exists():
            return str(candidate)
    return sys.executable


def pip(python: str, *args: str) -> list[str]:
    """The argument list of ``python -m pip <args>`` with :data:`PIP_QUIET`."""
    command, *rest = args
    return [python, "-m", "pip", command, *PIP_QUIET, *rest]


@dataclass(frozen=True)
class Distribution:
    """A file of a wheelhouse: its project, version, and whether this computer can use it."""

    name: str
    version: Version
    usable: bool
    file: str


def distributions(wheelhouse: Path, python: str | None = None) -> list[Distribution]:
    """The wheels and source archives in ``wheelhouse``.

    A wheel is usable when one of its tags is supported by this interpreter (the target
    environment's, when it is this one; every wheel otherwise).
    """
    supported = _supported_tags() if python in (None, sys.executable) else None
    found = []
    try:
        names = sorted(os.listdir(wheelhouse))
    except OSError:
        return []
    for name in names:
        try:
            if name.endswith(".whl"):
                project, version, _build, tags = parse_wheel_filename(name)
                usable = supported is None or any(t in supported for t in tags)
            elif name.endswith((".tar.gz", ".zip")):
                project, version = parse_sdist_filename(name)
                usable = True
            else:
                continue
        except (InvalidWheelFilename, InvalidSdistFilename):
            continue
        found.append(Distribution(str(project), version, usable, name))
    return found


@lru_cache(maxsize=1)
def _supported_tags() -> frozenset[object]:
    return frozenset(sys_tags())


def installed(python: str) -> dict[str, str]:
    """``{canonical name: version}`` of the distributions in ``python``'s environment."""
    if python == sys.executable:
        from importlib.metadata import distributions as installed_distributions

        return {
            canonicalize_name(d.metadata["Name"]): d.version
            for d in installed_distributions()
            if d.metadata["Name"]
        }
    script = (
        "import json, importlib.metadata as m;"
        "print(json.dumps({d.metadata['Name']: d.version for d in m.distributions() "
        "if d.metadata['Name']}))"
    )
    result = subprocess.run(
        [python, "-c", script], capture_output=True, text=True, check=False, timeout=60
    )
    if result.returncode != 0:
        return {}
    return {canonicalize_name(k): v for k, v in json.loads(result.stdout).items()}


def missing(
    requirements: Iterable[str],
    wheelhouse: Path | None,
    environment: dict[str, str],
    *,
    python: str | None = None,
) -> list[str]:
    """The requirements that neither ``environment`` (installed versions) nor the
    wheelhouse satisfies, as written.

    Requirements whose marker does not apply here are satisfied.
    """
    available = distributions(wheelhouse, python) if wheelhouse is not None else []
    absent = []
    for text in requirements:
        requirement = Requirement(text)
        if requirement.marker is not None and not requirement.marker.evaluate():
            continue
        name = canonicalize_name(requirement.name)
        have = environment.get(name)
        if have is not None and requirement.specifier.contains(have, prereleases=True):
            continue
        if any(
            canonicalize_name(d.name) == name
            and d.usable
            and requirement.specifier.contains(d.version, prereleases=True)
            for d in available
        ):
            continue
        absent.append(text)
    return absent


def download_command(
    python: str,
    wheelhouse: Path,
    requirements: Sequence[str],
    platform: str | None = None,
    python_version: str | None = None,
) -> list[str]:
    """``pip download`` of ``requirements`` into ``wheelhouse``, for another platform and
    Python when asked (then wheels only: pip cannot build for another platform)."""
    args = ["download", "-d", str(wheelhouse)]
    if platform:
        args += ["--platform", platform]
    if python_version:
        args += ["--python-version", python_version]
    if platform or python_version:
        args += ["--only-binary=:all:"]
    return pip(python, *args, *requirements)


def write_manifest(
    wheelhouse: Path, requirements: Sequence[str], platform: str | None, python_version: str | None
) -> None:
    """Record what the wheelhouse was filled for (read back by ``--offline`` messages)."""
    document = {
        "requirements": sorted(set(requirements)),
        "platform": platform,
        "python_version": python_version,
        "files": sorted(d.file for d in distributions(wheelhouse, python="")),
    }
    (wheelhouse / MANIFEST).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")
