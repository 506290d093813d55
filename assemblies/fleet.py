"""A generated assembly of many modules that need no physics, and their stand-in, for measuring
``msctl health`` and the data monitor at scale (issue 11: 40 modules).

``fleet_document(40)`` clones the Dragon's resolved modules (limbs and wheels, alternately)
into 40 slots ``m00`` ... ``m39``, each on its own computer, with the Dragon's ground station;
it is a resolved-assembly document like any other (checked by the lock schema). Nothing in it
is launched by ``msctl up``: :func:`emulate` plays every module in one process instead, putting
each module's nodes on the graph and publishing its ``health`` once a second, shaped exactly as
a simulated module's health monitor publishes it (components, topic rates, motors, host).

    python -m assemblies.fleet write --count 40 --home DIR   # DIR/assembly/assembly.lock.json
    python -m assemblies.fleet emulate --lock PATH           # until SIGINT/SIGTERM
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

#: Modules cloned, in turn, from the Dragon.
SOURCES = ("limb1", "wheel1")


def _rename(value: Any, old: str, new: str) -> Any:
    """``value`` with every name of slot ``old`` changed to ``new`` (recursively)."""
    if isinstance(value, str):
        if value == old:
            return new
        if value == f"/{old}":
            return f"/{new}"
        for before, after in (
            (f"/{old}/", f"/{new}/"),
            (f"{old}/", f"{new}/"),
            (f"{old}_", f"{new}_"),
        ):
            if value.startswith(before):
                return after + value[len(before) :]
        return value
    if isinstance(value, dict):
        return {k: _rename(v, old, new) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_rename(v, old, new) for v in value]
    return value


def fleet_document(count: int = 40) -> dict[str, Any]:
    """A resolved-assembly document with ``count`` modules and the Dragon's ground station.

    Raises:
        ValueError: If ``count`` is not between 1 and 99.
    """
    from components.assembly import to_builtins
    from msctl.assembler import resolve

    if not 1 <= count <= 99:
        raise ValueError(f"count must be from 1 to 99, not {count}")
    dragon = json.loads(json.dumps(to_builtins(resolve("dragon").lock)))
    modules, components, units = [], [], {}
    for index in range(count):
        source = SOURCES[index % len(SOURCES)]
        slot = f"m{index:02d}"
        module = _rename(next(m for m in dragon["modules"] if m["slot"] == source), source, slot)
        module["host"] = f"fleet-{index:02d}"
        module["unit"] = f"fleet-unit-{index:02d}"
        modules.append(module)
        units[slot] = module["unit"]
        for plan in dragon["components"]:
            if plan["module"] == source:
                clone = _rename(plan, source, slot)
                clone["host"] = module["host"]
                components.append(clone)
    stations = [c for c in dragon["components"] if c["module"] is None]
    components += stations
    counts: dict[str, int] = {}
    for plan in components:
        counts[plan["kind"]] = counts.get(plan["kind"], 0) + 1
    return {
        **dragon,
        "template": f"fleet{count}",
        "description": f"{count} emulated modules (assemblies.fleet), no physics",
        "mobile": False,
        "units": units,
        "modules": modules,
        "components": components,
        "hosts": [m["host"] for m in modules] + sorted({c["host"] for c in stations}),
        "host_plans": {},
        "component_counts": counts,
        "root_links": [],
        "robots": [],
        "connections": [],
        "sources": None,
    }


def write_fleet(home: Path, count: int = 40) -> Path:
    """Write the fleet's lock file as ``home/assembly/assembly.lock.json`` (checked by the
    lock schema on the way); returns its path."""
    from components.assembly import LOCK_NAME, decode_lock, encode_lock

    text = json.dumps(fleet_document(count))
    lock = decode_lock(text).lock  # the same checks as any resolved assembly
    target = home / "assembly"
    target.mkdir(parents=True, exist_ok=True)
    path = target / LOCK_NAME
    path.write_text(encode_lock(lock))
    return path


def health_array(module: Any, labels: list[str], t: float, stamp: float) -> Any:
    """One module's health at time ``t``, shaped as a simulated module's monitor sends it."""
    from components.messages import diagnostic_array, diagnostic_status

    slot = module.slot
    statuses = []
    for label in labels:
        values = {"node": f"/{slot}/{label}", "appearances": "1", "up_for": f"{t:.1f}"}
        statuses.append((f"components/{label}", f"/{slot}/{label} running", values))
    for topic, rate, stale in (
        ("joint_states", 200.0, 0.5),
        ("joint_read", 1.0, 2.5),
        ("diagnostics", 3.0, 3.0),
    ):
        values = {"topic": f"/{slot}/{topic}", "rate_hz": f"{rate:.1f}", "stale_after": str(stale)}
        statuses.append((f"topics/{topic}", f"{rate:.1f} Hz", values))
    for index, joint in enumerate(module.actuated_joints):
        position = 0.3 * math.sin(0.2 * t + index)
        values = {
            "source": f"{slot}/joint_manager/{joint.name}",
            "position": f"{position:.6g}",
            "velocity": f"{0.06 * math.cos(0.2 * t + index):.6g}",
            "effort": f"{2.0 + index:.3g}",
            "temperature": f"{38 + index % 7}",
            "input_voltage_v": "24.0",
            "mode": "position",
            "sources": "2",
        }
        statuses.append((f"motors/{joint.name}", "OK", values))
    statuses.append(("motors/bus", "emulated", {"joints": str(len(module.actuated_joints))}))
    statuses.append(("tracking", "every joint tracks its target", {"max_tracking_error": "0.2"}))
    for item, message, key, value in (
        ("cpu", "CPU load 12%", "cpu_percent", "12.0"),
        ("memory", "memory in use 20%", "memory_percent", "20.0"),
        ("disk", "disk / in use 40%", "disk_percent", "40.0"),
        ("temperature", "temperature 45 °C", "temperature", "45.0"),
    ):
        statuses.append((f"host/{item}", message, {key: value, "warn_at": "85.0"}))
    summary = diagnostic_status(
        slot, 0, f"all {len(statuses)} items OK", module.unit, {"items": str(len(statuses))}
    )
    items = [diagnostic_status(f"{slot}/{n}", 0, m, module.unit, v) for n, m, v in statuses]
    return diagnostic_array([summary, *items], stamp)


def emulate(lock: Path, period: float = 1.0, duration: float | None = None) -> None:
    """Play every module of the resolved assembly at ``lock`` until a signal (or
    ``duration``): its nodes on the graph, its ``health`` every ``period`` seconds."""
    from components.assembly import load_assembly
    from components.comm.node import Node
    from components.comm.session import open_session
    from components.data_monitor.plan import watched
    from components.messages import DIAGNOSTIC_ARRAY

    assembly = load_assembly(lock)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    session = open_session()
    nodes: list[Any] = []
    players = []
    try:
        for spec in watched(assembly):
            if spec.station:
                continue
            module = assembly.module(spec.name)
            mine = {}
            for expected in spec.expected:
                namespace, _, name = expected.node.rpartition("/")
                node = Node(session, name, namespace or "/")
                nodes.append(node)
                mine[expected.label] = node
            publisher = mine["health_monitor"].publisher("health", DIAGNOSTIC_ARRAY)
            labels = [e.label for e in spec.expected if e.label != "health_monitor"]
            players.append((module, labels, publisher))
        start = time.monotonic()
        print(f"emulating {len(players)} modules of {assembly.template}", flush=True)
        tick = 0
        while not stop.is_set():
            # Spread the modules over the period, as independent monitors would be.
            for index, (module, labels, publisher) in enumerate(players):
                due = start + tick * period + index * period / len(players)
                if stop.wait(max(0.0, due - time.monotonic())):
                    break
                now = time.monotonic() - start
                publisher.publish(health_array(module, labels, now, time.time()))
            tick += 1
            if duration is not None and time.monotonic() - start >= duration:
                break
    finally:
        for node in nodes:
            node.close()
        session.close()


def main(argv: list[str] | None = None) -> int:
    """``write`` a fleet's lock file, or ``emulate`` its modules."""
    parser = argparse.ArgumentParser(
        prog="python -m assemblies.fleet", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="verb", required=True)
    write = sub.add_parser("write", help="write DIR/assembly/assembly.lock.json")
    write.add_argument("--count", type=int, default=40)
    write.add_argument("--home", type=Path, required=True, help="an MSCTL_HOME")
    play = sub.add_parser("emulate", help="play every module of a fleet lock file")
    play.add_argument("--lock", type=Path, required=True)
    play.add_argument("--period", type=float, default=1.0)
    play.add_argument("--for", dest="duration", type=float, default=None)
    args = parser.parse_args(argv)
    if args.verb == "write":
        print(write_fleet(args.home, args.count))
    else:
        emulate(args.lock, args.period, args.duration)
    return 0


if __name__ == "__main__":
    sys.exit(main())
