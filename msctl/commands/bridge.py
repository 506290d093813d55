"""``msctl bridge``: relay between msctl's Zenoh data plane and a DDS ROS 2 graph, both ways.

Runs until Ctrl-C (or SIGTERM): every selected topic and service seen on either graph is
relayed to the other, as CDR bytes, and a line is printed as each relay starts or stops and
for each topic skipped (a type one side cannot carry). The DDS side is rclpy on this
computer's ROS 2 (the ``ros`` extra: Fast DDS), on ``ROS_DOMAIN_ID``. At the end, what was
relayed (``--json``: one JSON document on stdout).
"""

from __future__ import annotations

import signal
import threading
from dataclasses import asdict
from typing import Any

import typer

from msctl.errors import InputError

COMMAND_SETTINGS = {"help": "Relay topics and services between msctl and a DDS ROS 2 graph."}


def _names(values: list[str] | None) -> str:
    return " ".join(v for value in values or () for v in value.replace(",", " ").split())


def command(
    topics: list[str] = typer.Option(
        None, "--topics", "-t", help="Topics (or patterns like /limb1/*) to relay; repeatable."
    ),
    services: list[str] = typer.Option(
        None, "--services", "-s", help="Services (or patterns) to relay; repeatable."
    ),
    everything: bool = typer.Option(
        False, "--all", "-a", help="Relay every topic and service (ROS's and msctl's own left out)."
    ),
    name: str = typer.Option("msctl_bridge", "--name", help="The bridge's node on both sides."),
    json_output: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Relay topics and services between msctl's Zenoh plane and ROS 2 on DDS until Ctrl-C."""
    from components.bridge.core import Selection
    from components.bridge.relay import Bridge
    from components.comm.names import NameError_, check_node_name, qualify
    from components.ros import RclpyUnavailable
    from msctl.console import err
    from msctl.plane import connected

    try:
        check_node_name(name)
        selection = Selection.from_text(
            "*" if everything else " ".join(qualify(t, "/") for t in _names(topics).split()),
            "*" if everything else " ".join(qualify(s, "/") for s in _names(services).split()),
        )
    except (ValueError, NameError_) as exc:
        raise InputError(str(exc)) from None
    stop = threading.Event()
    previous = {
        signum: signal.signal(signum, lambda *_: stop.set())
        for signum in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        with connected("bridge") as node:
            try:
                bridge = Bridge(
                    node.session,
                    selection,
                    name=name,
                    domain=node.domain,
                    on_event=lambda line: err.print(line, highlight=False, markup=False),
                )
            except RclpyUnavailable as exc:
                raise InputError(
                    str(exc).replace("MSCTL_TRANSPORT=rclpy", "msctl bridge")
                ) from None
            err.print(
                f"bridging msctl (Zenoh, domain {node.domain}) and ROS 2 (DDS, domain "
                f"{bridge.plane.domain}) as {name}; Ctrl-C stops",
                highlight=False,
                markup=False,
            )
            try:
                stop.wait()
            finally:
                status = bridge.status()
                bridge.close()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    _summary(status, json_output)


def _summary(status: Any, json_output: bool) -> None:
    from msctl.console import err, print_json

    relays = [{**asdict(r), "direction": r.direction.value} for r in status.relays]
    if json_output:
        print_json({"relays": relays, "skipped": status.skipped})
        return
    for relay in relays:
        err.print(
            f"{relay['kind']} {relay['name']} ({relay['direction']}): {relay['relayed']} "
            f"relayed, {relay['failed']} failed",
            highlight=False,
            markup=False,
        )
    for skipped, why in status.skipped.items():
        err.print(f"skipped {skipped}: {why}", highlight=False, markup=False)
