"""A budget per link between computers: what crosses a radio, how big, and how soon a dead
link is noticed.

A template's ``[network]`` table names link classes, each with its settings, and which class
each computer's link is (every link between computers is ``radio`` unless it says otherwise)::

    [network.radio]
    lease_s = 5.0                # a link silent this long is dead (and opened again)
    protocol = "tls"             # "tls" (TCP) or "quic" (UDP), both mutual TLS
    max_message_bytes = 65536    # larger publications stay off the link (0: no limit)

    [network.radio.downsample_hz]    # when given, the whole list (else the defaults below)
    joint_states = 10            # each module's /<module>/joint_states, at most 10 a second
    "/limb1/tip_pose" = 5        # one topic, by its full name

    [network.links]
    hl-wheel-01 = "wired"        # this computer's link is a cable: no budget
    ground1 = "deep-space"       # Earth to the Moon: a 30 s lease (name both ends' computers)

Only the links that leave a computer get these settings (its router's TLS or QUIC links); its
own components, on loopback TCP, still see every sample at its full rate. Services, halts,
e-stops, liveliness and every publication not named are never downsampled.

This module is pure: it checks the template's table (errors name the file and the field) and
turns a class into the Zenoh router settings that carry it out
(:func:`router_settings`); :mod:`msctl.net.config` puts them in each router's config.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from components.links import (  # noqa: F401  (radio.Network etc. for the net package)
    DEFAULTS,
    RADIO_DOWNSAMPLE_HZ,
    LinkClass,
    Network,
    thinned_topics,
)
from msctl.errors import InputError

#: Link classes a template may name.
CLASSES = ("radio", "wired", "deep-space")
#: Link protocols a class may use between computers (both mutual TLS with the fleet CA).
PROTOCOLS = ("tls", "quic")
#: The link protocols between computers, on which a class's filters act (never on the
#: loopback TCP of a computer's own components).
ENCRYPTED = ("tls", "quic")
#: What ``[network.<class>]`` may say.
CLASS_KEYS = ("lease_s", "protocol", "max_message_bytes", "downsample_hz")
#: Keep-alives a router sends per lease when it has nothing else to send (Zenoh's own
#: advice, after ITU-T Y.1731: a link is failed after about 3.5 missed intervals).
KEEP_ALIVES_PER_LEASE = 4
#: Shortest lease a class may ask for: below it a router's keep-alives come faster than a
#: loaded computer schedules them.
MIN_LEASE_S = 0.5
#: A link's handshake (TCP or QUIC, TLS, then Zenoh's own) takes about five round trips;
#: a router waits this many leases for it (at least Zenoh's 10 s), so a link as slow as
#: the Moon's (2.56 s round trip) can still be opened.
HANDSHAKE_LEASES = 4
MIN_HANDSHAKE_S = 10.0

# ----------------------------------------------------------------------------- the template
#: A topic name as a downsample entry may give it: a ROS name, relative or absolute.
_TOPIC_RE = re.compile(r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")


def parse(table: Mapping[str, Any], path: Path, prefix: str = "network.") -> Network:
    """Check a template's ``[network]`` table (all but its other keys, such as ``secure``).

    Args:
        table: The ``[network]`` table.
        path: The template file, named in errors.
        prefix: The table's name in errors.

    Raises:
        InputError: Naming the file, the field and what it may be.
    """
    classes = dict(DEFAULTS)
    for name in CLASSES:
        if name in table:
            classes[name] = _link_class(name, table[name], path, f"{prefix}{name}")
    links: dict[str, str] = {}
    given = table.get("links", {})
    if not isinstance(given, dict):
        raise InputError(
            f"{path}: field {prefix}links is {given!r}",
            hint='it is a table of computer = class, e.g. hl-wheel-01 = "wired"',
        )
    for host, name in given.items():
        if name not in CLASSES:
            raise InputError(
                f"{path}: field {prefix}links.{host} is {name!r}",
                hint=f"a link's class is one of {', '.join(map(repr, CLASSES))}",
            )
        if name != "radio":
            links[host] = name
    return Network(classes, links)


def check_hosts(
    network: Network, hosts: Iterable[str], path: Path, prefix: str = "network."
) -> None:
    """Every computer ``[network.links]`` names runs something of the assembly.

    Raises:
        InputError: Naming the computer and the assembly's computers.
    """
    known = list(hosts)
    for host in network.links:
        if host not in known:
            raise InputError(
                f"{path}: field {prefix}links.{host}: no module or station runs on {host!r}",
                hint=f"the assembly's computers: {', '.join(known) or 'none'}",
            )


def _link_class(name: str, table: Any, path: Path, where: str) -> LinkClass:
    if not isinstance(table, dict):
        raise InputError(f"{path}: field {where} must be a table", hint=_class_hint())
    for key in table:
        if key not in CLASS_KEYS:
            raise InputError(
                f"{path}: field {where}.{key} is not a link setting", hint=_class_hint()
            )
    base = DEFAULTS[name]
    lease = table.get("lease_s", base.lease_s)
    if (
        isinstance(lease, bool)
        or not isinstance(lease, (int, float))
        or not math.isfinite(lease)
        or lease < MIN_LEASE_S
    ):
        raise InputError(
            f"{path}: field {where}.lease_s is {lease!r}",
            hint=f"seconds of silence before a link is dead, at least {MIN_LEASE_S:g}; longer "
            "than the link's round trip and a TCP retransmission (5 suits Wi-Fi and the Moon)",
        )
    protocol = table.get("protocol", base.protocol)
    if protocol not in PROTOCOLS:
        raise InputError(
            f"{path}: field {where}.protocol is {protocol!r}",
            hint=f"one of {', '.join(map(repr, PROTOCOLS))} (both mutual TLS; quic runs on UDP)",
        )
    size = table.get("max_message_bytes", base.max_message_bytes)
    if isinstance(size, bool) or not isinstance(size, int) or size < 0:
        raise InputError(
            f"{path}: field {where}.max_message_bytes is {size!r}",
            hint="a whole number of bytes (0: no limit)",
        )
    rates = table.get("downsample_hz", base.downsample_hz)
    if not isinstance(rates, dict):
        raise InputError(
            f"{path}: field {where}.downsample_hz is {rates!r}",
            hint="a table of topic = most samples a second, e.g. joint_states = 10",
        )
    downsample: dict[str, float] = {}
    for topic, rate in rates.items():
        if not _TOPIC_RE.match(topic):
            raise InputError(
                f"{path}: field {where}.downsample_hz.{topic!r} is not a topic name",
                hint="a module's topic (joint_states: every module's) or one topic by its full "
                'name ("/limb1/joint_states"); no wildcards: each topic has its own budget',
            )
        if (
            isinstance(rate, bool)
            or not isinstance(rate, (int, float))
            or not math.isfinite(rate)
            or rate <= 0
        ):
            raise InputError(
                f"{path}: field {where}.downsample_hz.{topic} is {rate!r}",
                hint="most samples a second across the link, a number above 0 (leave the "
                "topic out to send it at its full rate)",
            )
        downsample[topic] = float(rate)
    return LinkClass(name, float(lease), protocol, size, downsample)


def _class_hint() -> str:
    return (
        f"a link class takes {', '.join(CLASS_KEYS)}, e.g. lease_s = 5.0, "
        'protocol = "tls", max_message_bytes = 65536, downsample_hz = { joint_states = 10 }'
    )


# ----------------------------------------------------------------------------- the router
def router_settings(link: LinkClass, modules: Iterable[str], domain: int = 0) -> dict[str, Any]:
    """The Zenoh router settings that carry out ``link`` on the links leaving a computer.

    Downsampling and the size limit are egress filters on encrypted links only (TLS and
    QUIC: every link between computers), so the computer's own components, on loopback
    TCP, keep every sample (an operator's tool on the computer, a TLS client, gets what the
    radio would carry); a filter
    has one budget per rule, so each topic of each module gets a rule of its own. The lease
    is the router's (Zenoh has one per router; its local clients announce their own, which
    is what it holds them to).

    Args:
        link: The class of the computer's links.
        modules: The modules whose components run on the computer (module-relative topics
            are theirs).
        domain: ROS domain (the first chunk of every data key).

    Returns:
        Top-level Zenoh config sections: ``downsampling``, ``low_pass_filter`` and
        ``transport`` (``link/tx``: lease, keep-alive, how long a blocked sample may wait
        before the link is closed; ``unicast``: handshake timeouts), to be merged into the
        router's config.
    """
    lease_ms = round(link.lease_s * 1000)
    handshake_ms = round(max(MIN_HANDSHAKE_S, HANDSHAKE_LEASES * link.lease_s) * 1000)
    tx: dict[str, Any] = {
        "lease": lease_ms,
        "keep_alive": KEEP_ALIVES_PER_LEASE,
        # A reliable sample that finds the link's queue full waits for room; Zenoh closes the
        # link after 5 s of that. A slow link is not a dead one (the lease says which): on
        # the Moon's link, TCP's window grows one round trip (2.56 s) at a time, and the
        # declarations a reopened link carries took longer than 5 s, so the link was closed
        # again, and again (three times in a minute, measured).
        "queue": {"congestion_control": {"block": {"wait_before_close": handshake_ms * 1000}}},
    }
    settings: dict[str, Any] = {
        "downsampling": [],
        "low_pass_filter": [],
        "transport": {
            "link": {"tx": tx},
            "unicast": {"open_timeout": handshake_ms, "accept_timeout": handshake_ms},
        },
    }
    rules = [
        {"key_expr": key, "freq": rate}
        for key, rate in downsample_keys(link.downsample_hz, modules, domain).items()
    ]
    if rules:
        settings["downsampling"].append(
            {
                "id": f"{link.name}-downsample",
                "link_protocols": list(ENCRYPTED),
                "flows": ["egress"],
                "messages": ["put"],
                "rules": rules,
            }
        )
    if link.max_message_bytes:
        settings["low_pass_filter"].append(
            {
                "id": f"{link.name}-max-message",
                "link_protocols": list(ENCRYPTED),
                "flows": ["egress"],
                # Publications only: a service's request or answer (an agent's plan, a bag's
                # chunk) is asked for, so it crosses whatever its size.
                "messages": ["put"],
                "key_exprs": ["**"],
                "size_limit": link.max_message_bytes,
            }
        )
    return settings


def downsample_keys(
    rates: Mapping[str, float], modules: Iterable[str], domain: int = 0
) -> dict[str, float]:
    """Zenoh key expression -> rate for each downsampled topic: a module-relative name once
    per module, a full name as it is (any type: the key's last two chunks)."""
    modules = list(modules)
    keys: dict[str, float] = {}
    for topic, rate in rates.items():
        if topic.startswith("/"):
            keys[f"{domain}/{topic.strip('/')}/*/*"] = rate
        else:
            for module in modules:
                keys[f"{domain}/{module}/{topic}/*/*"] = rate
    return keys
