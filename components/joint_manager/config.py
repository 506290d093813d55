"""A joint manager's tuning, its counters, and what its command filters answer."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from components.config import require
from components.messages import JointSample

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
