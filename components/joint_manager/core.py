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
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from components.config import require
from components.executor.core import Core
from components.executor.interface import Serve
from components.joint_manager.presence import LOST, OperatorPresence
from components.joints import JointCalibration, JointSpec
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    JointSample,
    diagnostic_array,
    diagnostic_status,
    joint_samples,
    joint_state_batches,
    msg,
    trigger_response,
    worst,
)
from components.motors.base import RawLimits, refused_whole

LIST_JOINTS_RESPONSE = "msctl_msgs/srv/ListJoints_Response"
JOINT_INFO = "msctl_msgs/msg/JointInfo"

#: Counters every manager exposes (filters may add their own names). ``refused_oversize``
#: and ``refused_malformed`` count ``joint_set`` messages refused whole (more names than the
#: module has joints; arrays that do not match the names), ``feedback_oversize`` such
#: ``joint_states`` messages; ``duplicates`` counts entries superseded by a later one for the
#: same joint in the same message; ``speed_cuts`` efforts cut because the joint was already
#: faster than its max velocity; ``presence_holds`` how often the module held itself for
#: lost operators; the rest count entries (``refused_no_operator``: refused during such a
#: hold).
COUNTERS = (
    "refused_oversize",
    "refused_malformed",
    "duplicates",
    "refused_nan",
    "refused_unknown",
    "refused_other_module",
    "refused_locked",
    "refused_halted",
    "refused_no_state",
    "clamped",
    "watchdog_trips",
    "presence_holds",
    "refused_no_operator",
    "speed_cuts",
    "feedback_rejected",
    "feedback_oversize",
)


@dataclass(frozen=True)
class JointManagerConfig:
    """Tuning of one joint manager. Lengths are rad for revolute joints and m for prismatic.

    Attributes:
        position_margin: Distance kept from each URDF position limit: commands are clamped to
            ``[lower + margin, upper - margin]``; at most ``position_margin_fraction`` of the
            joint's range.
        position_margin_fraction: Largest margin as a fraction of the joint's range, so a
            short joint keeps its travel: a 0.04 m finger gets 0.002 m, not 0.02 m (which left
            it only its midpoint).
        watchdog_timeout: Seconds without a command for a moving joint before the watchdog
            stops it (velocity 0, position held where it is).
        read_position_threshold: Position change (calibrated) that publishes ``joint_read``
            at once.
        read_velocity_threshold: Velocity change that publishes ``joint_read`` at once; also
            the speed above which a position-commanded joint counts as moving.
        read_effort_threshold: Effort change that publishes ``joint_read`` at once.
        keepalive_period: Seconds between full ``joint_read`` publications when nothing
            changes, so a still robot does not flood the radio yet subscribers see it alive.
        velocity_limit_lookahead: A velocity-only command that would cross a limit (minus the
            margin) within this many seconds, from the measured position, becomes a hold;
            the same check runs on every feedback while a joint moves in velocity (or
            effort) mode, so it stops at the limit even between two commands.
        settle_tolerance: A position-commanded joint that is not measurably moving but is
            farther than this from its target counts as moving for the watchdog (stalled,
            e.g. pushing against an obstacle: it is held where it is). Nearer, it is settled:
            servos under load rest a few hundredths of a radian off their target, and holding
            them at that sagged reading after every motion would walk the pose downward.
        diagnostics_period: Seconds between ``diagnostics`` publications.
        stale_timeout: A joint whose latest ``joint_states`` is older than this is STALE: it
            is left out of keep-alives, and velocity commands to a bounded joint are refused
            (its position is no longer known well enough to keep it within limits).
        warn_window: A clamp or refusal keeps the manager (and that joint) at WARN for this
            many seconds.
    """

    position_margin: float = 0.02
    position_margin_fraction: float = 0.05
    watchdog_timeout: float = 0.5
    read_position_threshold: float = 1e-3
    read_velocity_threshold: float = 1e-2
    read_effort_threshold: float = 1e-2
    keepalive_period: float = 1.0
    velocity_limit_lookahead: float = 0.1
    settle_tolerance: float = 0.1
    diagnostics_period: float = 1.0
    stale_timeout: float = 1.0
    warn_window: float = 5.0

    def __post_init__(self) -> None:
        require(
            self,
            positive=(
                "watchdog_timeout",
                "keepalive_period",
                "diagnostics_period",
                "stale_timeout",
            ),
            non_negative=(
                "position_margin",
                "position_margin_fraction",
                "read_position_threshold",
                "read_velocity_threshold",
                "read_effort_threshold",
                "velocity_limit_lookahead",
                "settle_tolerance",
                "warn_window",
            ),
        )


