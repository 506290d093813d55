"""The teleop core: keys in, motion commands out, under a deadman. Pure: no I/O, no clock.

Terminals report key presses and the OS's key repeats, never a release. So motion lasts only
while key events keep coming: a motion key arms the :class:`Deadman`, which stays alive for
``first_timeout`` (longer than the OS's initial repeat delay) until the key repeats, then for
``repeat_timeout`` after each repeat. While it is alive, :meth:`TeleopCore.tick` gives one
:class:`Move` per period (``rate``); the first at once, the next ones never closer than a
period. When motion ends, for whatever reason (the deadman ran out, another mode, another
joint or limb, focus lost, quit, an e-stop, an unbound key), exactly one :class:`Stop` goes
out for what was moving, then nothing: no stream of zeros fighting other operators.

Time is passed in (``now``, seconds, any monotonic origin): tests drive the core with plain
calls, :class:`~msctl.teleop.operator.Operator` with the real clock on its own thread.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from components.config import require
from msctl.teleop.keys import (
    DRIVE,
    DRIVE_MOVES,
    DRIVE_SPEED,
    DRIVE_STOP,
    IK,
    IK_MOVES,
    JOINT,
    JOINT_MOVES,
    JOINT_SELECT,
    LIMB_SELECT,
    MODE_KEYS,
    MODES,
    MODULE_SELECT,
    SPEED,
)

#: Floating-point slack when comparing a tick's time with a due time.
_EPS = 1e-9


@dataclass(frozen=True)
class TeleopSettings:
    """Rates, deadman timeouts and speeds of the teleop. Angles in rad, lengths in m.

    Attributes:
        rate: Motion commands per second while a key is held (at most).
        first_timeout: The deadman's timeout after a key's first event: longer than the OS's
            initial key-repeat delay, or a held key would stop before it repeats.
        repeat_timeout: The deadman's timeout once the key repeats.
        joint_speed: Jog speed of a joint at start (rad/s, m/s for prismatic joints).
        tip_speed: IK tip speed at start (m/s).
        tip_turn: IK tip rotation speed at start (rad/s).
        drive_speed: Drive linear speed at start (m/s).
        drive_turn: Drive turn rate at start (rad/s).
        max_joint_speed: Largest jog speed the keys may reach (each joint's limit caps it
            again downstream).
        max_tip_speed: Largest IK tip speed.
        max_tip_turn: Largest IK tip rotation speed.
        max_drive_speed: Largest drive speed.
        max_drive_turn: Largest drive turn rate.
        min_fraction: The speeds never scale below this fraction of their start value.
    """

    rate: float = 20.0
    first_timeout: float = 0.6
    repeat_timeout: float = 0.15
    joint_speed: float = 0.2
    tip_speed: float = 0.03
    tip_turn: float = 0.2
    drive_speed: float = 0.2
    drive_turn: float = 0.5
    max_joint_speed: float = 1.0
    max_tip_speed: float = 0.1
    max_tip_turn: float = 1.0
    max_drive_speed: float = 1.0
    max_drive_turn: float = 2.0
    min_fraction: float = 0.01

    def __post_init__(self) -> None:
        require(self, positive=tuple(self.__dataclass_fields__))
        for name in ("joint_speed", "tip_speed", "tip_turn", "drive_speed", "drive_turn"):
            if getattr(self, name) > getattr(self, f"max_{name}"):
                raise ValueError(
                    f"TeleopSettings.{name} ({getattr(self, name)}) is above "
                    f"max_{name} ({getattr(self, f'max_{name}')})"
                )

    @property
    def period(self) -> float:
        """Seconds between two motion commands."""
        return 1.0 / self.rate


#: The speeds a teleop scales, by name (see :class:`TeleopSettings`).
SPEED_NAMES = ("joint_speed", "tip_speed", "tip_turn", "drive_speed", "drive_turn")
#: The speeds each mode's ``q``/``z`` scale together.
_MODE_SPEEDS = {JOINT: ("joint_speed",), IK: ("tip_speed", "tip_turn")}


class Deadman:
    """Whether a held key is still held, from its events alone.

    Args:
        first_timeout: Life after a key's first event.
        repeat_timeout: Life after each repeat.

    Attributes:
        key: The key held (None: none).
        last: Time of its latest event.
        repeating: The key has repeated at least once.
    """

    def __init__(self, first_timeout: float, repeat_timeout: float) -> None:
        self.first_timeout = first_timeout
        self.repeat_timeout = repeat_timeout
        self.key: str | None = None
        self.last = -math.inf
        self.repeating = False

    def event(self, key: str, now: float) -> None:
        """A motion key's event: the same key while alive is a repeat, anything else a press."""
        if key == self.key and self.alive(now):
            self.repeating = True
        else:
            self.key = key
            self.repeating = False
        self.last = now

    @property
    def timeout(self) -> float:
        """The timeout now in force."""
        return self.repeat_timeout if self.repeating else self.first_timeout

    def alive(self, now: float) -> bool:
        """Whether the held key's latest event is younger than the timeout."""
        return self.key is not None and now - self.last < self.timeout

    def expiry(self) -> float | None:
        """When it runs out if no event comes (None when no key is held)."""
        return None if self.key is None else self.last + self.timeout

    def release(self) -> None:
        """Forget the key (a stop that is not the timeout's)."""
        self.key = None
        self.repeating = False


