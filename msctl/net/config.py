"""Per-host Zenoh configs from the resolved assembly: routers, links, TLS and access control.

Topology: one router per robot computer and per ground station. Robot routers link to every
ground station's router (a station-less assembly links its robots to the first robot's). A
router takes its own computer's components on plain TCP on loopback only, and every link that
leaves the computer on mutual TLS with the fleet CA. Components are clients of their local
router, so no peer-to-peer link can go around the router's access control, and multicast
scouting is off everywhere.

The links between computers carry the template's budget (:mod:`msctl.net.radio`): high-rate
telemetry downsampled and large publications held back on the way out of a computer, a
lease that notices a dead link in seconds, TLS or QUIC. The loopback side, where the
computer's own components are, is never filtered.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from components.assembly import ResolvedAssembly
from components.comm.session import RECONNECT
from msctl.net import acl, pki, radio
from msctl.net.endpoints import EndpointError, parse

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
    """``transport/link/tls`` for an identity: the same key serves listening and connecting.

    Raises:
        NetConfigError: If the identity was revoked, or has no certificate or key here.
        pki.KeyModeError: If others may read its key.
    """
    name = identity.common_name
    try:
        # Never "run net init" for a revoked identity: say it is revoked, and how to lift it.
        pki.refuse_revoked(name, home)
    except pki.RevokedError as exc:
        raise NetConfigError(f"identity {name!r}: {exc}") from None
    for path in (identity.cert, identity.key):
        if not path.is_file():
            fix = (
                f"run `msctl net add-operator {name.removeprefix(pki.OPERATOR_PREFIX)}`"
                if identity.role == "operator"
                else f"run `msctl net init --host {name}` where the fleet CA is, then copy "
                "MSCTL_HOME/net to this computer (all but ca/ca.key)"
            )
            raise NetConfigError(f"identity {name!r} has no {path.name} at {path}: {fix}")
    pki.check_key_mode(identity.key)
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
    listen: Sequence[str] = (),
    connect: Sequence[str] | None = None,
    network: radio.Network | None = None,
) -> dict[str, Any]:
    """The Zenoh config of ``host``'s router.

    Args:
        assembly: The resolved assembly.
        host: The computer whose router it is.
        home: MSCTL_HOME (default: the environment's).
        ports: Ports and addresses (tests move them).
        domain: ROS domain.
        off_robot: ``host`` runs the whole assembly (``msctl up`` off-robot, simulated): its
            own components write every module's inputs, whichever computer the template
            places them on, and it links to no other router.
        listen: TLS endpoints to listen on in place of ``tls/0.0.0.0:<TLS port>``
            (``MSCTL_ROUTER_LISTEN``, e.g. one interface only).
        connect: TLS endpoints to link to in place of the links the topology gives
            (``MSCTL_ROUTER_CONNECT``, e.g. addresses where host names do not resolve).
        network: The link classes (default: the assembly's, from its template).

    Raises:
        NetConfigError: If ``host`` is not in the assembly (and does not run all of it), has
            no identity, or an endpoint given is not TLS or QUIC.
    """
    if not off_robot and host not in assembly.hosts:
        raise NetConfigError(
            f"host {host!r} runs nothing in assembly {assembly.template!r} "
            f"(its hosts: {', '.join(assembly.hosts)}): set MSCTL_HOST to one of them, or "
            "run the whole assembly here with `msctl up`"
        )
    ports = ports or Ports()
    # Each identity by its current certificate's CN: a revoked or replaced one matches none.
    certificates = pki.admitted(home)
    operators = [n for n in certificates if pki.role_of(n) == "operator"]
    enclaves = [n for n in certificates if pki.role_of(n) == "ros enclave"]
    fleet = acl.principals(assembly, operators, enclaves, certificates)
    guarded = acl.guarded_inputs(assembly)
    if off_robot:
        # Access control follows where the components run, not where the template puts
        # them: here, every computer's part runs on this one, so it is every module's own
        # computer (the station's too, when this computer is named as the station).
        placement = {other: host for other in assembly.hosts}
        guarded = acl.placed(guarded, placement)
        fleet = acl.placed_principals(fleet, placement)
    identity = pki.read_identity(host, home)
    network = network or radio.Network.from_dict(assembly.lock.network)
    link = own_link_class(assembly, host, network)
    tls_listen = list(_tls_only(listen, "MSCTL_ROUTER_LISTEN")) or [
        f"tls/0.0.0.0:{ports.tls_port(host)}"
    ]
    if not listen and "quic" in _linked_protocols(assembly, host, network):
        # Robots link to it over QUIC (UDP, the same port); operators still come over TLS.
        tls_listen.append(f"quic/0.0.0.0:{ports.tls_port(host)}")
    if connect is not None:
        linked = list(_tls_only(connect, "MSCTL_ROUTER_CONNECT"))
    elif off_robot:
        # Off-robot the whole assembly is simulated here: linking to the real robots'
        # routers would mix simulated and real data on the same topics.
        linked = []
    else:
        linked = [
            f"{link.protocol}/{ports.address(o)}:{ports.tls_port(o)}" for o in links(assembly, host)
        ]
    document: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{ports.local_port(host)}", *tls_listen]},
        # Links back within a second of the radio's return, not Zenoh's backoff's 4 s.
        "connect": {"endpoints": linked, "retry": dict(RECONNECT)},
        "scouting": {"multicast": {"enabled": False}, "delay": 0},
        "timestamping": {"enabled": True},
        "transport": {"link": {"tls": tls_block(identity, home)}},
        "access_control": acl.router_acl(host, fleet, guarded, domain),
    }
    if off_robot:
        return document  # no link leaves this computer: no budget to keep
    modules = [m.slot for m in assembly.modules if m.host == host]
    budget = radio.router_settings(link, modules, domain)
    document["downsampling"] = budget["downsampling"]
    document["low_pass_filter"] = budget["low_pass_filter"]
    document["transport"]["link"]["tx"] = budget["transport"]["link"]["tx"]
    document["transport"]["unicast"] = budget["transport"]["unicast"]
    return document


def own_link_class(
    assembly: ResolvedAssembly, host: str, network: radio.Network
) -> radio.LinkClass:
    """The class whose settings ``host``'s router applies to its links.

    A robot computer's is its own link's. A router others link to (a ground station, or the
    first robot of a station-less assembly) takes the radio's filters if any link to it is
    a radio, and the longest lease of them: a lease must outlast the slowest link's
    silences, and Zenoh has one lease per router.
    """
    own = network.link_class(host)
    linking = [o for o in assembly.hosts if o != host and host in links(assembly, o)]
    if not linking:
        return own
    classes = [network.link_class(o) for o in linking]
    base = next((c for c in classes if c.name == "radio"), classes[0])
    lease = max(c.lease_s for c in (*classes, own))
    return radio.LinkClass(
        base.name, lease, own.protocol, base.max_message_bytes, dict(base.downsample_hz)
    )


def _linked_protocols(assembly: ResolvedAssembly, host: str, network: radio.Network) -> set[str]:
    """The protocols of the links other computers open to ``host``."""
    return {
        network.link_class(o).protocol
        for o in assembly.hosts
        if o != host and host in links(assembly, o)
    }


def _tls_only(endpoints: Sequence[str], setting: str) -> list[str]:
    """``endpoints`` if each is TLS or QUIC (mutual TLS both); a plain one beside a secure
    router would let anyone in.

    The access control takes every plain TCP link as this computer's own components (subject
    ``local``): a plain listener beyond loopback would give the network their rights.

    Raises:
        NetConfigError: Naming the endpoint and the setting.
    """
    for text in endpoints:
        try:
            endpoint = parse(text)
        except EndpointError as exc:
            raise NetConfigError(f"{setting}: {exc}") from None
        if endpoint.protocol not in radio.ENCRYPTED:
            raise NetConfigError(
                f"{setting}={text}: a secure router takes other computers over mutual TLS "
                f"only; write it as tls/{text.partition('/')[2] or 'HOST:7448'}, or drop "
                "--secure (MSCTL_SECURE) for a plain TCP network you trust"
            )
    return list(endpoints)


def ports_from_env(environ: Mapping[str, str] | None = None) -> Ports:
    """This computer's router ports: loopback where its sessions connect
    (``MSCTL_ZENOH_CONNECT``, default 7447), TLS from ``MSCTL_NET_TLS_PORT`` (default 7448).

    Raises:
        NetConfigError: If ``MSCTL_NET_TLS_PORT`` is not a port number.
    """
    env = os.environ if environ is None else environ
    local = LOCAL_PORT
    for text in filter(None, (e.strip() for e in env.get("MSCTL_ZENOH_CONNECT", "").split(","))):
        endpoint = parse(text)
        if endpoint.protocol == "tcp" and endpoint.loopback and endpoint.port:
            local = endpoint.port
            break
    value = env.get("MSCTL_NET_TLS_PORT") or str(TLS_PORT)
    if not value.isdigit() or not 0 < int(value) < 65536:
        raise NetConfigError(f"MSCTL_NET_TLS_PORT={value!r} is not a port number (1-65535)")
    return Ports(local=local, tls=int(value))


def this_computer_router(
    host: str,
    off_robot: bool | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] | None = None,
    home: Path | None = None,
    ports: Ports | None = None,
) -> tuple[Path, list[str]]:
    """Write the config of this computer's secure router under ``MSCTL_HOME/net``.

    Args:
        host: This computer (``MSCTL_HOST`` or the hostname).
        off_robot: It runs the whole assembly (``msctl up`` off-robot); ``None``: when it is
            none of the assembly's computers (a standalone ``msctl router --secure``, an agent).
        listen: TLS endpoints in place of the generated TLS listener.
        connect: TLS endpoints in place of the generated links.
        home: MSCTL_HOME (default: the environment's).
        ports: Ports (default: :func:`ports_from_env`).

    Off-robot, a computer the fleet has no identity for gets one from the fleet CA here: a
    laptop that simulates the assembly is no computer ``msctl net init`` was told about.

    Returns:
        The config file, and lines worth telling the operator (an identity made).

    Raises:
        NetConfigError: No fleet CA, a host with no part and no identity, a non-TLS endpoint.
        components.assembly.AssemblyError: No resolved assembly.
    """
    from components.assembly import load_assembly

    if not pki.trusts(home):
        raise NetConfigError(
            f"this computer has no fleet CA certificate ({pki.ca_cert(home)}): run "
            "`msctl net init` on the ground station, then copy its MSCTL_HOME/net here "
            "(all but ca/ca.key)"
        )
    assembly = load_assembly()
    if off_robot is None:
        off_robot = host not in assembly.hosts
    notes = []
    identity = pki.read_identity(pki.check_name(host, "this computer's name (MSCTL_HOST)"), home)
    if off_robot and not identity.cert.is_file():
        pki.issue(host, home=home)
        notes.append(
            f"made an identity for {host} (this computer, running the whole assembly) with "
            f"the fleet CA in {pki.net_dir(home)}"
        )
    document = router_config(
        assembly,
        host,
        home=home,
        ports=ports or ports_from_env(),
        off_robot=off_robot,
        listen=listen,
        connect=connect,
    )
    target = pki.net_dir(home) / f"router-{host}.json5"
    target.write_text(dumps(document))
    return target, notes


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
