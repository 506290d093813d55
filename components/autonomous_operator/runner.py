"""Running an autonomous operator's script inside its component process.

:class:`ScriptRunner` is the component's ``on_bound`` hook: it starts a thread with an event
loop, attaches the robot on the component's node
(:func:`~components.autonomous_operator.robot.attach_robot`), loads the script and calls
``main(robot, **params)`` (a synchronous ``main`` runs on a thread of its own, with the
blocking facade of ``msctl run``). The script itself is imported by the builder, before the
executor runs: its imports (Pinocchio's C++ initialisation holds the GIL for tens of
milliseconds, seconds on a loaded machine) must not starve the executor's heartbeat, or the
supervisor kills the process as frozen. Then:

* ``main`` returns: the operator is *finished* (its status says so); the process stays, so
  the supervisor does not start the script again;
* ``main`` raises (or the robot cannot be found in ``connect_timeout``): the status says
  which line and what, the component is marked failed, and the process stops with a
  failure, so the supervisor restarts it like any crashed component (with its backoff);
* the component stops (``msctl down``, a restart): the script is cancelled, its motions
  stopped and what it commanded held, before the node closes.
"""

from __future__ import annotations

import asyncio
import importlib.util
import inspect
import logging
import threading
import traceback
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from components.autonomous_operator.core import FAILED, FINISHED, RUNNING, STARTING
from components.autonomous_operator.robot import attach_robot
from components.messages import ERROR, OK, WARN

if TYPE_CHECKING:
    from components.build import BuiltComponent
    from components.executor.executor import Component, Executor

log = logging.getLogger(__name__)


