"""``MSCTL_SECURE=1 msctl up`` (or ``[network] secure = true`` in the template): the embedded
router runs the generated config; an operator's identity runs the fleet, another identity's
requests (``msctl stop``, ``msctl down --all``) are refused. Real subprocesses."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port
from running import ROOT, Up

from msctl.net import pki


class SecureUp(Up):
    """:class:`Up` with the fleet initialised and its router secured (free TLS port)."""

    def __init__(
        self,
        home: Path,
        template: str,
        hosts: tuple[str, ...] = ("test-laptop", "hl-limb-02"),
        **env: str,
    ) -> None:
        self.tls_port = free_port()
        pki.init_fleet(list(hosts), ["alice@ground1"], home=home)
        env = {"MSCTL_NET_TLS_PORT": str(self.tls_port), **env}
        os.environ.update(env)
        try:
            super().__init__(home, template)
        finally:
            for key in env:
                del os.environ[key]

    def as_identity(self, identity: str, *args: str) -> Any:
        """Run msctl with ``identity`` over the router's TLS endpoint."""
        saved = dict(self.env)
        self.env.update(
            MSCTL_IDENTITY=identity, MSCTL_ZENOH_CONNECT=f"tls/127.0.0.1:{self.tls_port}"
        )
        try:
            return self.msctl(*args)
        finally:
            self.env = saved


@pytest.mark.e2e
def test_secure_up_obeys_operators_only(tmp_path: Path) -> None:
    up = SecureUp(tmp_path, "minimal", MSCTL_SECURE="1")
    try:
        listed = up.as_identity("hl-limb-02", "topic", "list", "--json")
        assert listed.returncode == 0, listed.stderr
        # `msctl down` on the same computer may signal the supervisor (the OS lets it); a
        # request over the network is what the ACL refuses to a non-operator.
        refused = up.as_identity("hl-limb-02", "stop", "limb1")
        assert refused.returncode != 0, refused.stdout + refused.stderr
        ps = up.as_identity("alice@ground1", "ps", "--json")
        assert ps.returncode == 0, ps.stderr
        assert json.loads(ps.stdout)
        stopped = up.as_identity("alice@ground1", "stop", "limb1")
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    finally:
        up.down()


@pytest.mark.e2e
def test_a_template_saying_secure_runs_the_secure_router_and_a_robot_cannot_down_it(
    tmp_path: Path,
) -> None:
    # The template says it, no flag or MSCTL_SECURE: `msctl up` runs the secure router.
    templates = tmp_path / "assemblies"
    shutil.copytree(ROOT / "assemblies", templates)
    with (templates / "minimal.toml").open("a") as f:
        f.write("\n[network]\nsecure = true\n")
    home = tmp_path / "home"
    # hl-limb-01 (minimal's limb's computer) has an identity from the fleet CA, but is no
    # operator; off-robot, the simulating laptop is the assembly's only computer.
    up = SecureUp(
        home, "minimal", ("test-laptop", "hl-limb-01"), MSCTL_ASSEMBLIES_DIR=str(templates)
    )
    try:
        lock = json.loads((home / "assembly" / "assembly.lock.json").read_text())
        assert lock["secure"] is True
        assert up.as_identity("alice@ground1", "ps", "--json").returncode == 0
        # Another computer of the fleet (its own home, the fleet's identities) asks every
        # supervisor to stop: the ACL drops a robot identity's request, and it says so.
        station = tmp_path / "station"
        shutil.copytree(home / "net", station / "net")
        up.env["MSCTL_HOME"] = str(station)
        refused = up.as_identity("hl-limb-01", "down", "--all")
        assert refused.returncode != 0, refused.stdout + refused.stderr
        said = " ".join(refused.stderr.split())
        assert "nothing was stopped" in said and "is not an operator" in said, said
        up.env["MSCTL_HOME"] = str(home)
        still = up.as_identity("alice@ground1", "ps", "--json")
        assert still.returncode == 0, still.stderr
        rows = json.loads(still.stdout)["components"]
        assert rows and all(r["state"] == "running" for r in rows), rows
    finally:
        up.env["MSCTL_HOME"] = str(home)
        up.down()


