"""View benchmark: what ``msctl view`` costs at 40 modules, beside a baseline measured in the
same run, and what it subscribes to.

The fleet (:mod:`assemblies.fleet`, 40 modules cloned from the Dragon's limb and wheel) gets a
composed URDF here (each module's links from the Dragon's, bolted to ``world`` on a grid), so
the view draws every module. One process plays the fleet's graph and health (the fleet's own
emulator), another publishes every module's ``joint_read`` at ``--rate`` Hz with every joint
moving (the ground's radio budget is 10 Hz a module; the default is twice that). Then:

* CPU at steady state (% of one core, user+system, over ``--window`` s after ``--warmup`` s) of
  the real ``msctl view --rerun`` (serving its web viewer, no browser attached) and of the
  baseline: a bare zenoh-python subscriber receiving exactly the same keys (every module's
  ``joint_read`` and ``health``) and doing nothing else. Target: well under a core.
* Its subscriptions, read from the graph (its node's liveliness tokens, as ``ros2 topic info``
  sees them): every topic it subscribes to is one it shows; anything else is printed.

Run: ``python bench/view.py [--count 40] [--rate 20] [--window 15] [--warmup 8]`` (about a
minute on a loaded two-core machine). Needs the view extra (``pip install '.[view]'``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import compiled_sources, free_port, msctl_env, print_table

ROOT = Path(__file__).resolve().parents[1]

BASELINE = """
import signal, threading, zenoh
config = zenoh.Config()
config.insert_json5("mode", '"client"')
config.insert_json5("connect/endpoints", '["%s"]')
config.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(config)
count = [0]
def on(_sample):
    count[0] += 1
subscribers = [session.declare_subscriber(key, on) for key in %r]
done = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: done.set())
done.wait()
for subscriber in subscribers:
    subscriber.undeclare()
session.close()
print(count[0], flush=True)
"""

JOINTS = """
import math, signal, sys, threading, time
import numpy as np
from components.assembly import load_assembly
from components.comm.node import Node
from components.comm.session import open_session
from components.messages import JOINT_STATE, msg
rate = float(sys.argv[1])
assembly = load_assembly()
session = open_session()
node = Node(session, "fleet_joints", "/")
players = []
for module in assembly.modules:
    names = [j.name for j in module.joints]
    players.append((names, node.publisher(f"/{module.slot}/joint_read", JOINT_STATE)))
done = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: done.set())
start = time.monotonic()
tick = 0
while not done.wait(max(0.0, start + tick / rate - time.monotonic())):
    t = time.monotonic() - start
    for k, (names, publisher) in enumerate(players):
        position = np.array([0.4 * math.sin(0.5 * t + k + i) for i in range(len(names))])
        publisher.publish(msg(JOINT_STATE, name=names, position=position))
    tick += 1
