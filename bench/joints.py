"""Joint benchmark: command-to-state latency through joint manager + simulator, and how fast
the simulator runs.

Run ``python bench/joints.py`` (about a minute). It resolves the ``minimal``, ``dragon`` and
``dragon_x4`` assemblies into a temporary directory, starts a Zenoh router on a free loopback
port, and measures:

1. **Bare round trip**: this process publishes a ``sensor_msgs/JointState`` payload on
   ``/bench/ping``; a server process echoes the bytes on ``/bench/pong`` from its Zenoh
   callback (no decoding, no executor). Same two processes, same router as step 2.
2. **Command to state**: the server process runs the ``minimal`` assembly's joint manager and
   the simulator in one Executor (as ``msctl up`` would off-robot). This process publishes a
   ``joint_set`` (a 0.05 rad step of ``limb1_joint3``) and times the first ``joint_read`` that
   reflects it (the joint moving toward the new target). Four data-plane hops: joint_set,
   joint_commands, joint_states, joint_read.
3. **Real-time factor** of ``dragon`` and ``dragon_x4``: physics alone (the world stepping as
   fast as it can, motors holding), then live: the simulator plus every module's joint manager
   in a server process on the data plane, at speed 5 (does it keep up?) and at speed 50
   (saturated: what it achieves), read from its ``/sim/diagnostics``.

4. **What the safety checks cost** (issue 10's hardening): the CPU per command of every check
   a ``joint_set`` meets on its way that the hardening added: the joint manager refusing a
   whole message (oversize, ragged) and collapsing duplicates, the sender's publisher looked up
   among the allowed ones (the GID check on ``joint_commands``), and the last stage (simulator
   or motor interface) refusing a whole message, collapsing duplicates and checking each
   joint's raw limits. Timed in this process on the same messages, for the one-joint command
   of step 2 and for a seven-joint one, as a share of step 2's p50 measured in the same run.

Targets: p50 command-to-state within 3x the bare round trip plus one simulation step;
real-time factor of ``dragon_x4`` at least 5; the added checks under 5 % of the p50.
"""

from __future__ import annotations

import argparse
import math
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

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # runnable as `python bench/joints.py` from anywhere
    sys.path.insert(0, str(REPO))

from components.comm.node import Node  # noqa: E402
from components.comm.session import SessionSettings, open_session  # noqa: E402
from components.comm.types import registry  # noqa: E402
from components.messages import (  # noqa: E402
    JOINT_STATE,
    JointSample,
    joint_samples,
    joint_state,
)

JOINT = "limb1_joint3"
STEP = 0.05  # rad: small enough to settle quickly, far above joint_read's 1 mm threshold
REFLECT_SPEED = 0.05  # rad/s toward the target: the joint_read shows the command acting
TEMPLATES = ("minimal", "dragon", "dragon_x4")


# ---------------------------------------------------------------------------- server side
def serve(assembly_dir: str, endpoint: str, speed: float, echo: bool) -> None:
    """Run the assembly's joint managers and the simulator until SIGTERM (server process)."""
    from components.assembly import load_assembly
    from components.build import build_component, simulator_plan
    from components.executor.executor import Executor

    assembly = load_assembly(Path(assembly_dir))
    settings = _peer(endpoint)
    session = open_session(settings)
    built = [build_component(c, assembly) for c in assembly.components if c.kind == "joint_manager"]
    built.append(
        build_component(
            simulator_plan("simulator"),
            assembly,
            {"speed": speed},
        )
    )
    echo_node = None
    try:
        executor = Executor(settings=settings, session=session)
        for component in built:
            executor.add(component.core, component.spec, component.namespace, component.node_name)
        if echo:
            # Echo from the Zenoh callback itself: the baseline is the data plane alone.
            echo_node = Node(session, "bench_echo", "/")
            pong = echo_node.publisher("/bench/pong", JOINT_STATE)
            echo_node.subscription("/bench/ping", JOINT_STATE, pong.publish_raw, raw=True)
        executor.run()
    finally:
        if echo_node is not None:
            echo_node.close()
        for component in built:
            component.close()
        session.close()


