"""The stepping logic of the joint syncer: pure numpy, no I/O, no clock (``dt`` is passed in).

Every step turns (measured state, last command, goal) into the next position command. The
safety property comes from the MoonBots paper (arXiv 2507.03934): a command never leaves an
L-infinity ball of radius ``delta`` around the *measured* state. A joint that lags (a heavy
load, a slow motor, a lost link) therefore holds the others back, and if commands stop
arriving, or measurements stop coming back, the limb ends at most ``delta`` away from where it
was last seen.

Modes (see :class:`SyncPlanner.step`):

* ``lerp``: all joints on one straight line in joint space from the last command to the
  target, each step the farthest point of that line inside the ball (so every joint covers
  the same fraction of its way, and the slowest paces the rest);
* ``asap``: each joint on its own, clipped to ``measured +- delta``;
* ``unsafe``: the target itself;
* ``speed_safe``: the last command advanced by ``velocity * dt``, clipped like ``asap``.

Every mode also caps each joint's advance per step at its speed limit times ``dt`` and clips
the command into the joint limits (less a margin), so nothing sent exceeds a limit even if the
joint manager's own clamp were missing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

LERP = "lerp"
ASAP = "asap"
UNSAFE = "unsafe"
SPEED_SAFE = "speed_safe"
MODES = (LERP, ASAP, UNSAFE, SPEED_SAFE)

# Comparisons of commands with the ball use this slack: a command built exactly on the ball's
# surface must count as inside it after floating-point rounding.
_EPS = 1e-9


@dataclass(frozen=True)
class SyncSettings:
    """Tuning of a joint syncer. Angles in rad (lengths in m for prismatic joints).

    Attributes:
        delta: Radius of the L-infinity ball around the measured state that every command
            stays in; also the largest gap between last command and measurement that still
            counts as in sync (a larger gap is a desync: the next step restarts from the
            measurement).
        tolerance: A joint has arrived when its measurement is this close to the target.
        speed: Largest speed of any joint's command (rad/s or m/s); each joint's own
            ``max_velocity`` caps it further.
        rate: Commands per second while a motion runs (the joint manager's watchdog needs
            them to keep coming; 30-50 Hz is right).
        limit_margin: Distance kept from each joint limit (the joint manager's
            ``position_margin``, so what is sent is what the joint does).
    """

    delta: float = 0.1
    tolerance: float = 0.03
    speed: float = 0.6
    rate: float = 40.0
    limit_margin: float = 0.02

    def __post_init__(self) -> None:
        for name in ("delta", "tolerance", "speed", "rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SyncSettings.{name} must be > 0, not {getattr(self, name)}")
        if not self.limit_margin >= 0:
            raise ValueError(f"SyncSettings.limit_margin must be >= 0, not {self.limit_margin}")

    @property
    def period(self) -> float:
        """Seconds between two commands."""
        return 1.0 / self.rate


@dataclass(frozen=True)
class PlanStep:
    """One step of a plan.

    Attributes:
        command: The position command of every joint (planner order).
        resynced: The last command had drifted more than ``delta`` from the measurement, so
            this step started from the measurement instead.
        arrived: Every measurement is within tolerance of the target and the command is the
            target (always False for ``speed_safe``, which has no target).
    """

    command: np.ndarray
    resynced: bool
    arrived: bool


class SyncPlanner:
    """Next-command logic for a fixed set of joints.

    Args:
        names: The joints, in the order of every array passed to and returned by the planner.
        lower: Lower position limits (``-inf`` when unbounded).
        upper: Upper position limits (``+inf`` when unbounded).
        max_velocity: Each joint's speed limit (``settings.speed`` caps it further).
        settings: Ball radius, tolerance, speed.
        last: The last command sent to these joints, if any (a motion continues from it when
            it is still within ``delta`` of the measurement).

    Attributes:
        last: The last command returned by :meth:`step` (None before the first).
        resyncs: How many steps had to restart from the measurement.
    """

    def __init__(
        self,
        names: Sequence[str],
        lower: Sequence[float],
        upper: Sequence[float],
        max_velocity: Sequence[float],
        settings: SyncSettings | None = None,
        last: Sequence[float] | None = None,
    ) -> None:
        self.names = tuple(names)
        self.settings = settings or SyncSettings()
        margin = self.settings.limit_margin
        lo = np.asarray(lower, dtype=float) + margin
        hi = np.asarray(upper, dtype=float) - margin
        # A range narrower than twice the margin: the middle is the only safe point.
        narrow = lo > hi
        with np.errstate(invalid="ignore"):  # inf - inf on unbounded joints, not used
            mid = (lo + hi) / 2.0
        self.lower = np.where(narrow, mid, lo)
        self.upper = np.where(narrow, mid, hi)
        self.speed = np.minimum(np.asarray(max_velocity, dtype=float), self.settings.speed)
        n = len(self.names)
        if not (self.lower.size == self.upper.size == self.speed.size == n):
            raise ValueError("names, lower, upper and max_velocity must have the same length")
        self.last = None if last is None else np.asarray(last, dtype=float).copy()
        self.resyncs = 0

    def clamp(self, values: np.ndarray) -> np.ndarray:
        """``values`` clipped into the joint limits (less the margin)."""
        return np.clip(values, self.lower, self.upper)

    def start(self, measured: np.ndarray) -> tuple[np.ndarray, bool]:
        """Where the next step starts: the last command while in sync, else the measurement.

        Returns:
            The start, and whether a desync forced a restart from the measurement.
        """
        last = self.last
        if last is None:
            return measured.copy(), False
        if np.abs(last - measured).max(initial=0.0) <= self.settings.delta + _EPS:
            return last, False
        return measured.copy(), True

    def step(
        self,
        mode: str,
        measured: np.ndarray,
        dt: float,
        target: np.ndarray | None = None,
        velocity: np.ndarray | None = None,
    ) -> PlanStep:
        """The next command.

        Args:
            mode: One of :data:`MODES`.
            measured: The joints' measured positions.
            dt: Seconds since the previous step (the speed cap and ``speed_safe`` use it).
            target: Goal positions (``lerp``, ``asap``, ``unsafe``).
            velocity: Requested speeds (``speed_safe``).

        Raises:
            ValueError: For an unknown mode, or a missing target or velocity.
        """
        measured = np.asarray(measured, dtype=float)
        delta = self.settings.delta
        start, resynced = self.start(measured)
        if resynced:
            self.resyncs += 1
        reach = self.speed * max(dt, 0.0)
        low, high = measured - delta, measured + delta
        if mode == SPEED_SAFE:
            if velocity is None:
                raise ValueError("speed_safe needs velocities")
            speeds = np.clip(np.asarray(velocity, dtype=float), -self.speed, self.speed)
            command = self.clamp(np.clip(start + speeds * dt, low, high))
            self.last = command
            return PlanStep(command, resynced, False)
        if target is None:
            raise ValueError(f"{mode} needs a target")
        goal = self.clamp(np.asarray(target, dtype=float))
        if mode == UNSAFE:
            command = goal.copy()
        elif mode == ASAP:
            command = np.clip(start + np.clip(goal - start, -reach, reach), low, high)
        elif mode == LERP:
            command = start + lerp_fraction(start, goal, measured, delta, reach) * (goal - start)
        else:
            raise ValueError(f"unknown mode {mode!r}; use one of {', '.join(MODES)}")
        command = self.clamp(command)
        self.last = command
        arrived = bool(
            np.abs(command - goal).max(initial=0.0) <= _EPS
            and np.abs(measured - goal).max(initial=0.0) <= self.settings.tolerance
        )
        return PlanStep(command, resynced, arrived)


def lerp_fraction(
    start: np.ndarray, goal: np.ndarray, measured: np.ndarray, delta: float, reach: np.ndarray
) -> float:
    """The largest ``a`` in [0, 1] with ``start + a * (goal - start)`` inside the L-infinity
    ball of radius ``delta`` around ``measured``, and each joint's advance within ``reach``.

    ``start`` must be inside the ball (the planner restarts from the measurement otherwise),
    so the feasible fractions form an interval from 0 and the answer is the smallest bound.
    """
    way = goal - start
    distance = np.abs(way)
    moving = distance > _EPS
    if not moving.any():
        return 1.0
    # Room left toward the goal on each axis: delta minus how far start already leans that way.
    room = np.maximum(delta - np.sign(way) * (start - measured), 0.0)
    bounds = np.minimum(room, reach)[moving] / distance[moving]
    return float(min(1.0, bounds.min()))
