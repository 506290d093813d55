"""Health benchmark: what ``msctl health`` and the data monitor cost, and how fast the screen
says what happened, against baselines measured in the same run.

For each scenario (``dragon`` and ``two_dragons`` brought up simulated with ``msctl up
--detach``; ``fleet40``, 40 modules from :mod:`assemblies.fleet`, played by its emulator, with
a data monitor started as the launcher would), on this computer, each with its own
``MSCTL_HOME`` and a random loopback router port:

  * CPU at steady state (% of one core, user+system, over ``--window`` seconds after a warm
    up) of the real ``msctl health`` screen running in tmux (160x48), of each data monitor
    process, and of the baseline: a bare zenoh-python subscriber receiving every module's
    ``health`` and doing nothing else (what merely getting the data costs). Targets at 40
    modules: screen < 15 %, data monitor < 10 %.
  * On ``dragon``, with the screen in this process (textual's Pilot, the same refresh as in a
    terminal): the time from a component's SIGKILL to its ERROR on screen (target <= 1.5 s),
    and from a monitor's SIGSTOP to STALE on screen (target <= 2.5 s); the baseline of each
    is when its node left the graph, seen by a bare graph watcher in this process.

Run: ``python bench/health.py [--scenarios dragon two_dragons fleet40] [--window 15]
[--warmup 5] [--trials 3]`` (about 5 minutes on a loaded two-core machine, mostly bringing
the assemblies up). Needs tmux.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._common import free_port, msctl_env, print_table

HOST = "bench-health-laptop"  # none of the assemblies' computers: everything simulated
ROOT = Path(__file__).resolve().parents[1]

BASELINE = """
import signal, sys, threading, zenoh
config = zenoh.Config()
config.insert_json5("mode", '"client"')
config.insert_json5("connect/endpoints", '["%s"]')
config.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(config)
count = [0]
def on(_sample):
    count[0] += 1
subscriber = session.declare_subscriber("*/*/health/**", on)
done = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: done.set())
done.wait()
subscriber.undeclare()
session.close()
"""


@dataclass
class CpuResult:
    """One scenario's steady-state CPU figures (% of one core)."""

    scenario: str
    modules: int = 0
    screen: float = float("nan")
    monitors: list[float] = field(default_factory=list)
    baseline: float = float("nan")
    emulator: float | None = None


@dataclass
class Timing:
    """Screen reaction times (s) and their baselines."""

    kill_to_error: list[float] = field(default_factory=list)
    kill_to_gone: list[float] = field(default_factory=list)
    stop_to_stale: list[float] = field(default_factory=list)
    stop_to_gone: list[float] = field(default_factory=list)


def _env(home: Path, endpoint: str) -> dict[str, str]:
    return msctl_env(home, endpoint, HOST)


def _msctl(env: dict[str, str], *args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        check=False,
    )


def _cpu(pids: list[int], window: float) -> list[float]:
    """% of one core each of ``pids`` used over ``window`` seconds (user + system)."""
    import psutil

    processes = [psutil.Process(pid) for pid in pids]
    before = [p.cpu_times() for p in processes]
    start = time.monotonic()
    time.sleep(window)
    elapsed = time.monotonic() - start
    after = [p.cpu_times() for p in processes]
    return [
        100.0 * ((a.user + a.system) - (b.user + b.system)) / elapsed
        for a, b in zip(after, before, strict=True)
    ]


class Screen:
    """The real ``msctl health`` in a tmux session."""

    def __init__(self, env: dict[str, str], name: str) -> None:
        self.name = name
        exports = " ".join(
            f"{k}={v}" for k, v in env.items() if k.startswith("MSCTL_") or k == "PYTHONPATH"
        )
        command = f"exec env {exports} {sys.executable} -m msctl health"
        subprocess.run(
            ["tmux", "new-session", "-d", "-s", name, "-x", "160", "-y", "48", command],
            check=True,
        )
        out = subprocess.run(
            ["tmux", "display", "-p", "-t", name, "#{pane_pid}"],
            capture_output=True,
            text=True,
            check=True,
        )
        self.pid = int(out.stdout.strip())

    def text(self) -> str:
        """What the pane shows."""
        return subprocess.run(
            ["tmux", "capture-pane", "-p", "-t", self.name], capture_output=True, text=True
        ).stdout

    def wait_for(self, words: list[str], timeout: float) -> None:
        """Until every word is on screen."""
        deadline = time.monotonic() + timeout
        while not all(w in self.text() for w in words):
            if time.monotonic() > deadline:
                raise SystemExit(f"the screen did not show {words} in {timeout} s:\n{self.text()}")
            time.sleep(0.5)

    def close(self) -> None:
        """Quit it."""
        subprocess.run(["tmux", "kill-session", "-t", self.name], capture_output=True)