@dataclass(frozen=True)
class Refusal:
    """What a command filter returns to refuse a command.

    Attributes:
        counter: Counter to increment (an existing one such as ``refused_locked``, or a new
            name, which then appears in :attr:`JointManagerCore.counters` and diagnostics).
        reason: Human text for diagnostics, naming the joint and what to do.
    """

    counter: str
    reason: str


#: A command filter: receives a calibrated command (fields ``None`` when not given) and
#: ``now``; returns the command to go on with (possibly rewritten) or a :class:`Refusal`.
CommandFilter = Callable[[JointSample, float], "JointSample | Refusal"]

# Command modes, per joint: what the last accepted command asked of the motor.
_IDLE, _POSITION, _VELOCITY, _EFFORT, _HOLD = "idle", "position", "velocity", "effort", "hold"


class _Joint:
    """Mutable per-joint state (slots: this is touched at every message)."""

    __slots__ = (
        "cal",
        "cmd_effort",
        "cmd_velocity",
        "effort",
        "filters",
        "hi",
        "last_clamp",
        "last_command",
        "last_refusal",
        "lo",
        "local",
        "mode",
        "note",
        "pin",
        "pin_note",
        "position",
        "position_seen",
        "pub_effort",
        "pub_position",
        "pub_velocity",
        "raw_position",
        "seen",
        "spec",
        "target_raw",
        "velocity",
    )

    def __init__(
        self, spec: JointSpec, local: str, cal: JointCalibration, margin: float, fraction: float
    ) -> None:
        self.spec = spec
        self.local = local
        self.cal = cal
        if spec.bounded:
            # Relative to the range: a fixed margin would eat a short joint's whole travel.
            margin = min(margin, fraction * (spec.upper - spec.lower))
            lo, hi = spec.lower + margin, spec.upper - margin
            if lo > hi:
                # A range narrower than two margins: the only safe command is its middle.
                lo = hi = 0.5 * (spec.lower + spec.upper)
        else:
            lo, hi = -math.inf, math.inf
        self.lo, self.hi = lo, hi
        # Latest feedback, calibrated (None until the motor interface reported it).
        self.position: float | None = None
        self.velocity: float | None = None
        self.effort: float | None = None
        self.raw_position: float | None = None
        self.seen: float | None = None
        # When the latest finite position came (velocity or effort alone do not refresh it).
        self.position_seen: float | None = None
        # What joint_read last carried, for change detection.
        self.pub_position: float | None = None
        self.pub_velocity: float | None = None
        self.pub_effort: float | None = None
        # Command side.
        self.mode = _IDLE
        self.last_command = -math.inf
        self.target_raw: float | None = None
        self.cmd_velocity = 0.0
        # Effort of the latest effort (or velocity + effort) command, calibrated; 0 if none.
        self.cmd_effort = 0.0
        self.filters: list[CommandFilter] = []
        self.pin: float | None = None
        self.pin_note: str | None = None
        self.last_clamp = -math.inf
        self.last_refusal = -math.inf
        self.note = ""

    def clamp_position(self, position: float) -> float:
        return min(max(position, self.lo), self.hi)


