"""A revocation that holds: every reissue path refuses a revoked name until it is lifted, and
the stolen certificate of a revoked (or replaced) identity is refused by a real router after
the name was issued a new one.

The fleet is dragon's, made with the real ``msctl net`` commands (in this process, see
:mod:`cli_inprocess`) and real openssl; the router is a real Zenoh router on 127.0.0.1 with
free ports, running the config ``msctl net config`` generates. A "stolen" identity is a copy
of an identity's files taken before it was revoked or issued again: what a thief holds.
"""

from __future__ import annotations

import json
import shutil
import threading
from typing import Any

import pytest
import zenoh
from cli_inprocess import msctl
from conftest import free_port, wait_until

from msctl.net import acl, pki
from msctl.net import config as netconfig

ROBOT = "hl-limb-01"  # limb1's computer: its router is the one the thieves try
HOST = "hl-limb-02"  # a robot computer whose identity is revoked, then issued again
BOB = "bob@ground1"  # an operator whose laptop was stolen
ALICE = "alice@ground1"  # an operator whose identity is issued again without a revocation
ENV = {"MSCTL_HOST": "ground1"}


def _open(config: dict[str, Any]) -> Any:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Dragon's fleet with operators bob and alice; copies of bob's, alice's and
    hl-limb-02's identities stolen; then bob and hl-limb-02 revoked."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path_factory.mktemp("home")
    write_resolution(home / "assembly", resolve("dragon", {}))
    done = msctl(home, "net", "init", "--operator", BOB, "--operator", ALICE, env=ENV)
    assert done.code == 0, done.stderr
    stolen = tmp_path_factory.mktemp("stolen")
    for name in (pki.operator_cn(BOB), pki.operator_cn(ALICE), HOST):
        shutil.copytree(pki.identity_dir(name, home), stolen / pki.identity_dir(name, home).name)
    for name in (BOB, HOST):
        done = msctl(home, "net", "revoke", name, env=ENV)
        assert done.code == 0, done.stderr
        assert f"unrevoke {name}" in done.said
    return {"home": home, "stolen": stolen}


def _stolen(fleet: dict[str, Any], name: str) -> pki.Identity:
    folder = fleet["stolen"] / pki.identity_dir(name, fleet["home"]).name
    cn = (folder / "cn").read_text().strip()
    return pki.Identity(name, pki.role_of(name), folder / "cert.pem", folder / "key.pem", None,
                        certificate_cn=cn)  # fmt: skip


def test_every_reissue_path_refuses_a_revoked_name_until_it_is_lifted(
    fleet: dict[str, Any],
) -> None:
    home = fleet["home"]
    bob_dir = pki.identity_dir(pki.operator_cn(BOB), home)
    host_dir = pki.identity_dir(HOST, home)
    # The stolen laptop's flow: give bob a new key. Refused, saying how to lift it.
    again = msctl(home, "net", "add-operator", BOB, env=ENV)
    assert again.code == 2 and "was revoked" in again.said, again.said
    assert f"msctl net unrevoke {BOB}" in again.said and not bob_dir.exists()
    named = msctl(home, "net", "init", "--operator", BOB, env=ENV)
    assert named.code == 2 and "was revoked" in named.said and not bob_dir.exists()
    # `net init` for the assembly's hosts: the revoked one is skipped and said.
    implied = msctl(home, "net", "init", env=ENV)
    assert implied.code == 0, implied.said
    assert f"{HOST}: revoked, not issued again" in implied.said and not host_dir.exists()
    host_named = msctl(home, "net", "init", "--host", HOST, env=ENV)
    assert host_named.code == 2 and f"msctl net unrevoke {HOST}" in host_named.said
    assert not host_dir.exists()
    # Its router config says it is revoked, never "run msctl net init" (which would re-admit).
    config = msctl(home, "net", "config", HOST, env=ENV)
    assert config.code == 2 and "was revoked" in config.said, config.said
    assert f"`msctl net init --host {HOST}`" not in config.said
    assert msctl(home, "net", "revoke", BOB, env=ENV).code == 2  # revoked already
    shown = json.loads(msctl(home, "net", "show", "--json", env=ENV).stdout)
    revoked = {i["common_name"] for i in shown["identities"] if i["revoked"]}
    assert revoked == {pki.operator_cn(BOB), HOST}
    # Every config generated meanwhile leaves both out.
    document = json.loads(msctl(home, "net", "config", ROBOT, env=ENV).stdout)
    named_cns = [cn for s in document["access_control"]["subjects"]
                 for cn in s.get("cert_common_names", [])]  # fmt: skip
    assert not [cn for cn in named_cns if pki.name_of(cn) in (pki.operator_cn(BOB), HOST)]
    # A ROS enclave likewise: revoked, `ros-enclave` does not make it again.
    enclave = ["net", "ros-enclave", "/field/viewer", "--router", "ground1"]
    assert msctl(home, *enclave, env=ENV).code == 0
    assert msctl(home, "net", "revoke", "/field/viewer", env=ENV).code == 0
    refused = msctl(home, *enclave, env=ENV)
    assert refused.code == 2 and "was revoked" in refused.said
    assert not pki.identity_dir("/field/viewer", home).exists()


