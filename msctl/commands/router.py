"""``msctl router``: a Zenoh router like rmw_zenoh's ``rmw_zenohd`` (tcp port 7447)."""

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
    secure: bool = typer.Option(
        False,
        "--secure",
        help="Run this computer's router from the config `msctl net config` generates: "
        "mutual TLS and access control (also MSCTL_SECURE=1).",
    ),
    host: str = typer.Option(
        None, "--host", help="With --secure: act as this computer (default MSCTL_HOST)."
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

    endpoints = tuple(listen) if listen else DEFAULT_ROUTER_LISTEN
    if secure or config_file is not None:
        config_file = config_file or _secure_config(host)
        endpoints, connect = _endpoints_of(config_file)
    try:
        settings = router_settings(listen=endpoints, config_file=config_file)
        if connect:
            settings = settings._replace(connect=tuple(connect))
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


def _secure_config(host: str | None) -> Path:
    """Write this computer's generated router config under MSCTL_HOME/net; its path."""
    import os
    import socket

    from components.assembly import AssemblyError, load_assembly
    from msctl.net import config as netconfig
    from msctl.net import pki

    host = host or os.environ.get("MSCTL_HOST") or socket.gethostname()
    if not pki.initialised():
        raise InputError(
            f"--secure: the fleet has no certificate authority in {pki.net_dir()}",
            hint="run `msctl net init` (then copy MSCTL_HOME/net to every computer)",
        )
    try:
        assembly = load_assembly()
        document = netconfig.router_config(
            assembly, host, ports=_ports(), off_robot=host not in assembly.hosts
        )
    except (AssemblyError, netconfig.NetConfigError, pki.PkiError) as exc:
        raise InputError(f"--secure: {exc}") from exc
    target = pki.net_dir() / f"router-{host}.json5"
    target.write_text(netconfig.dumps(document))
    return target


def _ports() -> Any:
    """The router's ports: loopback where this computer's sessions connect
    (MSCTL_ZENOH_CONNECT, default 7447), TLS from MSCTL_NET_TLS_PORT (default 7448)."""
    import os

    from components.comm.session import SessionSettings
    from msctl.net.config import LOCAL_PORT, TLS_PORT, Ports

    local = LOCAL_PORT
    for endpoint in SessionSettings.from_env(mode="router").connect:
        protocol, _, address = endpoint.partition("/")
        if protocol == "tcp" and address.startswith(("127.", "localhost")):
            local = int(address.rsplit(":", 1)[1])
    try:
        tls = int(os.environ.get("MSCTL_NET_TLS_PORT") or TLS_PORT)
    except ValueError:
        raise InputError("MSCTL_NET_TLS_PORT must be a port number") from None
    return Ports(local=local, tls=tls)


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
