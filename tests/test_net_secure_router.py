"""A real router with the config ``msctl net config`` generates: mutual TLS and the ACL.

Everything on 127.0.0.1 with free ports and real certificates from a fleet CA made in a tmp
dir. A denied write is checked with a marker: the same sender then writes something it may,
on the same route; once the marker arrives, the denied sample would have arrived before it.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port, resolved_assembly, wait_until

from msctl.net import config as netconfig
from msctl.net import pki

ROBOT = "hl-limb-01"  # limb1's computer in dragon
OTHER_ROBOT = "hl-limb-02"  # limb2's computer
QUERY_TIMEOUT = 3.0


def _open(config: dict[str, Any]) -> Any:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A dragon fleet: CA, host identities, operator alice; limb1's router running."""
    home = tmp_path_factory.mktemp("fleet")
    assembly = resolved_assembly(tmp_path_factory.mktemp("asm"), "dragon")
    pki.init_fleet(list(assembly.hosts), ["alice"], home=home)
    ports = netconfig.Ports(
        local=free_port(), tls=free_port(), addresses={h: "127.0.0.1" for h in assembly.hosts}
    )
    router = _open(netconfig.router_config(assembly, ROBOT, home=home, ports=ports))
    local = _open(netconfig.component_config(ROBOT, ports))
    received: list[str] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        with lock:
            received.append(str(sample.key_expr))

    subscriber = local.declare_subscriber("0/**", on_sample)
    served = [
        local.declare_queryable(key, lambda q: q.reply(q.key_expr, b"ok"), complete=True)
        for key in ("0/limb1/halt/**", "0/msctl/hl_limb_01/request/**")
    ]
    state = {
        "home": home,
        "ports": ports,
        "assembly": assembly,
        "received": received,
        "local": local,
    }
    try:
        yield state
    finally:
        for queryable in served:
            queryable.undeclare()
        subscriber.undeclare()
        local.close()
        router.close()


def _tls_client(fleet: dict[str, Any], cn: str, home: Path | None = None) -> Any:
    home = home or fleet["home"]
    identity = pki.read_identity(cn, home)
    ports = fleet["ports"]
    return _open(
        {
            "mode": "client",
            "connect": {"endpoints": [f"tls/127.0.0.1:{ports.tls}"]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"link": {"tls": netconfig.tls_block(identity, home)}},
        }
    )


def _delivered(fleet: dict[str, Any], session: Any, denied: str, marker: str) -> bool:
    """Put ``denied`` then ``marker``; wait for the marker; whether ``denied`` arrived.

    Each key gets a fresh last chunk: the subscriber's record is shared by the tests.
    """
    _count[0] += 1
    denied, marker = f"{denied}{_count[0]}", f"{marker}{_count[0]}"
    session.put(denied, b"x")
    session.put(marker, b"x")
    wait_until(lambda: marker in fleet["received"], 10.0, f"marker {marker}")
    return denied in fleet["received"]


_count = [0]


def _answered(session: Any, key: str) -> bool:
    replies = list(session.get(key, timeout=QUERY_TIMEOUT))
    return any(r.ok is not None for r in replies)


def test_plain_tcp_client_cannot_reach_the_tls_endpoint(fleet: dict[str, Any]) -> None:
    with pytest.raises(zenoh.ZError):
        _open(
            {
                "mode": "client",
                "connect": {"endpoints": [f"tcp/127.0.0.1:{fleet['ports'].tls}"]},
                "scouting": {"multicast": {"enabled": False}},
            }
        ).close()


def test_identity_from_another_ca_cannot_connect(fleet: dict[str, Any], tmp_path: Path) -> None:
    pki.init_fleet([], ["alice"], home=tmp_path)
    with pytest.raises(zenoh.ZError):
        _tls_client(fleet, pki.operator_cn("alice"), home=tmp_path).close()


def test_operator_sets_joints_but_never_sends_raw_commands(fleet: dict[str, Any]) -> None:
    session = _tls_client(fleet, pki.operator_cn("alice"))
    try:
        assert not _delivered(fleet, session, "0/limb1/joint_commands/t/h", "0/limb1/joint_set/t/h")
    finally:
        session.close()


def test_another_modules_computer_cannot_command_this_module(fleet: dict[str, Any]) -> None:
    session = _tls_client(fleet, OTHER_ROBOT)
    try:
        assert not _delivered(
            fleet, session, "0/limb1/joint_commands/t/h", "0/limb2/joint_read/t/1"
        )
        assert not _delivered(fleet, session, "0/limb1/joint_set/t/h", "0/limb2/joint_read/t/2")
        assert not _answered(session, "0/limb1/halt/t/h")
    finally:
        session.close()


