"""``msctl doctor``'s checks with a real router, a fake clock and a fake device tree."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until

from components.comm.session import open_session
from msctl.net import doctor


def _publish(publisher: Any, stop: threading.Event) -> None:
    while not stop.wait(0.02):
        publisher.put("0/limb1/joint_states/t", b"x")


@pytest.fixture
def publishing_router() -> Any:
    """A loopback router and a peer publishing timestamped samples at 50 Hz (another host)."""
    for endpoint in quick_router():
        publisher = open_session(quick_peer_settings(endpoint))
        stop = threading.Event()

        thread = threading.Thread(target=_publish, args=(publisher, stop), daemon=True)
        thread.start()
        try:
            yield endpoint
        finally:
            stop.set()
            thread.join()
            publisher.close()


@pytest.mark.parametrize(
    ("skew_s", "status"), [(0.2, doctor.WARN), (0.8, doctor.ERROR), (-1.0, doctor.ERROR)]
)
def test_a_skewed_clock_is_reported(publishing_router: str, skew_s: float, status: str) -> None:
    session = open_session(quick_peer_settings(publishing_router))
    try:
        offset, source = doctor.measure_clock_offset(
            session, "0/**", lambda: time.time_ns() + int(skew_s * 1e9), timeout=10.0
        )
        found = doctor.router("ground1", session, [publishing_router])
    finally:
        session.close()
    assert source == "0/limb1/joint_states/t"
    assert doctor.clock_offset("ground1", offset, source).status == status
    assert found.status == doctor.WARN and found.value == "tcp"  # reached, not encrypted


def test_a_sample_taken_in_late_does_not_skew_the_clock(publishing_router: str) -> None:
    # The same clock on both ends; the first sample's callback ran 400 ms late (a loaded
    # computer): the samples after it say what the clocks are.
    late = iter([400_000_000])

    def now_ns() -> int:
        return time.time_ns() + next(late, 0)

    session = open_session(quick_peer_settings(publishing_router))
    try:
        offset, _source = doctor.measure_clock_offset(session, "0/**", now_ns, timeout=10.0)
    finally:
        session.close()
    assert offset is not None and abs(offset) < doctor.CLOCK_ERROR_S / 2, offset


def test_a_secure_computers_own_router_on_loopback_is_its_tls_link(publishing_router: str) -> None:
    # An agent (or `msctl up --secure`) is a client of its own router over loopback TCP; what
    # leaves the computer is that router's mutual TLS, not the loopback link.
    session = open_session(quick_peer_settings(publishing_router))
    try:
        wait_until(lambda: list(session.info.routers_zid()), 30, "the session reaching its router")
        secure = doctor.router("hl-limb-01", session, [publishing_router], secure=True)
        plain = doctor.router("hl-limb-01", session, [publishing_router], secure=False)
        beyond = doctor.router("hl-limb-01", session, ["tcp/ground1:7447"], secure=True)
    finally:
        session.close()
    assert (secure.status, secure.value) == (doctor.OK, "tls"), secure
    assert "loopback" in secure.detail
    assert (plain.status, plain.value) == (doctor.WARN, "tcp")
    assert (beyond.status, beyond.value) == (doctor.WARN, "tcp")  # plain TCP leaving it


def test_missing_serial_port_and_can_interface(tmp_path: Path) -> None:
    (tmp_path / "dev").mkdir()
    (tmp_path / "dev" / "ttyUSB1").write_text("")
    modules = [
        SimpleNamespace(slot=slot, host=host, bus=SimpleNamespace(channel=channel, bitrate=None))
        for slot, host, channel in [
            ("limb1", "robot1", "/dev/ttyUSB0"),
            ("limb2", "robot1", "/dev/ttyUSB1"),
            ("wheel1", "robot1", "can0"),
            ("wheel2", "robot2", "/dev/ttyUSB0"),
        ]
    ]
    found = doctor.devices("robot1", SimpleNamespace(modules=modules), False, sys_root=tmp_path)
    by_check = {f.check: f for f in found}
    assert sorted(by_check) == ["bus limb1", "bus limb2", "bus wheel1"]
    assert by_check["bus limb1"].status == doctor.ERROR
    assert "/dev/ttyUSB0" in by_check["bus limb1"].detail
    assert by_check["bus limb2"].status == doctor.OK
    assert (
        by_check["bus wheel1"].status == doctor.ERROR and "ip link" in by_check["bus wheel1"].detail
    )
    simulated = doctor.devices("robot1", SimpleNamespace(modules=modules), True, sys_root=tmp_path)
    assert {f.status for f in simulated} == {doctor.OK}


def test_emulated_buses_need_no_device(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A rehearsal's robot computer (MSCTL_EMULATE_HARDWARE=1) has no CAN interface or serial
    # port: its motor interface emulates the bus in its own process.
    modules = [
        SimpleNamespace(
            slot="wheel1", host="robot1", bus=SimpleNamespace(channel="can0", bitrate=None)
        )
    ]
    monkeypatch.setenv("MSCTL_EMULATE_HARDWARE", "1")
    found = doctor.devices("robot1", SimpleNamespace(modules=modules), False, sys_root=tmp_path)
    assert [(f.status, "emulated" in f.detail) for f in found] == [(doctor.OK, True)]


def test_hosts_on_another_lock_disagree() -> None:
    rows = [
        doctor.Finding("robot1", "assembly lock", doctor.OK, "", "aaaa"),
        doctor.Finding("robot2", "assembly lock", doctor.OK, "", "bbbb"),
        doctor.Finding("ground1", "assembly lock", doctor.OK, "", "aaaa"),
    ]
    (disagreement,) = doctor.agreement(rows, "assembly lock")
    assert disagreement.host == "robot2" and disagreement.status == doctor.ERROR


def test_certificates_expiring_soon_warn(tmp_path: Path) -> None:
    from msctl.net import pki

    pki.init_fleet(["robot1"], [], home=tmp_path)
    pki.issue("robot2", home=tmp_path, days=3)
    found = {f.check: f.status for f in doctor.certificates("robot1", tmp_path)}
    assert found == {"cert robot1": doctor.OK, "cert robot2": doctor.WARN}


def test_doctor_command_json_and_exit_status(tmp_path: Path) -> None:
    env = {**os.environ, "MSCTL_HOME": str(tmp_path), "MSCTL_ZENOH_CONNECT": "tcp/127.0.0.1:9"}
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "doctor", "--json", "--clock-timeout", "0.2"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    report = json.loads(done.stdout)
    assert done.returncode == 1 and report["status"] == doctor.ERROR
    router = next(f for f in report["findings"] if f["check"] == "router")
    assert router["status"] == doctor.ERROR and "msctl up" in router["detail"]


@pytest.mark.e2e
def test_doctor_all_asks_every_supervisor(tmp_path: Path) -> None:
    from running import Up

    up = Up(tmp_path, "minimal")
    try:
        saved = dict(up.env)
        up.env["MSCTL_HOST"] = "ground-laptop"  # a second computer, asking the first
        try:
            done = up.msctl("doctor", "--all", "--json", "--clock-timeout", "5", timeout=90)
        finally:
            up.env = saved
    finally:
        up.down()
    report = json.loads(done.stdout)
    hosts = {f["host"] for f in report["findings"]}
    assert hosts == {"ground-laptop", "test-laptop"}, report
    clock = {f["host"]: f for f in report["findings"] if f["check"] == "clock"}
    assert clock["test-laptop"]["value"] is not None  # the running assembly's samples
    lock = [f for f in report["findings"] if f["check"] == "assembly lock"]
    assert len({f["value"] for f in lock}) == 1  # one MSCTL_HOME: the same lock