@dataclass(frozen=True)
class Move:
    """One motion command to put on the wire.

    Attributes:
        mode: ``joint``, ``ik`` or ``drive``.
        target: The module (joint mode), the limb (IK) or the drive target's name (drive).
        joint: The jogged joint (joint mode), else None.
        velocity: Joint mode ``(v,)``; IK ``(vx, vy, vz, wx, wy, wz)`` in the limb's base
            frame; drive ``(vx, vy, wz)`` in the robot's frame.
        dt: Seconds since this motion's previous command (one period for the first, at most
            two periods: a late tick never turns into a big step).
        first: The first command of a motion (after silence or a stop).
    """

    mode: str
    target: str
    joint: str | None
    velocity: tuple[float, ...]
    dt: float
    first: bool


@dataclass(frozen=True)
class Stop:
    """The one stop command that ends a motion.

    Attributes:
        mode: The mode of the motion it ends.
        target: Its module, limb or drive target.
        joint: Its joint (joint mode).
        reason: Why it stopped (``deadman``, ``mode changed``, ``focus lost``, ...).
    """

    mode: str
    target: str
    joint: str | None
    reason: str


Command = Move | Stop


@dataclass(frozen=True)
class TeleopView:
    """What the screen shows of the core.

    Attributes:
        mode: The mode.
        modules: Modules of joint mode, in order.
        module: The selected module (joint mode).
        joint: The selected joint (joint mode).
        limb: The selected limb (IK mode).
        speeds: Every speed by name (:data:`SPEED_NAMES`).
        moving: Motion commands are going out.
        key: The key held (while moving).
        repeating: That key has repeated (the short timeout is in force).
        stopped_because: Why the last motion ended ("" before any).
        note: The latest thing worth telling the operator (a speed, a refusal).
        blocked: Modules no longer commanded, and why.
        moves: Motion commands given so far.
        stops: Stop commands given so far.
        held_back: Why the selected target cannot be commanded ("" when it can).
    """

    mode: str
    modules: tuple[str, ...]
    module: str | None
    joint: str | None
    limb: str | None
    speeds: dict[str, float]
    moving: bool
    key: str | None
    repeating: bool
    stopped_because: str
    note: str
    blocked: dict[str, str]
    moves: int
    stops: int
    held_back: str = ""


@dataclass
class _Motion:
    """What is moving: the key that drives it and where its commands go."""

    mode: str
    target: str
    joint: str | None
    direction: tuple[float, ...] = field(default_factory=tuple)

    def same_target(self, other: _Motion) -> bool:
        return (self.mode, self.target, self.joint) == (other.mode, other.target, other.joint)


