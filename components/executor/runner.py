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

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from components.comm.session import SessionSettings, open_session
from components.errors import ComponentError
from components.executor.executor import Component, Executor
from components.executor.heartbeat import Heartbeat
from components.executor.orders import Orders

if TYPE_CHECKING:
    from components.build import BuiltComponent

log = logging.getLogger("msctl.worker")


class RebuildFailed(ComponentError, RuntimeError):
    """A component could not be rebuilt in place: its process must restart whole."""


class ComponentFailed(ComponentError, RuntimeError):
    """A component could not go on (its ``failed``, an operator's script raised) and
    stopped its executor: its process must restart."""


def run_built(
    built: Sequence[BuiltComponent],
    settings: SessionSettings | None = None,
    duration: float | None = None,
    on_ready: Callable[[Executor], None] | None = None,
    heartbeat: Heartbeat | None = None,
    rebuild: Callable[[str], BuiltComponent] | None = None,
    transport: str = "zenoh",
) -> None:
    """Run ``built`` components in one process until stopped, then release everything.

    Args:
        built: The components, in the order they are added.
        settings: Session settings (default: from the environment).
        duration: Seconds to run (``None``: until a signal or ``Executor.stop``).
        on_ready: Called with the executor once every component is bound, just before it
            runs (lets a caller keep a handle to stop it from another thread).
        heartbeat: The supervisor's proof-of-life pipe, beaten by the executor loop.
        rebuild: Builds one component anew by name; with it, the supervisor's ``rebuild``
            orders (``MSCTL_ORDERS_FD``, :mod:`components.executor.orders`) replace that one
            component while the others run on.
        transport: ``zenoh`` (msctl's data plane) or ``rclpy`` (every core a real rclpy node,
            :mod:`components.executor.rclpy_executor`); the same steps either way.

    Raises:
        RebuildFailed: If a rebuild order failed: the process stopped, to be restarted.
        ComponentFailed: If a component failed (:attr:`BuiltComponent.failed`): the process
            stopped, to be restarted.
        RclpyUnavailable: If ``transport`` is ``rclpy`` and rclpy cannot be imported.
        Exception: Whatever adding a component or an ``on_bound`` hook raised; what was
            opened is closed first.
    """
    settings = settings or SessionSettings.from_env()
    live = list(built)  # what is bound now, in order; rebuilt ones are replaced in place
    failed: list[str] = []
    session = None
    if transport == "rclpy":
        from components.executor.rclpy_executor import RclpyExecutor

        executor: Executor = RclpyExecutor(settings, heartbeat=heartbeat)
    else:
        session = open_session(settings)
    try:
        if session is not None:
            executor = Executor(settings, session=session, heartbeat=heartbeat)
        try:
            components: dict[str, Component] = {}
            for item in live:
                component = executor.add(item.core, item.spec, item.namespace, item.node_name)
                components[component.name] = component
                if item.on_bound is not None:
                    item.on_bound(executor, component)
            if rebuild is not None:

                def on_order(order: str, name: str) -> None:
                    del order  # the only order is rebuild
                    executor.post(
                        lambda: _rebuild(executor, live, components, name, rebuild, failed)
                    )

                orders = Orders.from_env(on_order)
                if orders is not None:
                    orders.start()
            if on_ready is not None:
                on_ready(executor)
            executor.run(duration)
        finally:
            # run() closes the nodes; this covers a failure before run() was reached. The
            # resources (graph watchers) close first: on rclpy they read the context.
            for item in reversed(live):
                item.close()
            executor.close()
    finally:
        if session is not None:
            session.close()
    if failed:
        raise RebuildFailed(failed[0])
    gave_up = [item.failed for item in live if item.failed]
    if gave_up:
        raise ComponentFailed("; ".join(gave_up))


def _rebuild(
    executor: Executor,
    live: list[BuiltComponent],
    components: dict[str, Component],
    name: str,
    rebuild: Callable[[str], BuiltComponent],
    failed: list[str],
) -> None:
    """Replace one running component by a freshly built one (on the executor thread).

    The old one is stopped and released first: a new motor interface needs the bus the old
    one holds. Should the new one fail to build or bind, the process stops (its siblings
    with it) and the supervisor restarts it whole, as for a crash: a process missing one of
    its components must not go on looking healthy.
    """
    old = components.get(name)
    if old is None:
        log.error("cannot rebuild %s: this process runs %s", name, ", ".join(components))
        return
    index = next(i for i, item in enumerate(live) if item.core is old.core)
    log.info("rebuilding %s (its siblings run on)", name)
    executor.remove(old)
    live.pop(index).close()
    try:
        item = rebuild(name)
    except Exception as exc:
        log.exception("cannot rebuild %s; the process stops to be restarted whole", name)
        failed.append(f"cannot rebuild {name}: {exc}")
        executor.stop()
        return
    live.insert(index, item)
    try:
        component = executor.add(item.core, item.spec, item.namespace, item.node_name)
        if item.on_bound is not None:
            item.on_bound(executor, component)
    except Exception as exc:
        log.exception("cannot bind the rebuilt %s; the process stops to be restarted", name)
        failed.append(f"cannot bind the rebuilt {name}: {exc}")
        executor.stop()
        return
    components[name] = component
    executor.start_component(component)
    log.info("rebuilt %s", name)
