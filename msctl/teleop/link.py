"""The teleop's link to the running assembly: what each mode commands and how, claims,
health, halt.

Opened on a node of the caller's (``msctl.plane.connected``), it asks every commanded
module's joint manager for its joints and limits (``/<slot>/joints``), claims the modules for
that node (:mod:`components.claims`: refused while another operator holds one, unless taken
over), follows their ``joint_read`` (the Python API's
:class:`~components.api.joints.JointHandler`), builds the IK syncer of the limbs from the
resolved assembly's URDF, the ``cmd_vel`` publisher of a mobile assembly, and a live health
board for the latest alarm. Everything it declares it undeclares in :meth:`Link.close`; the
node and its session stay the caller's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

from components.assembly import ResolvedAssembly
from components.robots import cmd_vel_topic, robots_of, root_link
from msctl.errors import MsctlError, NetworkError, NotFoundError, did_you_mean
from msctl.teleop.keys import DRIVE, IK, JOINT
from msctl.teleop.station import RelayedJointHandler
from msctl.teleop.wire import JointJog, Output, TipJog, TwistDrive

log = logging.getLogger(__name__)

#: Seconds to wait for a module's joint manager to list its joints.
ANSWER_TIMEOUT = 5.0
#: Seconds after which a module whose joint manager is not on the graph, while another
#: module's is, is taken as stopped (a graph just joined may lag a moment).
STOPPED_AFTER = 1.0


def check_modules(assembly: ResolvedAssembly, modules: Sequence[str]) -> list[str]:
    """The modules asked for, in assembly order (all of them when none is named).

    Raises:
        NotFoundError: For a module the assembly does not have, naming the ones it has.
    """
    slots = [m.slot for m in assembly.modules]
    for name in modules:
        if name not in slots:
            near = did_you_mean(name, slots)
            raise NotFoundError(
                f"{assembly.template} has no module {name!r}"
                + (f" ({near})" if near else "")
                + f"; its modules: {', '.join(slots)}"
            )
    wanted = set(modules) or set(slots)
    return [s for s in slots if s in wanted]


def unavailable_modes(
    assembly: ResolvedAssembly, slots: Sequence[str], cmd_vel: str | None = None
) -> dict[str, str]:
    """Modes the assembly's data rules out for these modules, and why (no network needed)."""
    out: dict[str, str] = {}
    if not any(assembly.module(s).chains for s in slots):
        out[IK] = "no commanded module is a limb with a kinematic chain"
    elif not assembly.urdf_path.exists():
        out[IK] = (
            f"IK needs the assembly's URDF, missing at {assembly.urdf_path}: run "
            f"`msctl assemble {assembly.template}` again"
        )
    if cmd_vel is None and cmd_vel_topic(assembly, slots) is None:
        out[DRIVE] = (
            f"{assembly.template} does not drive (not mobile, or no wheels)"
            if cmd_vel_topic(assembly, [m.slot for m in assembly.modules][:1]) is None
            else "the modules belong to several robots: pick one robot's modules, or --cmd-vel"
        )
    return out


