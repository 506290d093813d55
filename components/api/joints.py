"""One module's joints: what they are, where they are, and a way to command them.

A :class:`JointHandler` follows ``/<slot>/joint_read`` (calibrated states from the module's
joint manager) and publishes on ``/<slot>/joint_set``. It learns the joints and their limits
from the joint manager's ``/<slot>/joints`` service (``msctl_msgs/srv/ListJoints``), so it
needs nothing but the slot name; the lock file, when present, only adds each joint's control
mode (position or velocity).

The subscription callback runs on a Zenoh thread and only stores numbers under a lock; every
reader gets a copy.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from components.api.errors import ApiError, JointNotReadyError, UnknownJointError
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state_batches

LIST_JOINTS = "msctl_msgs/srv/ListJoints"


@dataclass(frozen=True)
class JointInfo:
    """One joint as its joint manager describes it (calibrated space, SI units).

    Attributes:
        name: Assembly name (``limb1_joint3``).
        type: URDF type (``revolute``, ``continuous``, ``prismatic``).
        lower: Lower position limit (``-inf`` when unbounded).
        upper: Upper position limit (``+inf`` when unbounded).
        max_velocity: Speed limit.
        max_effort: Effort limit.
        locked: Pinned by an override: commands to it are refused.
        control: ``position`` or ``velocity`` (wheels): how it is held when stopping.
    """

    name: str
    type: str
    lower: float
    upper: float
    max_velocity: float
    max_effort: float
    locked: bool = False
    control: str = "position"


@dataclass(frozen=True)
class JointState:
    """The latest measurement of one joint (None where ``joint_read`` did not carry it).

    Attributes:
        position: rad or m.
        velocity: rad/s or m/s.
        effort: N·m or N.
        stamp: ``time.monotonic()`` when it arrived here.
    """

    position: float | None
    velocity: float | None
    effort: float | None
    stamp: float


class JointHandler:
    """The joints of one module.

    Create it with :meth:`create` (asks the joint manager for the joints), or directly with
    known :class:`JointInfo` (tests, or when the caller already has them).

    Args:
        node: The node publishing and subscribing (the caller owns its session).
        slot: The module's slot (``limb1``); its topics live under ``/<slot>``.
        joints: The module's joints.
    """

    def __init__(self, node: Any, slot: str, joints: Iterable[JointInfo]) -> None:
        self.slot = slot
        self.namespace = f"/{slot}"
        self.joints: dict[str, JointInfo] = {j.name: j for j in joints}
        if not self.joints:
            raise ApiError(f"module {slot} has no joints to handle")
        self._lock = threading.Lock()
        self._states: dict[str, JointState] = {}
        self._closed = False
        #: The syncer commanding this module now (one commander per module at a time).
        self.commander: Any = None
        #: The last position sent to each joint (a new motion continues from it while the
        #: joint is near it: restarting from the measurement would drop a loaded joint by
        #: its tracking error).
        self.last_command: dict[str, float] = {}
        #: Called before every command is sent (the Robot claims the module there, and
        #: raises if another operator holds it); ``None``: commands go out as they are.
        self.before_send: Callable[[], None] | None = None
        self._publisher = node.publisher(f"{self.namespace}/joint_set", JOINT_STATE)
        self._subscription = node.subscription(
            f"{self.namespace}/joint_read", JOINT_STATE, self._on_joint_read
        )

    @classmethod
    async def create(
        cls,
        node: Any,
        slot: str,
        controls: Mapping[str, str] | None = None,
        timeout: float = 3.0,
    ) -> JointHandler:
        """Ask ``/<slot>/joints`` for the module's joints and build the handler.

        Args:
            node: The node to use.
            slot: The module's slot.
            controls: Joint name -> control mode (from the lock file); joints not named are
                position-controlled, except that a module whose joints are all continuous
                is taken for a wheel module (velocity).
            timeout: Seconds to wait for the joint manager's answer.

        Raises:
            ApiError: If the joint manager does not answer (the message names the service).
        """
        infos = await asyncio.to_thread(list_joints, node, slot, timeout)
        controls = dict(controls or {})
        if not controls and infos and all(i.type == "continuous" for i in infos):
            controls = {i.name: "velocity" for i in infos}
        infos = [replace(i, control=controls.get(i.name, "position")) for i in infos]
        return cls(node, slot, infos)

    # ------------------------------------------------------------------ state
    def _on_joint_read(self, message: Any) -> None:
        now = time.monotonic()
        with self._lock:
            for name, position, velocity, effort in joint_samples(message):
                if name not in self.joints:
                    continue
                old = self._states.get(name)
                # joint_read may carry position and velocity in separate batches: keep
                # what a message did not carry.
                if old is not None:
                    position = old.position if position is None else position
                    velocity = old.velocity if velocity is None else velocity
                    effort = old.effort if effort is None else effort
                self._states[name] = JointState(position, velocity, effort, now)

    @property
    def ready(self) -> bool:
        """Whether every joint has a measured position."""
        with self._lock:
            return all(
                (s := self._states.get(n)) is not None and s.position is not None
                for n in self.joints
            )

    def missing(self) -> list[str]:
        """Joints with no measured position yet."""
        with self._lock:
            return [
                n for n in self.joints if (s := self._states.get(n)) is None or s.position is None
            ]

    async def wait_ready(self, timeout: float = 5.0) -> None:
        """Wait until every joint has a measured position.

        Raises:
            JointNotReadyError: After ``timeout`` seconds, naming the joints still silent.
        """
        deadline = time.monotonic() + timeout
        while not self.ready:
            if time.monotonic() > deadline:
                raise JointNotReadyError(
                    f"no joint_read for {', '.join(self.missing())} on "
                    f"{self.namespace}/joint_read within {timeout:g} s; is the joint manager "
                    "of this module running (`msctl ps`)?"
                )
            await asyncio.sleep(0.02)

    def states(self) -> dict[str, JointState]:
        """The latest state of every joint heard from."""
        with self._lock:
            return dict(self._states)

    def positions(self) -> dict[str, float]:
        """The latest measured position of every joint heard from."""
        with self._lock:
            return {n: s.position for n, s in self._states.items() if s.position is not None}

    def resolve(self, name: str) -> str:
        """The assembly name of ``name`` (``joint3`` is read as ``<slot>_joint3``).

        Raises:
            UnknownJointError: If the module has no such joint.
        """
        if name in self.joints:
            return name
        qualified = f"{self.slot}_{name}"
        if qualified in self.joints:
            return qualified
        raise UnknownJointError(
            f"module {self.slot} has no joint {name!r}; its joints: {', '.join(self.joints)}"
        )

    # ------------------------------------------------------------------ commands
    def send(self, commands: Mapping[str, float] | Iterable[JointSample]) -> list[JointSample]:
        """Publish commands on ``joint_set``, positions clipped into the limits.

        Args:
            commands: ``{joint: position}`` or :class:`JointSample` rows (any fields).

        Returns:
            What was actually sent (after clipping).

        Raises:
            UnknownJointError: If a joint is not this module's.
            ModuleClaimedError: If another operator holds the module (through
                :attr:`before_send`).
            ClaimLostError: If another operator took the module over from this one.
        """
        if self.before_send is not None and not self._closed:
            self.before_send()
        if isinstance(commands, Mapping):
            rows = [JointSample(name, float(value)) for name, value in commands.items()]
        else:
            rows = list(commands)
        sent = []
        for row in rows:
            name = self.resolve(row.name)
            info = self.joints[name]
            position = row.position
            if position is not None:
                position = min(max(position, info.lower), info.upper)
            velocity = row.velocity
            if velocity is not None:
                velocity = min(max(velocity, -info.max_velocity), info.max_velocity)
            sent.append(JointSample(name, position, velocity, row.effort))
            if position is not None:
                self.last_command[name] = position
            else:
                self.last_command.pop(name, None)
        if sent and not self._closed:
            for message in joint_state_batches(sent):
                self._publisher.publish(message)
        return sent

    def hold_samples(self) -> list[JointSample]:
        """Commands that hold every joint where it is measured: position for position joints,
        velocity 0 for velocity (wheel) joints, and never a velocity other than 0."""
        states = self.states()
        out = []
        for name, info in self.joints.items():
            if info.locked:
                continue
            state = states.get(name)
            if info.control == "velocity" or state is None or state.position is None:
                out.append(JointSample(name, None, 0.0, None))
            else:
                out.append(JointSample(name, state.position, None, None))
        return out

    def hold(self) -> list[JointSample]:
        """Send :meth:`hold_samples` and return them."""
        return self.send(self.hold_samples())

    def close(self) -> None:
        """Stop listening and publishing (idempotent); the node stays open."""
        if self._closed:
            return
        self._closed = True
        self._subscription.close()
        self._publisher.close()


def list_joints(node: Any, slot: str, timeout: float = 3.0) -> list[JointInfo]:
    """Ask ``/<slot>/joints`` which joints the module has (blocking).

    Raises:
        ApiError: If nobody answers, naming the service.
    """
    from components.comm.services import ServiceError

    client = node.client(f"/{slot}/joints", LIST_JOINTS)
    try:
        response = client.call(client.request_type()(), timeout=timeout)
    except ServiceError as exc:
        raise ApiError(f"cannot list the joints of {slot}: {exc}") from exc
    finally:
        client.close()
    return [
        JointInfo(
            name=j.name,
            type=j.type,
            lower=_limit(j.lower, -math.inf),
            upper=_limit(j.upper, math.inf),
            max_velocity=float(j.max_velocity),
            max_effort=float(j.max_effort),
            locked=bool(j.locked),
        )
        for j in response.joints
    ]


def _limit(value: float, unbounded: float) -> float:
    # Unbounded joints may come as +-inf, NaN or a huge number, depending on the sender.
    value = float(value)
    if math.isnan(value) or abs(value) >= 1e8:
        return unbounded
    return value