def load_main(path: Path, name: str) -> Any:
    """Import the script at ``path`` (as a module of its own) and return its ``main``.

    Raises:
        ValueError: If it defines no callable ``main``.
    """
    spec = importlib.util.spec_from_file_location(f"_msctl_operator_{name}", path)
    if spec is None or spec.loader is None:
        raise ValueError(f"{path} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    main = getattr(module, "main", None)
    if not callable(main):
        raise ValueError(f"{path} defines no main(robot)")
    return main


def where_it_failed(path: Path, exc: BaseException) -> str:
    """``path:line (function): Type: message`` at the script's deepest line in the trace."""
    where = str(path)
    resolved = path.resolve()
    for frame in traceback.extract_tb(exc.__traceback__):
        if Path(frame.filename).resolve() == resolved:
            where = f"{path.name}:{frame.lineno} ({frame.name})"
    return f"{where}: {type(exc).__name__}: {exc}"


class ScriptRunner:
    """Runs one operator's script on a thread of its own; closed with the component.

    Args:
        built: The built component (marked ``failed`` when the script fails).
        assembly: The resolved assembly.
        path: The script.
        main: Its ``main`` (:func:`load_main`).
        params: ``main``'s keyword arguments.
        slots: The modules of the operator's robot.
        robot: The robot's name (its root module).
        root_link: The robot's root link.
        connect_timeout: Seconds to find the robot's joint managers.
        stop_timeout: Seconds the script gets to stop.
    """

    def __init__(
        self,
        built: BuiltComponent,
        assembly: Any,
        path: Path,
        main: Any,
        params: Mapping[str, Any],
        slots: list[str],
        robot: str,
        root_link: str,
        connect_timeout: float,
        stop_timeout: float,
    ) -> None:
        self.built = built
        self.assembly = assembly
        self.path = path
        self.main = main
        self.params = dict(params)
        self.slots = slots
        self.robot_name = robot
        self.root_link = root_link
        self.connect_timeout = connect_timeout
        self.stop_timeout = stop_timeout
        self.executor: Executor | None = None
        self.component: Component | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[Any] | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._ready = threading.Event()

    # ------------------------------------------------------------------ reporting
    def _post(self, handler: str, *args: Any) -> None:
        if self.executor is not None and self.component is not None:
            self.executor.call_soon(self.component, handler, *args)

    def state(self, state: str, level: int, message: str) -> None:
        """Tell the core what became of the script."""
        self._post("on_state", state, int(level), message)

    def report(self, level: int, message: str, values: Mapping[str, Any]) -> None:
        """The script's own report (``robot.report``), from any thread."""
        self._post("on_report", int(level), message, dict(values))

    # ------------------------------------------------------------------ running
    def __call__(self, executor: Executor, component: Component) -> None:
        """Start the script's thread (called once, before the executor runs)."""
        self.executor, self.component = executor, component
        self._thread = threading.Thread(
            target=self._run, name=f"operator-{component.name}", daemon=True
        )
        self._thread.start()

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            self._task = loop.create_task(self._main())
            self._ready.set()
            loop.run_until_complete(self._task)
        except BaseException:  # reported by _main; nothing may escape the thread
            log.debug("operator loop ended", exc_info=True)
        finally:
            self._ready.set()
            self._finish(loop)
            loop.close()

    def _finish(self, loop: asyncio.AbstractEventLoop) -> None:
        """Let what is still pending end (the robot's close, shielded from the cancel that
        stopped ``main``), then cancel whatever outlives ``stop_timeout``."""
        pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
        if not pending:
            return
        try:
            loop.run_until_complete(asyncio.wait(pending, timeout=self.stop_timeout))
        except BaseException:
            log.debug("operator tasks did not end", exc_info=True)
        left = [t for t in pending if not t.done()]
        for task in left:
            task.cancel()
        if left:
            loop.run_until_complete(asyncio.gather(*left, return_exceptions=True))

    async def _main(self) -> None:
        assert self.component is not None and self.executor is not None
        robot = None
        name = self.component.name
        try:
            self.state(STARTING, WARN, f"waiting for {', '.join(self.slots)}")
            robot = await attach_robot(
                self.component.node,
                self.assembly,
                self.slots,
                self.connect_timeout,
                robot=self.robot_name,
                root_link=self.root_link,
                loop=asyncio.get_running_loop(),
                report=self.report,
                guard=self.executor.claim_guard,
                name=name,
            )
            main = self.main
            self.state(RUNNING, OK, f"{self.path.name} running on {self.robot_name}")
            if inspect.iscoroutinefunction(main):
                await main(robot, **self.params)
            else:
                await self._in_thread(main, robot)
            self.state(FINISHED, OK, f"{self.path.name}: main returned")
            log.info("%s: main returned; the operator stays, finished", name)
        except asyncio.CancelledError:
            pass  # stopping: the finally below stops its motions
        except Exception as exc:
            why = where_it_failed(self.path, exc)
            log.error("%s failed: %s", name, why, exc_info=True)
            self.state(FAILED, int(ERROR), why)
            if not self._stopping.is_set():
                # The process stops with a failure: its supervisor starts it again.
                self.built.failed = f"{name}: {why}"
                self.executor.stop()
        finally:
            if robot is not None:
                try:
                    await asyncio.shield(robot.close())
                except Exception:
                    log.exception("%s: closing the robot failed", name)

    async def _in_thread(self, main: Any, robot: Any) -> None:
        """A synchronous ``main`` on a thread of its own, the loop serving its calls."""
        from components.api.sync import Blocking

        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()
        blocking = Blocking(robot, loop)

        def target() -> None:
            try:
                main(blocking, **self.params)
            except BaseException as exc:
                loop.call_soon_threadsafe(_settle, done, exc)
            else:
                loop.call_soon_threadsafe(_settle, done, None)

        threading.Thread(target=target, name="operator-script", daemon=True).start()
        await done

    # ------------------------------------------------------------------ stopping
    def stop(self) -> None:
        """Cancel the script and wait (``stop_timeout``) for its motions to stop."""
        self._stopping.set()
        loop, task, thread = self._loop, self._task, self._thread
        if thread is None:
            return
        self._ready.wait(self.stop_timeout)
        if loop is not None and task is not None and not task.done():
            try:
                loop.call_soon_threadsafe(task.cancel)
            except RuntimeError:
                pass  # the loop closed meanwhile
        thread.join(self.stop_timeout)
        if thread.is_alive():
            log.warning("%s: the script did not stop within %g s", self.path, self.stop_timeout)

    def close(self) -> None:
        """Stop the script (idempotent)."""
        self.stop()


def _settle(future: asyncio.Future[None], exc: BaseException | None) -> None:
    if future.done():
        return
    if exc is None:
        future.set_result(None)
    else:
        future.set_exception(exc)
