"""Launch benchmark: ``msctl up`` to all-healthy, against the floor of bare interpreters, and
recovery after the router restarts.

In one run, for ``dragon`` and ``two_dragons`` (the paper's 60-component deployment), in
simulation on this computer (off-robot), each with its own ``MSCTL_HOME`` and a random
loopback router port:

  * up: from invoking ``msctl up TEMPLATE --sim`` (resolution included, as a user types it) to
    its "up in" line, printed once every component is healthy (its node seen on the graph and
    its first output received); the launcher's own figure is shown too;
  * the floor: the same number of bare ``python -c "import zenoh"`` processes started at
    once and waited for, N = the processes msctl starts (router included) and N = the
    assembly's components (one process per component, as in a ROS launch); each measured
    just before and just after that template's run and averaged, so load that drifts over
    the run (a shared machine) weighs on both sides of the ratio alike;
  * router restart: the embedded router SIGKILLed; time until it listens again (the
    supervisor restarts it), then until data flows through it again (a fresh client
    subscriber, which only the router can feed, gets a simulator ``joint_states``), and for
    a client subscribed before the kill;
  * shutdown: Ctrl-C (SIGINT) to exit, every process group checked gone.

msctl's sources are compiled before anything is timed, as an installed msctl has them
(``bench._common.compiled_sources``): with ``PYTHONDONTWRITEBYTECODE`` set, every msctl
process compiled them from source on each run.

Only components whose kind exists in the code are started; the count of the plan's total
is printed (never a placeholder to make up the number): a component counts as started when
it runs itself, or when it is a motor interface and the simulator standing in for it runs.
Targets on the 2-core machine: ``two_dragons`` all-healthy within 2.5x the floor of its
components (issue 16); data again under 1 s after the router restarts.

Run: ``python bench/launch.py [--templates dragon two_dragons]``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench._common import compiled_sources, free_port, msctl_env, print_table
from components import kinds
from msctl.launcher.state import process_group_alive

HOST = "bench-laptop"  # none of the robots' computers: the whole assembly runs here, simulated


@dataclass
class Result:
    """What one template's run measured."""

    template: str
    planned: int = 0
    started: int = 0
    started_themselves: int = 0
    simulated_motors: int = 0
    not_built: list[tuple[str, str]] = field(default_factory=list)
    processes: int = 0
    up_s: float = float("nan")
    launcher_s: float = float("nan")
    router_listen_s: float = float("nan")
    fresh_data_s: float = float("nan")
    existing_data_s: float = float("nan")
    restarted_components: int = 0
    shutdown_s: float = float("nan")
    leftovers: int = 0
    floor_processes_s: list[float] = field(default_factory=list)
    floor_components_s: list[float] = field(default_factory=list)
    router_problem: str = ""

    @property
    def ratio(self) -> float:
        """``msctl up`` over the floor of one bare interpreter per planned component."""
        return self.up_s / (sum(self.floor_components_s) / len(self.floor_components_s))


def _state(home: Path) -> dict:
    return json.loads((home / "run" / "state.json").read_text())


def _listening(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.05)
        return sock.connect_ex(("127.0.0.1", port)) == 0


class _FirstSample:
    """A client-mode subscriber (it reaches the others only through the router)."""

    def __init__(self, endpoint: str, topic: str) -> None:
        from components.comm.node import Node
        from components.comm.session import SessionSettings, open_session
        from components.messages import JOINT_STATE

        self.received = threading.Event()
        self.at = 0.0
        self._after = float("-inf")
        settings = SessionSettings(mode="client", connect=(endpoint,), listen=())
        self.session = open_session(settings)
        self.node = Node(self.session, "bench_launch", "/bench")
        self.node.subscription(topic, JOINT_STATE, self._on, raw=True)

    def _on(self, _payload: object) -> None:
        now = time.monotonic()
        if not self.received.is_set() and now >= self._after:
            self.at = now
            self.received.set()

    def rearm(self, after: float) -> None:
        """Wait for a sample again, counting only those that arrive from ``after`` on (one
        already on its way through the old router arrives late, and is not the new one's)."""
        self._after = after
        self.received.clear()

    def close(self) -> None:
        self.node.close()
        self.session.close()


class RouterProblem(RuntimeError):
    """The router-restart part could not be measured (reported beside the start-up figures)."""


#: Seconds the restarted router has to listen again (a heavily loaded machine took 12 s).
ROUTER_BACK_WITHIN = 45.0


