"""A frozen router (its process stopped: TCP still accepted by the kernel, nothing answered)
costs a command its own deadline, not Zenoh's 10 s handshake timeout, and is named as frozen,
not "no router" (issue 32, case 8: ``health --once --timeout 3`` took 10.5 s).

A real ``msctl router`` subprocess on a random loopback port, SIGSTOPped.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port, wait_until

from msctl.errors import NetworkError

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(300)]


def _accepts(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def _start_router(home: Path) -> tuple[subprocess.Popen[bytes], str]:
    """A `msctl router` listening on a free port: its own listener, not a port another
    test's router took between our pick and its bind (a free port is only free a moment;
    that race once let the session open to a live router: CI at 175dbf3)."""
    from msctl.net.endpoints import _listening_pid

    for _attempt in range(5):
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        router = subprocess.Popen(
            [sys.executable, "-m", "msctl", "router", "--listen", endpoint, "--for", "280"],
            env={**os.environ, "MSCTL_HOME": str(home)},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        wait_until(
            lambda r=router, p=port: (
                r.poll() is not None or (_accepts(p) and _listening_pid(p) == r.pid)
            ),
            60,
            "the router listens",
        )
        if router.poll() is None:
            return router, endpoint
        # Its port was taken by another process meanwhile: pick another.
    pytest.fail("no free port held by the router in 5 attempts")


@pytest.fixture(scope="module")
def frozen_router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A router that listened, then was stopped (SIGSTOP); continued and ended at teardown."""
    router, endpoint = _start_router(tmp_path_factory.mktemp("router-home"))
    try:
        router.send_signal(signal.SIGSTOP)
        yield endpoint
    finally:
        router.send_signal(signal.SIGCONT)
        router.terminate()
        try:
            router.wait(timeout=20)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()


def test_a_session_to_a_frozen_router_gives_up_at_its_bound_naming_it(
    frozen_router: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.plane import connected

    monkeypatch.setenv("MSCTL_ZENOH_CONNECT", frozen_router)
    monkeypatch.setenv("MSCTL_ZENOH_MULTICAST", "0")
    started = time.monotonic()
    with pytest.raises(NetworkError) as caught, connected("test", open_timeout=1.0):
        pass
    took = time.monotonic() - started
    message = str(caught.value)
    assert f"the Zenoh router at {frozen_router} accepts connections but did not" in message
    assert "within 1 s" in message and "frozen" in message
    # Its own 1 s bound, not Zenoh's 10 s handshake timeout (generous for a loaded machine).
    assert took < 7.0, took


def test_health_once_against_a_frozen_router_fails_at_its_timeout(
    frozen_router: str, tmp_path: Path
) -> None:
    env = {
        **os.environ,
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_ZENOH_CONNECT": frozen_router,
        "MSCTL_ZENOH_MULTICAST": "0",
        "COLUMNS": "200",
    }
    assembled = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "dragon"],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert assembled.returncode == 0, assembled.stderr
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "health", "--once", "--timeout", "2"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 3, result.stderr
    said = " ".join(result.stderr.split())
    assert "accepts connections but did not answer the session's handshake within 2 s" in said
    assert "Traceback" not in result.stderr
