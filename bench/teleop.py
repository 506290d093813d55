"""Teleop benchmark: key event -> command on the wire, and last key -> motion stops.

Run ``python bench/teleop.py`` (about two minutes). A Dragon is resolved into a temporary
directory; a server process runs every module's joint manager and the MuJoCo simulator in one
Executor (as ``msctl up`` does off-robot), behind a Zenoh router on a free loopback port.
This process runs the real teleop: :class:`~msctl.teleop.link.Link`, the
:class:`~msctl.teleop.operator.Operator` and the textual app headless, fed key events as the
terminal driver feeds them (``post_message`` from another thread). An observer on its own
session timestamps what arrives.

Measured:

1. **Bare publish -> receive** (the baseline): a raw Zenoh put of a Twist-sized payload from
   the teleop's session to the observer's, through the same router.
2. **Key event -> command on the wire**, from a stopped robot, per mode: drive (``i``, a Twist
   on ``/cmd_vel``), joint (``w`` on a wheel's velocity joint, and on limb1's joint1 through
   the jog's planner), IK (``i``: one IK step of limb1). Each trial ends with an unbound key
   (one stop, at once) so the next starts from rest. Ratio: p50 over the bare p50. IK's own
   step (prepare, solve, publish), timed alone at the same poses, is printed beside it.
3. **Last key -> motion commands stop**, drive mode: a tap (the first-press timeout, 0.6 s)
   and a held key (repeats every 33 ms after 0.5 s, then the repeat timeout, 0.15 s), from
   the last key event to the zero Twist's arrival. Target: the timeout plus one tick (50 ms);
   baseline: the timeout plus the bare publish -> receive p50.

Nothing here asserts a speed; it prints figures and ratios.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable as `python bench/teleop.py` from anywhere
    sys.path.insert(0, str(REPO))

from bench._common import free_port, print_table, summary  # noqa: E402
from components.comm.node import Node  # noqa: E402
from components.comm.session import SessionSettings, open_session  # noqa: E402
from components.messages import JOINT_STATE, joint_samples  # noqa: E402

TICK = 0.05  # the teleop's period at its default 20 Hz


# ---------------------------------------------------------------------------- server side
def serve(assembly_dir: str, endpoint: str) -> None:
    """Every joint manager and the simulator until SIGTERM (the server process)."""
    from components.assembly import load_assembly
    from components.build import build_component, simulator_plan
    from components.executor.executor import Executor

    assembly = load_assembly(Path(assembly_dir))
    settings = _peer(endpoint)
    built = [build_component(c, assembly) for c in assembly.components if c.kind == "joint_manager"]
    built.append(build_component(simulator_plan("simulator"), assembly, {"speed": 1.0}))
    with Executor(settings=settings) as executor:
        for component in built:
            executor.add(component.core, component.spec, component.namespace, component.node_name)
        executor.run()
    for component in built:
        component.close()


def _peer(endpoint: str) -> SessionSettings:
    return SessionSettings(
        mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False
    )


class Server:
    """The server process, stopped with SIGTERM as ``msctl down`` would."""

    def __init__(self, assembly_dir: Path, endpoint: str) -> None:
        command = [sys.executable, str(Path(__file__).resolve()), "--serve", str(assembly_dir)]
        self.process = subprocess.Popen([*command, "--endpoint", endpoint], cwd=REPO)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


# ---------------------------------------------------------------------------- client side
class Arrivals:
    """What arrives on one topic, with the arrival time (monotonic), thread-safe."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.items: list[tuple[float, Any]] = []

    def __call__(self, item: Any) -> None:
        arrived = time.monotonic()
        with self.cond:
            self.items.append((arrived, item))
            self.cond.notify_all()

    def wait_for(self, predicate: Callable[[Any], bool], since: float, timeout: float) -> float:
        """Arrival time of the first item after ``since`` matching ``predicate``.

        Raises:
            TimeoutError: If none comes within ``timeout``.
        """
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for arrived, item in self.items:
                    if arrived >= since and predicate(item):
                        return arrived
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"nothing matching within {timeout} s")
                self.cond.wait(left)

    def last(self) -> tuple[float, Any]:
        with self.cond:
            return self.items[-1]

    def clear(self) -> None:
        with self.cond:
            self.items.clear()


def _until(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)
    return value