class JointManagerCore(Core):
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
        self._joints: dict[str, _Joint] = {}
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
            self._joints[spec.name] = _Joint(
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
        if j.mode in (_VELOCITY, _EFFORT) and (j.cmd_velocity or j.cmd_effort):
            return True
        return j.mode in (_POSITION, _VELOCITY, _EFFORT) and self._moving(j)

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
            if j.mode not in (_IDLE, _HOLD) or j.pin is not None:
                out.append(self._hold_sample(j))
                j.mode = _HOLD
        self._send(out, now)

    # ------------------------------------------------------------------ feedback
    def on_joint_states(self, message: Any, now: float) -> None:
        """Raw feedback from the motor interface: update state, publish ``joint_read``.

        Joints that changed by more than the read thresholds go out at once in one batch;
        every fresh joint goes out at the keep-alive period. Names this manager does not
        control and non-finite values are ignored (counted as ``feedback_rejected``).
        """
        if len(message.name) > self._size:
            # A flood (or a bug): dropped before it costs anything per name.
            self._counters["feedback_oversize"] += 1
            return
        changed: dict[str, _Joint] = {}
        holds: list[JointSample] = []
        for name, raw_pos, raw_vel, raw_eff in joint_samples(message):
            j = self._joints.get(name)
            if j is None:
                self._counters["feedback_rejected"] += 1
                continue
            updated = False
            cal = j.cal
            if raw_pos is not None:
                if math.isfinite(raw_pos):
                    j.raw_position = raw_pos
                    j.position = cal.to_calibrated(raw_pos)
                    j.position_seen = now
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if raw_vel is not None:
                if math.isfinite(raw_vel):
                    j.velocity = cal.rate_to_calibrated(raw_vel)
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if raw_eff is not None:
                if math.isfinite(raw_eff):
                    j.effort = cal.rate_to_calibrated(raw_eff)
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if not updated:
                continue
            j.seen = now
            self._last_feedback = now
            if j.pin_note is not None and j.pin is None and j.position is not None:
                # A pin "where it is" takes effect at the first measured position.
                j.pin = j.clamp_position(j.position)
                holds.append(self._hold_sample(j))
            elif j.mode in (_VELOCITY, _EFFORT) and self._heading_past_limit(j):
                # Between two commands a joint keeps its velocity: check it on every
                # feedback, not only when a command arrives, or it could run through a limit
                # for a whole watchdog timeout.
                self._mark_clamp(j, f"{j.spec.name}: reached a limit, holding", now)
                holds.append(self._hold_sample(j))
                j.mode = _HOLD
            elif (
                j.cmd_effort and j.mode in (_VELOCITY, _EFFORT) and self._too_fast(j, j.cmd_effort)
            ):
                holds.append(self._cut_effort(j, now))
            if self._changed(j):
                changed[name] = j
        self._send(holds, now)
        if not self._keepalive_if_due(now) and changed:
            self._publish_read(changed.values(), now)

    def _too_fast(self, j: _Joint, effort: float) -> bool:
        """Whether ``effort`` pushes a joint already above its max velocity on (effort mode
        has no speed bound of its own; an effort that brakes is never cut)."""
        speed = j.velocity
        return speed is not None and abs(speed) > j.spec.max_velocity and effort * speed > 0

    def _cut_effort(self, j: _Joint, now: float) -> JointSample:
        """The raw command that takes a too-fast joint's effort away (counted)."""
        self._counters["speed_cuts"] += 1
        self._mark_clamp(j, f"{j.spec.name}: faster than {j.spec.max_velocity:g}, effort cut", now)
        j.cmd_effort = 0.0
        if j.mode == _VELOCITY:
            return JointSample(j.spec.name, None, j.cal.rate_to_raw(j.cmd_velocity), None)
        return JointSample(j.spec.name, None, None, 0.0)

    def _heading_past_limit(self, j: _Joint, velocity: float | None = None) -> bool:
        """Whether a bounded joint would cross ``lo``/``hi`` within the lookahead.

        ``velocity`` defaults to the commanded one in velocity mode and the measured one in
        effort mode (an effort command has no velocity of its own).
        """
        if not j.spec.bounded or j.position is None:
            return False
        if velocity is None:
            velocity = j.cmd_velocity if j.mode == _VELOCITY else (j.velocity or 0.0)
        ahead = j.position + velocity * self.config.velocity_limit_lookahead
        return (velocity > 0 and ahead >= j.hi) or (velocity < 0 and ahead <= j.lo)

    def _changed(self, j: _Joint) -> bool:
        cfg = self.config
        return (
            _moved(j.position, j.pub_position, cfg.read_position_threshold)
            or _moved(j.velocity, j.pub_velocity, cfg.read_velocity_threshold)
            or _moved(j.effort, j.pub_effort, cfg.read_effort_threshold)
        )

    def _keepalive_if_due(self, now: float) -> bool:
        if self._last_keepalive is not None and (
            now - self._last_keepalive < self.config.keepalive_period
        ):
            return False
        self._last_keepalive = now
        stale = self.config.stale_timeout
        fresh = [j for j in self._joints.values() if j.seen is not None and now - j.seen <= stale]
        if fresh:
            self._publish_read(fresh, now)
        return True

    def _publish_read(self, joints: Iterable[_Joint], now: float) -> None:
        samples = []
        for j in joints:
            samples.append(JointSample(j.spec.name, j.position, j.velocity, j.effort))
            j.pub_position, j.pub_velocity, j.pub_effort = j.position, j.velocity, j.effort
        for message in joint_state_batches(samples, self.stamp(now)):
            self.publish("joint_read", message)

    # ------------------------------------------------------------------ commands
    def on_joint_set(self, message: Any, now: float) -> None:
        """Calibrated commands from above: validate, filter, clamp, convert, send raw.

        Each joint of the message is judged on its own: a refused joint (unknown, another
        module's, non-finite value, refused by a filter, halted, velocity with no fresh
        position) is counted and left out; the others go out on ``joint_commands``. An
        accepted command feeds that joint's watchdog.
        """
        refused = refused_whole(message, self._size)
        if refused is not None:
            self._counters[refused] += 1
            self._last_refusal = now
            why = (
                f"the module has {self._size} joints"
                if refused == "refused_oversize"
                else "its arrays do not match its names"
            )
            self._refusal_note = f"joint_set with {len(message.name)} names refused: {why}"
            return
        samples = joint_samples(message)
        if self._halted:
            self._refuse_all(samples, now)
            return
        if self.presence_held:
            self._refuse_all(samples, now, no_operator=True)
            return
        # The last entry per joint wins: one command per joint however often it is named.
        latest = {sample.name: sample for sample in samples}
        if len(latest) != len(samples):
            self._counters["duplicates"] += len(samples) - len(latest)
        out: list[JointSample] = []
        accepted = False
        for sample in latest.values():
            j = self._joints.get(sample.name)
            if j is None:
                self._refuse_name(sample.name, now)
                continue
            command = sample
            if command.position is None and command.velocity is None and command.effort is None:
                continue
            if not _finite(command):
                self._refuse(j, "refused_nan", f"{j.spec.name}: NaN or inf in command", now)
                continue
            refused = False
            for command_filter in j.filters:
                result = command_filter(command, now)
                if isinstance(result, Refusal):
                    self._refuse(j, result.counter, result.reason, now)
                    refused = True
                    break
                command = result
            if refused:
                if j.pin is not None:
                    out.append(self._hold_sample(j))
                continue
            sent = self._limit(j, command, now)
            if sent is None:
                continue
            out.append(sent)
            j.last_command = now
            accepted = True
        if accepted:
            # A fresh accepted command is the operator back: the trip is over.
            self._tripped_at = None
            self._tripped_joints = []
        self._send(out, now)

    def _limit(self, j: _Joint, command: JointSample, now: float) -> JointSample | None:
        """Clamp one calibrated command and express it in raw space (None: refused)."""
        spec, cal = j.spec, j.cal
        position, velocity, effort = command.position, command.velocity, command.effort
        clamped = False
        if position is not None:
            limited = j.clamp_position(position)
            clamped |= limited != position
            position = limited
        if velocity is not None:
            limited = min(max(velocity, -spec.max_velocity), spec.max_velocity)
            clamped |= limited != velocity
            velocity = limited
        if effort is not None:
            limited = min(max(effort, -spec.max_effort), spec.max_effort)
            clamped |= limited != effort
            effort = limited
            if position is None and self._too_fast(j, effort):
                self._counters["speed_cuts"] += 1
                self._mark_clamp(
                    j, f"{spec.name}: faster than {spec.max_velocity:g}, effort cut", now
                )
                effort = 0.0 if velocity is None else None
        if position is None and (velocity is not None or effort is not None) and spec.bounded:
            # Velocity or effort mode on a bounded joint drives it toward its limits: only
            # safe while we know where the joint is. The position's own age: velocity-only
            # feedback (an encoder reporting NaN, a motor interface sending positions in
            # another batch) must not make it look fresh.
            seen = j.position_seen
            stale = seen is None or j.position is None or now - seen > self.config.stale_timeout
            if stale:
                mode = "velocity" if velocity is not None else "effort"
                self._refuse(
                    j,
                    "refused_no_state",
                    f"{spec.name}: {mode} command refused, no fresh joint_states "
                    "(is the motor interface running?)",
                    now,
                )
                return None
        if (
            position is None
            and velocity is not None
            and spec.bounded
            and self._heading_past_limit(j, velocity)
        ):
            self._mark_clamp(j, f"{spec.name}: velocity toward a limit, holding", now)
            j.mode = _HOLD
            j.target_raw = None
            return self._hold_sample(j)
        if clamped:
            self._mark_clamp(j, f"{spec.name}: command clamped to limits", now)
        j.cmd_effort = effort or 0.0
        if position is not None:
            j.mode = _POSITION
            j.target_raw = cal.to_raw(position)
        elif velocity is not None:
            j.mode = _VELOCITY
            j.target_raw = None
            j.cmd_velocity = velocity
        else:
            j.mode = _EFFORT
            j.target_raw = None
        return JointSample(
            spec.name,
            None if position is None else j.target_raw,
            None if velocity is None else cal.rate_to_raw(velocity),
            None if effort is None else cal.rate_to_raw(effort),
        )

    def _hold_sample(self, j: _Joint) -> JointSample:
        """Raw command holding a joint: at its pin, else where it is; velocity 0.

        Without any known position the only safe thing to send is velocity 0.
        """
        hold = j.pin if j.pin is not None else j.position
        if hold is None:
            return JointSample(j.spec.name, None, 0.0, None)
        # Clamped here too: a pin may have left the limits through a calibration change.
        return JointSample(j.spec.name, j.cal.to_raw(j.clamp_position(hold)), 0.0, None)

    def _send(self, out: list[JointSample], now: float) -> None:
        if out:
            for message in joint_state_batches(out, self.stamp(now)):
                self.publish("joint_commands", message)

    def _refuse_name(self, name: str, now: float) -> None:
        name = name if len(name) <= 64 else name[:64] + "..."  # notes stay small
        head, sep, _ = name.partition("_")
        if sep and head and not name.startswith(self._prefix):
            counter = "refused_other_module"
            reason = (
                f"command for {name!r} refused: it belongs to module {head!r}, not {self.module!r}"
            )
        else:
            counter = "refused_unknown"
            reason = f"command for unknown joint {name!r} refused; known: {sorted(self._joints)}"
        self._counters[counter] += 1
        self._last_refusal = now
        self._refusal_note = reason

    def _refuse_all(
        self, samples: list[JointSample], now: float, no_operator: bool = False
    ) -> None:
        for sample in samples:
            j = self._joints.get(sample.name)
            if j is None:
                self._refuse_name(sample.name, now)
            elif no_operator:
                assert self.presence is not None
                why = f"{j.spec.name}: {self.presence.reason(now)}; held until one is visible"
                self._refuse(j, "refused_no_operator", why, now)
            else:
                self._refuse(j, "refused_halted", f"{j.spec.name}: halted, call recover", now)

    def _refuse(self, j: _Joint, counter: str, reason: str, now: float) -> None:
        self._counters[counter] = self._counters.get(counter, 0) + 1
        j.last_refusal = now
        j.note = reason
        self._last_refusal = now
        self._refusal_note = reason

    def _mark_clamp(self, j: _Joint, note: str, now: float) -> None:
        self._counters["clamped"] += 1
        j.last_clamp = now
        j.note = note
        self._last_clamp = now

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
            if j.mode in (_IDLE, _HOLD) or now - j.last_command <= timeout:
                continue
            if j.mode == _POSITION and not self._moving(j):
                # The move finished before commands stopped: nothing to stop.
                j.mode = _IDLE
                continue
            out.append(self._hold_sample(j))
            j.mode = _HOLD
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
            j.mode = _HOLD
            j.target_raw = None
        self._send(out, now)
        return out

    def _moving(self, j: _Joint) -> bool:
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
                    position=_or_nan(j.position),
                    velocity=_or_nan(j.velocity),
                    effort=_or_nan(j.effort),
                    age=math.inf if j.seen is None else now - j.seen,
                )
            )
        return msg(LIST_JOINTS_RESPONSE, module=self.module, joints=infos)

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, now: float) -> Any:
        """The DiagnosticArray ``tick`` publishes: one status for the manager, one per joint."""
        statuses = [self._manager_status(now)]
        statuses.extend(self._joint_status(j, now) for j in self._joints.values())
        return diagnostic_array(statuses, self.stamp(now))

    def _manager_status(self, now: float) -> Any:
        cfg = self.config
        levels, notes = [OK], []
        if self._halted:
            levels.append(ERROR)
            notes.append("halted: commands refused until recover")
        if self._tripped_at is not None:
            levels.append(ERROR)
            notes.append(
                f"watchdog stopped {', '.join(self._tripped_joints)}: no command for "
                f"{cfg.watchdog_timeout} s; send a command or recover"
            )
        if self.presence is not None:
            if self.presence.held:
                levels.append(ERROR)
                notes.append(
                    f"{self.presence.reason(now)}: motors held, commands refused until an "
                    "operator is visible again"
                )
            else:
                # Said at OK: the robot is fine again, and "back to OK" after an outage
                # must not wait for a warning window.
                back = self.presence.lifted(now, cfg.warn_window)
                if back is not None:
                    notes.append(back)
        age = None if self._last_feedback is None else now - self._last_feedback
        if age is None or age > cfg.stale_timeout:
            # Below ERROR: "no news" must not hide a halt or a watchdog trip.
            levels.append(STALE)
            notes.append(
                "no joint_states yet" if age is None else f"no joint_states for {age:.1f} s"
            )
        if now - self._last_refusal <= cfg.warn_window:
            levels.append(WARN)
            notes.append(self._refusal_note)
        if now - self._last_clamp <= cfg.warn_window:
            levels.append(WARN)
            notes.append("commands clamped to limits")
        level = worst(levels)
        values: dict[str, Any] = {
            "module": self.module,
            "halted": self._halted,
            "operators": _operators(self.presence),
            "joints": len(self._joints),
            "feedback_age": "never" if age is None else f"{age:.3f}",
        }
        values.update(self._counters)
        return diagnostic_status(
            self.name, level, "; ".join(notes) or "OK", hardware_id=self.module, values=values
        )

    def _joint_status(self, j: _Joint, now: float) -> Any:
        cfg = self.config
        levels, notes = [OK], []
        if j.seen is None or now - j.seen > cfg.stale_timeout:
            levels.append(STALE)
            notes.append("no joint_states" if j.seen is None else f"stale {now - j.seen:.1f} s")
        if j.pin_note is not None:
            levels.append(WARN)
            where = "current position" if j.pin is None else f"{j.pin:.4f}"
            notes.append(f"{j.pin_note}, held at {where}")
        if max(j.last_refusal, j.last_clamp) >= now - cfg.warn_window:
            levels.append(WARN)
            notes.append(j.note)
        if self.presence is not None:
            # On every joint too: the module's health monitor reads the joints' statuses,
            # so the module's own health says why its motors hold, and when they may move
            # again (at OK: the alarm history keeps that message with the change to OK).
            if self.presence.held:
                levels.append(ERROR)
                notes.insert(0, f"held: {self.presence.reason(now)}")
            else:
                back = self.presence.lifted(now, cfg.warn_window)
                if back is not None:
                    notes.append(back)
        level = worst(levels)
        values = {
            "position": _fmt(j.position),
            "velocity": _fmt(j.velocity),
            "effort": _fmt(j.effort),
            "age": "never" if j.seen is None else f"{now - j.seen:.3f}",
            "mode": j.mode,
            "locked": j.pin_note is not None,
        }
        return diagnostic_status(
            f"{self.name}/{j.spec.name}",
            level,
            "; ".join(notes) or "OK",
            hardware_id=self.module,
            values=values,
        )


def _operators(presence: OperatorPresence | None) -> str:
    """The ``operators`` diagnostic value: who attends the module now."""
    if presence is None:
        return "not watched"
    if presence.held:
        return "none: held"
    seen = presence.visible()
    if presence.holder is not None:
        seen.insert(0, presence.holder)
    return ", ".join(seen) or "none"


def _moved(value: float | None, published: float | None, threshold: float) -> bool:
    if value is None:
        return False
    return published is None or abs(value - published) > threshold


def _finite(sample: JointSample) -> bool:
    return all(
        v is None or math.isfinite(v) for v in (sample.position, sample.velocity, sample.effort)
    )


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"