class _Watch:
    """Every key a session receives on ``0/**``."""

    def __init__(self, session: Any) -> None:
        self.keys: list[str] = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber("0/**", self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        with self._lock:
            self.keys.append(str(sample.key_expr))

    def __contains__(self, key: str) -> bool:
        with self._lock:
            return key in self.keys

    def close(self) -> None:
        self._subscriber.undeclare()


def test_stolen_certificates_are_refused_by_a_real_router_after_the_name_is_reissued(
    fleet: dict[str, Any],
) -> None:
    """After lifting (both ways) and reissuing, the new identities are admitted and every
    stolen one (revoked, or replaced by a plain reissue) is refused: it delivers nothing and
    receives nothing."""
    home = fleet["home"]
    assert msctl(home, "net", "unrevoke", BOB, env=ENV).code == 0
    assert msctl(home, "net", "add-operator", BOB, env=ENV).code == 0
    assert msctl(home, "net", "init", "--host", HOST, "--lift", env=ENV).code == 0
    assert msctl(home, "net", "add-operator", ALICE, env=ENV).code == 0  # a plain reissue
    assert pki.revoked_names(home) == {"/field/viewer"}

    from components.assembly import load_assembly

    assembly = load_assembly(home / "assembly")
    ports = netconfig.Ports(local=free_port(), tls=free_port())
    config = netconfig.router_config(assembly, ROBOT, home=home, ports=ports)
    subjects = {s["id"]: s.get("cert_common_names") for s in config["access_control"]["subjects"]}
    for name in (pki.operator_cn(BOB), pki.operator_cn(ALICE), HOST):
        new, old = pki.read_identity(name, home).certificate_cn, _stolen(fleet, name)
        assert new != old.certificate_cn and pki.name_of(new) == pki.name_of(old.certificate_cn)
    for name in (ALICE, BOB):
        cn = pki.operator_cn(name)
        assert pki.read_identity(cn, home).certificate_cn in subjects[acl.OPERATORS]
        assert _stolen(fleet, cn).certificate_cn not in subjects[acl.OPERATORS]
    assert subjects[f"host:{HOST}"] == [pki.read_identity(HOST, home).certificate_cn]

    def client(identity: pki.Identity) -> Any:
        return _open(
            {
                "mode": "client",
                "connect": {"endpoints": [f"tls/127.0.0.1:{ports.tls}"]},
                "scouting": {"multicast": {"enabled": False}},
                "transport": {"link": {"tls": netconfig.tls_block(identity, home)}},
            }
        )

    router = _open(config)
    sessions: list[Any] = []
    watches: list[_Watch] = []
    try:
        local = _open(netconfig.component_config(ROBOT, ports))
        sessions.append(local)
        at_robot = _Watch(local)
        watches.append(at_robot)
        cases = [
            # (who, the input it writes: an operator's joint_set, a computer's telemetry)
            (pki.operator_cn(BOB), "0/limb1/joint_set/t/h"),
            (pki.operator_cn(ALICE), "0/limb1/joint_set/t/h"),
            (HOST, "0/limb2/joint_read/t/h"),
        ]
        for number, (name, key) in enumerate(cases):
            new = client(pki.read_identity(name, home))
            # The TLS handshake passes (the fleet CA signed it; it has not expired): the
            # access control is what must refuse it.
            thief = client(_stolen(fleet, name))
            sessions += [new, thief]
            new_sees, thief_sees = _Watch(new), _Watch(thief)
            watches += [new_sees, thief_sees]
            denied, allowed = f"{key}/stolen{number}", f"{key}/new{number}"
            telemetry = f"0/limb1/joint_read/t/h/tick{number}"

            def delivered(
                thief: Any = thief, new: Any = new, denied: str = denied, allowed: str = allowed
            ) -> bool:
                # The thief writes first each time: had the router let it through, its
                # sample would be there by the time the one after it is.
                thief.put(denied, b"x")
                new.put(allowed, b"x")
                return allowed in at_robot

            def read(telemetry: str = telemetry, sees: _Watch = new_sees) -> bool:
                local.put(telemetry, b"x")
                return telemetry in sees

            wait_until(delivered, 15.0, f"{name}'s new identity writing {key}")
            wait_until(read, 15.0, f"{name}'s new identity reading the robot")
            for round_ in range(3):  # more rounds after the first arrival, thief first
                thief.put(denied, b"x")
                marker = f"{allowed}/after{round_}"
                new.put(marker, b"x")
                wait_until(lambda m=marker: m in at_robot, 15.0, "the marker after the thief")
            assert denied not in at_robot, f"{name}'s stolen certificate wrote {key}"
            assert telemetry not in thief_sees, f"{name}'s stolen certificate read the robot"
    finally:
        for watch in watches:
            watch.close()
        for session in reversed(sessions):
            session.close()
        router.close()
