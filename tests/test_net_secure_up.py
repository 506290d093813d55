"""``MSCTL_SECURE=1 msctl up``: the embedded router runs the generated config; an operator's
identity runs the fleet, another identity's request (``msctl stop``) is refused. Real
subprocesses."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port
from running import Up

from msctl.net import pki


class SecureUp(Up):
    """:class:`Up` with the fleet initialised and its router secured (free TLS port)."""

    def __init__(self, home: Path, template: str) -> None:
        self.tls_port = free_port()
        pki.init_fleet(["test-laptop", "hl-limb-02"], ["alice@ground1"], home=home)
        os.environ["MSCTL_SECURE"] = "1"
        os.environ["MSCTL_NET_TLS_PORT"] = str(self.tls_port)
        try:
            super().__init__(home, template)
        finally:
            del os.environ["MSCTL_SECURE"], os.environ["MSCTL_NET_TLS_PORT"]

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
    up = SecureUp(tmp_path, "minimal")
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