# --------------------------------------------------------------------------- off-robot dragon
class OffRobotDragon(Up):
    """``msctl assemble dragon && msctl net init && msctl up dragon --sim --detach --secure``
    as a user types them on a computer running the whole assembly (``host``), its router's
    ports moved to free ones (MSCTL_ZENOH_CONNECT, MSCTL_NET_TLS_PORT)."""

    def __init__(self, home: Path, host: str) -> None:
        self.host = host
        self.tls_port = free_port()
        steps = {
            **os.environ,
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": host,
            "PYTHONPATH": str(ROOT),
        }
        for argv in (["assemble", "dragon"], ["net", "init", "--operator", "alice@ground1"]):
            done = subprocess.run(
                [sys.executable, "-m", "msctl", *argv],
                env=steps,
                capture_output=True,
                text=True,
                timeout=60,
                cwd=ROOT,
            )
            assert done.returncode == 0, done.stderr
        self.init_said = done.stderr
        super().__init__(
            home, "dragon", "--sim", "--secure", env={"MSCTL_HOST": host, **self._tls_env()}
        )

    def _tls_env(self) -> dict[str, str]:
        return {"MSCTL_NET_TLS_PORT": str(self.tls_port)}

    def operator(self, *args: str) -> Any:
        """Run msctl as operator alice over the router's TLS endpoint."""
        saved = dict(self.env)
        self.env.update(
            MSCTL_IDENTITY="alice@ground1", MSCTL_ZENOH_CONNECT=f"tls/127.0.0.1:{self.tls_port}"
        )
        try:
            return self.msctl(*args)
        finally:
            self.env = saved


@pytest.fixture(scope="module")
def laptop(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OffRobotDragon]:
    """A secure simulated dragon on a laptop that is none of the assembly's computers."""
    up = OffRobotDragon(tmp_path_factory.mktemp("laptop"), "test-laptop")
    try:
        yield up
    finally:
        up.down()


@pytest.fixture(scope="module")
def station_laptop(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OffRobotDragon]:
    """The same on a laptop named as the dragon's ground station (ground1)."""
    up = OffRobotDragon(tmp_path_factory.mktemp("ground1"), "ground1")
    try:
        yield up
    finally:
        up.down()


def _all_running(up: OffRobotDragon) -> list[dict[str, Any]]:
    ps = up.operator("ps", "--json")
    assert ps.returncode == 0, ps.stderr
    rows = json.loads(ps.stdout)["components"]
    assert len(rows) > 15 and all(r["state"] == "running" for r in rows), rows
    return rows


@pytest.mark.e2e
def test_net_init_gives_this_computer_an_identity_and_the_laptop_comes_up(
    laptop: OffRobotDragon,
) -> None:
    assert "test-laptop" in laptop.init_said, laptop.init_said
    assert pki.read_identity("test-laptop", laptop.home).cert.is_file()
    rows = _all_running(laptop)
    assert {r["host"] for r in rows} == {"test-laptop"}
    config = json.loads((laptop.home / "net" / "router-test-laptop.json5").read_text())
    assert config["connect"]["endpoints"] == []  # a simulation links to no real robot


@pytest.mark.e2e
def test_a_laptop_named_as_the_station_runs_every_module_under_its_acl(
    station_laptop: OffRobotDragon,
) -> None:
    """ground1 is the dragon's station host; off-robot it runs every module's part too, so
    its router lets its own components write every module's inputs (it used to deny the
    joint managers' raw commands: 'limb1/joint_manager ... it never published')."""
    rows = _all_running(station_laptop)
    assert any(r["name"] == "limb1/joint_manager" for r in rows)
    config = json.loads((station_laptop.home / "net" / "router-ground1.json5").read_text())
    acl_block = config["access_control"]
    denied_local = [
        key
        for policy in acl_block["policies"]
        if "local" in policy["subjects"]
        for rule in acl_block["rules"]
        if rule["id"] in policy["rules"] and rule["permission"] == "deny"
        for key in rule["key_exprs"]
    ]
    assert not any("joint_commands" in key for key in denied_local), denied_local


