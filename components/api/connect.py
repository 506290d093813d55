"""Connecting to the running assembly: :func:`connect` finds it and returns a :class:`Robot`.

Finding the robot needs nothing but the data plane (the same Zenoh settings every msctl
process reads, ``MSCTL_ZENOH_CONNECT`` and friends):

1. the ROS graph names the modules: every namespace with a joint manager's ``joints``
   service (``/<slot>/joints``, ``msctl_msgs/srv/ListJoints``) is a module;
2. each joint manager lists its joints and limits over that service;
3. when an assembly name is given, the launchers' supervisors (``/msctl/<host>/request``,
   verb ``ps``) say which template runs, and a different one is refused.

The resolved assembly's lock file, when this computer has one for the running template, adds
what the graph does not carry: each module's kind (limb or wheel), each joint's control mode,
and the URDF the IK syncer and the wheel helper compute with.

Claims: a module is claimed (:mod:`components.claims`, as ``user@host`` on this process's
node) the first time the script commands it, so while the script drives it no other operator
does, and one that does hold it is named in a :class:`ModuleClaimedError` before anything
moves. A module taken over from the script refuses its next command with
:class:`ClaimLostError`. Claims go with the robot's connection.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import threading
import time
from collections.abc import Sequence
from dataclasses import fields
from typing import Any

from components.api.errors import (
    ApiError,
    ClaimLostError,
    ModuleClaimedError,
    RobotNotFoundError,
)
from components.api.joints import LIST_JOINTS, JointHandler
from components.api.planner import SyncSettings
from components.api.syncer import Commander, JointSyncer

log = logging.getLogger(__name__)

AGENT_SRV = "msctl_msgs/srv/AgentRequest"
_JOINTS_SERVICE = re.compile(r"^/([A-Za-z][A-Za-z0-9_]*)/joints$")


class Robot:
    """A running assembly, connected: its modules and the syncers that move them.

    Made by :func:`connect`; use it as ``async with await connect() as robot:`` or call
    :meth:`close`. Every syncer made here is stopped and closed with the robot.

    Attributes:
        template: The running template (``dragon``), when known.
        assembly: The resolved assembly from the lock file, when it matches (else None).
        modules: Slot -> :class:`JointHandler`, in assembly order.
        kinds: Slot -> ``limb`` or ``wheel``.
        holder: Who this script's claims name (``user@host``).
    """

    def __init__(
        self,
        session: Any,
        node: Any,
        modules: Sequence[JointHandler],
        kinds: dict[str, str],
        template: str | None = None,
        assembly: Any = None,
        claims: Any = None,
    ) -> None:
        from components.claims import default_holder

        self.session = session
        self.node = node
        self.modules: dict[str, JointHandler] = {h.slot: h for h in modules}
        self.kinds = kinds
        self.template = template
        self.assembly = assembly
        self.holder = default_holder()
        self._claims = claims
        self._claimed: dict[str, Any] = {}
        self._claim_lock = threading.Lock()
        self._commanders: list[Commander] = []
        self._closed = False
        if claims is not None:
            for handler in self.modules.values():
                handler.before_send = lambda slot=handler.slot: self._hold_claim(slot)

    def __repr__(self) -> str:
        parts = ", ".join(f"{s} ({self.kinds.get(s, '?')})" for s in self.modules)
        return f"<Robot {self.template or '?'}: {parts}>"

    # ------------------------------------------------------------------ what there is
    @property
    def limbs(self) -> list[str]:
        """Slots of the limb modules."""
        return [s for s in self.modules if self.kinds.get(s) == "limb"]

    @property
    def wheels(self) -> list[str]:
        """Slots of the wheel modules."""
        return [s for s in self.modules if self.kinds.get(s) == "wheel"]

    def handler(self, slot: str) -> JointHandler:
        """The joints of one module.

        Raises:
            KeyError: If the robot has no such module (the message lists them).
        """
        try:
            return self.modules[slot]
        except KeyError:
            raise KeyError(f"no module {slot!r}; modules: {', '.join(self.modules)}") from None

    def positions(self) -> dict[str, float]:
        """Every joint's latest measured position."""
        out: dict[str, float] = {}
        for handler in self.modules.values():
            out.update(handler.positions())
        return out

    # ------------------------------------------------------------------ claims
    def claim(self, *slots: str, take: bool = False) -> None:
        """Claim modules now (default: every module) rather than at their first command.

        Args:
            slots: The modules.
            take: Take them over from whoever holds them (they are told at once).

        Raises:
            ModuleClaimedError: If another operator holds one and ``take`` is false.
            ClaimLostError: If one was taken over from this script already.
        """
        for slot in slots or tuple(self.modules):
            self.handler(slot)
            self._hold_claim(slot, take)

    def claimed(self) -> list[str]:
        """The modules this script holds now."""
        with self._claim_lock:
            return [slot for slot, claim in self._claimed.items() if claim.held]

    def _hold_claim(self, slot: str, take: bool = False) -> None:
        """Claim ``slot`` once; afterwards check it is still ours."""
        from components.claims import ClaimRefused

        if self._claims is None:
            return
        with self._claim_lock:
            claim = self._claimed.get(slot)
            if claim is None:
                try:
                    claim = self._claims.claim(slot, self.holder, self.node, take=take)
                except ClaimRefused as exc:
                    raise ModuleClaimedError(
                        f"{exc}; this script does not command {slot} while they hold it",
                        exc.holder,
                    ) from None
                self._claimed[slot] = claim
        if claim.lost.is_set():
            new = claim.lost_to
            raise ClaimLostError(
                f"module {slot} was taken over by {new.holder} (node {new.node}) at "
                f"{new.since_text()}: this script commands it no more"
            )

    def _adopt(self, commander: Commander) -> Any:
        try:
            # Claimed as the syncer is made: a module someone else drives is named now,
            # before any motion starts, not at the first command of the first motion.
            for slot in commander.handlers:
                self._hold_claim(slot)
        except ApiError:
            commander.close()
            raise
        self._commanders.append(commander)
        return commander

    # ------------------------------------------------------------------ syncers
    def syncer(self, *slots: str, settings: SyncSettings | None = None, **tuning: Any) -> Any:
        """A :class:`~components.api.syncer.JointSyncer` over ``slots`` (default: every limb).

        Args:
            slots: Modules to drive together.
            settings: Full settings; or give some of their fields as keywords
                (``delta=0.05, speed=0.3``).
        """
        settings = _settings(SyncSettings, settings, tuning)
        handlers = [self.handler(s) for s in (slots or self.limbs or tuple(self.modules))]
        return self._adopt(JointSyncer(handlers, settings))

    def ik(self, *slots: str, **tuning: Any) -> Any:
        """An :class:`~components.api.ik_syncer.IkSyncer` over limbs ``slots`` (default:
        every limb). Keywords are :class:`~components.api.ik_syncer.IkSyncSettings` fields.

        Raises:
            ApiError: Without the resolved assembly (the URDF is needed).
        """
        from components.api.ik_syncer import IkSyncer, IkSyncSettings

        settings = _settings(IkSyncSettings, tuning.pop("settings", None), tuning)
        urdf = self._urdf("the IK syncer")
        limbs = slots or tuple(self.limbs)
        chains = []
        for slot in limbs:
            module = self.assembly.module(slot)
            if not module.chains:
                raise ApiError(f"module {slot} has no kinematic chain (it is a {module.kind})")
            chains.append((self.handler(slot), module.chains[0]))
        return self._adopt(IkSyncer(chains, urdf, settings))

    def drive(self, *slots: str, **tuning: Any) -> Any:
        """A :class:`~components.api.wheels.WheelDrive` over wheel modules ``slots``
        (default: every wheel module), geometry from the resolved assembly's URDF at the
        measured limb angles (again at the start of every motion), steering with the limbs
        (:class:`~components.api.steering.WheelSteering`)."""
        from components.api.steering import WheelSteering
        from components.api.wheels import WheelDrive, wheel_joints

        urdf = self._urdf("the wheel helper")
        wheels = slots or tuple(self.wheels)
        if not wheels:
            raise ApiError(f"{self.template or 'this robot'} has no wheel module")
        handlers = [self.handler(s) for s in wheels]
        steering = WheelSteering(urdf, self.assembly.root_links[0], wheel_joints(handlers))
        geometry = steering.geometry(self.positions())
        return self._adopt(
            WheelDrive(handlers, geometry, steering=steering, positions=self.positions, **tuning)
        )

    def _urdf(self, what: str) -> str:
        if self.assembly is None:
            raise ApiError(
                f"{what} needs the resolved assembly (its URDF), and this computer has no lock "
                f"file for {self.template or 'the running assembly'}: run `msctl assemble "
                f"{self.template or '<template>'}` here (or set MSCTL_HOME) first"
            )
        return self.assembly.urdf_path.read_text(encoding="utf-8")

    # ------------------------------------------------------------------ stopping
    async def stop(self) -> None:
        """Cancel every motion and hold every joint where it is measured (velocity 0 for
        wheels). Not a halt: the robot stays ready for the next command."""
        await asyncio.gather(*(c.stop() for c in self._commanders), return_exceptions=True)
        # Only modules this script commands: another operator's (claimed) are not ours to
        # hold, and one never commanded holds by itself (its joint manager's watchdog).
        held = set(self.claimed()) if self._claims is not None else set(self.modules)
        for slot in held:
            self.modules[slot].hold()

    async def close(self) -> None:
        """Stop, then close every syncer, handler, the node and the Zenoh session
        (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            await self.stop()
            # Let the hold commands leave before the session goes away.
            await asyncio.sleep(0.05)
        finally:
            for commander in self._commanders:
                commander.close()
            for handler in self.modules.values():
                handler.close()
            if self._claims is not None:
                self._claims.close()  # after the holds went out: they were ours to send
            self.node.close()
            await asyncio.to_thread(self.session.close)

    async def __aenter__(self) -> Robot:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


def _settings(cls: type, settings: Any, tuning: dict[str, Any]) -> Any:
    if settings is not None and tuning:
        raise TypeError("give either settings or keyword fields, not both")
    if settings is not None:
        return settings
    known = {f.name for f in fields(cls)}
    unknown = set(tuning) - known
    if unknown:
        raise TypeError(f"unknown {cls.__name__} fields {sorted(unknown)}; known: {sorted(known)}")
    return cls(**tuning)


async def connect(
    assembly: str | None = None,
    *,
    settings: Any = None,
    timeout: float = 10.0,
    slots: Sequence[str] | None = None,
) -> Robot:
    """Connect to the running assembly.

    Args:
        assembly: The template expected to run (``dragon``); None takes whatever runs.
        settings: Zenoh :class:`~components.comm.session.SessionSettings` (default: from the
            environment, as a client of the router: see
            :meth:`~components.comm.session.SessionSettings.joining`).
        timeout: Seconds to find the modules and hear from every joint.
        slots: Only these modules (default: every module found).

    Raises:
        RobotNotFoundError: If no module is found, or another assembly runs than the one named.
        JointNotReadyError: If a module's joints stay silent.
    """
    from components.claims import Claims
    from components.comm import Node, SessionSettings, open_session
    from components.comm.session import SessionOpenError

    # A script joins a running assembly: a client of its router, which knows the whole graph
    # (SessionSettings.joining; MSCTL_ZENOH_MODE still wins).
    settings = settings or SessionSettings.joining()
    try:
        session = await asyncio.to_thread(open_session, _failing_fast(settings))
    except SessionOpenError as exc:
        raise RobotNotFoundError(_unreachable(settings, _refusal(exc, settings))) from exc
    node = None
    handlers: list[JointHandler] = []
    try:
        await _wait_for_network(session, settings, min(timeout, NETWORK_WAIT))
        node = Node(session, f"api_{os.getpid()}", "/", domain=settings.domain)
        local = _lock_for(assembly)
        expected = set(local.units) if local is not None else None
        found, template = await _discover(node, assembly, timeout, expected)
        resolved = local if local is not None and template in (None, local.template) else None
        if template is None and resolved is not None and set(found) <= set(resolved.units):
            template = resolved.template
        if slots:
            absent = [s for s in slots if s not in found]
            if absent:
                raise RobotNotFoundError(
                    f"no module {', '.join(absent)} on the data plane; found {', '.join(found)}"
                )
            found = [s for s in found if s in slots]
        if resolved is not None:
            order = {s: i for i, s in enumerate(resolved.units)}
            found.sort(key=lambda s: order.get(s, len(order)))
        # The whole timeout for each module's joint list: a busy computer's joint manager
        # answered later than 3 s (a module with no server still fails at once).
        handlers = list(
            await asyncio.gather(
                *(
                    JointHandler.create(node, slot, _controls(resolved, slot), timeout)
                    for slot in found
                )
            )
        )
        deadline = time.monotonic() + timeout
        for handler in handlers:
            await handler.wait_ready(max(deadline - time.monotonic(), 0.5))
        kinds = {h.slot: _kind(resolved, h) for h in handlers}
        claims = Claims(session, settings.domain, modules=[h.slot for h in handlers])
        return Robot(session, node, handlers, kinds, template, resolved, claims)
    except BaseException:
        for handler in handlers:
            handler.close()
        if node is not None:
            node.close()
        await asyncio.to_thread(session.close)
        raise


#: Seconds to reach a router or peer before saying none is there (a local router answers in
#: milliseconds; waiting the whole ``timeout`` for one that does not exist helps nobody).
NETWORK_WAIT = 2.0
#: Seconds with neither a module nor a supervisor on a reachable network before saying
#: nothing runs (an ``msctl up`` that is starting already serves its supervisor).
NOTHING_RUNS_WAIT = 2.0
#: Seconds one graph query may take.
GRAPH_QUERY = 1.0


def _failing_fast(settings: Any) -> Any:
    """``settings`` whose session fails to open when its connect endpoints refuse it.

    With multicast scouting off those endpoints are the only way to the robot, and Zenoh
    knows at once that they refuse (``msctl topic list`` says so in a fraction of a second):
    waiting for a peer that cannot come helps nobody. Once open, the session still
    reconnects to a restarted router by itself. With scouting on, a peer may yet be found
    without them, so the short wait of :func:`_wait_for_network` decides instead.
    """
    keys = ("connect/exit_on_failure", "connect/timeout_ms")
    if settings.multicast or not settings.connect or any(k in settings.extra for k in keys):
        return settings
    return settings._replace(extra={**settings.extra, keys[0]: True, keys[1]: 0})


def _refusal(exc: Exception, settings: Any) -> str:
    """What Zenoh's long open error says, in a few words.

    A client's error does not say why ("Unable to connect to any of [...]"), so its first
    TCP endpoint is tried once more here, to name the cause all the same.
    """
    text = str(exc)
    for words in ("Connection refused", "No route to host", "Network is unreachable"):
        if words in text:
            return words.lower()
    for endpoint in settings.connect:
        why = _tcp_refusal(endpoint)
        if why is not None:
            return why
    return "could not connect"


def _tcp_refusal(endpoint: str, wait: float = 1.0) -> str | None:
    """Why a TCP connection to ``endpoint`` (``tcp/host:port``, ``tls/...``) fails, in a few
    words; ``None`` when it does not fail, or the endpoint is not one to try."""
    import errno
    import socket

    protocol, _, address = endpoint.partition("/")
    host, _, port = address.split("#", 1)[0].rpartition(":")
    if protocol not in ("tcp", "tls") or not port.isdigit():
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=wait):
            return None
    except ConnectionRefusedError:
        return "connection refused"
    except TimeoutError:
        return f"no answer within {wait:g} s"
    except OSError as exc:
        if exc.errno == errno.EHOSTUNREACH:
            return "no route to host"
        if exc.errno == errno.ENETUNREACH:
            return "network is unreachable"
        return None


def _unreachable(settings: Any, why: str) -> str:
    return (
        f"no Zenoh router or peer reachable at {', '.join(settings.connect) or 'any'} ({why}); "
        "start the assembly with `msctl up <template>`, or point MSCTL_ZENOH_CONNECT at its "
        "router"
    )


async def _wait_for_network(session: Any, settings: Any, wait: float) -> None:
    """Fail fast when no router or peer answers at the configured endpoints."""
    deadline = time.monotonic() + wait
    while True:
        info = session.info
        if list(info.routers_zid()) or list(info.peers_zid()):
            return
        if time.monotonic() > deadline:
            raise RobotNotFoundError(_unreachable(settings, f"nothing answered in {wait:g} s"))
        await asyncio.sleep(0.02)


async def _discover(
    node: Any, assembly: str | None, timeout: float, expected: set[str] | None = None
) -> tuple[list[str], str | None]:
    """Module slots on the graph, and the running template when the supervisors say it.

    The graph fills in as tokens arrive: wait for every module of the lock file
    (``expected``) when there is one, else (or when modules outside it show up: another
    assembly runs) for two snapshots in a row to agree.
    """
    from components.comm.graph import snapshot

    started = time.monotonic()
    deadline = started + timeout
    previous: list[str] | None = None
    while True:
        asked = time.monotonic()
        graph = await asyncio.to_thread(snapshot, node.session, node.domain, GRAPH_QUERY)
        # A query that ended before its bound is the network's whole answer; one cut off by
        # it (a loaded machine, a slow link) may have missed what runs, so it proves nothing.
        whole = time.monotonic() - asked < 0.9 * GRAPH_QUERY
        services = graph.services()
        topics = graph.topics()
        found = []
        for name, info in services.items():
            match = _JOINTS_SERVICE.match(name)
            if match and LIST_JOINTS in info.types and info.servers:
                slot = match.group(1)
                read = topics.get(f"/{slot}/joint_read")
                if read is not None and read.publishers:
                    found.append(slot)
        supervisors = [
            n for n, i in services.items() if n.startswith("/msctl/") and AGENT_SRV in i.types
        ]
        if time.monotonic() > deadline:
            break
        # The snapshot asked the router (a peer session's question goes through a client of
        # it), which knows every token; still, a peer linked to this session means
        # something runs, whatever one query said.
        peers = bool(list(node.session.info.peers_zid()))
        nothing = not found and not supervisors and whole and not peers
        if nothing and time.monotonic() - started > NOTHING_RUNS_WAIT:
            break  # a router, and nothing behind it
        if expected is not None and expected <= set(found):
            break
        # Stable, and not a part of the lock file's assembly (no lock, or another one runs).
        if found and found == previous and (expected is None or not set(found) <= expected):
            break
        previous = found
        await asyncio.sleep(0.2)
    if not found:
        waited = time.monotonic() - started
        raise RobotNotFoundError(
            f"no running assembly found on the data plane ({waited:.1f} s; looked for "
            "joint managers' /<slot>/joints services); start one with `msctl up <template>`, "
            "and check MSCTL_ZENOH_CONNECT points at its router"
        )
    templates = await asyncio.to_thread(_running_templates, node, supervisors)
    template = templates[0] if len(templates) == 1 else None
    if assembly is not None:
        if templates and assembly not in templates:
            raise RobotNotFoundError(
                f"assembly {assembly!r} is not running; running: {', '.join(templates)}"
            )
        template = assembly
    return found, template


def _running_templates(node: Any, services: Sequence[str]) -> list[str]:
    """Templates the supervisors report (``ps``), deduplicated; silent ones are skipped."""
    from components.comm.services import ServiceError
    from components.comm.types import registry

    templates: list[str] = []
    for service in services:
        client = node.client(service, AGENT_SRV)
        try:
            request = registry().msg_class(client.parts.request)(verb="ps", args="{}")
            response = client.call(request, timeout=2.0)
            if response.success and response.payload:
                template = json.loads(response.payload).get("template")
                if template and template not in templates:
                    templates.append(template)
        except (ServiceError, ValueError) as exc:
            log.debug("supervisor %s did not say its template: %s", service, exc)
        finally:
            client.close()
    return templates


def _lock_for(template: str | None) -> Any:
    """This computer's resolved assembly, when it is the running one (or nothing says)."""
    from components.assembly import AssemblyError, load_assembly

    try:
        resolved = load_assembly()
    except AssemblyError:
        return None
    if template is not None and resolved.template != template:
        log.info(
            "the lock file here is for %s, not the running %s: ignored",
            resolved.template,
            template,
        )
        return None
    return resolved


def _controls(resolved: Any, slot: str) -> dict[str, str] | None:
    if resolved is None:
        return None
    try:
        module = resolved.module(slot)
    except KeyError:
        return None
    return {j.name: j.control for j in module.joints}


def _kind(resolved: Any, handler: JointHandler) -> str:
    if resolved is not None:
        try:
            return resolved.module(handler.slot).kind
        except KeyError:
            pass
    controls = {i.control for i in handler.joints.values()}
    return "wheel" if controls == {"velocity"} else "limb"