def _monitor_pids(env: dict[str, str]) -> list[int]:
    result = _msctl(env, "ps", "--json")
    rows = json.loads(result.stdout)["components"]
    return sorted({r["pid"] for r in rows if r["kind"] == "data_monitor" and r["pid"]})


def _measure(
    scenario: str,
    env: dict[str, str],
    endpoint: str,
    modules: list[str],
    monitor_pids: list[int],
    window: float,
    warmup: float,
    emulator: int | None = None,
) -> CpuResult:
    result = CpuResult(scenario, len(modules))
    baseline = subprocess.Popen(
        [sys.executable, "-c", BASELINE % endpoint], stdin=subprocess.DEVNULL
    )
    screen = Screen(env, f"bench-health-{os.getpid()}-{scenario}")
    try:
        screen.wait_for([modules[0], modules[-1], "router linked"], timeout=300.0)
        time.sleep(warmup)
        pids = [screen.pid, baseline.pid, *monitor_pids] + ([emulator] if emulator else [])
        figures = _cpu(pids, window)
        result.screen, result.baseline = figures[0], figures[1]
        result.monitors = figures[2 : 2 + len(monitor_pids)]
        if emulator:
            result.emulator = figures[-1]
    finally:
        screen.close()
        baseline.terminate()
        baseline.wait(timeout=10.0)
    return result


