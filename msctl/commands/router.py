"""``msctl router``: a Zenoh router like rmw_zenoh's ``rmw_zenohd`` (tcp port 7447).

Its settings that cannot work (a port another process holds, an address that is not this
computer's, an identity the fleet never made) fail before it opens, as an :class:`InputError`
(exit code 2): whoever supervises it (``msctl up``, ``msctl agent``) then knows a restart
would fail the same way (:data:`msctl.launcher.router.ROUTER_FINAL_EXITS`).
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, NetworkError

COMMAND_SETTINGS = {"help": "Run a Zenoh router (default tcp/[::]:7447, as rmw_zenohd)."}

#: The admin space a plain router serves, read-only: `msctl up --all` reads every router's
#: links there (``@/<zid>/router``) to refuse commanding agents over plain TCP unawares.
#: rmw_zenohd's default config serves it too. A secure router's access control denies it.
ADMIN_SPACE = {"adminspace/enabled": True, "adminspace/permissions": {"read": True, "write": False}}


def command(
    listen: list[str] = typer.Option(
        None,
        "--listen",
        "-l",
        help="Endpoint to listen on (repeatable). Default tcp/[::]:7447, like rmw_zenohd. "
        "With --secure: a tls/ endpoint in place of the generated TLS listener.",
    ),
    connect: list[str] = typer.Option(
        None,
        "--connect",
        "-c",
        help="Another router to link to (repeatable), e.g. a base station. With --secure: "
        "tls/ endpoints in place of the links the assembly gives.",
    ),
    duration: float = typer.Option(
        None, "--for", help="Stop after this many seconds (default: until Ctrl-C)."
    ),
    secure: bool = typer.Option(
        False,
        "--secure",
        help="Run this computer's router from the config `msctl net config` generates: "
        "mutual TLS and access control (also MSCTL_SECURE=1).",
    ),
    host: str = typer.Option(
        None, "--host", help="With --secure: act as this computer (default MSCTL_HOST)."
    ),
    whole_assembly: bool = typer.Option(
        None,
        "--whole-assembly/--own-part",
        help="With --secure: this computer runs the whole assembly (`msctl up` off-robot), so "
        "its components write every module's inputs and it links to no other router; or only "
        "its own part. Default: the whole assembly when it is none of the assembly's hosts.",
    ),
    config_file: Path = typer.Option(
        None, "--config", help="Run from this json5 Zenoh config (e.g. `msctl net config -o`)."
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
    from msctl.net import endpoints as net_endpoints

    endpoints = tuple(listen) if listen else DEFAULT_ROUTER_LISTEN
    connect = list(connect or [])
    extra: dict[str, Any] = {}
    if secure or config_file is not None:
        if config_file is None:
            config_file = _secure_config(host, whole_assembly, list(listen or []), connect or None)
        endpoints, connect = _endpoints_of(config_file)
    else:
        extra = dict(ADMIN_SPACE)
        warning = plain_exposure(endpoints, connect)
        if warning:
            err.print(f"[bold yellow]warning:[/] {warning}", highlight=False)
    for endpoint in endpoints:
        try:
            net_endpoints.check_listen(endpoint, setting="--listen")
        except net_endpoints.EndpointError as exc:
            raise InputError(str(exc)) from None
    try:
        settings = router_settings(listen=endpoints, config_file=config_file, extra=extra)
        if config_file is not None and (lease := _lease_of(config_file)) is not None:
            # The config's lease is its links' (the radio's, msctl net config): the 1 s of
            # msctl's local sessions would drop a radio link at each burst of losses.
            settings = settings._replace(lease_ms=lease)
        if connect:
            settings = settings._replace(connect=tuple(connect))
        session = open_session(settings)
    except SessionConfigError as exc:
        # The bind check passed a moment ago: another process took a port since, or Zenoh
        # refused something else. Say which endpoint in one line when it can be told.
        for endpoint in endpoints:
            try:
                net_endpoints.check_listen(endpoint, setting="--listen")
            except net_endpoints.EndpointError as taken:
                raise InputError(str(taken)) from None
        raise NetworkError(str(exc)) from exc
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


def plain_exposure(listen: Any, connect: Any) -> str:
    """The warning for a plain (not TLS) router open beyond this computer, or ``""``.

    Args:
        listen: Endpoints it listens on.
        connect: Endpoints it links to.
    """
    from msctl.net.endpoints import EndpointError, parse

    def exposed(texts: Any) -> list[str]:
        found = []
        for text in texts:
            try:
                endpoint = parse(text)
            except EndpointError:
                continue  # Zenoh says what is wrong with it
            if endpoint.leaves_computer and not endpoint.encrypted:
                found.append(text)
        return found

    listening, linking = exposed(listen), exposed(connect)
    if not listening and not linking:
        return ""
    where = "; ".join(
        part
        for part in (
            f"listens on {', '.join(listening)}" if listening else "",
            f"links to {', '.join(linking)}" if linking else "",
        )
        if part
    )
    return (
        f"this router {where} over plain TCP: anyone on that network can command joints, halt "
        "modules and stop runs through it; outside a network you trust, secure the fleet "
        "(`msctl net init`, then MSCTL_SECURE=1)"
    )


def _secure_config(
    host: str | None,
    whole_assembly: bool | None,
    listen: list[str],
    connect: list[str] | None,
) -> Path:
    """Write this computer's generated router config under MSCTL_HOME/net; its path."""
    from components.assembly import AssemblyError
    from msctl.console import err
    from msctl.launcher.plan import this_host
    from msctl.net import config as netconfig
    from msctl.net import pki

    host = host or this_host()
    try:
        target, notes = netconfig.this_computer_router(
            host, whole_assembly, listen=listen, connect=connect
        )
    except (AssemblyError, netconfig.NetConfigError, pki.PkiError) as exc:
        raise InputError(f"--secure: {exc}") from exc
    for note in notes:
        err.print(f"[yellow]{note}[/]", highlight=False)
    return target


def _lease_of(config_file: Path) -> int | None:
    """The lease (ms) a JSON config sets itself (``transport.link.tx.lease``), else None.

    Only what the file says counts: Zenoh reads an absent lease as its own 10 s default."""
    try:
        document = json.loads(config_file.read_text())
        lease = document["transport"]["link"]["tx"]["lease"]
    except (OSError, ValueError, KeyError, TypeError):
        return None  # json5 beyond JSON, or no lease: msctl's own stands
    return lease if isinstance(lease, int) and not isinstance(lease, bool) else None


def _endpoints_of(config_file: Path) -> tuple[tuple[str, ...], list[str]]:
    """The listen and connect endpoints a json5 config names (msctl's own settings are
    applied over the file, so they must repeat them)."""
    import zenoh

    try:
        config = zenoh.Config.from_file(str(config_file))
        listen = json.loads(config.get_json("listen/endpoints"))
        connect = json.loads(config.get_json("connect/endpoints"))
    except Exception as exc:
        raise InputError(f"cannot use Zenoh config {config_file}: {exc}") from exc
    if isinstance(listen, dict):  # per-mode form: {"router": [...]}
        listen = listen.get("router", [])
    if isinstance(connect, dict):
        connect = connect.get("router", [])
    return tuple(listen), list(connect)
