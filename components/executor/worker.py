"""A component process: builds the named components of a resolved assembly and runs them.

The launcher starts one of these per process group (a module, the simulator, a ground
station) with an argument list made only from the assembly's own data::

    python -m msctl.launcher.boot components.executor.worker --lock PATH --component ...

(:mod:`msctl.launcher.boot` first makes an early Ctrl-C end it silently; run by hand,
``python -m components.executor.worker ...`` works the same.) Under a supervisor, the executor
loop beats a heartbeat pipe the supervisor hands down (``MSCTL_HEARTBEAT_FD``,
:mod:`components.executor.heartbeat`), so a frozen worker is noticed, and reads its orders
(``MSCTL_ORDERS_FD``, :mod:`components.executor.orders`: rebuild one component alone).

Exit codes: 0 after a clean stop (SIGINT/SIGTERM), 3 when a component cannot be built (the
reason is the last line of stderr, which the launcher shows), 2 for bad arguments, 1 when a
component failed while running (an operator's script raised: restarted, with backoff).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from components import kinds
from components.assembly import AssemblyError, load_assembly
from components.build import BuildError, build_component, simulator_plan
from components.comm.session import SessionConfigError, SessionSettings
from components.executor.heartbeat import Heartbeat
from components.motors.emulation import EMULATE_ENV

#: Seconds between GIL hand-overs in a component process (see :func:`main`).
SWITCH_INTERVAL = 0.0005


def main(argv: list[str] | None = None) -> int:
    """Run the worker; returns the process exit code."""
    parser = argparse.ArgumentParser(prog="msctl-worker", description=__doc__.split("\n")[0])
    parser.add_argument("--lock", required=True, type=Path, help="assembly.lock.json to read")
    parser.add_argument(
        "--component", action="append", required=True, help="component name (repeatable)"
    )
    parser.add_argument("--speed", type=float, default=1.0, help="simulation speed factor")
    parser.add_argument("--for", dest="duration", type=float, default=None)
    args = parser.parse_args(argv)
    # A Zenoh callback (a halt's request, a sample) needs the GIL the executor thread holds
    # while it works; Python hands it over only every switch interval (5 ms by default), so
    # every request waited up to that twice over. 0.5 ms: halts answered sooner (bench/teleop.py
    # --part estop), for little more switching.
    sys.setswitchinterval(SWITCH_INTERVAL)
    logging.basicConfig(
        level=logging.INFO,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    log = logging.getLogger("msctl.worker")
    # Taken first, so that nothing built below inherits the supervisor's pipe.
    heartbeat = Heartbeat.from_env()
    try:
        assembly = load_assembly(args.lock)
    except AssemblyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    # Assembly-wide stand-ins (the simulator) are in no lock file: the launcher names them.
    stand_ins = {k.component_name: k.name for k in kinds.simulators()}
    options = {
        "sim": any(name in stand_ins for name in args.component),
        "speed": args.speed,
        # A rehearsal's robot computer: real backends against emulated hardware.
        "emulate": os.environ.get(EMULATE_ENV) == "1",
    }
    _yield_cpu(args.component, stand_ins, assembly)

    def build(name: str) -> Any:
        plan = simulator_plan(stand_ins[name]) if name in stand_ins else assembly.component(name)
        item = build_component(plan, assembly, options)
        log.info("built %s (%s)", name, plan.kind)
        return item

    # Started through msctl.launcher.boot, a SIGINT ended this process at once until here
    # (nothing to close). While building (the supervisor stopping a run still starting), one
    # is noted and acted on between components, what was built closed: raised as
    # KeyboardInterrupt inside the builders' imports instead, it can turn into another error
    # (MuJoCo's extension then fails with an ImportError) and a traceback.
    interrupted = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: interrupted.set())
    built = []
    try:
        for name in args.component:
            if interrupted.is_set():
                raise KeyboardInterrupt
            built.append(build(name))
        if interrupted.is_set():
            raise KeyboardInterrupt
    except (BuildError, AssemblyError, KeyError) as exc:
        for item in built:
            item.close()
        print(f"error: cannot build {name}: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        for item in built:
            item.close()
        log.info("stopped while building (SIGINT)")
        return 0
    transport = os.environ.get("MSCTL_TRANSPORT", "zenoh")
    try:
        # Built: until the executor takes SIGINT over, it interrupts at once, not after
        # every component is bound.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        if interrupted.is_set():
            raise KeyboardInterrupt
        if transport not in ("zenoh", "rclpy"):
            for item in built:
                item.close()
            print(f"error: MSCTL_TRANSPORT={transport!r}: use zenoh or rclpy", file=sys.stderr)
            return 2
        from components.executor.runner import ComponentFailed, RebuildFailed, run_built

        settings = SessionSettings.launched()
        try:
            run_built(
                built,
                settings=settings,
                duration=args.duration,
                heartbeat=heartbeat,
                rebuild=build,
                transport=transport,
            )
        except RebuildFailed as exc:
            # Not a final exit: restarted whole, the process builds everything afresh.
            print(f"error: {exc}; restarting the whole process", file=sys.stderr)
            return 1
        except ComponentFailed as exc:
            # A crash like any other (an operator's script raised): started again.
            print(f"error: {exc}", file=sys.stderr)
            return 1
    except (SessionConfigError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:  # before the executor ran
        for item in built:
            item.close()  # what run_built had not closed yet (closing is idempotent)
        log.info("stopped while starting (SIGINT)")
        return 0
    log.info("stopped cleanly")
    return 0


def _yield_cpu(names: list[str], stand_ins: dict[str, str], assembly: Any) -> None:
    """Lower this process's CPU priority as its kinds ask (:attr:`ComponentKind.niceness`).

    Done before anything is built: every thread made later (Zenoh's, the executor's)
    inherits it, where a nice value set afterwards would reach this thread only.
    """
    try:
        niceness = kinds.process_niceness(
            stand_ins.get(name) or assembly.component(name).kind for name in names
        )
    except LookupError:
        return  # an unknown component or kind: refused below, with its own message
    if niceness > 0:
        os.nice(niceness)


if __name__ == "__main__":
    sys.exit(main())