def run_up(
    template: str, window: float, warmup: float, trials: int
) -> tuple[CpuResult, Timing | None]:
    """Bring ``template`` up simulated, measure, bring it down."""
    from components.assembly import load_assembly

    home = Path(tempfile.mkdtemp(prefix=f"msctl_bench_health_{template}_"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = _env(home, endpoint)
    up = _msctl(env, "up", template, "--detach", "--sim", "--timeout", "240", timeout=600.0)
    if up.returncode != 0:
        raise SystemExit(f"msctl up {template} failed:\n{up.stderr[-3000:]}")
    try:
        assembly = load_assembly(home / "assembly")
        modules = [m.slot for m in assembly.modules]
        result = _measure(template, env, endpoint, modules, _monitor_pids(env), window, warmup)
        timing = _timings(env, home, trials) if template == "dragon" and trials else None
    finally:
        _msctl(env, "down", timeout=120.0)
    return result, timing


def run_fleet(count: int, window: float, warmup: float) -> CpuResult:
    """The generated fleet: router in this process, emulator and data monitor as processes."""
    from assemblies.fleet import write_fleet
    from components.comm.session import SessionSettings, open_session

    home = Path(tempfile.mkdtemp(prefix=f"msctl_bench_health_fleet{count}_"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = _env(home, endpoint)
    lock = write_fleet(home, count)
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    children: list[subprocess.Popen] = []
    try:
        emulator = subprocess.Popen(
            [sys.executable, "-m", "assemblies.fleet", "emulate", "--lock", str(lock)],
            env=env,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
        )
        children.append(emulator)
        monitor = subprocess.Popen(
            [sys.executable, "-m", "components.executor.worker", "--lock", str(lock),
             "--component", "gc1/data_monitor"],
            env=env,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        children.append(monitor)
        modules = [f"m{i:02d}" for i in range(count)]
        return _measure(
            f"fleet{count}", env, endpoint, modules, [monitor.pid], window, warmup, emulator.pid
        )
    finally:
        for child in reversed(children):
            child.send_signal(signal.SIGINT)
            try:
                child.wait(timeout=30.0)
            except subprocess.TimeoutExpired:
                child.kill()
        router.close()


# ---------------------------------------------------------------------------------- timings
def _timings(env: dict[str, str], home: Path, trials: int) -> Timing:
    """SIGKILL -> ERROR and SIGSTOP -> STALE on a screen run in this process (Pilot)."""
    for key, value in env.items():
        if key.startswith("MSCTL_"):
            os.environ[key] = value
    from components.assembly import load_assembly
    from components.data_monitor.feeds import NodeFeed
    from msctl.health.app import HealthApp
    from msctl.health.live import LiveHealth
    from msctl.plane import connected

    assembly = load_assembly(home / "assembly")
    timing = Timing()
    gone: dict[str, float] = {}
    lock = threading.Lock()

    def on_node(node: str, count: int) -> None:
        if count == 0:
            with lock:
                gone.setdefault(node, time.monotonic())

    def pid_of(component: str) -> int:
        rows = json.loads(_msctl(env, "ps", "--json").stdout)["components"]
        return next(r["pid"] for r in rows if r["name"] == component)

    async def scenario(live: LiveHealth) -> None:
        app = HealthApp(live, fetch_history=False)
        async with app.run_test(size=(160, 48)) as pilot:

            async def until(predicate: Any, timeout: float) -> float | None:
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    if app.snapshot is not None and predicate(app.snapshot):
                        return time.monotonic()
                    await pilot.pause(0.01)
                return None

            def settled(module: str) -> Any:
                def check(snapshot: Any) -> bool:
                    row = snapshot.row(module)
                    health = next(i for i in row.items if i.name == f"{module}/health")
                    return health.level.name == "OK" and all(
                        c.level.name == "OK" and c.state == "running" for c in row.components
                    )

                return check

            def item(module: str, name: str, levels: tuple[str, ...]) -> Any:
                def check(snapshot: Any) -> bool:
                    row = snapshot.row(module)
                    return any(
                        i.name == f"{module}/{name}" and i.level.name in levels for i in row.items
                    )

                return check

            for _ in range(trials):
                if await until(settled("wheel2"), 300.0) is None:
                    raise SystemExit("wheel2 did not settle")
                pid = pid_of("wheel2/joint_manager")
                with lock:
                    gone.clear()
                killed = time.monotonic()
                os.kill(pid, signal.SIGKILL)
                seen = await until(item("wheel2", "components/joint_manager", ("ERROR",)), 30.0)
                if seen is not None:
                    timing.kill_to_error.append(seen - killed)
                with lock:
                    if "/wheel2/joint_manager" in gone:
                        timing.kill_to_gone.append(gone["/wheel2/joint_manager"] - killed)
            for _ in range(trials):
                if await until(settled("limb2"), 300.0) is None:
                    raise SystemExit("limb2 did not settle")
                pid = pid_of("limb2/health_monitor")
                with lock:
                    gone.clear()
                stopped = time.monotonic()
                os.kill(pid, signal.SIGSTOP)
                quiet = item("limb2", "health", ("STALE",))
                frozen = item("limb2", "components/health_monitor", ("STALE",))
                try:
                    seen = await until(lambda s, q=quiet, f=frozen: q(s) or f(s), 30.0)
                finally:
                    os.kill(pid, signal.SIGCONT)
                if seen is not None:
                    timing.stop_to_stale.append(seen - stopped)
                with lock:
                    if "/limb2/health_monitor" in gone:
                        timing.stop_to_gone.append(gone["/limb2/health_monitor"] - stopped)

    with connected("bench_health") as node, LiveHealth(node, assembly) as live:
        feed = NodeFeed({"/wheel2/joint_manager", "/limb2/health_monitor"}, on_node)
        feed.attach(node.session, node.domain)
        try:
            asyncio.run(scenario(live))
        finally:
            feed.close()
    return timing


def _stat(values: list[float]) -> str:
    if not values:
        return "-"
    return f"{statistics.median(values):.2f} (max {max(values):.2f}, n={len(values)})"


def main() -> None:
    """Run the scenarios and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=["dragon", "two_dragons", "fleet40"])
    parser.add_argument("--window", type=float, default=15.0, help="CPU window (s)")
    parser.add_argument("--warmup", type=float, default=5.0, help="after the screen is up (s)")
    parser.add_argument("--trials", type=int, default=3, help="kills and stops on dragon")
    args = parser.parse_args()
    if shutil.which("tmux") is None:
        raise SystemExit("bench/health.py runs the real screen in tmux: apt-get install tmux")
    import psutil

    results: list[CpuResult] = []
    timing: Timing | None = None
    for scenario in args.scenarios:
        print(f"{scenario}: starting (load {os.getloadavg()[0]:.1f})", flush=True)
        if scenario.startswith("fleet"):
            results.append(run_fleet(int(scenario[5:] or 40), args.window, args.warmup))
        else:
            result, measured = run_up(scenario, args.window, args.warmup, args.trials)
            results.append(result)
            timing = timing or measured
    rows = []
    for r in results:
        monitor = statistics.fmean(r.monitors) if r.monitors else float("nan")
        rows.append(
            (
                r.scenario,
                r.modules,
                f"{r.screen:.1f}",
                f"{monitor:.1f} x{len(r.monitors)}",
                f"{r.baseline:.1f}",
                f"{r.screen / r.baseline:.1f}" if r.baseline > 0 else "-",
                f"{monitor / r.baseline:.1f}" if r.baseline > 0 else "-",
                "-" if r.emulator is None else f"{r.emulator:.1f}",
            )
        )
    print_table(
        f"CPU at steady state, % of one core over {args.window:g} s "
        f"({psutil.cpu_count()} cores; targets at 40 modules: screen < 15, monitor < 10)",
        (
            "scenario",
            "modules",
            "screen",
            "data monitor (each)",
            "baseline sub",
            "screen/base",
            "monitor/base",
            "emulator",
        ),
        rows,
    )
    if timing is not None:
        print_table(
            "dragon: reaction on screen, s (median, max); baseline: the node leaving the graph",
            ("event", "on screen", "baseline", "target"),
            [
                ("SIGKILL -> ERROR", _stat(timing.kill_to_error), _stat(timing.kill_to_gone), 1.5),
                ("SIGSTOP -> STALE", _stat(timing.stop_to_stale), _stat(timing.stop_to_gone), 2.5),
            ],
        )
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
