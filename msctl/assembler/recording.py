"""Robot-side recording, a template option: each robot computer records its own modules' data
locally, no radio needed, and ``msctl bag pull HOST`` brings the bags to the ground later.

A template turns it on with::

    [recording]
    robots = true               # a data archiver on every robot computer
    max_file_duration = 60.0    # seconds per MCAP file (a pull resumes per file)
    max_file_size = 8_000_000   # bytes per MCAP file
    compression = "zstd"        # or "none"

The assembler then adds one ``data_archiver`` per robot computer, belonging to the first
module on it (``limb1/data_archiver``, in ``/limb1``: its status is one of that module's
items at the ground), recording into ``$MSCTL_HOME/bags`` of that computer (where its agent
serves them, :mod:`msctl.recorder.shelf`).

What it records is named, never a wildcard: every topic the components of that computer's
modules publish or subscribe to, from their kinds' interfaces. A wildcard subscription on a
robot's router would draw every other computer's data across the radio to it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from components.assembly import ComponentPlan
from msctl.errors import InputError

#: The data archiver's kind, as the registry names it.
ARCHIVER = "data_archiver"
#: Where a robot computer's own bags go, under its ``MSCTL_HOME`` (the shelf it serves).
DIRECTORY = "bags"
#: What ``[recording]`` takes, and the archiver parameter each becomes.
KEYS = {
    "robots": "",
    "max_file_duration": "max_bag_duration",
    "max_file_size": "max_bag_size",
    "compression": "compression",
}
#: Defaults: a minute or 8 MB per file, so a long session is many files and a cut costs at
#: most one file's remainder (at 256 kbit/s, 8 MB is about 4 minutes of radio).
DEFAULTS = {"max_bag_duration": 60.0, "max_bag_size": 8_000_000, "compression": "zstd"}


def parse(table: Mapping[str, Any], path: Path) -> dict[str, Any] | None:
    """A template's ``[recording]`` table: the archiver parameters of every robot computer's
    recorder (``None``: robot-side recording is off).

    Raises:
        InputError: For an unknown key or a bad value, naming the file and field.
    """
    for key in table:
        if key not in KEYS:
            raise InputError(
                f"{path}: field recording.{key} is not a recording setting",
                hint=f"the [recording] table takes {', '.join(KEYS)}",
            )
    robots = table.get("robots", False)
    if not isinstance(robots, bool):
        raise InputError(
            f"{path}: field recording.robots is {robots!r}",
            hint="write robots = true (each robot computer records its own modules) or false",
        )
    params = dict(DEFAULTS)
    for key, param in KEYS.items():
        if param and key in table:
            params[param] = table[key]
    from components.data_archiver.core import ArchiverConfig

    try:
        ArchiverConfig(topics="*", directory=DIRECTORY, **params)
    except (TypeError, ValueError) as exc:
        fields = ", ".join(f"recording.{k}" for k in table if k != "robots") or "recording"
        raise InputError(
            f"{path}: field {fields}: {exc}",
            hint="max_file_duration in seconds and max_file_size in bytes, 0 or more; "
            'compression "zstd" or "none"',
        ) from None
    return params if robots else None


def topics_of(components: Iterable[ComponentPlan], namespaces: Mapping[str, str]) -> list[str]:
    """Every topic the given module components publish or subscribe to, fully qualified, from
    their kinds' interfaces (private ``~`` names left out)."""
    from components import kinds
    from components.executor.interface import InterfaceSpec

    found: set[str] = set()
    for component in components:
        kind = kinds.get(component.kind)
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if not isinstance(spec, InterfaceSpec) or component.module is None:
            continue
        base = namespaces[component.module].rstrip("/")
        for name in [p.topic for p in spec.publish] + [s.topic for s in spec.subscribe]:
            if not name.startswith("~"):
                found.add(name if name.startswith("/") else f"{base}/{name}")
    return sorted(found)


def robot_archivers(
    params: Mapping[str, Any] | None,
    modules: Iterable[tuple[str, str]],
    components: list[ComponentPlan],
) -> list[ComponentPlan]:
    """One data archiver per robot computer, recording its own modules' topics.

    Args:
        params: :func:`parse`'s result (``None``: none).
        modules: ``(slot, host)`` of every module, in template order.
        components: The modules' components planned so far.
    """
    if params is None:
        return []
    by_host: dict[str, list[str]] = {}
    for slot, host in modules:
        by_host.setdefault(host, []).append(slot)
    namespaces = {slot: f"/{slot}" for slots in by_host.values() for slot in slots}
    archivers = []
    for host, slots in by_host.items():
        own = [c for c in components if c.module in slots]
        # Its own status too: diagnostics in the first module's namespace.
        topics = sorted({*topics_of(own, namespaces), f"/{slots[0]}/diagnostics"})
        archivers.append(
            ComponentPlan(
                name=f"{slots[0]}/{ARCHIVER}",
                kind=ARCHIVER,
                host=host,
                module=slots[0],
                namespace=f"/{slots[0]}",
                params={**params, "directory": DIRECTORY, "topics": " ".join(topics)},
            )
        )
    return archivers