@pytest.mark.e2e
def test_a_port_held_by_this_homes_running_router_fails_at_once_naming_the_run(
    laptop: OffRobotDragon,
) -> None:
    """An agent of the same MSCTL_HOME, its own router asked to listen where the run's secure
    router takes TLS: refused before any router starts, naming that run."""
    port = laptop.tls_port
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "agent"],
        env={
            **laptop.env,
            "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
            "MSCTL_ROUTER_LISTEN": f"tcp/0.0.0.0:{port}",
        },
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert done.returncode == 2, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    assert f"cannot listen on tcp/0.0.0.0:{port}" in error, error
    assert "the router of `msctl up dragon` running on test-laptop" in error, error
    assert "msctl down" in error, error
    # At once, not after a supervisor's five restarts of a router that cannot listen (a
    # wall-clock bound here failed on a loaded machine): no restart was ever tried.
    assert "restart" not in done.stderr.lower(), done.stderr


@pytest.mark.e2e
def test_a_missing_identity_fails_at_once_before_detaching(tmp_path: Path) -> None:
    """On a robot computer (its own part, no identity made for it): one line naming the
    certificate file and the command that makes it, in seconds, no router ever started."""
    env = {
        **os.environ,
        "MSCTL_HOME": str(tmp_path),
        "MSCTL_HOST": "hl-limb-01",
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_MULTICAST": "0",
        "MSCTL_NET_TLS_PORT": str(free_port()),
        "PYTHONPATH": str(ROOT),
    }

    def msctl(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            cwd=ROOT,
        )

    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    write_resolution(tmp_path / "assembly", resolve("dragon", {}))
    pki.init_fleet(["ground1"], [], home=tmp_path)  # `msctl net init --host ground1`
    done = msctl("up", "--sim", "--detach", "--secure")  # the resolved dragon
    assert done.returncode == 2, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    cert = tmp_path / "net" / "identities" / "hl-limb-01" / "cert.pem"
    assert f"identity 'hl-limb-01' has no cert.pem at {cert}" in error, error
    assert "msctl net init --host hl-limb-01" in error, error
    # At once: no router was ever started (a wall-clock bound failed on a loaded machine, at
    # 11 s for a check that takes well under one when the machine is idle).
    assert not (tmp_path / "run" / "logs" / "router.log").exists()


# --------------------------------------------------------------------------- configs
def test_off_robot_config_makes_this_computers_identity_and_follows_the_plan(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution
    from msctl.net import acl
    from msctl.net import config as netconfig

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    write_resolution(tmp_path / "assembly", resolve("dragon", {}))
    pki.init_fleet(["ground1"], ["alice@ground1"], home=tmp_path)
    path, notes = netconfig.this_computer_router("vm", off_robot=True)
    assert "made an identity for vm" in notes[0]
    assert pki.read_identity("vm", tmp_path).cert.is_file()
    document = json.loads(path.read_text())
    assert document["connect"]["endpoints"] == []
    # Every module's raw commands: this computer's own components, nobody else.
    for rule in document["access_control"]["rules"]:
        if rule["permission"] == "deny" and "0/limb1/joint_commands/**" in rule["key_exprs"]:
            policy = next(
                p for p in document["access_control"]["policies"] if rule["id"] in p["rules"]
            )
            assert acl.LOCAL not in policy["subjects"]
    # A robot computer's own part: its identity is never made for it behind its back.
    with pytest.raises(netconfig.NetConfigError, match="msctl net init --host hl-limb-01"):
        netconfig.this_computer_router("hl-limb-01")
    # A secure router links and listens over TLS only: plain TCP would pass for `local`.
    pki.init_fleet(["hl-limb-01"], [], home=tmp_path)
    with pytest.raises(netconfig.NetConfigError, match="MSCTL_ROUTER_CONNECT=tcp/ground1:7448"):
        netconfig.this_computer_router("hl-limb-01", connect=["tcp/ground1:7448"])
    path, _ = netconfig.this_computer_router(
        "hl-limb-01", listen=["tls/127.0.0.1:9448"], connect=["tls/10.0.0.1:7448"]
    )
    document = json.loads(path.read_text())
    assert document["listen"]["endpoints"][1:] == ["tls/127.0.0.1:9448"]
    assert document["connect"]["endpoints"] == ["tls/10.0.0.1:7448"]
