"""Finding and asking every supervisor on the network (this computer's and the agents')."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from msctl.launcher import state
from msctl.launcher.control import AGENT_SRV, encode_args

T = TypeVar("T")
R = TypeVar("R")


def supervisors(node: Any) -> dict[str, str]:
    """``{host namespace: service name}`` of every supervisor on the graph."""
    from components.comm.graph import snapshot
    from components.comm.types import dds_type_name

    # Only the servers of AgentRequest (zid/node/entity/SS/enclave/namespace/node/service/
    # type/hash/qos): not the whole graph's tokens, parsed to keep a few.
    servers = f"*/*/*/SS/*/*/*/*/{dds_type_name(AGENT_SRV)}/*/*"
    found = {}
    graph = snapshot(node.session, node.domain, timeout=3.0, tokens=servers)
    for name, info in graph.services().items():
        if name.startswith("/msctl/") and name.endswith("/request") and AGENT_SRV in info.types:
            found[name[: -len("/request")]] = name
    return found


def at_once(work: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[work(item) for item in items]``, every call in its own thread at the same time.

    For asking a fleet: one after another, loaded computers took the sum of their answer
    times, and a slow one ate the time the others had. Plain threads, because
    concurrent.futures imports logging, which ``msctl ps`` has no use for.

    Raises:
        Exception: The first exception a call raised, after every call ended.
    """
    import threading

    results: list[Any] = [None] * len(items)
    failures: list[BaseException] = []

    def run(index: int, item: T) -> None:
        try:
            results[index] = work(item)
        except BaseException as exc:  # handed to the caller's thread below
            failures.append(exc)

    threads = [
        threading.Thread(target=run, args=(i, item), daemon=True) for i, item in enumerate(items)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failures:
        raise failures[0]
    return results


def ask_all(
    node: Any, verb: str, args: dict[str, Any] | None = None, timeout: float = 3.0
) -> dict[str, Any]:
    """Send one request to every supervisor, all at once; ``{namespace: payload or
    {"error": ...}}``, in the graph's order."""
    from components.comm.services import ServiceError
    from msctl.agent_wire import AgentClient

    clients = {ns: AgentClient(node, service) for ns, service in supervisors(node).items()}

    def ask(client: AgentClient) -> Any:
        try:
            response = client.ask(verb, encode_args(args), timeout=timeout)
        except ServiceError as exc:
            return {"error": str(exc)}
        if response.success:
            return json.loads(response.payload) if response.payload else {}
        return {"error": response.message}

    try:
        return dict(zip(clients, at_once(ask, list(clients.values())), strict=True))
    finally:
        for client in clients.values():
            client.close()


def fleet_state(timeout: float = 3.0) -> tuple[list[dict[str, Any]], list[str]]:
    """Every host's run document (network first, this computer's state file as fallback),
    and notes about what could not be reached."""
    from msctl.errors import NetworkError
    from msctl.plane import connected

    documents: dict[str, dict[str, Any]] = {}
    notes: list[str] = []
    local = state.read_state()
    try:
        with connected("ps") as node:
            for namespace, answer in ask_all(node, "ps", timeout=timeout).items():
                if "error" in answer:
                    notes.append(f"{namespace}: {answer['error']}")
                elif "host" in answer:
                    documents[answer["host"]] = answer
    except NetworkError as exc:
        notes.append(f"network: {exc} (showing this computer's state file only)")
    if local and local.get("host") not in documents:
        if not state.supervisor_alive(local) and local.get("state") != "stopped":
            local = _supervisor_gone(local)
            left = state.groups_left(local)
            if left:
                notes.append(
                    f"the supervisor of {local.get('template')} on {local['host']} (pid "
                    f"{local.get('supervisor_pid')}) is gone; processes left running: "
                    f"{', '.join(left)} — stop them with `msctl down`"
                )
        documents[local["host"]] = local
    return list(documents.values()), notes


def _supervisor_gone(document: dict[str, Any]) -> dict[str, Any]:
    """A state file whose supervisor died: its components are no longer watched, so none is
    "running"; each is "orphaned" while its process group lives, else "stopped"."""
    alive = set(state.groups_left(document))
    components = []
    for c in document.get("components", []):
        orphaned = c.get("process") in alive
        components.append(
            {
                **c,
                "state": "orphaned (supervisor gone)" if orphaned else "stopped",
                "pid": c.get("pid") if orphaned else None,
                "uptime": c.get("uptime", 0.0) if orphaned else 0.0,
            }
        )
    return {**document, "state": "stopped (supervisor gone)", "components": components}
