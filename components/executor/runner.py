"""Run built components (:class:`~components.build.BuiltComponent`) in one executor.

This is the one place that knows the order a process goes through, so the launcher and tests
do not each reinvent it:

1. open one Zenoh session;
2. add every built core to one :class:`~components.executor.executor.Executor`;
3. call each component's ``on_bound(executor, component)`` hook (e.g. the health monitor
   starts watching the graph on the executor's session);
4. run until ``duration``, a signal, or :meth:`Executor.stop`; every core's ``stop`` runs;
5. close every component's resources (graph watchers, motor buses) while the session is
   still open, so their Zenoh declarations are undone cleanly;
6. close the session.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from components.comm.session import SessionSettings, open_session
from components.executor.executor import Executor
from components.executor.heartbeat import Heartbeat

if TYPE_CHECKING:
    from components.build import BuiltComponent


def run_built(
    built: Sequence[BuiltComponent],
    settings: SessionSettings | None = None,
    duration: float | None = None,
    on_ready: Callable[[Executor], None] | None = None,
    heartbeat: Heartbeat | None = None,
) -> None:
    """Run ``built`` components in one process until stopped, then release everything.

    Args:
        built: The components, as :func:`components.build.build_component` returns them.
        settings: Session settings (default: from the environment).
        duration: Seconds to run (``None``: until a signal or ``Executor.stop``).
        on_ready: Called with the executor once every component is bound, just before it
            runs (lets a caller keep a handle to stop it from another thread).
        heartbeat: The supervisor's proof-of-life pipe, beaten by the executor loop.

    Raises:
        Exception: Whatever adding a component or an ``on_bound`` hook raised; what was
            opened so far is closed first.
    """
    settings = settings or SessionSettings.from_env()
    session = open_session(settings)
    try:
        executor = Executor(settings, session=session, heartbeat=heartbeat)
        try:
            for item in built:
                component = executor.add(item.core, item.spec, item.namespace, item.node_name)
                if item.on_bound is not None:
                    item.on_bound(executor, component)
            if on_ready is not None:
                on_ready(executor)
            executor.run(duration)
        finally:
            # run() closes the nodes; this covers a failure before run() was reached.
            executor.close()
            for item in reversed(built):
                item.close()
    finally:
        session.close()