def bare_latency(teleop_session: Any, observer_session: Any, samples: int) -> list[float]:
    """One-way latencies (s) of raw Zenoh puts between the two sessions."""
    arrivals = Arrivals()
    subscriber = observer_session.declare_subscriber("bench/teleop/ping", arrivals)
    publisher = teleop_session.declare_publisher("bench/teleop/ping")
    payload = bytes(52)  # a Twist in CDR: 4-byte header and six float64
    try:
        _until(lambda: publisher.put(payload) or arrivals.items, 20.0, "the bare route to come up")
        times = []
        for _ in range(samples):
            sent = time.monotonic()
            publisher.put(payload)
            times.append(arrivals.wait_for(lambda _item: True, sent, 2.0) - sent)
            time.sleep(0.005)
        return times
    finally:
        publisher.undeclare()
        subscriber.undeclare()


class Bench:
    """The teleop under test and its observer."""

    def __init__(self, app: Any, link: Any, observer: Node) -> None:
        self.app = app
        self.link = link
        self.twists = Arrivals()
        self.sets: dict[str, Arrivals] = {s: Arrivals() for s in ("limb1", "wheel1")}
        observer.subscription("/cmd_vel", "geometry_msgs/msg/Twist", self.twists)
        for slot, arrivals in self.sets.items():
            observer.subscription(f"/{slot}/joint_set", JOINT_STATE, arrivals)

    def key(self, name: str) -> float:
        """Feed one key event as the terminal driver does; its time."""
        from textual import events

        character = name if len(name) == 1 else None
        key = {",": "comma", " ": "space"}.get(name, name)
        at = time.monotonic()
        self.app.post_message(events.Key(key, character))
        return at

    def stopped(self) -> bool:
        return self.app.operator.idle

    def mode(self, key: str, name: str) -> None:
        self.key(key)
        _until(lambda: self.app.operator.view().mode == name, 10.0, f"{name} mode")


def key_to_wire(
    bench: Bench, arrivals: Arrivals, key: str, moving: Callable[[Any], bool], trials: int
) -> list[float]:
    """Latencies (s) from a motion key (robot at rest) to its first command's arrival."""
    times = []
    for _ in range(trials):
        _until(bench.stopped, 10.0, "the teleop at rest")
        pressed = bench.key(key)
        times.append(arrivals.wait_for(moving, pressed, 5.0) - pressed)
        bench.key("x")  # unbound: one stop at once, the next trial starts from rest
        time.sleep(0.01)
    return times


def last_key_to_stop(bench: Bench, held: bool, trials: int) -> list[float]:
    """Seconds from the last key event to the zero Twist's arrival, drive mode."""

    def zero(message: Any) -> bool:
        return message.linear.x == 0.0 and message.angular.z == 0.0

    times = []
    for _ in range(trials):
        _until(bench.stopped, 10.0, "the teleop at rest")
        last = bench.key("i")
        if held:
            # The OS's repeat: first after 0.5 s, then every 33 ms, for half a second.
            start = last
            repeat = start + 0.5
            while repeat < start + 1.0:
                time.sleep(max(repeat - time.monotonic(), 0.0))
                last = bench.key("i")
                repeat += 0.033
        times.append(bench.twists.wait_for(zero, last, 5.0) - last)
    return times


def _ms(values: list[float], q: str) -> str:
    return f"{summary(values)[q] * 1e3:.2f}"


