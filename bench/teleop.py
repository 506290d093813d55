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

4. **``msctl estop`` -> every module halted** (``--part estop``), on ``msctl up --detach``
   of dragon and two_dragons (each in its own MSCTL_HOME behind its own loopback router, as
   tests/running.py does): the time from the first halt request to the last module's
   acknowledgement, with :class:`components.estop.Estop` (the clients ``msctl estop`` and an
   operator use), halting every module at once, then recovering (untimed) for the next
   trial. Target: p99 < 50 ms. Baseline, in the same run: a bare Zenoh query round trip
   from this process to a queryable in another process through the same router. Beside
   it: one module's halt alone, and the real ``msctl estop`` command (its wall time, start
   of the interpreter included, and the slowest acknowledgement it reports).

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

from bench._common import free_port, msctl_env, print_table, summary  # noqa: E402
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


# ---------------------------------------------------------------------------- e-stop
QUERYABLE = """
import sys, zenoh
from components.comm.session import SessionSettings, open_session
session = open_session(SessionSettings(connect=(sys.argv[1],), listen=("tcp/127.0.0.1:0",)))
queryable = session.declare_queryable(
    f"bench/estop/ping/{sys.argv[2]}", lambda q: q.reply(q.key_expr, b"ok"), complete=True
)
print("ready", flush=True)
sys.stdin.readline()
queryable.undeclare()
session.close()
"""


class Detached:
    """``msctl up TEMPLATE --detach`` in its own MSCTL_HOME, behind its own loopback router."""

    def __init__(self, home: Path, template: str) -> None:
        self.template = template
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.env = msctl_env(home, self.endpoint)  # bench-laptop: simulated
        result = self.msctl("up", template, "--detach", "--speed", "1", timeout=600.0)
        if result.returncode != 0:
            self.down()
            raise RuntimeError(f"msctl up {template} failed: {result.stdout}{result.stderr}")

    def msctl(self, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=REPO,
            check=False,
        )

    def down(self) -> None:
        self.msctl("down", timeout=120.0)