node.close()
session.close()
"""


def fleet_home(home: Path, count: int) -> Any:
    """Write the fleet's lock, with a composed URDF (every module on ``world``), under home."""
    from assemblies.fleet import fleet_document
    from components.assembly import LOCK_NAME, decode_lock, encode_lock, load_assembly
    from msctl.assembler import resolve

    dragon = resolve("dragon")
    source = ET.fromstring(Path(dragon_urdf(dragon, home)).read_text())
    document = fleet_document(count)
    robot = ET.Element("robot", {"name": f"fleet{count}"})
    ET.SubElement(robot, "link", {"name": "world"})
    for index, module in enumerate(document["modules"]):
        old = "limb1" if module["kind"] == "limb" else "wheel1"
        prefix, new = f"{old}_", f"{module['slot']}_"
        for element in source:
            if element.tag == "link" and element.get("name", "").startswith(prefix):
                robot.append(_renamed(element, prefix, new))
            if element.tag == "joint" and element.get("name", "").startswith(prefix):
                parent = element.find("parent")
                if parent is not None and parent.get("link", "").startswith(prefix):
                    robot.append(_renamed(element, prefix, new))
        mount = ET.SubElement(robot, "joint", {"name": f"{new}mount", "type": "fixed"})
        ET.SubElement(mount, "parent", {"link": "world"})
        ET.SubElement(mount, "child", {"link": module["root_link"]})
        x, y = 1.5 * (index % 8), 1.0 * (index // 8)
        ET.SubElement(mount, "origin", {"xyz": f"{x} {y} 0", "rpy": "0 0 0"})
    target = home / "assembly"
    target.mkdir(parents=True, exist_ok=True)
    (target / document["artifacts"]["urdf"]).write_text(ET.tostring(robot, encoding="unicode"))
    document["root_links"] = ["world"]
    document["robots"] = [{"root": "m00", "root_link": "world", "xyz": [0, 0, 0], "rpy": [0, 0, 0]}]
    lock = decode_lock(json.dumps(document)).lock
    (target / LOCK_NAME).write_text(encode_lock(lock))
    return load_assembly(target / LOCK_NAME)


def dragon_urdf(resolution: Any, home: Path) -> Path:
    """The Dragon's composed URDF, written once under ``home``."""
    from components.assembly import load_assembly
    from msctl.assembler.store import write_resolution

    return Path(load_assembly(write_resolution(home / "dragon", resolution)).urdf_path)


def _renamed(element: ET.Element, old: str, new: str) -> ET.Element:
    copy = ET.fromstring(ET.tostring(element))
    for node in copy.iter():
        for key in ("name", "link"):
            value = node.get(key)
            if value and value.startswith(old):
                node.set(key, new + value[len(old) :])
    return copy


def _lines(stream: Any) -> list[str]:
    """Lines of a text stream, collected by a thread as they come."""
    import threading

    lines: list[str] = []

    def read() -> None:
        for line in stream:
            lines.append(line.rstrip())

    threading.Thread(target=read, daemon=True).start()
    return lines


def cpu_percent(pids: list[int], window: float) -> list[float]:
    """Each process's CPU (user+system, % of one core) over ``window`` seconds."""
    import psutil

    processes = [psutil.Process(pid) for pid in pids]
    before = [p.cpu_times() for p in processes]
    time.sleep(window)
    after = [p.cpu_times() for p in processes]
    return [
        100 * ((a.user - b.user) + (a.system - b.system)) / window
        for a, b in zip(after, before, strict=True)
    ]


def subscriptions_of(endpoint: str, node_prefix: str) -> list[str]:
    """Topics the nodes named ``node_prefix*`` subscribe to, from their liveliness tokens."""
    from components.comm.session import SessionSettings, open_session

    session = open_session(SessionSettings(mode="client", connect=(endpoint,), multicast=False))
    try:
        topics = set()
        for reply in session.liveliness().get("@ros2_lv/**", timeout=5.0):
            key = str(reply.ok.key_expr) if reply.ok is not None else ""
            parts = key.split("/")
            # @ros2_lv/<domain>/<zid>/<nid>/<eid>/MS/<enclave>/<ns>/<node>/<topic>/...
            if len(parts) > 9 and parts[5] == "MS" and parts[8].startswith(node_prefix):
                topics.add("/" + parts[9].replace("%", "/").strip("/"))
        return sorted(topics)
    finally:
        session.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--rate", type=float, default=20.0, help="joint_read Hz per module")
    parser.add_argument("--window", type=float, default=15.0)
    parser.add_argument("--warmup", type=float, default=8.0)
    args = parser.parse_args(argv)
    compiled_sources()

    from components.comm.session import SessionSettings, open_session
    from msctl.view.live import LiveView

    home = Path(tempfile.mkdtemp(prefix="msctl-bench-view-"))
    assembly = fleet_home(home, args.count)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = msctl_env(home, endpoint, host="bench-view-laptop")
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    children: list[subprocess.Popen] = []

    def start(*command: str, out: Any = subprocess.DEVNULL) -> subprocess.Popen:
        child = subprocess.Popen(
            command, env=env, cwd=ROOT, stdout=out, stderr=subprocess.PIPE, text=True
        )
        children.append(child)
        return child

    try:
        lock = home / "assembly" / "assembly.lock.json"
        start(sys.executable, "-m", "assemblies.fleet", "emulate", "--lock", str(lock))
        start(sys.executable, "-c", JOINTS, str(args.rate))
        keys = [f"0/{m.slot}/joint_read/**" for m in assembly.modules]
        keys += [f"0/{m.slot}/health/**" for m in assembly.modules]
        baseline = start(sys.executable, "-c", BASELINE % (endpoint, keys), out=subprocess.PIPE)
        view = start(
            sys.executable,
            "-m",
            "msctl",
            "view",
            "--rerun",
            "--port",
            str(free_port()),
            "--grpc-port",
            str(free_port()),
        )
        said = _lines(view.stderr)
        deadline = time.monotonic() + 300
        while not any("following" in line for line in said):
            if view.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("msctl view did not start following:\n" + "\n".join(said))
            time.sleep(0.2)
        time.sleep(args.warmup)
        for child in children:
            if child.poll() is not None:
                raise SystemExit(
                    f"a process of the bench ended: {child.args!r}: "
                    f"{child.stderr.read() if child.stderr else ''}"
                )
        view_cpu, baseline_cpu = cpu_percent([view.pid, baseline.pid], args.window)
        following = next(line for line in said if "following" in line)
        subscribed = subscriptions_of(endpoint, "msctl_view_")
        shown = {f"/{m.slot}/health" for m in assembly.modules}
        shown |= {f"/{m.slot}/joint_read" for m in assembly.modules if m.joints}
        shown |= {
            f"/{m.slot}/{t}"
            for m in assembly.modules
            if m.chains
            for t in ("tip_pose", "ik_target")
        }
        # A wheel module's commanded twist is drawn from its joint_set.
        shown |= {
            f"/{m.slot}/joint_set"
            for m in assembly.modules
            if any(j.control == "velocity" for j in m.joints)
        }
        stations = {c.namespace.strip("/") for c in assembly.components if c.module is None}
        shown |= {f"/{s}/diagnostics" for s in stations}
        not_shown = [t for t in subscribed if t not in shown]
    finally:
        for child in children:
            if child.poll() is None:
                child.send_signal(
                    signal.SIGINT if child.args[1:3] == ["-m", "msctl"] else signal.SIGTERM
                )
        for child in children:
            try:
                child.wait(timeout=30)
            except subprocess.TimeoutExpired:
                child.kill()
        router.close()
    received = int((baseline.stdout.read() if baseline.stdout else "0").strip() or 0)
    import psutil

    print_table(
        f"msctl view at {args.count} modules, joint_read at {args.rate:g} Hz each "
        f"({psutil.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; % of one core over "
        f"{args.window:g} s)",
        ["process", "cpu %"],
        [
            ["msctl view --rerun (web viewer served, no browser)", f"{view_cpu:.1f}"],
            ["baseline: bare subscriber to the same keys", f"{baseline_cpu:.1f}"],
        ],
    )
    print(f"\nthe view said: {following.strip()}; the baseline received {received:,} samples")
    print(
        f"\nsubscriptions of msctl view: {len(subscribed)} topics, "
        f"{len(subscribed) - len(not_shown)} of them shown"
        + (f"; NOT shown: {', '.join(not_shown)}" if not_shown else "; none it does not show")
    )
    print(f"LiveView follows: {LiveView.__doc__.splitlines()[0]}")
    return 1 if not_shown else 0


if __name__ == "__main__":
    raise SystemExit(main())
