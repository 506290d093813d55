"""This computer's part of an assembly an agent is sent: the document checked as data
(plain names only, resolved again from this computer's own module data) and the part of it
planned for this host."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.supervision.contract import RequestError
from msctl.launcher.plan import SAFE_NAME, HostPlan, ProcessPlan, plan_host


def _check_name(value: Any, where: str, *, file_stem: bool = False) -> None:
    """Refuse anything but a plain name (``file_stem``: also no ``/``, it names a data file)."""
    if (
        not isinstance(value, str)
        or not SAFE_NAME.match(value)
        or ".." in value
        or "//" in value
        or (file_stem and "/" in value)
    ):
        raise RequestError(
            f"the assembly sent is refused: {where} {value!r} is not a plain name "
            "(letters, digits, _ . - and / only, no '..')"
        )


def _check_names(assembly: ResolvedAssembly) -> None:
    _check_name(assembly.template, "template", file_stem=True)
    for slot, unit in assembly.units.items():
        _check_name(slot, "slot", file_stem=True)
        _check_name(unit, f"unit of slot {slot}", file_stem=True)
    for host in assembly.hosts:
        _check_name(host, "host")
    for module in assembly.modules:
        _check_name(module.slot, "module slot", file_stem=True)
        _check_name(module.host, f"host of module {module.slot}")
        _check_name(module.unit, f"unit of module {module.slot}", file_stem=True)
        _check_name(module.module_type, f"module type of {module.slot}", file_stem=True)
    for component in assembly.components:
        _check_name(component.name, "component name")
        _check_name(component.host, f"host of component {component.name}")
        if component.kind not in kinds.registry():
            raise RequestError(
                f"the assembly sent is refused: component {component.name} has kind "
                f"{component.kind!r}; known kinds: {', '.join(kinds.names())}"
            )
        if component.module is not None:
            _check_name(component.module, f"module of component {component.name}")
        if not (isinstance(component.namespace, str) and component.namespace.startswith("/")):
            raise RequestError(
                f"the assembly sent is refused: namespace of {component.name} must start with /"
            )
        _check_name(component.namespace[1:], f"namespace of component {component.name}")


def check_assembly(document: Mapping[str, Any], host: str) -> ResolvedAssembly:
    """Read an ``up`` request's assembly document, refusing anything that is not plain data.

    Args:
        document: The lock document as sent.
        host: This computer.

    Returns:
        The assembly (not yet bound to a lock path).

    Raises:
        RequestError: If it does not read as a resolved assembly, holds a name that is not
            plain, a component of unknown kind, or gives this computer nothing to run.
    """
    try:
        assembly = from_document(document)
    except Exception as exc:  # any shape of bad JSON object: a refusal, never a crash
        raise RequestError(f"the assembly sent is not a resolved assembly: {exc}") from None
    _check_names(assembly)
    if not assembly.components_on(host):
        raise RequestError(
            f"{host} has no part in {assembly.template} (its computers: "
            f"{', '.join(assembly.hosts)}); start this agent with MSCTL_HOST set to one of them"
        )
    return assembly


def _same_resolution(sent: Mapping[str, Any], local: Mapping[str, Any]) -> list[str]:
    """Top-level fields where the two documents differ (file paths are each computer's own)."""
    local = json.loads(json.dumps(local))  # tuples -> lists, as the sent one went through JSON

    def comparable(document: Mapping[str, Any]) -> dict[str, Any]:
        out = {k: v for k, v in document.items() if k != "sources"}
        if isinstance(out.get("modules"), list):
            out["modules"] = [
                {k: v for k, v in m.items() if k != "calibration_file"}
                if isinstance(m, dict)
                else m
                for m in out["modules"]
            ]
        return out

    sent, local = comparable(sent), comparable(local)
    return sorted(k for k in {*sent, *local} if sent.get(k) != local.get(k))


def plan_part(assembly: ResolvedAssembly, host: str, sim: bool | None) -> HostPlan:
    """What ``host``'s agent runs: its own part of the assembly, never more.

    A robot computer's part is :func:`~msctl.launcher.plan.plan_host`'s (one simulator for
    the whole assembly, on the first module's computer). A ground-control station is not a
    robot computer, where ``plan_host`` would run the whole assembly (right for a lone
    ``msctl up`` on a laptop, wrong for one agent among several): its agent runs only the
    station's own components, which have no motors to simulate.
    """
    if host in {m.host for m in assembly.modules}:
        return plan_host(assembly, host, sim)
    whole = plan_host(assembly, host, sim=False)
    own = {c.name for c in assembly.components_on(host)}
    processes = [
        ProcessPlan(p.name, tuple(c for c in p.components if c.name in own))
        for p in whole.processes
    ]
    return HostPlan(
        host=host,
        simulated=False,
        off_robot=True,
        processes=[p for p in processes if p.components],
        not_built=[(n, k) for n, k in whole.not_built if n in own],
    )
