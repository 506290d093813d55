"""A rehearsal while it runs: its link emulator asked, a computer rebooted, its status.

The link emulator answers on its control socket
(:mod:`msctl.rehearse.emulator_control`); a reboot is a power cut of every process of a
computer, then its agent started again.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from msctl.rehearse.computers import RehearseError, describe_processes, kill_all

if TYPE_CHECKING:
    from msctl.rehearse.rehearsal import Rehearsal


def link_request(rehearsal: Rehearsal, request: dict[str, Any]) -> dict[str, Any]:
    """Ask the link emulator; its answer.

    Raises:
        RehearseError: If it is not running, or refused the request.
    """
    from msctl.rehearse.emulator_control import control

    try:
        answer = control(rehearsal.control_socket, request)
    except Exception as exc:
        raise RehearseError(
            f"the link emulator does not answer: {exc}",
            hint="`msctl rehearse down`, then up again",
        ) from exc
    if not answer.get("ok", True):
        raise RehearseError(str(answer.get("error", answer)))
    return answer


def reboot(rehearsal: Rehearsal, name: str, after: float = 0.0) -> int:
    """Kill every process of computer ``name`` at once (a power cut), then, ``after``
    seconds later, start its agent again as systemd would at boot. Returns how many
    processes it killed."""
    computer = rehearsal.computer(name)
    killed = kill_all(computer.netns, grace=0.0, privileges=computer.privileges)
    if after > 0:
        time.sleep(after)
    rehearsal.start_agent(computer)
    return killed


def status(rehearsal: Rehearsal) -> dict[str, Any]:
    """Computers, addresses, processes and each link's profile and counters."""
    try:
        links = link_request(rehearsal, {"op": "status"}).get("hosts", {})
        emulator = "running"
    except RehearseError as exc:
        links, emulator = {}, f"not answering: {exc}"
    computers = []
    for computer in rehearsal.computers:
        computers.append(
            {
                "name": computer.name,
                "role": computer.role,
                "netns": computer.netns,
                "address": computer.address,
                "home": str(computer.home),
                "processes": describe_processes(computer.netns, computer.privileges),
                "link": links.get(computer.name),
            }
        )
    return {
        "template": rehearsal.template,
        "secure": rehearsal.secure,
        "operator": rehearsal.operator,
        "root": str(rehearsal.root),
        "seed": rehearsal.seed,
        "privileges": rehearsal.privileges.to_json(),
        "emulator": emulator,
        "computers": computers,
    }