def query_round_trips(
    session: Any, endpoint: str, processes: int, samples: int
) -> tuple[list[float], list[float]]:
    """Bare Zenoh query round trips (s) to queryables in other processes: to one of them,
    and to all ``processes`` at once (the time to the last reply)."""
    import zenoh

    helpers = [
        subprocess.Popen(
            [sys.executable, "-c", QUERYABLE, endpoint, str(i)],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for i in range(processes)
    ]
    try:
        for helper in helpers:
            assert helper.stdout.readline().strip() == "ready"

        def once(key: str, expected: int) -> float | None:
            sent = time.monotonic()
            got = 0
            replies = session.get(
                key,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=2.0,
            )
            for reply in replies:
                if reply.ok is not None:
                    got += 1
                    if got == expected:
                        return time.monotonic() - sent
            return None

        _until(lambda: once("bench/estop/ping/*", processes), 60.0, "every queryable's route")
        one = [t for _ in range(samples) if (t := once("bench/estop/ping/0", 1)) is not None]
        every = [
            t for _ in range(samples) if (t := once("bench/estop/ping/*", processes)) is not None
        ]
        return one, every
    finally:
        for helper in helpers:
            helper.stdin.write("\n")
            helper.stdin.close()
            helper.wait(30)
            helper.stdout.close()


def estop_figures(up: Detached, trials: int, pings: int) -> list[tuple[object, ...]]:
    """The e-stop rows of one running assembly."""
    import json

    from components.assembly import load_assembly
    from components.estop import Estop

    assembly = load_assembly(Path(up.env["MSCTL_HOME"]) / "assembly")
    modules = {
        p.module: p.namespace
        for p in assembly.components
        if p.kind == "joint_manager" and p.module is not None
    }
    session = open_session(_peer(up.endpoint))
    node = Node(session, "bench_estop")
    rows: list[tuple[object, ...]] = []
    try:
        bare, bare_every = query_round_trips(session, up.endpoint, len(modules), pings)
        with Estop(node, modules) as estop:
            _until(lambda: all(a.ok for a in estop.halt()), 120.0, "every joint manager's halt")
            estop.recover()
            everyone, one = [], []
            for _ in range(trials):
                answers = estop.halt()
                if all(a.ok for a in answers):
                    everyone.append(max(a.seconds for a in answers))
                estop.recover()
                (single,) = estop.halt([next(iter(modules))])
                if single.ok:
                    one.append(single.seconds)
                estop.recover()
        cli_wall, cli_ack = [], []
        for _ in range(5):
            started = time.monotonic()
            result = up.msctl("estop", "--json")
            wall = time.monotonic() - started
            if result.returncode == 0:
                document = json.loads(result.stdout)
                cli_wall.append(wall)
                cli_ack.append(max(m["seconds"] for m in document["modules"]))
            up.msctl("recover")
        base = summary(bare)
        label = f"{up.template} ({len(modules)} modules)"
        for case, values, target in (
            ("bare zenoh query round trip (baseline)", bare, None),
            (f"bare query to {len(modules)} processes at once", bare_every, None),
            ("one module's halt", one, None),
            ("every module halted (Estop, at once)", everyone, 0.050),
            ("msctl estop: slowest acknowledgement", cli_ack, 0.050),
            ("msctl estop: command wall time", cli_wall, None),
        ):
            if not values:
                rows.append((label, case, "-", "-", "-", "no answer"))
                continue
            figures = summary(values)
            verdict = "-" if target is None else ("yes" if figures["p99"] < target else "NO")
            rows.append(
                (
                    label,
                    case,
                    len(values),
                    _ms(values, "p50"),
                    _ms(values, "p99"),
                    f"{figures['p50'] / base['p50']:.1f}",
                    verdict,
                )
            )
    finally:
        node.close()
        session.close()
    return rows


def estop_main(trials: int, pings: int, templates: tuple[str, ...]) -> int:
    """``msctl estop`` on each template brought up, one at a time; print the figures."""
    print(
        f"msctl estop benchmark ({os.cpu_count()} CPUs, load averages "
        f"{', '.join(f'{x:.1f}' for x in os.getloadavg())})",
        flush=True,
    )
    rows: list[tuple[object, ...]] = []
    for template in templates:
        with tempfile.TemporaryDirectory(prefix=f"msctl-bench-estop-{template}-") as tmp:
            print(f"msctl up {template} --detach ...", flush=True)
            up = Detached(Path(tmp) / "home", template)
            try:
                print(f"e-stop on {template} ...", flush=True)
                rows += estop_figures(up, trials, pings)
            finally:
                up.down()
    print(f"load averages after: {', '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print_table(
        "msctl estop -> every module halted (ms; target p99 < 50 ms on loopback)",
        ("assembly", "case", "n", "p50", "p99", "p50/baseline", "p99 < 50 ms"),
        [r if len(r) == 7 else (*r[:2], "-", "-", "-", "-", r[-1]) for r in rows],
    )
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=200, help="Key -> wire trials per path.")
    parser.add_argument("--pings", type=int, default=500, help="Bare put -> receive samples.")
    parser.add_argument(
        "--part",
        choices=("all", "keys", "estop"),
        default="all",
        help="keys: key -> wire and key -> stop; estop: msctl estop on dragon and two_dragons.",
    )
    parser.add_argument(
        "--estop-trials", type=int, default=100, help="Halts of every module per assembly."
    )
    parser.add_argument(
        "--templates",
        default="dragon,two_dragons",
        help="Comma-separated templates brought up for the e-stop part.",
    )
    parser.add_argument("--serve", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.serve:
        serve(arguments.serve, arguments.endpoint)
        sys.exit(0)
    code = 0
    if arguments.part in ("all", "keys"):
        code = main(arguments.trials, arguments.pings)
    if arguments.part in ("all", "estop"):
        templates = tuple(t for t in arguments.templates.split(",") if t)
        code = code or estop_main(arguments.estop_trials, arguments.pings, templates)
    sys.exit(code)
