"""Shared fixtures: real Zenoh routers and sessions on 127.0.0.1, random ports, no multicast."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from components.comm.session import SessionSettings, open_session


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_until(
    predicate: Callable[[], Any], timeout: float = 5.0, what: str = "", interval: float = 0.02
) -> Any:
    """Poll ``predicate`` until it returns something truthy; fail the test on timeout.

    Args:
        predicate: What to poll.
        timeout: Seconds before failing.
        what: Said in the failure (what was awaited).
        interval: Seconds between polls.
    """
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what or 'condition'}")
        time.sleep(interval)


_resolved: dict[tuple[str, tuple[tuple[str, str], ...]], Any] = {}


def resolved_assembly(directory: Any, template: str, units: dict[str, str] | None = None) -> Any:
    """A shipped template resolved (with ``units`` for some slots) and written under
    ``directory``; loaded as the launcher would load it. Cached per template and units."""
    from components.assembly import load_assembly
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    key = (template, tuple(sorted((units or {}).items())))
    if key not in _resolved:
        resolution = resolve(template, units or {})
        target = write_resolution(directory / f"{template}-assembly", resolution)
        _resolved[key] = load_assembly(target)
    return _resolved[key]


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A real Zenoh router listening on a random loopback port; yields its endpoint."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    settings = SessionSettings(mode="router", connect=(), listen=(endpoint,))
    router = open_session(settings)
    try:
        yield endpoint
    finally:
        router.close()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Peer settings that reach the test router and nothing else."""
    return SessionSettings(
        mode="peer", connect=(router_endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False
    )


@pytest.fixture
def zenoh_env(router_endpoint: str, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Environment for msctl subprocesses so they join the test router only."""
    env = {
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return env


@pytest.fixture
def open_sessions(session_settings: SessionSettings) -> Iterator[Callable[[], Any]]:
    """A factory of peer sessions on the test router; every one is closed at teardown."""
    sessions: list[Any] = []

    def make() -> Any:
        session = open_session(session_settings)
        sessions.append(session)
        return session

    try:
        yield make
    finally:
        for session in reversed(sessions):
            session.close()


# --------------------------------------------------------------------------- quick opening
#: Zenoh waits ``scouting/delay`` (0.5 s) in ``zenoh.open`` for the first connections; tests
#: that poll for routes anyway can skip it. Modules opt in by overriding ``router_endpoint``
#: and ``session_settings`` with :func:`quick_router` and :func:`quick_peer_settings`.
QUICK_OPEN = {"scouting/delay": 0}


def quick_router() -> Iterator[str]:
    """A real loopback router that opens at once (use as ``yield from quick_router()``)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(
        SessionSettings(mode="router", connect=(), listen=(endpoint,), extra=dict(QUICK_OPEN))
    )
    try:
        yield endpoint
    finally:
        router.close()


def quick_peer_settings(router_endpoint: str) -> SessionSettings:
    """Peer settings joining ``router_endpoint`` that open at once (routes come soon after)."""
    return SessionSettings(
        mode="peer",
        connect=(router_endpoint,),
        listen=("tcp/127.0.0.1:0",),
        multicast=False,
        extra=dict(QUICK_OPEN),
    )