def started_components(assembly: Any, plan: Any) -> tuple[int, int]:
    """``(run as themselves, motor interfaces the simulator runs for)`` of a host plan.

    A motor interface counts only when the plan starts the simulator standing in for it.
    """
    themselves = sum(not kinds.get(c.kind).stands_in_for for c in plan.components)
    simulator = any(kinds.get(c.kind).stands_in_for for c in plan.components)
    replaced = sum(kinds.replaced_in_simulation(c.kind) for c in assembly.components)
    return themselves, replaced if simulator else 0


def _router_restart(result: Result, home: Path, endpoint: str, topic: str) -> None:
    from components.comm.session import SessionOpenError

    port = int(endpoint.rsplit(":", 1)[1])
    before = {p["name"]: p["restarts"] for p in _state(home)["processes"]}
    router = next(p for p in _state(home)["processes"] if p["name"] == "router")
    existing = _FirstSample(endpoint, topic)
    try:
        if not existing.received.wait(5.0):
            raise RouterProblem(f"no {topic} through the router before the kill")
        existing.rearm(float("inf"))  # nothing counts until the router listens again
        os.killpg(router["pgid"], signal.SIGKILL)
        killed = time.monotonic()
        while _listening(port) and time.monotonic() - killed < 2.0:
            time.sleep(0.002)  # the old socket closes with the process
        while not _listening(port):
            if time.monotonic() - killed > ROUTER_BACK_WITHIN:
                raise RouterProblem(
                    f"the router did not listen again within {ROUTER_BACK_WITHIN:g} s"
                )
            time.sleep(0.005)
        listening = time.monotonic()
        existing.rearm(listening)
        result.router_listen_s = listening - killed
        fresh = None
        while fresh is None and time.monotonic() - listening < 10.0:
            try:
                fresh = _FirstSample(endpoint, topic)
            except SessionOpenError:
                time.sleep(0.01)
        if fresh is None:
            raise RouterProblem("cannot reach the restarted router")
        try:
            if fresh.received.wait(10.0):
                result.fresh_data_s = fresh.at - listening
        finally:
            fresh.close()
        if existing.received.wait(10.0):
            result.existing_data_s = existing.at - listening
    finally:
        existing.close()
    after = {p["name"]: p["restarts"] for p in _state(home)["processes"]}
    result.restarted_components = sum(
        after[name] != count for name, count in before.items() if name != "router"
    )


