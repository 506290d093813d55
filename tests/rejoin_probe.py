"""What the ground sees of one module while a computer reboots, run as a ground station's command.

``python rejoin_probe.py watch MODULE`` follows the module's row with msctl's own health board
(:class:`~msctl.health.live.LiveHealth`, as ``msctl health`` does) and prints one JSON line each
time the row turns healthy or not (``{"at": unix seconds, "healthy": bool, "bad": [...]}``),
and one line per alarm of the board (``{"alarm": {...}}``), until it is killed.

``python rejoin_probe.py agent HOST`` prints the ``ps`` document of ``HOST``'s agent (what the
ground's data monitor reads), or exits 1 if it does not answer within 30 s.

Healthy is what ``msctl health --once`` exits 0 for (every item OK or WARN), but the computer's
own CPU, memory and disk items: five rehearsed computers share this machine's cores with the
rest of the suite, so its load is not theirs.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any


def _bad(row: Any) -> list[str]:
    return [
        f"{item.name}: {item.level.name} {item.message}"
        for item in row.items
        if item.level.name not in ("OK", "WARN") and "/host/" not in item.name
    ]


def watch(module: str) -> None:
    """Print the module's row each time it turns healthy or not, and every alarm."""
    from components.assembly import load_assembly
    from msctl.health.live import LiveHealth
    from msctl.plane import connected

    with connected("rejoin_probe") as node, LiveHealth(node, load_assembly()) as live:
        last: bool | None = None
        while True:
            row = live.evaluate().row(module)
            bad = _bad(row) if row is not None else ["no such row"]
            healthy = row is not None and row.health_age is not None and not bad
            if healthy != last:
                print(json.dumps({"at": time.time(), "healthy": healthy, "bad": bad}), flush=True)
                last = healthy
            for alarm in live.take_alarms():
                print(json.dumps({"alarm": alarm.to_json()}), flush=True)
            time.sleep(0.05)  # the probe's sampling period: transitions are timed to 50 ms


def agent(host: str) -> int:
    """Print ``host``'s agent's own ``ps`` document; 1 if it does not answer."""
    from components.comm.services import ServiceError
    from msctl.launcher.control import call_supervisor
    from msctl.plane import connected

    with connected("rejoin_probe") as node:
        try:
            document = call_supervisor(node, host, "ps", timeout=30.0, grace=5.0)
        except ServiceError as exc:
            print(f"the agent of {host} did not answer: {exc}", file=sys.stderr)
            return 1
    print(json.dumps(document))
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["watch"]:
        watch(sys.argv[2])
    else:
        sys.exit(agent(sys.argv[2]))