class TeleopCore:
    """Key events to motion and stop commands.

    Args:
        settings: Rate, deadman and speeds.
        modules: Joint mode's modules and their joints, in order (assembly joint names).
        limbs: IK mode's limbs (none: IK mode is unavailable).
        drive_target: The name of drive mode's output (its ``cmd_vel`` topic); None: drive
            mode is unavailable.
        mode: The mode to start in.

    Raises:
        ValueError: If the starting mode has nothing to command.
    """

    def __init__(
        self,
        settings: TeleopSettings | None = None,
        modules: Mapping[str, Sequence[str]] | None = None,
        limbs: Sequence[str] = (),
        drive_target: str | None = None,
        mode: str = JOINT,
    ) -> None:
        self.settings = settings or TeleopSettings()
        self.modules = {slot: tuple(joints) for slot, joints in (modules or {}).items() if joints}
        self.limbs = tuple(limbs)
        self.drive_target = drive_target
        self.deadman = Deadman(self.settings.first_timeout, self.settings.repeat_timeout)
        self.speeds = {name: float(getattr(self.settings, name)) for name in SPEED_NAMES}
        self._module = 0
        self._joint: dict[str, int] = dict.fromkeys(self.modules, 0)
        self._limb = 0
        #: The motion the keys ask for (None: none).
        self._intent: _Motion | None = None
        #: The motion commands went out for (its stop is owed; None: silent).
        self._moving: _Motion | None = None
        self._pending: list[Command] = []
        self._last_move = -math.inf
        self._next_move = -math.inf
        self.stopped_because = ""
        self.note = ""
        self.moves = 0
        self.stops = 0
        #: Modules this teleop may no longer command, and why (a claim taken over).
        self.blocked: dict[str, str] = {}
        why = self.unavailable(mode)
        if why:
            raise ValueError(why)
        self.mode = mode

    # ------------------------------------------------------------------ what there is
    def unavailable(self, mode: str) -> str:
        """Why ``mode`` cannot be used here ("" when it can)."""
        if mode not in MODES:
            return f"unknown mode {mode!r}; modes: {', '.join(MODES)}"
        if mode == JOINT and not self.modules:
            return "joint mode needs a module with joints"
        if mode == IK and not self.limbs:
            return "IK mode needs a limb with a kinematic chain"
        if mode == DRIVE and self.drive_target is None:
            return "drive mode needs wheel modules (a mobile assembly)"
        return ""

    @property
    def module(self) -> str | None:
        """The selected module of joint mode."""
        return list(self.modules)[self._module] if self.modules else None

    @property
    def joint(self) -> str | None:
        """The selected joint of joint mode."""
        module = self.module
        return None if module is None else self.modules[module][self._joint[module]]

    @property
    def limb(self) -> str | None:
        """The selected limb of IK mode."""
        return self.limbs[self._limb] if self.limbs else None

    @property
    def moving(self) -> bool:
        """Whether motion commands are going out (a stop is owed)."""
        return self._moving is not None

    def view(self) -> TeleopView:
        """A snapshot for the screen."""
        return TeleopView(
            mode=self.mode,
            modules=tuple(self.modules),
            module=self.module,
            joint=self.joint,
            limb=self.limb,
            speeds=dict(self.speeds),
            moving=self.moving,
            key=self.deadman.key if self.moving else None,
            repeating=self.deadman.repeating,
            stopped_because=self.stopped_because,
            note=self.note,
            blocked=dict(self.blocked),
            moves=self.moves,
            stops=self.stops,
            held_back=self.blocked_target(),
        )

    # ------------------------------------------------------------------ inputs
    def press(self, key: str, now: float) -> str:
        """One key event (a press or a repeat).

        Returns:
            What it did: ``move``, ``speed``, ``select``, ``mode``, ``stop`` (an unbound key
            or drive mode's ``k``: the motion ends) or ``refused`` (a mode that cannot be
            used; :attr:`note` says why).
        """
        self._expire(now)
        if key in MODE_KEYS:
            return self.set_mode(MODE_KEYS[key], now)
        intent = self._intent_of(key)
        why = self._blocked(intent)
        if why:
            self.note = why
            return "refused"
        if intent is not None:
            if self._intent is not None and not intent.same_target(self._intent):
                self.stop("another target", now)
            self._intent = intent
            self.deadman.event(key, now)
            return "move"
        if self._scale(key):
            return "speed"
        if self._select(key, now):
            return "select"
        # Drive mode's k is its explicit stop; any other unbound key stops all the same.
        self.stop("k" if (self.mode, key) == (DRIVE, DRIVE_STOP) else f"key {key}", now)
        return "stop"

    def set_mode(self, mode: str, now: float) -> str:
        """Switch mode; the motion of the old one stops.

        Returns:
            ``mode``, or ``refused`` when the mode cannot be used (:attr:`note` says why).
        """
        why = self.unavailable(mode)
        if why:
            self.note = why
            return "refused"
        if mode != self.mode:
            self.stop("mode changed", now)
            self.mode = mode
            self.note = f"{mode} mode"
        return "mode"

    def stop(self, reason: str, now: float) -> None:
        """End the motion now: one :class:`Stop` at the next :meth:`tick` if commands went
        out, nothing otherwise. Focus lost, quit, e-stop and the like come in here."""
        self._intent = None
        self.deadman.release()
        if self._moving is not None:
            self._owe_stop(reason)

    def block(self, module: str, reason: str, now: float, why: str = "claim lost") -> None:
        """Command ``module`` no more (its claim was taken over, it was halted, its joint
        manager is gone): a motion that moves it stops (one stop, for ``why``), and its keys
        are refused with ``reason`` until :meth:`unblock`."""
        self.blocked[module] = reason
        moving = self._moving or self._intent
        if moving is not None and self._blocked(moving):
            self.stop(why, now)
        self.note = reason

    def unblock(self, module: str) -> None:
        """Command ``module`` again (its claim is back, it was recovered)."""
        self.blocked.pop(module, None)

    def blocked_target(self) -> str:
        """Why the selected target of the mode cannot be commanded ("" when it can)."""
        if self.mode == JOINT:
            target = self.module
        elif self.mode == IK:
            target = self.limb
        else:
            return next(iter(self.blocked.values()), "")
        return self.blocked.get(target, "") if target is not None else ""

    def _blocked(self, motion: _Motion | None) -> str:
        """Why ``motion`` may not go out ("" when it may): a module it moves is blocked; a
        drive moves the whole robot, so any blocked module blocks it."""
        if motion is None or not self.blocked:
            return ""
        if motion.mode == DRIVE:
            return next(iter(self.blocked.values()))
        return self.blocked.get(motion.target, "")

    def _owe_stop(self, reason: str) -> None:
        moving, self._moving = self._moving, None
        assert moving is not None
        self._pending.append(Stop(moving.mode, moving.target, moving.joint, reason))
        self.stopped_because = reason
        self.stops += 1

    # ------------------------------------------------------------------ time
    def tick(self, now: float) -> list[Command]:
        """The commands due at ``now``: owed stops first, then at most one move.

        Call it whenever :meth:`next_wake` says, and after every :meth:`press`.
        """
        self._expire(now)
        out, self._pending = self._pending, []
        intent = self._intent
        if intent is None:
            return out
        period = self.settings.period
        first = self._moving is None
        if not first and now < self._next_move - _EPS:
            return out
        dt = period if first else min(max(now - self._last_move, 0.0), 2 * period)
        out.append(
            Move(intent.mode, intent.target, intent.joint, self._velocity(intent), dt, first)
        )
        self._moving = intent
        self._last_move = now
        # A strict minimum interval: however late this tick was, the next is a period away.
        self._next_move = now + period
        self.moves += 1
        return out

    def _expire(self, now: float) -> None:
        # Judged before anything else at ``now``: a key arriving after the deadman ran out
        # starts a new motion, it does not rescue the old one from its stop.
        if self._intent is not None and not self.deadman.alive(now):
            self._intent = None
            if self._moving is not None:
                self._owe_stop("deadman")

    def next_wake(self, now: float) -> float | None:
        """When :meth:`tick` has something to do next (None: not until a key comes)."""
        if self._pending:
            return now
        if self._intent is None:
            return None
        expiry = self.deadman.expiry()
        due = now if self._moving is None else self._next_move
        return due if expiry is None else min(due, expiry)

    # ------------------------------------------------------------------ keys
    def _intent_of(self, key: str) -> _Motion | None:
        if self.mode == JOINT and key in JOINT_MOVES and self.module is not None:
            return _Motion(JOINT, self.module, self.joint, (JOINT_MOVES[key],))
        if self.mode == IK and key in IK_MOVES and self.limb is not None:
            return _Motion(IK, self.limb, None, IK_MOVES[key])
        if self.mode == DRIVE and key in DRIVE_MOVES and self.drive_target is not None:
            return _Motion(DRIVE, self.drive_target, None, DRIVE_MOVES[key])
        return None

    def _velocity(self, intent: _Motion) -> tuple[float, ...]:
        s = self.speeds
        d = intent.direction
        if intent.mode == JOINT:
            return (d[0] * s["joint_speed"],)
        if intent.mode == IK:
            return tuple(v * s["tip_speed"] for v in d[:3]) + tuple(
                v * s["tip_turn"] for v in d[3:]
            )
        return (d[0] * s["drive_speed"], d[1] * s["drive_speed"], d[2] * s["drive_turn"])

    def _scale(self, key: str) -> bool:
        if self.mode == DRIVE:
            if key not in DRIVE_SPEED:
                return False
            linear, angular = DRIVE_SPEED[key]
            factors = {"drive_speed": linear, "drive_turn": angular}
        else:
            if key not in SPEED:
                return False
            factors = dict.fromkeys(_MODE_SPEEDS[self.mode], SPEED[key])
        for name, factor in factors.items():
            start = getattr(self.settings, name)
            top = getattr(self.settings, f"max_{name}")
            self.speeds[name] = min(
                max(self.speeds[name] * factor, start * self.settings.min_fraction), top
            )
        self.note = "speed " + ", ".join(f"{n} {self.speeds[n]:.3g}" for n in factors)
        return True

    def _select(self, key: str, now: float) -> bool:
        if self.mode == JOINT and self.modules:
            module = self.module
            assert module is not None
            if key in JOINT_SELECT:
                count = len(self.modules[module])
                self.stop("another joint", now)
                self._joint[module] = (self._joint[module] + JOINT_SELECT[key]) % count
                return True
            if key in MODULE_SELECT:
                self.stop("another module", now)
                self._module = (self._module + MODULE_SELECT[key]) % len(self.modules)
                return True
        if self.mode == IK and self.limbs and key in LIMB_SELECT:
            self.stop("another limb", now)
            self._limb = (self._limb + LIMB_SELECT[key]) % len(self.limbs)
            return True
        return False

    def select(self, module: str, joint: str | None = None, now: float = 0.0) -> None:
        """Select a module (and joint) of joint mode by name (the screen's mouse, tests).

        Raises:
            KeyError: If there is no such module or joint.
        """
        if module not in self.modules:
            raise KeyError(f"no module {module!r}; modules: {', '.join(self.modules)}")
        index = list(self.modules).index(module)
        joint_index = self._joint[module]
        if joint is not None:
            if joint not in self.modules[module]:
                raise KeyError(f"module {module} has no joint {joint!r}")
            joint_index = self.modules[module].index(joint)
        if (index, joint_index) != (self._module, self._joint[module]):
            self.stop("another joint", now)
        self._module = index
        self._joint[module] = joint_index
