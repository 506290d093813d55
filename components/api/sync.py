"""The synchronous facade: the same API for short scripts that do not want ``async``.

:func:`connect_sync` runs an event loop in a background thread, connects there, and hands
back a :class:`Blocking` proxy of the :class:`~components.api.connect.Robot`: every method
runs on the loop thread and returns when done; a motion comes back as a
:class:`BlockingMotion` whose :meth:`~BlockingMotion.wait` blocks until it ends::

    from components.api import connect_sync

    with connect_sync() as robot:
        limb = robot.syncer("limb1")
        limb.lerp({"joint2": 0.4}).wait()
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

from components.api.motion import Motion

# Objects handed back wrapped in a proxy (rather than as is) from the loop thread.
_PROXIED = ("Robot", "JointSyncer", "IkSyncer", "WheelDrive", "JointHandler")


class BlockingMotion:
    """A motion seen from another thread."""

    def __init__(self, motion: Motion, loop: asyncio.AbstractEventLoop) -> None:
        self._motion = motion
        self._loop = loop

    def __repr__(self) -> str:
        return repr(self._motion)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the motion ends; True when it arrived, False when cancelled.

        Raises:
            TimeoutError: If ``timeout`` seconds pass first (the motion goes on).
        """
        return asyncio.run_coroutine_threadsafe(self._motion.wait(timeout), self._loop).result()

    def done(self) -> bool:
        """Whether it ended."""
        return self._motion.done()

    @property
    def arrived(self) -> bool:
        """Whether it ended by arriving."""
        return self._motion.arrived


class Blocking:
    """A proxy running every method of ``target`` on ``loop`` and waiting for the result.

    Coroutines are awaited there, motions become :class:`BlockingMotion`, and robots,
    syncers and handlers come back proxied in turn. Plain attributes are read directly.
    """

    def __init__(self, target: Any, loop: asyncio.AbstractEventLoop) -> None:
        object.__setattr__(self, "_target", target)
        object.__setattr__(self, "_loop", loop)

    def __repr__(self) -> str:
        return f"<blocking {self._target!r}>"

    def __getattr__(self, name: str) -> Any:
        attribute = getattr(self._target, name)
        if not callable(attribute):
            return self._wrap(attribute)
        return self._blocking(attribute)

    def _blocking(self, function: Callable[..., Any]) -> Callable[..., Any]:
        loop = self._loop

        async def call(*args: Any, **kwargs: Any) -> Any:
            result = function(*args, **kwargs)
            if isinstance(result, Motion):
                return result
            if asyncio.iscoroutine(result):
                result = await result
            return result

        def blocking(*args: Any, **kwargs: Any) -> Any:
            if _on_loop(loop):
                raise RuntimeError("the blocking API was called from its own event loop thread")
            result = asyncio.run_coroutine_threadsafe(call(*args, **kwargs), loop).result()
            return self._wrap(result)

        blocking.__doc__ = function.__doc__
        blocking.__name__ = getattr(function, "__name__", "call")
        return blocking

    def _wrap(self, value: Any) -> Any:
        if isinstance(value, Motion):
            return BlockingMotion(value, self._loop)
        if type(value).__name__ in _PROXIED:
            return Blocking(value, self._loop)
        if isinstance(value, dict) and any(type(v).__name__ in _PROXIED for v in value.values()):
            return {k: self._wrap(v) for k, v in value.items()}
        return value


def _on_loop(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False


class SyncRobot(Blocking):
    """A connected robot for synchronous scripts; close it (or use ``with``) to stop every
    motion, close the Zenoh session and end the background loop."""

    def __init__(self, robot: Any, loop: asyncio.AbstractEventLoop, thread: Any = None) -> None:
        super().__init__(robot, loop)
        object.__setattr__(self, "_thread", thread)

    def close(self) -> None:
        """Stop, disconnect, and end the loop thread if this facade started it (idempotent)."""
        loop, thread = self._loop, self._thread
        if not loop.is_closed() and loop.is_running():
            asyncio.run_coroutine_threadsafe(self._target.close(), loop).result()
        if thread is not None and thread.is_alive():
            loop.call_soon_threadsafe(loop.stop)
            thread.join()

    def __enter__(self) -> SyncRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def connect_sync(assembly: str | None = None, **options: Any) -> SyncRobot:
    """Connect from synchronous code (see :func:`components.api.connect.connect` for the
    arguments); the event loop runs in a background thread until :meth:`SyncRobot.close`."""
    from components.api.connect import connect

    loop = asyncio.new_event_loop()
    ready = threading.Event()

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.call_soon(ready.set)
        loop.run_forever()
        loop.close()

    thread = threading.Thread(target=run, name="msctl-api-loop", daemon=True)
    thread.start()
    ready.wait()
    try:
        robot = asyncio.run_coroutine_threadsafe(connect(assembly, **options), loop).result()
    except BaseException:
        loop.call_soon_threadsafe(loop.stop)
        thread.join()
        raise
    return SyncRobot(robot, loop, thread)
