"""``msctl run SCRIPT.py [ARGS...]``: the autonomous operator — a user script driving the robot.

The script contract:

* it defines ``main(robot)``, either ``async def main(robot)`` (``robot`` is the asyncio
  :class:`components.api.Robot`) or ``def main(robot)`` (``robot`` is the synchronous
  facade: every call blocks, motions have ``.wait()``);
* ``msctl run`` connects to the running assembly first (found on the data plane; with
  ``--assembly NAME`` it refuses another one), then calls ``main``;
* the script's own arguments follow its path; ``sys.argv`` is ``[SCRIPT, ARGS...]`` inside it;
* when ``main`` returns, raises, or Ctrl-C comes, every motion is stopped cleanly: joints are
  held where they are measured, wheels commanded to 0 (no halt, no velocity left behind),
  then the connection closes. A failure prints one line naming the script's line and exits
  non-zero (1; 130 for Ctrl-C).

Example::

    # wave.py
    async def main(robot):
        limb = robot.syncer("limb1")
        await limb.lerp({"joint2": 0.5})

    $ msctl run wave.py
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import inspect
import signal
import sys
import threading
import traceback
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, MsctlError, NetworkError

COMMAND_SETTINGS = {
    "help": "Run a Python script driving the running assembly (it defines main(robot)).",
    "context_settings": {"allow_extra_args": True, "ignore_unknown_options": True},
}


def command(
    ctx: typer.Context,
    script: Path = typer.Argument(..., help="The script: defines main(robot), async or not."),
    assembly: str = typer.Option(
        None, "--assembly", help="Refuse to run unless this template is the one running."
    ),
    timeout: float = typer.Option(15.0, "--timeout", help="Seconds to find the robot."),
) -> None:
    """Connect to the running assembly and run SCRIPT's main(robot); ARGS go to the script."""
    from msctl.console import err

    main = _load(script, list(ctx.args))
    code = asyncio.run(_run(script, main, assembly, timeout))
    if code:
        raise typer.Exit(code)
    err.print(f"[green]done[/]: {script.name}", highlight=False)


def _load(script: Path, args: list[str]) -> Any:
    """Import the script as ``__msctl_script__`` and return its ``main``."""
    if not script.is_file():
        raise InputError(f"no script at {script}")
    spec = importlib.util.spec_from_file_location("__msctl_script__", script)
    if spec is None or spec.loader is None:
        raise InputError(f"{script} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.argv = [str(script), *args]
    sys.path.insert(0, str(script.resolve().parent))
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        raise _script_error(script, exc, "while loading") from exc
    main = getattr(module, "main", None)
    if not callable(main):
        raise InputError(f"{script} defines no main(robot); write `async def main(robot): ...`")
    return main


async def _run(script: Path, main: Any, assembly: str | None, timeout: float) -> int:
    from components.api import ApiError, connect
    from components.api.sync import Blocking

    try:
        robot = await connect(assembly, timeout=timeout)
    except ApiError as exc:
        raise NetworkError(str(exc)) from exc
    from msctl.console import err

    err.print(f"connected: {robot!r}", highlight=False)
    # SIGTERM (systemd, `kill`) and SIGHUP (a dropped terminal) stop the script exactly as
    # Ctrl-C does: the main task is cancelled and its motions are stopped, joints held.
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    for signum in (signal.SIGTERM, signal.SIGHUP):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(signum, task.cancel)
    try:
        if inspect.iscoroutinefunction(main):
            await main(robot)
        else:
            await _in_thread(main, Blocking(robot, asyncio.get_running_loop()))
        return 0
    except asyncio.CancelledError:
        # Ctrl-C: asyncio.run cancels this task; stop cleanly, then report.
        err.print("[yellow]interrupted[/]: motions stopped, joints held")
        return 130
    except Exception as exc:
        from rich.markup import escape

        failure = _script_error(script, exc, "in main")
        err.print(f"[bold red]error:[/] {escape(str(failure))}", highlight=False)
        return 1
    finally:
        # Closing refuses new motions first, so a script thread still running stops at its
        # next call instead of moving the robot again.
        await asyncio.shield(robot.close())


async def _in_thread(main: Any, robot: Any) -> None:
    """Run a synchronous main in a daemon thread while this loop serves its calls."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()

    def target() -> None:
        try:
            main(robot)
        except BaseException as exc:
            loop.call_soon_threadsafe(_settle, done, exc)
        else:
            loop.call_soon_threadsafe(_settle, done, None)

    threading.Thread(target=target, name="msctl-run-script", daemon=True).start()
    await done


def _settle(future: asyncio.Future[None], exc: BaseException | None) -> None:
    if future.done():
        return
    if exc is None:
        future.set_result(None)
    else:
        future.set_exception(exc)


def _script_error(script: Path, exc: BaseException, when: str) -> MsctlError:
    """One line naming the script's deepest line in the traceback, and the error."""
    where = str(script)
    resolved = script.resolve()
    for frame in traceback.extract_tb(exc.__traceback__):
        if Path(frame.filename).resolve() == resolved:
            where = f"{script}:{frame.lineno} ({frame.name})"
    return MsctlError(f"{where} {when}: {type(exc).__name__}: {exc}", exit_code=1)
