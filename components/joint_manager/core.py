"""The Joint Manager core: the one gate between the motor interface and everything above it.

Raw joint space (``joint_states`` in, ``joint_commands`` out) faces the motor interface;
calibrated joint space (``joint_set`` in, ``joint_read`` out) faces the API, kinematics and
teleop. Between the two the core applies the unit's calibration, clamps every command to the
URDF limits, refuses what it cannot make safe, and stops the joints by itself when commands
stop arriving (the watchdog). Nothing out of limits is ever published on ``joint_commands``.

Robot specifics never appear here. They come in through a few documented hook points that
injections and overrides use (see :class:`JointManagerCore`):

* :meth:`JointManagerCore.add_command_filter`: a per-joint chain that may rewrite or refuse
  a calibrated command before it is clamped (clamping always runs last, so no filter can
  push a command out of limits).
* :meth:`JointManagerCore.pin`: hold a joint at a fixed position (reported as *locked*).
* :meth:`JointManagerCore.set_calibration`: change a joint's calibration at runtime.
* :attr:`JointManagerCore.extra_serve`: services an injection adds, bound by the executor
  in addition to the static :data:`~components.joint_manager.interface.JOINT_MANAGER` spec.

A module that loses its operators holds itself (:mod:`components.joint_manager.presence`):
given an :class:`~components.joint_manager.presence.OperatorPresence`, the core holds every
joint and refuses commands once no ground station or claim holder has been visible for the
template's ``operator_timeout``, and lifts that hold by itself when one is visible again (a
dead-man's hold, like the watchdog's). A halt someone asked for is a separate latch: only
``recover`` lifts it, never an operator's return.

The core keeps all state on the instance: several managers in one process share nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from components.executor.core import Core
from components.executor.interface import Serve
from components.joint_manager.commands import CommandPath
from components.joint_manager.config import (
    COUNTERS,
    CommandFilter,
    JointManagerConfig,
    Refusal,
)
from components.joint_manager.feedback import FeedbackPath
from components.joint_manager.joint import (
    EFFORT,
    HOLD,
    IDLE,
    POSITION,
    VELOCITY,
    ManagedJoint,
    or_nan,
)
from components.joint_manager.presence import LOST, OperatorPresence
from components.joint_manager.status import ManagerStatus
from components.joints import JointCalibration, JointSpec
from components.messages import JointSample, msg, trigger_response
from components.motors.base import RawLimits

__all__ = [
    "COUNTERS",
    "JOINT_INFO",
    "LIST_JOINTS_RESPONSE",
    "CommandFilter",
    "JointManagerConfig",
    "JointManagerCore",
    "Refusal",
]

LIST_JOINTS_RESPONSE = "msctl_msgs/srv/ListJoints_Response"
JOINT_INFO = "msctl_msgs/msg/JointInfo"


class JointManagerCore(FeedbackPath, CommandPath, ManagerStatus, Core):
    """Calibration, limits, watchdog and joint_read batching for one module's joints.

    Handlers (see :data:`~components.joint_manager.interface.JOINT_MANAGER`):
    :meth:`on_joint_states`, :meth:`on_joint_set`, :meth:`tick`, :meth:`on_halt`,
    :meth:`on_recover`, :meth:`on_joints`.

    Hook points for injections and overrides: :meth:`add_command_filter`, :meth:`pin`,
    :meth:`set_calibration`, :attr:`extra_serve`; read access through :meth:`resolve`,
    :meth:`calibration`, :meth:`latest`, :meth:`latest_raw_position`, :meth:`feedback_age`,
    :meth:`position_age`.

    Args:
        name: Component name (diagnostics are named after it).
        module: Module (slot) name, e.g. ``limb1``; every joint name starts with
            ``<module>_``.
        joints: The joints this manager controls, limits in calibrated space.
        calibration: The unit's calibration per joint, keyed by full (``limb1_joint3``) or
            raw (``joint3``) name; a joint left out is uncalibrated (offset 0, direction 1).
        config: Tuning; defaults when omitted.
        presence: Watches the module's operators (ground stations, claim holder): the
            module holds itself while they are gone (see the module docstring); ``None``:
            not watched (an assembly without stations, or off-robot).

    Attributes:
        module: The module name.
        config: The tuning in use.
        extra_serve: Services added by injections; the executor binds these in addition to
            the static interface spec. Each handler names a method or attribute of this core.

    Raises:
        ValueError: If a joint name lacks the module prefix, is repeated, or a calibration
            entry names a joint this manager does not control.
    """

    def __init__(
        self,
        name: str,
        module: str,
        joints: Sequence[JointSpec],
        calibration: Mapping[str, JointCalibration] | None = None,
        config: JointManagerConfig | None = None,
        presence: OperatorPresence | None = None,
    ) -> None:
        super().__init__(name)
        self.module = module
        self.config = config or JointManagerConfig()
        self.presence = presence
        self.extra_serve: list[Serve] = []
        self._prefix = f"{module}_"
        self._joints: dict[str, ManagedJoint] = {}
        self._local: dict[str, str] = {}
        calibration = dict(calibration or {})
        for spec in joints:
            if not spec.name.startswith(self._prefix) or spec.name == self._prefix:
                raise ValueError(
                    f"joint {spec.name!r} of module {module!r} must be named "
                    f"'{self._prefix}<joint>' (assembly-unique names)"
                )
            if spec.name in self._joints:
                raise ValueError(f"joint {spec.name!r} is listed twice for module {module!r}")
            local = spec.name[len(self._prefix) :]
            cal = calibration.pop(spec.name, None) or calibration.pop(local, None)
            self._joints[spec.name] = ManagedJoint(
                spec,
                local,
                cal or JointCalibration(),
                self.config.position_margin,
                self.config.position_margin_fraction,
            )
            self._local[local] = spec.name
        if calibration:
            raise ValueError(
                f"calibration for module {module!r} names joints it does not control: "
                f"{sorted(calibration)}; known: {sorted(self._local)}"
            )
        self._size = len(self._joints)
        self._counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._halted = False
        self._halted_at: float | None = None
        self._tripped_at: float | None = None
        self._tripped_joints: list[str] = []
        self._last_feedback: float | None = None
        self._last_keepalive: float | None = None
        self._last_diagnostics: float | None = None
        self._last_clamp = -math.inf
        self._last_refusal = -math.inf
        self._refusal_note = ""

    # ------------------------------------------------------------------ read access
    @property
    def joint_names(self) -> list[str]:
        """Full names of the joints this manager controls, in declaration order."""
        return list(self._joints)

    @property
    def counters(self) -> dict[str, int]:
        """A copy of the refusal/clamp/watchdog counters (cumulative since construction)."""
        return dict(self._counters)

    @property
    def halted(self) -> bool:
        """Whether ``halt`` was called and ``recover`` not yet."""
        return self._halted

    @property
    def presence_held(self) -> bool:
        """Whether the module holds itself because its operators are gone (lifts by itself)."""
        return self.presence is not None and self.presence.held

    def resolve(self, joint: str) -> str:
        """The full name of a joint given by full (``limb1_joint3``) or raw (``joint3``) name.

        Raises:
            KeyError: If this manager controls no such joint (the message lists the known ones).
        """
        if joint in self._joints:
            return joint
        if joint in self._local:
            return self._local[joint]
        raise KeyError(
            f"module {self.module!r} has no joint {joint!r}; known: {sorted(self._joints)}"
        )

    def local_name(self, joint: str) -> str:
        """The raw (module-scoped, URDF) name of a joint: ``limb1_joint3`` -> ``joint3``."""
        return self._joints[self.resolve(joint)].local

    def spec(self, joint: str) -> JointSpec:
        """The static description of a joint (full or raw name)."""
        return self._joints[self.resolve(joint)].spec

    def calibration(self, joint: str) -> JointCalibration:
        """The calibration currently applied to a joint (full or raw name)."""
        return self._joints[self.resolve(joint)].cal

    def command_range(self, joint: str) -> tuple[float, float]:
        """The calibrated positions commands are clamped to: the limits minus the margin."""
        j = self._joints[self.resolve(joint)]
        return j.lo, j.hi

    def raw_limits(self, joint: str) -> RawLimits:
        """A joint's limits in raw space under its current calibration, with no margin.

        The same numbers the motor interface and the simulator check every command against
        (they take them from the resolved assembly at start, so a runtime re-zero does not
        widen theirs).
        """
        j = self._joints[self.resolve(joint)]
        return RawLimits.of_joint(j.spec, j.cal)

    def latest(self, joint: str) -> JointSample | None:
        """Latest calibrated feedback of a joint, or ``None`` before any ``joint_states``."""
        j = self._joints[self.resolve(joint)]
        if j.seen is None:
            return None
        return JointSample(j.spec.name, j.position, j.velocity, j.effort)

    def latest_raw_position(self, joint: str) -> float | None:
        """Latest raw (motor) position of a joint, or ``None`` if never reported."""
        return self._joints[self.resolve(joint)].raw_position

    def feedback_age(self, joint: str, now: float) -> float:
        """Seconds since the joint's latest feedback (``inf`` if never)."""
        seen = self._joints[self.resolve(joint)].seen
        return math.inf if seen is None else now - seen

    def position_age(self, joint: str, now: float) -> float:
        """Seconds since the joint's latest finite position (``inf`` if never)."""
        seen = self._joints[self.resolve(joint)].position_seen
        return math.inf if seen is None else now - seen

    def is_pinned(self, joint: str) -> bool:
        """Whether a joint is pinned (reported as locked)."""
        return self._joints[self.resolve(joint)].pin_note is not None

    def in_motion(self, joint: str) -> bool:
        """Whether a command is moving a joint: a velocity or effort command in force, or a
        position target not reached yet (as the watchdog judges it). Measured speed alone is
        read with :meth:`latest`."""
        j = self._joints[self.resolve(joint)]
        if j.mode in (VELOCITY, EFFORT) and (j.cmd_velocity or j.cmd_effort):
            return True
        return j.mode in (POSITION, VELOCITY, EFFORT) and self._moving(j)

    # ------------------------------------------------------------------ hook points
    def add_command_filter(self, joint: str, command_filter: CommandFilter) -> None:
        """Append a filter to a joint's command chain (hook for overrides and injections).

        Filters run in the order added, after the command is validated (known joint, finite
        values, not halted) and before it is clamped, in calibrated space. A filter returns
        the command to go on with (it may rewrite it) or a :class:`Refusal`. Clamping runs
        after the chain, so no filter can send anything out of limits.
        """
        self._joints[self.resolve(joint)].filters.append(command_filter)

    def pin(self, joint: str, position: float | None = None, note: str = "pinned") -> None:
        """Hold a joint at a fixed calibrated position; ListJoints reports it as locked.

        The core sends the hold at :meth:`start` (or at the joint's first feedback when
        ``position`` is ``None``, meaning "where it is then"), after every refused command
        naming the joint, and on halt, watchdog and stop. Pinning decides nothing about
        commands: add a command filter to refuse or rewrite them.

        Args:
            joint: Full or raw joint name.
            position: Calibrated position to hold (clamped to the limits when sent), or
                ``None`` for the position measured when the pin first takes effect.
            note: Why, for diagnostics (e.g. ``"locked by override locked_joint"``).

        Raises:
            KeyError: If the joint is unknown.
            ValueError: If ``position`` is not finite.
        """
        j = self._joints[self.resolve(joint)]
        if position is not None and not math.isfinite(position):
            raise ValueError(f"pin position for {j.spec.name} must be finite, not {position}")
        if position is None and j.position is not None:
            position = j.position
        j.pin = None if position is None else j.clamp_position(float(position))
        j.pin_note = note

    def set_calibration(self, joint: str, calibration: JointCalibration) -> None:
        """Replace a joint's calibration at runtime (e.g. re-zeroing).

        The latest feedback is re-expressed in the new calibrated space, and a pin keeps its
        physical (raw) position, so nothing moves because of the change.
        """
        j = self._joints[self.resolve(joint)]
        old = j.cal
        j.cal = calibration
        if j.pin is not None:
            j.pin = calibration.to_calibrated(old.to_raw(j.pin))
        if j.raw_position is not None:
            j.position = calibration.to_calibrated(j.raw_position)
        if j.velocity is not None:
            j.velocity = calibration.rate_to_calibrated(old.rate_to_raw(j.velocity))
        if j.effort is not None:
            j.effort = calibration.rate_to_calibrated(old.rate_to_raw(j.effort))
        # Force the next joint_read to carry the re-expressed values.
        j.pub_position = j.pub_velocity = j.pub_effort = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, now: float) -> None:
        """Send the holds of pinned joints whose position is already known; start watching
        the operators (their grace at start-up counts from here)."""
        out = [self._hold_sample(j) for j in self._joints.values() if j.pin is not None]
        self._send(out, now)
        if self.presence is not None:
            self.presence.start(now)

    def stop(self, now: float) -> None:
        """Leave the joints safe: hold every joint that is being commanded."""
        out = []
        for j in self._joints.values():
            if j.mode not in (IDLE, HOLD) or j.pin is not None:
                out.append(self._hold_sample(j))
                j.mode = HOLD
        self._send(out, now)

    # ------------------------------------------------------------------ periodic
    def tick(self, now: float) -> None:
        """Periodic work (the interface runs it at 50 Hz): watchdog, operators' presence,
        keep-alive, diagnostics."""
        self._watchdog(now)
        self._watch_presence(now)
        self._keepalive_if_due(now)
        if (
            self._last_diagnostics is None
            or now - self._last_diagnostics >= self.config.diagnostics_period
        ):
            self._last_diagnostics = now
            self.publish("diagnostics", self.diagnostics(now))

    def _watchdog(self, now: float) -> None:
        timeout = self.config.watchdog_timeout
        out: list[JointSample] = []
        tripped: list[str] = []
        for j in self._joints.values():
            if j.mode in (IDLE, HOLD) or now - j.last_command <= timeout:
                continue
            if j.mode == POSITION and not self._moving(j):
                # The move finished before commands stopped: nothing to stop.
                j.mode = IDLE
                continue
            out.append(self._hold_sample(j))
            j.mode = HOLD
            j.target_raw = None
            tripped.append(j.spec.name)
        if tripped:
            self._counters["watchdog_trips"] += 1
            self._tripped_at = now
            self._tripped_joints = tripped
            self._send(out, now)

    # ------------------------------------------------------------------ operators
    def on_station(self, station: str, visible: bool, now: float) -> None:
        """A ground station became visible or invisible on this module's computer (posted by
        the builder's presence feed); ignored when presence is not watched."""
        if self.presence is not None:
            self.presence.on_station(station, visible, now)
            self._watch_presence(now)

    def on_holder(self, holder: str | None, now: float) -> None:
        """The module's claim holder changed (``None``: its claim is gone)."""
        if self.presence is not None:
            self.presence.on_holder(holder, now)
            self._watch_presence(now)

    def _watch_presence(self, now: float) -> None:
        if self.presence is None:
            return
        # On BACK nothing moves: the joints stay held until commanded, as after recover.
        if self.presence.update(now) == LOST:
            # The halt path's hold, on a latch of its own: an operator's return lifts this
            # one, and only recover lifts a halt someone asked for.
            self._counters["presence_holds"] += 1
            self._hold_all(now)

    def _hold_all(self, now: float) -> list[JointSample]:
        out = []
        for j in self._joints.values():
            out.append(self._hold_sample(j))
            j.mode = HOLD
            j.target_raw = None
        self._send(out, now)
        return out

    def _moving(self, j: ManagedJoint) -> bool:
        if j.velocity is not None and abs(j.velocity) > self.config.read_velocity_threshold:
            return True
        if j.target_raw is None or j.raw_position is None:
            # Unknown progress: assume moving, stopping a still joint is harmless.
            return j.raw_position is None
        return abs(j.raw_position - j.target_raw) > self.config.settle_tolerance

    # ------------------------------------------------------------------ services
    def on_halt(self, request: Any, now: float) -> Any:
        """``halt`` (std_srvs/Trigger): hold every joint now and refuse commands until recover."""
        out = self._hold_all(now)
        was = self._halted
        self._halted = True
        self._halted_at = now
        blind = [s.name for s in out if s.position is None]
        text = f"{'still ' if was else ''}halted: {len(out)} joints held"
        if blind:
            text += f" ({', '.join(blind)}: no position known, velocity 0 only)"
        return trigger_response(True, text + "; commands are refused until recover")

    def on_recover(self, request: Any, now: float) -> Any:
        """``recover`` (std_srvs/Trigger): rearm after a halt or a watchdog trip."""
        was_halted, was_tripped = self._halted, self._tripped_at is not None
        self._halted = False
        self._halted_at = None
        self._tripped_at = None
        self._tripped_joints = []
        if not (was_halted or was_tripped):
            text = "not halted; nothing to recover"
        else:
            text = "recovered: commands accepted again (joints stay held until commanded)"
        age = None if self._last_feedback is None else now - self._last_feedback
        if age is None or age > self.config.stale_timeout:
            text += "; warning: no fresh joint_states, velocity commands will be refused"
        if self.presence_held:
            assert self.presence is not None
            # Not lifted by recover: only an operator's return does (a dead-man's hold).
            text += (
                f"; still held: {self.presence.reason(now)} (lifts by itself when a ground "
                "station or a claim holder is visible again)"
            )
        return trigger_response(True, text)

    def on_joints(self, request: Any, now: float) -> Any:
        """``joints`` (msctl_msgs/ListJoints): joints, limits, locked flag, latest state.

        Unknown state is NaN and its age ``inf``.
        """
        infos = []
        for j in self._joints.values():
            spec = j.spec
            infos.append(
                msg(
                    JOINT_INFO,
                    name=spec.name,
                    type=spec.type,
                    lower=float(spec.lower),
                    upper=float(spec.upper),
                    max_velocity=float(spec.max_velocity),
                    max_effort=float(spec.max_effort),
                    locked=j.pin_note is not None,
                    position=or_nan(j.position),
                    velocity=or_nan(j.velocity),
                    effort=or_nan(j.effort),
                    age=math.inf if j.seen is None else now - j.seen,
                )
            )
        return msg(LIST_JOINTS_RESPONSE, module=self.module, joints=infos)