# ---------------------------------------------------------------------------- client side
def _peer(endpoint: str) -> SessionSettings:
    return SessionSettings(
        mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False
    )


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _wait(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)


class Server:
    """A server process (``--serve``), stopped with SIGTERM like ``msctl down`` would."""

    def __init__(self, assembly_dir: Path, endpoint: str, speed: float, echo: bool) -> None:
        command = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--serve",
            str(assembly_dir),
            "--endpoint",
            endpoint,
            "--speed",
            str(speed),
        ]
        if echo:
            command.append("--echo")
        self.process = subprocess.Popen(command, cwd=REPO)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


class Watch:
    """Latest samples of one topic with their arrival time (perf_counter), thread-safe."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.items: list[tuple[float, Any]] = []

    def __call__(self, item: Any) -> None:
        arrived = time.perf_counter()
        with self.cond:
            self.items.append((arrived, item))
            self.cond.notify_all()

    def wait_for(
        self, predicate: Callable[[float, Any], bool], since: float, timeout: float
    ) -> float | None:
        """Arrival time of the first item after ``since`` matching ``predicate``."""
        deadline = time.perf_counter() + timeout
        checked = 0
        with self.cond:
            while True:
                for arrived, item in self.items[checked:]:
                    if arrived >= since and predicate(arrived, item):
                        return arrived
                checked = len(self.items)
                left = deadline - time.perf_counter()
                if left <= 0:
                    return None
                self.cond.wait(left)

    def clear(self) -> None:
        with self.cond:
            self.items.clear()


def _joint(message: Any, name: str) -> tuple[float | None, float | None]:
    names = list(message.name)
    if name not in names:
        return None, None
    i = names.index(name)
    position = float(message.position[i]) if i < len(message.position) else None
    velocity = float(message.velocity[i]) if i < len(message.velocity) else None
    return position, velocity


def bare_round_trip(session: Any, samples: int) -> np.ndarray:
    """Round trips (s) of a JointState payload echoed by the server's Zenoh callback."""
    node = Node(session, "bench_ping", "/")
    try:
        watch = Watch()
        node.subscription("/bench/pong", JOINT_STATE, watch, raw=True)
        ping = node.publisher("/bench/ping", JOINT_STATE)
        payload = registry().serialize(
            joint_state([JointSample(JOINT, 0.1, None, None)]), JOINT_STATE
        )

        def echoed() -> bool:
            ping.publish_raw(payload)
            return watch.wait_for(lambda *_: True, 0.0, 0.05) is not None

        _wait(echoed, 10, "the echo server")
        times = []
        for _ in range(samples):
            watch.clear()
            sent = time.perf_counter()
            ping.publish_raw(payload)
            arrived = watch.wait_for(lambda *_: True, sent, 1.0)
            if arrived is not None:
                times.append(arrived - sent)
            time.sleep(0.002)
        return np.array(times)
    finally:
        node.close()


