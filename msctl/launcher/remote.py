"""Acting on components wherever they run: find the host's supervisor, send it a request."""

from __future__ import annotations

from typing import Any

from msctl.errors import MsctlError, NetworkError, NotFoundError
from msctl.launcher.control import RequestError


def _host_of(component: str, node: Any) -> str:
    from msctl.launcher import state
    from msctl.launcher.fleet import ask_all

    for namespace, answer in ask_all(node, "ps").items():
        for c in answer.get("components", []):
            if component in (c["name"], c.get("process")):
                return answer["host"]
        for p in answer.get("processes", []):
            if component == p["name"]:
                return answer["host"]
        del namespace
    local = state.read_state()
    if local and state.supervisor_alive(local):
        return local["host"]
    raise NotFoundError(
        f"no running supervisor knows {component!r}",
        hint="see what runs with `msctl ps`",
    )


def control_component(verb: str, component: str) -> None:
    """Send ``verb`` (restart/stop/start) for ``component`` to the host that runs it."""
    from components.comm.services import ServiceTimeout
    from msctl.console import err
    from msctl.launcher.control import call_supervisor
    from msctl.plane import connected

    with connected(verb) as node:
        host = _host_of(component, node)
        try:
            answer = call_supervisor(node, host, verb, {"component": component})
        except ServiceTimeout as exc:
            raise NetworkError(f"the supervisor of {host} did not answer: {exc}") from exc
        except RequestError as exc:
            raise MsctlError(str(exc)) from exc
    err.print(
        f"[green]{verb}[/] {component} on {host}: process {answer['process']} is {answer['state']}",
        highlight=False,
    )


def up_all(assembly: Any, sim: bool | None, speed: float, timeout: float) -> None:
    """Start every host's part through its agent; name the unreachable ones."""
    import json
    import time

    from rich.table import Table

    from components.comm.services import ServiceTimeout
    from msctl.console import err
    from msctl.launcher.control import call_supervisor
    from msctl.plane import connected

    document = json.loads(assembly.lock_path.read_text()) if assembly.lock_path else {}
    hosts = list(dict.fromkeys(assembly.hosts))
    started: list[str] = []
    unreachable: list[tuple[str, str]] = []
    with connected("up_all") as node:
        for host in hosts:
            try:
                call_supervisor(
                    node,
                    host,
                    "up",
                    {"assembly": document, "sim": sim, "speed": speed},
                    timeout=10.0,
                )
                started.append(host)
            except (ServiceTimeout, RequestError) as exc:
                unreachable.append((host, str(exc)))
        deadline = time.monotonic() + timeout
        status: dict[str, dict[str, Any]] = {}
        while started and time.monotonic() < deadline:
            status = {}
            for host in started:
                try:
                    status[host] = call_supervisor(node, host, "ps", timeout=2.0)
                except (ServiceTimeout, RequestError) as exc:
                    status[host] = {"error": str(exc)}
            done = all(
                d.get("components") and all(c["state"] == "running" for c in d["components"])
                for d in status.values()
            )
            if done:
                break
            time.sleep(0.2)
    table = Table(title=f"{assembly.template}: every host", title_justify="left")
    for column in ("host", "components", "healthy", "note"):
        table.add_column(column)
    for host in started:
        d = status.get(host, {})
        components = d.get("components", [])
        healthy = sum(c["state"] == "running" for c in components)
        table.add_row(host, str(len(components)), str(healthy), d.get("error", ""))
    for host, why in unreachable:
        table.add_row(host, "-", "-", f"[red]unreachable: {why}[/]")
    err.print(table)
    if unreachable:
        names = ", ".join(h for h, _ in unreachable)
        raise NetworkError(
            f"no agent answered for {names}",
            hint="start `msctl agent` there (or `msctl agent install`), check its network",
        )
