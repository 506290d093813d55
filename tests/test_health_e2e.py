"""Health monitor end to end on real Zenoh, plus the executor pieces it relies on.

The monitored components run in a subprocess so that SIGKILL is a real crash: the router
sees the link drop and the components' liveliness tokens vanish, as in the field.
"""

from __future__ import annotations

import threading

from components.comm.session import SessionSettings
from components.executor.core import Core
from components.executor.executor import Executor
from components.executor.interface import InterfaceSpec


class _Recorder(Core):
    def __init__(self) -> None:
        super().__init__("recorder")
        self.calls: list[tuple] = []

    def on_event(self, *args: object) -> None:
        self.calls.append((threading.current_thread().name, *args))


def test_call_soon_runs_on_the_executor_thread_with_now(session_settings: SessionSettings) -> None:
    """call_soon from another thread: handler(*args, now) runs on the run() thread, in order."""
    clock_values = iter(range(1000))
    with Executor(session_settings, clock=lambda: float(next(clock_values))) as executor:
        core = _Recorder()
        component = executor.add(core, InterfaceSpec(), "/test", "recorder")
        poster = threading.Thread(
            target=lambda: [executor.call_soon(component, "on_event", "a", i) for i in range(3)],
            name="poster",
        )
        poster.start()
        poster.join()
        executor.call_soon(component, core.on_event, "callable")
        executor.call_soon(component, lambda now: executor.stop())
        executor.run(duration=5.0)
    runner = threading.current_thread().name
    assert [c[1:-1] for c in core.calls] == [("a", 0), ("a", 1), ("a", 2), ("callable",)]
    assert all(c[0] == runner for c in core.calls)
    assert all(isinstance(c[-1], float) for c in core.calls)
    assert component.errors == 0