def command_to_state(session: Any, samples: int) -> np.ndarray:
    """Latencies (s) from a joint_set step to the first joint_read showing the joint move."""
    node = Node(session, "bench_operator", "/")
    try:
        reads = Watch()
        node.subscription("/limb1/joint_read", JOINT_STATE, reads)
        command = node.publisher("/limb1/joint_set", JOINT_STATE)

        def current() -> tuple[float | None, float | None]:
            with reads.cond:
                position = velocity = None
                for _, message in reversed(reads.items):
                    p, v = _joint(message, JOINT)
                    position = p if position is None else position
                    velocity = v if velocity is None else velocity
                    if position is not None and velocity is not None:
                        break
                return position, velocity

        _wait(lambda: current()[0] is not None, 15, "joint_read from the joint manager")
        home = current()[0]
        assert home is not None
        # Warm-up: routes, caches and the first moves.
        for target in (home + STEP, home):
            command.publish(joint_state([JointSample(JOINT, target, None, None)]))
            time.sleep(0.3)
        latencies = []
        for i in range(samples):
            target = home + (STEP if i % 2 == 0 else 0.0)
            _wait(lambda: abs(current()[1] or 0.0) < 0.02, 2, "the joint to settle")
            position = current()[0] or 0.0
            direction = math.copysign(1.0, target - position)

            def reflects(_: float, message: Any, direction: float = direction) -> bool:
                _, velocity = _joint(message, JOINT)
                return velocity is not None and direction * velocity > REFLECT_SPEED

            sent = time.perf_counter()
            command.publish(joint_state([JointSample(JOINT, target, None, None)]))
            arrived = reads.wait_for(reflects, sent, 1.0)
            if arrived is not None:
                latencies.append(arrived - sent)
            time.sleep(0.08)  # let the 0.05 rad move finish
            with reads.cond:
                del reads.items[:-50]
        return np.array(latencies)
    finally:
        node.close()


def live_rtf(session: Any, windows: int = 3) -> dict[str, float]:
    """The simulator's own figures from ``/sim/diagnostics``, after ``windows`` 1 s windows."""
    from components.messages import diagnostic_values

    node = Node(session, "bench_diagnostics", "/")
    try:
        watch = Watch()
        node.subscription("/sim/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", watch)
        _wait(lambda: len(watch.items) >= windows + 1, 20 + windows, "/sim/diagnostics")
        with watch.cond:
            values = diagnostic_values(watch.items[-1][1].status[0])
        return {
            key: float(values[key]) if values.get(key) else math.nan
            for key in ("real_time_factor", "speed", "step_rate_hz", "state_rate_hz", "load")
        }
    finally:
        node.close()


def _resolve(root: Path) -> dict[str, Path]:
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    dirs = {}
    for name in TEMPLATES:
        resolution = resolve(name)
        target = root / name / "assembly"
        write_resolution(target, resolution)
        dirs[name] = target
    return dirs


def checks_cost(joints: int, rounds: int = 20000) -> float:
    """Seconds of CPU per command spent in the hardening's checks, for a ``joint_set`` of
    ``joints`` joints (see the module docstring, step 4): the joint manager's and the last
    stage's whole-message and duplicate checks, the sender lookup, each joint's raw limits."""
    from components.motors.base import RawLimits, check_command, refused_whole

    names = [f"limb1_joint{i + 1}" for i in range(joints)]
    message = joint_state([JointSample(n, 0.1 * i, None, None) for i, n in enumerate(names)])
    checks = RawLimits(-2.0, 2.0, 5.0, 10.0).checks()
    allowed = {bytes(16): "/limb1/joint_manager"}  # the GID -> node table a subscription keeps
    gid = bytes(16)
    size = 7

    def one_command() -> None:
        # Joint manager, on joint_set: refused whole? duplicates collapsed.
        if refused_whole(message, size) is None:
            latest = {s.name: s for s in joint_samples(message)}
            assert len(latest) == len(message.name)
        # The last stage: the sender, then the same whole-message checks, then each joint.
        if gid in allowed and refused_whole(message, size) is None:
            latest = {s.name: s for s in joint_samples(message)}
            for _, position, velocity, effort in latest.values():
                check_command(checks, position, velocity, effort)

    for _ in range(1000):  # warm up
        one_command()
    started = time.process_time()
    for _ in range(rounds):
        one_command()
    return (time.process_time() - started) / rounds


def _ms(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q) * 1e3) if len(values) else math.nan


