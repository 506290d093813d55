"""``msctl router``: a Zenoh router like rmw_zenoh's ``rmw_zenohd`` (tcp port 7447)."""

from __future__ import annotations

import signal
import threading
import time

import typer

from msctl.errors import NetworkError

COMMAND_SETTINGS = {"help": "Run a Zenoh router (default tcp/[::]:7447, as rmw_zenohd)."}


def command(
    listen: list[str] = typer.Option(
        None,
        "--listen",
        "-l",
        help="Endpoint to listen on (repeatable). Default tcp/[::]:7447, like rmw_zenohd.",
    ),
    connect: list[str] = typer.Option(
        None, "--connect", "-c", help="Another router to link to (repeatable), e.g. a base station."
    ),
    duration: float = typer.Option(
        None, "--for", help="Stop after this many seconds (default: until Ctrl-C)."
    ),
) -> None:
    """Run a Zenoh router so ROS 2 nodes and msctl components on this computer meet."""
    from components.comm.session import (
        DEFAULT_ROUTER_LISTEN,
        SessionConfigError,
        open_session,
        router_settings,
    )
    from msctl.console import err

    endpoints = tuple(listen) if listen else DEFAULT_ROUTER_LISTEN
    try:
        settings = router_settings(listen=endpoints)
        if connect:
            settings = settings.__class__(**{**settings.__dict__, "connect": tuple(connect)})
        session = open_session(settings)
    except SessionConfigError as exc:
        raise NetworkError(
            str(exc),
            hint="another router (rmw_zenohd or msctl router) may already hold the port; "
            "use it, or pass --listen tcp/[::]:7448",
        ) from exc
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        err.print(
            f"[green]router[/] {session.zid()} listening on {', '.join(endpoints)}"
            + (f", linked to {', '.join(connect)}" if connect else ""),
            highlight=False,
        )
        deadline = None if duration is None else time.monotonic() + duration
        while not stop.is_set():
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                break
            stop.wait(0.2 if remaining is None else min(0.2, remaining))
    finally:
        session.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        err.print("router stopped")
