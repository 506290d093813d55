"""A dead motor bus never delays the joint manager's 50 Hz watchdog tick.

A G-line limb's motor interface (the Dynamixel backend, real dynamixel-sdk over a pty to the
emulated servo chain) and its joint manager run in one process and one executor thread,
exactly as the worker runs them (:func:`components.executor.runner.run_built`). Once the limb
is up, every servo on the chain stops answering: the emulator keeps reading the line and never
replies, as a chain does whose power dropped while the USB adapter stays plugged in. Every
exchange with such a chain waits for a full reply timeout; none of that may reach the executor
thread, so the joint manager keeps ticking on time while the motor interface reports the
silent servos.

The bound is generous (the test machine is a loaded two-core box); the measured p50 and p99
are printed (run with ``-s``).
"""

from __future__ import annotations

import itertools
import statistics
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from conftest import resolved_assembly, wait_until

from components.assembly import ResolvedAssembly
from components.build import build_component
from components.comm.session import SessionSettings
from components.executor.executor import Executor
from components.executor.runner import run_built
from components.motors.emulation.dynamixel import EmulatedDynamixelChain

pytestmark = pytest.mark.e2e

SLOT = "limb1"
UNIT = "gl-limb-01"
#: The joint manager's tick period (its interface: Every(0.02, "tick")).
TICK_PERIOD = 0.02
#: p99 of the gap between two ticks: 12 periods, far below the hundreds of ms a dead chain
#: costs per exchange round (one reply timeout per servo) when the I/O runs on the tick thread.
P99_BOUND = 0.25
#: How long the ticks are observed with the chain dead.
OBSERVE_S = 3.0
#: Reply timeout as for a slow adapter (the emulator is a Python thread on a loaded machine):
#: every exchange with a silent servo costs 2 * 40 + 2 = 82 ms.
BUS_OPTIONS = {"latency_timer_ms": 40.0}


@pytest.fixture(scope="module")
def assembly(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    """``minimal`` with a G-line limb (a Dynamixel chain) in limb1."""
    return resolved_assembly(tmp_path_factory.mktemp("dead-bus"), "minimal", {SLOT: UNIT})


def percentile(values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1) of ``values``, nearest rank."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * len(ordered)) - 1))]


def test_a_dead_chain_never_delays_the_joint_manager_tick(
    assembly: ResolvedAssembly, session_settings: SessionSettings
) -> None:
    module = assembly.module(SLOT)
    joints = module.actuated_joints
    with EmulatedDynamixelChain(
        ids=[j.motor_id for j in joints], models={j.motor_id: j.motor_model for j in joints}
    ) as chain:
        options = {"channel": chain.port, "bus_options": dict(BUS_OPTIONS)}
        motors = build_component(assembly.component(f"{SLOT}/motor_interface"), assembly, options)
        manager = build_component(assembly.component(f"{SLOT}/joint_manager"), assembly, options)
        backend = motors.core.backend

        ticks: list[float] = []
        tick = manager.core.tick

        def timed_tick(now: float, tick: Callable[[float], None] = tick) -> None:
            ticks.append(time.monotonic())
            tick(now)

        manager.core.tick = timed_tick  # bound by the executor when it adds the core

        ready = threading.Event()
        executors: list[Executor] = []

        def on_ready(executor: Executor) -> None:
            executors.append(executor)
            ready.set()

        failures: list[BaseException] = []

        def worker() -> None:
            try:
                run_built([motors, manager], session_settings, on_ready=on_ready)
            except BaseException as exc:  # reported by the test thread
                failures.append(exc)
                ready.set()

        runner = threading.Thread(target=worker, name="executor-dead-bus", daemon=True)
        runner.start()
        try:
            assert ready.wait(30.0) and not failures, failures

            def levels() -> dict[str, int]:
                return {d.joint: d.level for d in backend.diagnostics() if d.joint}

            wait_until(
                lambda: (
                    set(levels()) == {j.raw_name for j in joints} and set(levels().values()) == {0}
                ),
                15.0,
                "every servo OK",
            )
            wait_until(lambda: len(ticks) > 10, 10.0, "the joint manager ticking")

            for j in joints:
                chain.silence(j.motor_id)
            dead_at = time.monotonic()
            wait_until(
                lambda: set(levels().values()) == {2}, 15.0, "every silent servo reported ERROR"
            )
            # The observation window: the ticks a dead chain would delay (retries, re-probes)
            # keep coming for as long as the chain stays dead.
            wait_until(lambda: time.monotonic() - dead_at >= OBSERVE_S, OBSERVE_S + 15.0)
            observed = [t for t in list(ticks) if t >= dead_at]
        finally:
            if executors:
                executors[0].stop()
            runner.join(timeout=20.0)
        assert not runner.is_alive(), "the executor did not stop"
        assert not failures, failures

    gaps = [b - a for a, b in itertools.pairwise(observed)]
    assert gaps, f"no joint manager tick in {OBSERVE_S} s with a dead chain"
    p50, p99 = statistics.median(gaps), percentile(gaps, 0.99)
    print(
        f"\njoint manager tick with a dead chain: {len(gaps)} gaps over {OBSERVE_S:g} s, "
        f"p50 {p50 * 1000:.1f} ms, p99 {p99 * 1000:.1f} ms, max {max(gaps) * 1000:.1f} ms "
        f"(nominal {TICK_PERIOD * 1000:.0f} ms)"
    )
    assert p99 < P99_BOUND, f"p99 tick gap {p99:.3f} s with a dead chain (bound {P99_BOUND} s)"
    # A quarter of the nominal count: the executor skips ticks it fell behind on, never bursts.
    assert len(gaps) >= OBSERVE_S / TICK_PERIOD / 4, f"only {len(gaps)} ticks in {OBSERVE_S} s"


def test_percentile_is_nearest_rank() -> None:
    values: list[Any] = [float(i) for i in range(1, 101)]
    assert percentile(values, 0.99) == 99.0
    assert percentile(values, 0.5) == 50.0
    assert percentile([0.3], 0.99) == 0.3