def run(bench: Bench, bare: list[float], trials: int) -> None:
    """Every measurement on the running app (from a thread: the app's loop stays free)."""
    from msctl.teleop.keys import DRIVE, IK, JOINT

    # The routes to the observer first: a move and, at once, its stop per try.
    bench.mode("3", DRIVE)

    def warm() -> bool:
        bench.key("i")
        bench.key("x")
        time.sleep(0.05)
        return bool(bench.twists.items)

    _until(warm, 60.0, "the route to the observer")
    bare_p50 = summary(bare)["p50"]
    rows = [("bare zenoh put -> receive", _ms(bare, "p50"), _ms(bare, "p99"), "1.00")]

    def row(what: str, values: list[float]) -> None:
        ratio = summary(values)["p50"] / bare_p50
        rows.append((what, _ms(values, "p50"), _ms(values, "p99"), f"{ratio:.2f}"))

    def twist_moving(message: Any) -> bool:
        return message.linear.x != 0.0

    def joint_moving(message: Any) -> bool:
        sample = joint_samples(message)[0]
        return sample.velocity != 0.0 if sample.position is None else True

    row(
        "drive: i -> Twist on /cmd_vel", key_to_wire(bench, bench.twists, "i", twist_moving, trials)
    )
    bench.mode("1", JOINT)
    bench.app.operator.select("wheel1")
    row(
        "joint: w -> wheel1 velocity joint_set",
        key_to_wire(bench, bench.sets["wheel1"], "w", joint_moving, trials),
    )
    bench.app.operator.select("limb1", "limb1_joint1")
    row(
        "joint: w -> limb1 position joint_set",
        key_to_wire(bench, bench.sets["limb1"], "w", joint_moving, trials),
    )
    bench.mode("2", IK)
    row(
        "ik: i -> limb1 joint_set (IK step)",
        key_to_wire(bench, bench.sets["limb1"], "i", lambda _m: True, trials),
    )
    # IK's own cost at the same poses, without the key path: the tip output called directly
    # (one IK step from rest, as the first command of a motion is), then its stop.
    from msctl.teleop.core import Move, Stop

    _until(bench.stopped, 10.0, "the teleop at rest")
    tips = bench.link.tips
    alone = []
    for _ in range(trials):
        started = time.monotonic()
        tips.move(Move(IK, "limb1", None, (0.0, 0.0, 0.03, 0.0, 0.0, 0.0), TICK, True))
        alone.append(time.monotonic() - started)
        tips.stop(Stop(IK, "limb1", None, "bench"))
        time.sleep(0.01)
    rows.append(
        (
            "ik: the IK step alone (no key, no wire)",
            _ms(alone, "p50"),
            _ms(alone, "p99"),
            f"{summary(alone)['p50'] / bare_p50:.2f}",
        )
    )
    print_table(
        "key event -> command on the wire (ms; ratio = p50 / bare p50)",
        ("path", "p50", "p99", "ratio"),
        rows,
    )

    bench.mode("3", DRIVE)
    settings = bench.app.operator.core.settings
    stop_rows = []
    for label, held, timeout, count in (
        ("tap (first-press timeout)", False, settings.first_timeout, max(trials // 10, 5)),
        ("held (repeat timeout)", True, settings.repeat_timeout, max(trials // 10, 5)),
    ):
        values = last_key_to_stop(bench, held, count)
        target = timeout + TICK
        baseline = timeout + bare_p50
        s = summary(values)
        stop_rows.append(
            (
                label,
                f"{s['p50'] * 1e3:.1f}",
                f"{s['p99'] * 1e3:.1f}",
                f"{target * 1e3:.0f}",
                f"{baseline * 1e3:.1f}",
                f"{s['p50'] / baseline:.3f}",
                "yes" if s["p99"] <= target else "NO",
            )
        )
    print_table(
        "last key event -> motion commands stop, drive mode (ms)",
        ("case", "p50", "p99", "target", "baseline", "p50/baseline", "p99 within target"),
        stop_rows,
    )


def main(trials: int, pings: int) -> int:
    """Set up, measure, print."""
    from components.assembly import load_assembly
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution
    from msctl.teleop.app import TeleopApp
    from msctl.teleop.core import TeleopCore
    from msctl.teleop.link import Link
    from msctl.teleop.operator import Operator

    print(f"msctl teleop benchmark ({os.cpu_count()} CPUs)", flush=True)
    with tempfile.TemporaryDirectory(prefix="msctl-bench-teleop-") as tmp:
        directory = write_resolution(Path(tmp) / "assembly", resolve("dragon"))
        assembly = load_assembly(directory)
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
        server = Server(directory, endpoint)
        teleop_session = open_session(_peer(endpoint))
        observer_session = open_session(_peer(endpoint))
        node = Node(teleop_session, "bench_teleop")
        observer = Node(observer_session, "bench_observer")
        link = operator = None
        try:
            print("baseline: bare zenoh put -> receive ...", flush=True)
            bare = bare_latency(teleop_session, observer_session, pings)
            print("the teleop on a simulated Dragon ...", flush=True)
            link = Link.open(node, assembly, ("limb1", "wheel1"), health=False, timeout=120.0)
            for handler in link.handlers.values():
                asyncio.run(handler.wait_ready(120.0))
            core = TeleopCore(None, link.joints(), link.limbs, link.drive_target, "drive")
            operator = Operator(core, link.outputs()).start()
            app = TeleopApp(operator, link, template="dragon")
            bench = Bench(app, link, observer)

            async def measure() -> None:
                async with app.run_test(size=(120, 40), headless=True):
                    await asyncio.to_thread(run, bench, bare, trials)

            asyncio.run(measure())
        finally:
            if operator is not None:
                operator.close()
            if link is not None:
                link.close()
            observer.close()
            node.close()
            observer_session.close()
            teleop_session.close()
            server.stop()
            router.close()
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=200, help="Key -> wire trials per path.")
    parser.add_argument("--pings", type=int, default=500, help="Bare put -> receive samples.")
    parser.add_argument("--serve", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.serve:
        serve(arguments.serve, arguments.endpoint)
        sys.exit(0)
    sys.exit(main(arguments.trials, arguments.pings))
