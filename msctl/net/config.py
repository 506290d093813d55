"""Per-host Zenoh configs from the resolved assembly: routers, links, TLS and access control.

Topology: one router per robot computer and per ground station. Robot routers link to every
ground station's router (a station-less assembly links its robots to the first robot's). A
router takes its own computer's components on plain TCP on loopback only, and every link that
leaves the computer on mutual TLS with the fleet CA. Components are clients of their local
router, so no peer-to-peer link can go around the router's access control, and multicast
scouting is off everywhere.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from components.assembly import ResolvedAssembly
from msctl.net import acl, pki

#: Where a router takes its own computer's components (rmw_zenohd's port, loopback only).
LOCAL_PORT = 7447
#: Where a router takes other computers and operators, over mutual TLS.
TLS_PORT = 7448


class NetConfigError(ValueError):
    """A host or identity the config needs is missing; the message says what to run."""


@dataclass(frozen=True)
class Ports:
    """Ports and addresses of the routers (tests move them to free loopback ports).

    Attributes:
        local: The loopback TCP port for the computer's own components.
        tls: The mutual-TLS port for links from other computers and operators.
        addresses: Host -> address other computers reach it at (default: the host name).
        tls_ports: Host -> its TLS port when hosts share one machine (tests).
        local_ports: Host -> its loopback port when hosts share one machine (tests).
    """

    local: int = LOCAL_PORT
    tls: int = TLS_PORT
    addresses: dict[str, str] | None = None
    tls_ports: dict[str, int] | None = None
    local_ports: dict[str, int] | None = None

    def address(self, host: str) -> str:
        """Where ``host`` is reached."""
        return (self.addresses or {}).get(host, host)

    def tls_port(self, host: str) -> int:
        """``host``'s TLS port."""
        return (self.tls_ports or {}).get(host, self.tls)

    def local_port(self, host: str) -> int:
        """``host``'s loopback port."""
        return (self.local_ports or {}).get(host, self.local)


def tls_block(identity: pki.Identity, home: Path | None) -> dict[str, Any]:
    """``transport/link/tls`` for an identity: the same key serves listening and connecting."""
    for path in (identity.cert, identity.key):
        if not path.is_file():
            raise NetConfigError(
                f"identity {identity.common_name!r} has no {path.name} at {path}: run "
                f"`msctl net init` (hosts) or `msctl net add-operator NAME` (operators)"
            )
    return {
        "root_ca_certificate": str(pki.ca_cert(home)),
        "listen_private_key": str(identity.key),
        "listen_certificate": str(identity.cert),
        "connect_private_key": str(identity.key),
        "connect_certificate": str(identity.cert),
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }


def links(assembly: ResolvedAssembly, host: str) -> list[str]:
    """The hosts whose routers ``host``'s router connects to."""
    fleet = acl.principals(assembly, [])
    if host in fleet.stations:
        return []
    if fleet.stations:
        return list(fleet.stations)
    first = fleet.robots[0]
    return [] if host == first else [first]


def router_config(
    assembly: ResolvedAssembly,
    host: str,
    home: Path | None = None,
    ports: Ports | None = None,
    domain: int = 0,
    off_robot: bool = False,
) -> dict[str, Any]:
    """The Zenoh config of ``host``'s router.

    ``off_robot``: ``host`` runs the whole assembly simulated (``msctl up`` off-robot), so
    its own components write every module's inputs.

    Raises:
        NetConfigError: If ``host`` is not in the assembly, or has no identity.
    """
    if off_robot:
        # One computer runs every module (simulated): it is every module's own computer.
        assembly_guarded = [
            acl.GuardedInput(g.topic, frozenset({host}), g.operators, g.stations, g.why)
            for g in acl.guarded_inputs(assembly)
        ]
    elif host not in assembly.hosts:
        raise NetConfigError(
            f"host {host!r} runs nothing in assembly {assembly.template!r} "
            f"(its hosts: {', '.join(assembly.hosts)})"
        )
    ports = ports or Ports()
    revoked = pki.revoked_names(home)
    names = [cn for cn in pki.common_names(home) if cn not in revoked]
    operators = [cn for cn in names if pki.role_of(cn) == "operator"]
    enclaves = [cn for cn in names if pki.role_of(cn) == "ros enclave"]
    fleet = acl.principals(assembly, operators, enclaves)
    if off_robot:
        fleet.robots = [host]
    if not off_robot:
        assembly_guarded = acl.guarded_inputs(assembly)
    identity = pki.read_identity(host, home)
    # Off-robot the whole assembly is simulated here: linking to the real robots' routers
    # would mix simulated and real data on the same topics.
    linked = [] if off_robot else links(assembly, host)
    return {
        "mode": "router",
        "listen": {
            "endpoints": [
                f"tcp/127.0.0.1:{ports.local_port(host)}",
                f"tls/0.0.0.0:{ports.tls_port(host)}",
            ]
        },
        "connect": {
            "endpoints": [f"tls/{ports.address(other)}:{ports.tls_port(other)}" for other in linked]
        },
        "scouting": {"multicast": {"enabled": False}, "delay": 0},
        "timestamping": {"enabled": True},
        "transport": {"link": {"tls": tls_block(identity, home)}},
        "access_control": acl.router_acl(host, fleet, assembly_guarded, domain),
    }


def component_config(host: str, ports: Ports | None = None) -> dict[str, Any]:
    """The Zenoh config of a component on ``host``: a client of its local router only."""
    ports = ports or Ports()
    return {
        "mode": "client",
        "connect": {"endpoints": [f"tcp/127.0.0.1:{ports.local_port(host)}"]},
        "scouting": {"multicast": {"enabled": False}},
        "timestamping": {"enabled": True},
    }


def operator_config(
    operator: str, router: str, home: Path | None = None, ports: Ports | None = None
) -> dict[str, Any]:
    """The Zenoh config of operator ``operator``'s commands: a TLS client of ``router``."""
    ports = ports or Ports()
    identity = pki.read_identity(pki.operator_cn(operator), home)
    return {
        "mode": "client",
        "connect": {"endpoints": [f"tls/{ports.address(router)}:{ports.tls_port(router)}"]},
        "scouting": {"multicast": {"enabled": False}},
        "timestamping": {"enabled": True},
        "transport": {"link": {"tls": tls_block(identity, home)}},
    }


def dumps(config: dict[str, Any]) -> str:
    """A config as json5 text (JSON is json5)."""
    return json.dumps(config, indent=2) + "\n"