@dataclass
class Link:
    """The commanded modules and each mode's output.

    Attributes:
        node: The node everything is declared on.
        assembly: The resolved assembly.
        handlers: Slot -> joint handler of every commanded module.
        tips: The IK output (None: no limb with a chain, or no URDF here).
        drive: The drive output (None: the assembly does not move).
        health: The live health board (None: not watched).
        unavailable: Mode -> why it cannot be used here.
        claims: The claims watcher (None: this link claims nothing).
        held: Slot -> this link's claim of the module (taken over ones stay, ``lost`` set).
        estop: Halt and recover of the commanded modules (:class:`components.estop.Estop`).
        through: The station's human operator relaying this screen (its node), or None when
            the screen runs on its own (see :mod:`msctl.teleop.station`).
        watch: Whether each module can move now (halted, gone), as another shell left it
            (:class:`~msctl.teleop.watch.ModuleWatch`; None: not watched).
    """

    node: Any
    assembly: ResolvedAssembly
    handlers: dict[str, Any]
    tips: TipJog | None = None
    drive: TwistDrive | None = None
    health: Any = None
    unavailable: dict[str, str] = field(default_factory=dict)
    claims: Any = None
    held: dict[str, Any] = field(default_factory=dict)
    estop: Any = None
    through: str | None = None
    watch: Any = None
    _joints: JointJog | None = None

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(
        cls,
        node: Any,
        assembly: ResolvedAssembly,
        modules: Sequence[str] = (),
        cmd_vel: str | None = None,
        stamped: bool = False,
        health: bool = True,
        timeout: float = ANSWER_TIMEOUT,
        claim: bool = True,
        take: bool = False,
        station: str | None = None,
        watch: bool = True,
    ) -> Link:
        """Connect to the commanded modules (default: every module), and claim them.

        Args:
            node: The node every command goes out on (the claims name it).
            assembly: The resolved assembly.
            modules: The modules to command.
            cmd_vel: Drive mode's topic (default: the robot's).
            stamped: Drive mode publishes TwistStamped.
            health: Watch the modules' health for the latest alarm.
            timeout: Seconds to wait for each joint manager.
            claim: Claim the modules before commanding them.
            take: Take the claims over from whoever holds them.
            station: This computer, as the assembly names it: when it plans a human
                operator here and it answers, the screen attaches to it (its claims and
                relays, its second deadman); None: the screen runs on its own.
            watch: Follow whether each module can move (halted, gone) for the screen.

        Raises:
            NotFoundError: For a module the assembly does not have.
            NetworkError: If a module's joint manager does not answer, naming it: at once
                when the rest of the assembly answers and it is not on the graph (stopped).
            MsctlError: If another operator holds a module's claim (and not ``take``),
                naming them and since when.
        """
        from components.api.errors import ApiError
        from components.api.joints import JointHandler, list_joints

        slots = check_modules(assembly, modules)
        started = time.monotonic()
        deadline = started + timeout
        stopped: list[str] = []

        def listing(slot: str) -> list[Any]:
            # A fresh session learns the routes to the services in its first moments: a
            # query that ends at once found no server yet, so ask again until the deadline,
            # unless the graph shows the rest of the assembly and not this module.
            while True:
                remaining = deadline - time.monotonic()
                try:
                    return list_joints(node, slot, max(min(remaining, STOPPED_AFTER), 0.1))
                except ApiError:
                    if deadline - time.monotonic() < 0.2:
                        raise
                    if time.monotonic() - started >= STOPPED_AFTER and _stopped(
                        node, assembly, slot
                    ):
                        stopped.append(slot)
                        raise
                time.sleep(0.1)

        infos: dict[str, Any] = {}
        silent: list[str] = []
        with ThreadPoolExecutor(max(len(slots), 1), thread_name_prefix="teleop") as pool:
            listed = {slot: pool.submit(listing, slot) for slot in slots}
            for slot, future in listed.items():
                try:
                    infos[slot] = future.result()
                except ApiError as exc:
                    log.debug("%s: %s", slot, exc)
                    silent.append(slot)
        if stopped:
            raise NetworkError(
                f"{', '.join(sorted(stopped))} not running: nothing serves "
                f"/{sorted(stopped)[0]}/joints (its joint manager is stopped or gone) while "
                "the rest of the assembly answers",
                hint="see `msctl ps`; `msctl restart COMPONENT` (or `msctl up`) brings it back",
            )
        if silent:
            raise NetworkError(
                f"no answer from the joint manager of {', '.join(silent)} "
                f"(/{silent[0]}/joints) within {timeout:g} s",
                hint="is the assembly up? check `msctl ps` and `msctl health`",
            )
        from components.estop import Estop

        handlers: dict[str, Any] = {}
        link = cls(node, assembly, handlers)
        try:
            relays: dict[str, str] = {}
            if claim and station is not None and not stamped:
                # The station's human operator claims and relays for this screen (a
                # TwistStamped it does not relay: the screen then runs on its own).
                relays = link._attach(slots, take, station)
            for slot in slots:
                controls = {j.name: j.control for j in assembly.module(slot).joints}
                joints = [replace(i, control=controls.get(i.name, i.control)) for i in infos[slot]]
                relay = relays.get(f"{assembly.module(slot).namespace}/joint_set")
                if relay is not None:
                    handlers[slot] = RelayedJointHandler(node, slot, joints, relay)
                else:
                    handlers[slot] = JointHandler(node, slot, joints)
            # The halt and recover clients are declared now: space must not wait for them.
            link.estop = Estop(node, {s: assembly.module(s).namespace for s in slots})
            link._joints = JointJog(handlers)
            link.unavailable.update(unavailable_modes(assembly, slots, cmd_vel))
            if IK not in link.unavailable:
                link._open_tips(slots)
            topic = cmd_vel or cmd_vel_topic(assembly, slots)
            if topic is not None:
                frame = root_link(assembly, robots_of(assembly)[slots[0]]) if slots else ""
                relayed = relays.get(topic)
                link.drive = TwistDrive(node, relayed or topic, stamped=stamped, frame_id=frame)
                link.drive.topic = topic  # what the screen shows: where the Twists end up
            if claim and link.through is None:
                link._claim(take)
            if watch:
                from msctl.teleop.watch import ModuleWatch

                link.watch = ModuleWatch(node, {s: assembly.module(s).namespace for s in slots})
            if health:
                from msctl.health.live import LiveHealth

                link.health = LiveHealth(node, assembly, supervisors=False).start()
        except BaseException:
            link.close()
            raise
        return link

    def _attach(self, slots: Sequence[str], take: bool, station: str) -> dict[str, str]:
        """Attach to the station's human operator, if it runs; its relays (empty if not)."""
        from components.human_operator.client import AttachRefused
        from msctl.teleop.station import RelayedClaim, attach_to_station

        try:
            found = attach_to_station(self.node, self.assembly, list(slots), take, station)
        except AttachRefused as exc:
            raise MsctlError(
                str(exc), hint="take it over with `msctl teleop --take`, or ask them"
            ) from exc
        if found is None:
            return {}
        operator, attached, claims = found
        self.through, self.claims = operator, claims
        for slot in attached.claimed:
            info = attached.claims.get(slot)
            if info is not None:
                self.held[slot] = RelayedClaim(info)
        claims.on_change(
            lambda module, holder: (
                self.held[module].changed(holder) if module in self.held else None
            )
        )
        return dict(attached.relays)

    def _claim(self, take: bool) -> None:
        """Claim every commanded module for this node, all or none."""
        from components.claims import ClaimRefused, Claims, default_holder

        self.claims = Claims(
            self.node.session, self.node.domain, [m.slot for m in self.assembly.modules]
        )
        holder = default_holder()
        try:
            for slot in self.handlers:
                self.held[slot] = self.claims.claim(slot, holder, self.node, take=take)
        except ClaimRefused as exc:
            held = exc.holder
            raise MsctlError(
                f"module {held.module} is claimed by {held.holder} (node {held.node}) since "
                f"{held.since_text()}",
                hint="take it over with `msctl teleop --take`, or ask them to release it",
            ) from exc

    def _open_tips(self, slots: Sequence[str]) -> None:
        from components.api.ik_syncer import IkSyncer

        chains = [
            (self.handlers[s], self.assembly.module(s).chains[0])
            for s in slots
            if self.assembly.module(s).chains
        ]
        urdf = self.assembly.urdf_path.read_text(encoding="utf-8")
        self.tips = TipJog(IkSyncer(chains, urdf))

    # ------------------------------------------------------------------ what each mode has
    @property
    def modules(self) -> list[str]:
        """The commanded modules, in assembly order."""
        return list(self.handlers)

    def joints(self) -> dict[str, tuple[str, ...]]:
        """Joint mode's joints per module (locked joints left out)."""
        return {
            slot: tuple(name for name, info in h.joints.items() if not info.locked)
            for slot, h in self.handlers.items()
        }

    @property
    def limbs(self) -> tuple[str, ...]:
        """IK mode's limbs."""
        return () if self.tips is None else tuple(self.tips.syncer.limbs)

    @property
    def drive_target(self) -> str | None:
        """Drive mode's ``cmd_vel`` topic (None: no drive mode)."""
        return None if self.drive is None else self.drive.topic

    def why_not(self, slot: str) -> str:
        """Why ``slot`` cannot move now (halted, its joint manager gone; "" when it can, or
        when nothing is watched)."""
        return "" if self.watch is None else self.watch.why_not(slot)

    def claimed(self) -> list[str]:
        """The modules this link holds the claims of (every commanded module when it
        claims nothing)."""
        if self.claims is None:
            return self.modules
        return [slot for slot, claim in self.held.items() if not claim.lost.is_set()]

    def outputs(self) -> dict[str, Output]:
        """Each available mode's output."""
        out: dict[str, Output] = {}
        if self._joints is not None:
            out[JOINT] = self._joints
        if self.tips is not None:
            out[IK] = self.tips
        if self.drive is not None:
            out[DRIVE] = self.drive
        return out

    def joint_state(self, slot: str, joint: str) -> tuple[float | None, float, float]:
        """A joint's measured position and its limits (for the screen's bar)."""
        handler = self.handlers[slot]
        info = handler.joints[joint]
        return handler.positions().get(joint), info.lower, info.upper

    def latest_alarm(self) -> Any:
        """The health board's latest alarm (None: none yet, or health not watched)."""
        if self.health is None:
            return None
        self.health.evaluate()
        alarms = self.health.alarms()
        return alarms[-1] if alarms else None

    # ------------------------------------------------------------------ halt and recover
    def halt(self, modules: Sequence[str] | None = None) -> list[Any]:
        """Halt the modules (default: every commanded one) at once, through the e-stop's
        clients; each module's :class:`~components.estop.Acknowledgement` and its time."""
        answers = self.estop.halt(modules)
        if self.watch is not None:
            self.watch.acknowledged("halt", answers)
        return answers

    def recover(self, modules: Sequence[str] | None = None) -> list[Any]:
        """Recover the modules (default: every commanded one) at once."""
        answers = self.estop.recover(modules)
        if self.watch is not None:
            self.watch.acknowledged("recover", answers)
        return answers

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Undeclare everything this link declared (idempotent); the node stays open."""
        if self.health is not None:
            self.health.close()
            self.health = None
        if self.watch is not None:
            self.watch.close()
            self.watch = None
        if self.through is not None:
            # After the last stop went out (the caller closed its operator first).
            from components.comm.services import ServiceError
            from components.human_operator.client import detach

            try:
                detach(self.node, self.through)
            except ServiceError as exc:  # it lets go anyway once this node leaves
                log.info("detaching from %s: %s", self.through, exc)
            self.through = None
        if self.claims is not None:
            # After the last stop went out (the caller closed its operator first): the
            # claims go only once nothing more will be sent.
            self.claims.close()
            self.claims = None
        if self.drive is not None:
            self.drive.close()
        if self.estop is not None:
            self.estop.close()
        for handler in self.handlers.values():
            handler.close()


def _stopped(node: Any, assembly: ResolvedAssembly, slot: str) -> bool:
    """Whether the graph shows another module's joints listing but not ``slot``'s: the
    assembly is up and this module's joint manager is not."""
    from components.comm.graph import snapshot
    from components.comm.liveliness import EntityKind

    servers = snapshot(node.session, node.domain, 1.0, f"*/*/*/{EntityKind.SERVICE.value}/**")
    served = set(servers.services())
    listings = {m.slot: f"{m.namespace.rstrip('/')}/joints" for m in assembly.modules}
    others = any(topic in served for other, topic in listings.items() if other != slot)
    return others and listings[slot] not in served