def test_operator_halts_and_reaches_the_supervisor_a_robot_cannot(fleet: dict[str, Any]) -> None:
    operator = _tls_client(fleet, pki.operator_cn("alice"))
    robot = _tls_client(fleet, OTHER_ROBOT)
    try:
        assert _answered(operator, "0/limb1/halt/t/h")
        assert _answered(operator, "0/msctl/hl_limb_01/request/t/h")
        assert not _answered(robot, "0/msctl/hl_limb_01/request/t/h")
    finally:
        robot.close()
        operator.close()


def test_liveliness_crosses_the_acl(fleet: dict[str, Any]) -> None:
    robot = _tls_client(fleet, OTHER_ROBOT)
    try:
        token = robot.liveliness().declare_token("@ros2_lv/0/test/NN/limb2")
        wait_until(
            lambda: list(fleet["local"].liveliness().get("@ros2_lv/0/**", timeout=2.0)),
            10.0,
            "the other robot's liveliness token",
        )
        token.undeclare()
    finally:
        robot.close()


def test_a_ros_enclave_config_in_rmw_zenoh_form_joins(tmp_path: Path) -> None:
    """An enclave identity from the fleet CA, its rmw_zenoh-form config, a router that knows
    it: the router accepts it, its publication arrives, a raw command does not."""
    from msctl.net.ros import enclave_config

    assembly = resolved_assembly(tmp_path / "asm", "dragon")
    pki.init_fleet(list(assembly.hosts), [], home=tmp_path)
    viewer = pki.issue("/field/viewer", home=tmp_path)
    ports = netconfig.Ports(local=free_port(), tls=free_port())
    router_config = netconfig.router_config(assembly, ROBOT, home=tmp_path, ports=ports)
    # Named by its certificate's CN: its path and this issuance's token.
    assert viewer.certificate_cn.startswith("/field/viewer#")
    assert {"id": "ros_enclaves", "cert_common_names": [viewer.certificate_cn]} in (
        router_config["access_control"]["subjects"]
    )
    router = _open(router_config)
    local = _open(netconfig.component_config(ROBOT, ports))
    received: list[str] = []
    subscriber = local.declare_subscriber("0/**", lambda s: received.append(str(s.key_expr)))
    enclave = _open(
        enclave_config(
            "/field/viewer",
            f"tls/127.0.0.1:{ports.tls}",
            publish=["/chatter"],
            subscribe=["/limb1/joint_read"],
            home=tmp_path,
        )
    )
    try:
        assert list(enclave.info.routers_zid())
        enclave.put("0/limb1/joint_commands/t/h", b"x")
        wait_until(
            lambda: enclave.put("0/chatter/t/h", b"x") or "0/chatter/t/h" in received,
            10.0,
            "the enclave's chatter",
        )
        assert "0/limb1/joint_commands/t/h" not in received
    finally:
        enclave.close()
        subscriber.undeclare()
        local.close()
        router.close()


def test_operator_at_the_station_reaches_the_robot_through_linked_routers(
    tmp_path: Path,
) -> None:
    """Station and robot routers linked over mutual TLS as the topology says: an operator
    on the station's router sets limb1's joints; raw commands stop at the station."""
    assembly = resolved_assembly(tmp_path / "asm", "dragon")
    pki.init_fleet(list(assembly.hosts), ["alice"], home=tmp_path)
    ports = netconfig.Ports(
        addresses={h: "127.0.0.1" for h in assembly.hosts},
        tls_ports={"ground1": free_port(), ROBOT: free_port()},
        local_ports={"ground1": free_port(), ROBOT: free_port()},
    )
    station = _open(netconfig.router_config(assembly, "ground1", home=tmp_path, ports=ports))
    robot = _open(netconfig.router_config(assembly, ROBOT, home=tmp_path, ports=ports))
    local = _open(netconfig.component_config(ROBOT, ports))
    received: list[str] = []
    subscriber = local.declare_subscriber("0/**", lambda s: received.append(str(s.key_expr)))
    operator = _open(netconfig.operator_config("alice", "ground1", tmp_path, ports))
    try:
        operator.put("0/limb1/joint_commands/t/h", b"x")
        wait_until(
            lambda: (
                operator.put("0/limb1/joint_set/t/h", b"x") or "0/limb1/joint_set/t/h" in received
            ),
            15.0,
            "the operator's joint_set across both routers",
        )
        assert "0/limb1/joint_commands/t/h" not in received
    finally:
        operator.close()
        subscriber.undeclare()
        local.close()
        robot.close()
        station.close()