def _run_template(template: str) -> Result:
    """Resolve ``template``, measure the floors, ``msctl up`` it, measure the floors again."""
    from components.assembly import load_assembly
    from msctl.launcher.plan import plan_host

    result = Result(template)
    home = Path(tempfile.mkdtemp(prefix=f"msctl_bench_{template}_"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = msctl_env(home, endpoint, HOST)
    # Resolved once first, for the floors' N (`up` below resolves it again, as typed).
    subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", template],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=True,
    )
    assembly = load_assembly(home / "assembly")
    plan = plan_host(assembly, HOST, sim=True)
    result.planned = len(assembly.components)
    result.started_themselves, result.simulated_motors = started_components(assembly, plan)
    result.started = result.started_themselves + result.simulated_motors
    result.not_built = list(plan.not_built)
    result.processes = len(plan.processes) + 1  # the router included
    result.floor_processes_s.append(floor(result.processes))
    result.floor_components_s.append(floor(result.planned))
    _run_up(result, home, env, endpoint)
    result.floor_processes_s.append(floor(result.processes))
    result.floor_components_s.append(floor(result.planned))
    return result


def _run_up(result: Result, home: Path, env: dict[str, str], endpoint: str) -> None:
    """``msctl up``, the router restart and Ctrl-C, measured into ``result``."""
    from components.assembly import load_assembly

    template = result.template
    stderr_lines: list[str] = []
    up_line = threading.Event()
    started = time.monotonic()
    up = subprocess.Popen(
        [sys.executable, "-m", "msctl", "up", template, "--sim", "--timeout", "60"],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )

    def read() -> None:
        assert up.stderr is not None
        for line in up.stderr:
            stderr_lines.append(line)
            if f"{template} up in" in line and not up_line.is_set():
                result.up_s = time.monotonic() - started
                result.launcher_s = float(line.split(" up in ")[1].split()[0])
                up_line.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    pgids: set[int] = {up.pid}
    try:
        while not up_line.wait(0.1):
            if up.poll() is not None or time.monotonic() - started > 90.0:
                raise SystemExit(f"msctl up {template} failed:\n" + "".join(stderr_lines[-30:]))
        assembly = load_assembly(home / "assembly")
        document = _state(home)
        pgids |= {p["pgid"] for p in document["processes"] if p["pgid"]}
        result.processes = len(document["processes"])  # the router included
        first_module = assembly.modules[0].namespace
        try:
            _router_restart(result, home, endpoint, f"{first_module}/joint_states")
        except RouterProblem as exc:
            result.router_problem = str(exc)  # the start-up figures still stand
        pgids |= {p["pgid"] for p in _state(home)["processes"] if p["pgid"]}
        stopping = time.monotonic()
        os.killpg(up.pid, signal.SIGINT)  # Ctrl-C in its terminal
        up.wait(timeout=30.0)
        result.shutdown_s = time.monotonic() - stopping
        time.sleep(0.05)
        result.leftovers = sum(process_group_alive(pgid) for pgid in pgids)
    finally:
        for pgid in pgids:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        up.wait(timeout=5.0)
        reader.join(timeout=2.0)


def floor(count: int) -> float:
    """Seconds to start ``count`` bare ``python -c "import zenoh"`` at once and wait for all."""
    started = time.monotonic()
    children = [
        subprocess.Popen([sys.executable, "-c", "import zenoh"], stdin=subprocess.DEVNULL)
        for _ in range(count)
    ]
    for child in children:
        child.wait()
    return time.monotonic() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--templates", nargs="+", default=["dragon", "two_dragons"])
    args = parser.parse_args()
    print(f"msctl launch benchmark on {os.cpu_count()} cores, simulated, off-robot ({HOST})")
    compiled_sources()
    results = [_run_template(template) for template in args.templates]

    for r in results:
        kinds = sorted({k for _, k in r.not_built})
        print(
            f"{r.template}: started {r.started} of {r.planned} components "
            f"({r.started_themselves} run as themselves, {r.simulated_motors} motor interfaces "
            "by the simulator standing in for them"
            + (f"; not built yet: {len(r.not_built)} ({', '.join(kinds)})" if kinds else "")
            + f") in {r.processes} processes, router included"
        )

    def floors(values: list[float]) -> str:
        return f"{sum(values) / len(values):.2f} ({' / '.join(f'{v:.2f}' for v in values)})"

    print_table(
        "msctl up -> all healthy (s), against N bare `python -c 'import zenoh'` at once "
        "(floors: mean (just before / just after the run))",
        [
            "template",
            "started",
            "processes",
            "msctl up (s)",
            "launcher (s)",
            "floor N=processes",
            "floor N=components",
            "up / floor N=components",
            "Ctrl-C exit (s)",
            "groups left",
        ],
        [
            [
                r.template,
                f"{r.started}/{r.planned}",
                r.processes,
                f"{r.up_s:.2f}",
                f"{r.launcher_s:.2f}",
                f"{floors(r.floor_processes_s)} N={r.processes}",
                f"{floors(r.floor_components_s)} N={r.planned}",
                f"{r.ratio:.2f}x",
                f"{r.shutdown_s:.2f}",
                r.leftovers,
            ]
            for r in results
        ],
    )
    print_table(
        "Router SIGKILLed (supervisor restarts it), seconds",
        [
            "template",
            "kill -> listening",
            "listening -> data (fresh client)",
            "listening -> data (client from before)",
            "kill -> data",
            "components restarted",
        ],
        [
            [
                r.template,
                f"{r.router_listen_s:.2f}",
                f"{r.fresh_data_s:.2f}",
                f"{r.existing_data_s:.2f}",
                f"{r.router_listen_s + max(r.fresh_data_s, r.existing_data_s):.2f}",
                r.restarted_components,
            ]
            for r in results
        ],
    )
    for r in results:
        if r.router_problem:
            print(f"{r.template}: router restart not measured: {r.router_problem}")
    two = next((r for r in results if r.template == "two_dragons"), None)
    print("\ntargets:")
    if two is not None:
        verdict = "met" if two.ratio <= 2.5 and two.started == two.planned else "NOT met"
        print(
            f"  two_dragons all-healthy, {two.started} of {two.planned} components, within 2.5x "
            f"the floor of {two.planned} bare interpreters: {two.ratio:.2f}x, {verdict}"
        )
    worst = max(max(r.fresh_data_s, r.existing_data_s) for r in results)
    verdict = "met" if worst < 1.0 else "NOT met"
    print(f"  data again < 1 s after the router restarts: worst {worst:.2f} s, {verdict}")


if __name__ == "__main__":
    main()
