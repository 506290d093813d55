"""``MSCTL_SECURE=1 msctl up`` (or ``[network] secure = true`` in the template): the embedded
router runs the generated config; an operator's identity runs the fleet, another identity's
requests (``msctl stop``, ``msctl down --all``) are refused. Real subprocesses."""

from __future__ import annotations

import json
import os
import shutil
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
