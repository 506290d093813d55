"""Where the assembler's data lives, and reading it: TOML parsed once per change.

Module types, templates and units are read from the ``assemblies`` and ``calibration``
packages shipped with msctl, or the directories named by ``MSCTL_ASSEMBLIES_DIR`` and
``MSCTL_CALIBRATION_DIR`` (a field team may keep its calibration in its own repository).
Parsed files are cached by modification time, so resolving again in the same process only
stats them.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from msctl.errors import InputError, NotFoundError

T = TypeVar("T")


def _package_dir(package: str) -> Path:
    import importlib.util

    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise NotFoundError(f"the {package!r} data package is not installed", hint="pip install .")
    return Path(next(iter(spec.submodule_search_locations)))


def assemblies_dir() -> Path:
    """Templates live here, module types in ``modules/`` below (``MSCTL_ASSEMBLIES_DIR``)."""
    env = os.environ.get("MSCTL_ASSEMBLIES_DIR")
    return Path(env) if env else _package_dir("assemblies")


def modules_dir() -> Path:
    """Module type files (``<type>.toml``) and their URDFs (``urdf/``)."""
    return assemblies_dir() / "modules"


def calibration_dir() -> Path:
    """One ``<serial>.toml`` per physical unit (``MSCTL_CALIBRATION_DIR``)."""
    env = os.environ.get("MSCTL_CALIBRATION_DIR")
    return Path(env) if env else _package_dir("calibration")


# ---------------------------------------------------------------------------------- caching

_cache: dict[tuple[str, Path], tuple[tuple[int, int], Any]] = {}


def cached(kind: str, path: Path, parse: Callable[[Path], T]) -> T:
    """``parse(path)``, reused while the file's mtime and size are unchanged."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise
    stamp = (st.st_mtime_ns, st.st_size)
    hit = _cache.get((kind, path))
    if hit is not None and hit[0] == stamp:
        return hit[1]
    value = parse(path)
    _cache[(kind, path)] = (stamp, value)
    return value


def forget(kind: str, path: Path) -> None:
    """Parse ``path`` again next time (a file it depends on has changed)."""
    _cache.pop((kind, path), None)


def clear_cache() -> None:
    """Forget every parsed file (tests that edit files within one mtime tick use this)."""
    _cache.clear()


def read_toml(path: Path) -> dict[str, Any]:
    """Parse a TOML file.

    Raises:
        InputError: If it is malformed, naming the line.
    """
    try:
        with path.open("rb") as fh:
            document = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        text = str(exc)
        match = re.search(r"line (\d+)", text)
        where = f"{path}:{match.group(1)}" if match else str(path)
        raise InputError(f"{where}: malformed TOML: {text}", hint="fix the syntax there") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text", hint="save it as UTF-8") from None
    _check_finite(path, document, "")
    return document


def _check_finite(path: Path, value: Any, where: str) -> None:
    """Every number in a data file is finite: nan and inf are never a limit, an offset or
    a gain, and downstream (MuJoCo, JSON, the motors) cannot take them."""
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(
            f"{path}: field {where or '(root)'} is {value}: every number must be finite",
            hint="write a finite number (an unbounded joint is type continuous)",
        )
    if isinstance(value, dict):
        for key, item in value.items():
            _check_finite(path, item, f"{where}.{key}" if where else str(key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_finite(path, item, f"{where}[{i}]")
