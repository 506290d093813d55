"""Using the fleet's security: ``msctl router --config``, MSCTL_IDENTITY sessions, the
embedded router on loopback, and ``msctl up --all`` refusing plain links."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, resolved_assembly, wait_until

from components.comm.session import SessionConfigError, SessionSettings, open_session
from msctl.launcher.router import router_argv
from msctl.net import config as netconfig
from msctl.net import pki


def _env(home: Path, **more: str) -> dict[str, str]:
    return {**os.environ, "MSCTL_HOME": str(home), **more}


@pytest.fixture
def secure_router(tmp_path: Path) -> Any:
    """``msctl router --config`` running limb1's generated config on free loopback ports."""
    assembly = resolved_assembly(tmp_path / "asm", "dragon")
    pki.init_fleet(list(assembly.hosts), ["alice@ground1"], home=tmp_path)
    ports = netconfig.Ports(local=free_port(), tls=free_port())
    config = tmp_path / "router.json5"
    config.write_text(
        netconfig.dumps(netconfig.router_config(assembly, "hl-limb-01", tmp_path, ports))
    )
    router = subprocess.Popen(
        [sys.executable, "-m", "msctl", "router", "--config", str(config), "--for", "120"],
        env=_env(tmp_path),
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert "listening on" in router.stderr.readline()
        yield tmp_path, ports
    finally:
        router.terminate()
        router.wait(30)
        router.stderr.close()


def test_operator_identity_session_commands_through_the_secure_router(
    secure_router: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    home, ports = secure_router
    monkeypatch.setenv("MSCTL_HOME", str(home))
    local = open_session(
        SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{ports.local}",), listen=())
    )
    got = threading.Event()
    subscriber = local.declare_subscriber("0/limb1/joint_set/**", lambda _s: got.set())
    operator_env = {
        "MSCTL_IDENTITY": "alice@ground1",
        "MSCTL_ZENOH_CONNECT": f"tls/127.0.0.1:{ports.tls}",
    }
    operator = open_session(SessionSettings.from_env(operator_env))
    try:
        assert list(operator.info.routers_zid())
        wait_until(
            lambda: operator.put("0/limb1/joint_set/t/h", b"x") or got.is_set(),
            10.0,
            "the operator's joint_set through the router",
        )
    finally:
        operator.close()
        subscriber.undeclare()
        local.close()


def test_identity_settings_name_what_is_missing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    with pytest.raises(SessionConfigError, match="msctl net add-operator bob"):
        SessionSettings.from_env({"MSCTL_IDENTITY": "bob"})
    pki.init_fleet([], ["bob"], home=tmp_path)
    settings = SessionSettings.from_env({"MSCTL_IDENTITY": "bob"})
    assert settings.mode == "client" and settings.connect == ("tls/localhost:7448",)
    tls = settings.extra["transport/link/tls"]
    assert tls["enable_mtls"] and Path(tls["connect_certificate"]).is_file()
    # A router never takes an operator's identity from the shell that started it.
    assert SessionSettings.from_env({"MSCTL_IDENTITY": "bob"}, mode="router").extra == {}


def test_embedded_router_listens_on_loopback_unless_told(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("MSCTL_SECURE", "MSCTL_ROUTER_LISTEN", "MSCTL_ROUTER_CONNECT"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("MSCTL_HOST", "hl-limb-01")
    assert router_argv("tcp/localhost:7447") == ["router", "--listen", "tcp/127.0.0.1:7447"]
    # The same port on every interface covers loopback: it replaces the loopback listener
    # (one process cannot bind both), another port is added beside it.
    monkeypatch.setenv("MSCTL_ROUTER_LISTEN", "tcp/0.0.0.0:7447")
    assert router_argv("tcp/localhost:7447") == ["router", "--listen", "tcp/0.0.0.0:7447"]
    monkeypatch.setenv("MSCTL_ROUTER_LISTEN", "tcp/[::]:7447, tcp/0.0.0.0:7448")
    assert router_argv("tcp/127.0.0.1:7447") == [
        "router", "--listen", "tcp/[::]:7447", "--listen", "tcp/0.0.0.0:7448"
    ]  # fmt: skip
    monkeypatch.setenv("MSCTL_ROUTER_LISTEN", "tcp/0.0.0.0:7448")
    monkeypatch.setenv("MSCTL_ROUTER_CONNECT", "tcp/ground1:7448,tcp/ground2:7448")
    assert router_argv("tcp/localhost:7447") == [
        "router", "--listen", "tcp/127.0.0.1:7447", "--listen", "tcp/0.0.0.0:7448",
        "--connect", "tcp/ground1:7448", "--connect", "tcp/ground2:7448",
    ]  # fmt: skip
    monkeypatch.delenv("MSCTL_ROUTER_LISTEN")
    monkeypatch.delenv("MSCTL_ROUTER_CONNECT")
    monkeypatch.setenv("MSCTL_SECURE", "1")
    assert router_argv("tcp/localhost:7447") == ["router", "--secure", "--host", "hl-limb-01"]


def test_up_all_refuses_agents_over_plain_tcp(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "up", "dragon", "--all"],
        env=_env(tmp_path, MSCTL_ZENOH_CONNECT="tcp/192.0.2.1:7447"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "tcp/192.0.2.1:7447" in done.stderr and "msctl net init" in done.stderr
    assert "--insecure" in done.stderr