def main(samples: int, pings: int) -> int:
    """Run every measurement and print the figures, ratios and target verdicts."""
    from components.assembly import load_assembly
    from components.simulator.world import max_real_time_factor

    print(f"msctl joint benchmark ({os.cpu_count()} CPUs)", flush=True)
    with tempfile.TemporaryDirectory(prefix="msctl-bench-joints-") as tmp:
        dirs = _resolve(Path(tmp))
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
        client = open_session(_peer(endpoint))
        rows: list[tuple[str, str]] = []
        verdicts: list[tuple[str, bool]] = []
        try:
            print("latency: minimal, joint manager + simulator at speed 1 ...", flush=True)
            server = Server(dirs["minimal"], endpoint, 1.0, echo=True)
            try:
                bare = bare_round_trip(client, pings)
                latency = command_to_state(client, samples)
            finally:
                server.stop()
            timestep = _timestep(dirs["minimal"])
            bare50, bare99 = _ms(bare, 50), _ms(bare, 99)
            lat50, lat99 = _ms(latency, 50), _ms(latency, 99)
            budget = 3 * bare50 + timestep * 1e3
            rows += [
                (
                    "bare Zenoh round trip p50 / p99",
                    f"{bare50:.3f} / {bare99:.3f} ms (n={len(bare)})",
                ),
                (
                    "joint_set -> joint_read p50 / p99",
                    f"{lat50:.3f} / {lat99:.3f} ms (n={len(latency)})",
                ),
                ("simulation step", f"{timestep * 1e3:.1f} ms"),
                ("p50 / bare p50", f"{lat50 / bare50:.2f}x"),
                ("p50 / (3 x bare p50 + 1 step)", f"{lat50 / budget:.2f} (target <= 1)"),
            ]
            verdicts.append(("p50 within 3x bare round trip + 1 step", lat50 <= budget))
            for joints in (1, 7):
                cost = checks_cost(joints) * 1e3  # ms
                share = cost / lat50
                rows.append(
                    (
                        f"added checks, {joints}-joint command",
                        f"{cost * 1e3:.1f} us CPU = {share * 100:.2f} % of the p50",
                    )
                )
                verdicts.append((f"added checks < 5 % of p50 ({joints} joints)", share < 0.05))

            for name in ("dragon", "dragon_x4"):
                print(f"real-time factor: {name} ...", flush=True)
                physics = max_real_time_factor(load_assembly(dirs[name]), seconds=2.0)
                rows.append((f"{name}: physics only, max RTF", f"{physics:.1f}"))
                for speed in (5.0, 50.0):
                    server = Server(dirs[name], endpoint, speed, echo=False)
                    try:
                        live = live_rtf(client)
                    finally:
                        server.stop()
                    rows.append(
                        (
                            f"{name}: live at speed {speed:g}, RTF",
                            f"{live['real_time_factor']:.2f} (steps {live['step_rate_hz']:.0f}/s,"
                            f" states {live['state_rate_hz']:.0f}/s per module,"
                            f" physics load {live['load']:.2f})",
                        )
                    )
                    if name == "dragon_x4" and speed == 5.0:
                        verdicts.append(
                            ("dragon_x4 keeps up at speed 5", live["real_time_factor"] >= 4.9)
                        )
                    if name == "dragon_x4" and speed == 50.0:
                        verdicts.append(
                            ("dragon_x4 live max RTF >= 5", live["real_time_factor"] >= 5.0)
                        )
        finally:
            client.close()
            router.close()

    width = max(len(label) for label, _ in rows)
    print()
    for label, value in rows:
        print(f"  {label:<{width}}  {value}")
    print()
    for label, ok in verdicts:
        print(f"  [{'PASS' if ok else 'MISS'}] {label}")
    return 0 if all(ok for _, ok in verdicts) else 1


def _timestep(assembly_dir: Path) -> float:
    import mujoco

    from components.assembly import load_assembly

    model = mujoco.MjModel.from_xml_path(str(load_assembly(assembly_dir).mjcf_path))
    return float(model.opt.timestep)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=200, help="command-to-state samples")
    parser.add_argument("--pings", type=int, default=500, help="bare round-trip samples")
    parser.add_argument("--serve", metavar="ASSEMBLY_DIR", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--speed", type=float, default=1.0, help=argparse.SUPPRESS)
    parser.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve, args.endpoint, args.speed, args.echo)
        sys.exit(0)
    sys.exit(main(args.samples, args.pings))
