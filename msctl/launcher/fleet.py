"""Finding and asking every supervisor on the network (this computer's and the agents')."""

from __future__ import annotations

import json
from typing import Any

from msctl.launcher import state
from msctl.launcher.control import AGENT_SRV, encode_args


def supervisors(node: Any) -> dict[str, str]:
    """``{host namespace: service name}`` of every supervisor on the graph."""
    from components.comm.graph import snapshot

    found = {}
    for name, info in snapshot(node.session, node.domain, timeout=3.0).services().items():
        if name.startswith("/msctl/") and name.endswith("/request") and AGENT_SRV in info.types:
            found[name[: -len("/request")]] = name
    return found


def ask_all(
    node: Any, verb: str, args: dict[str, Any] | None = None, timeout: float = 3.0
) -> dict[str, Any]:
    """Send one request to every supervisor; ``{namespace: payload or {"error": ...}}``."""
    from components.comm.services import ServiceError
    from components.comm.types import registry

    answers: dict[str, Any] = {}
    for namespace, service in supervisors(node).items():
        client = node.client(service, AGENT_SRV)
        try:
            request = registry().msg_class(client.parts.request)(verb=verb, args=encode_args(args))
            response = client.call(request, timeout=timeout)
            if response.success:
                answers[namespace] = json.loads(response.payload) if response.payload else {}
            else:
                answers[namespace] = {"error": response.message}
        except ServiceError as exc:
            answers[namespace] = {"error": str(exc)}
        finally:
            client.close()
    return answers


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
