"""The human operator's relay and its deadman. Pure: no I/O, time passed in.

Each route (:mod:`~components.human_operator.routes`) is a stream of commands from a screen.
A command that moves something (a Twist that is not zero; a ``joint_set`` with a velocity
other than 0, or a position target other than the last one) keeps the stream *moving*; one
that does not (a zero Twist, a hold) ends it. While a stream moves, a silence longer than
``deadman_timeout`` ends it here: exactly one stop goes out (a zero Twist; velocity 0 for the
joints driven by velocity and the last target again for the others, so they hold where they
were sent), then nothing until the screen sends again. So motion stops even when the screen
itself cannot send its stop (it froze, its computer slept, its link dropped), and a silent
stream never becomes a stream of zeros fighting other operators.

The same one stop goes out when the screen that drove a stream lets go of it (it detached,
its claim was taken over) and when the component stops.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from components.config import require
from components.executor.core import Core
from components.human_operator.routes import DRIVE, Route
from components.messages import (
    OK,
    TWIST,
    JointSample,
    diagnostic_array,
    diagnostic_status,
    joint_samples,
    joint_state_batches,
    msg,
)

#: A position target this close to the last one is the same target (a hold), not motion.
SAME_TARGET = 1e-9
#: Longest deadman the data may ask for: beyond it a frozen screen lets the robot run on.
MAX_DEADMAN = 2.0


@dataclass(frozen=True)
class HumanOperatorConfig:
    """The human operator's parameters (station data: ``params.human_operator``).

    Attributes:
        deadman_timeout: Seconds of silence after which a moving stream gets its one stop.
            Above the screen's command period (``msctl teleop --rate``: 20 per second), with
            room for a busy link; at most :data:`MAX_DEADMAN`.
        status_period: Seconds between two status reports on the station's ``diagnostics``.
    """

    deadman_timeout: float = 0.3
    status_period: float = 1.0

    def __post_init__(self) -> None:
        require(self, positive=("deadman_timeout", "status_period"))
        if self.deadman_timeout > MAX_DEADMAN:
            raise ValueError(
                f"HumanOperatorConfig.deadman_timeout must be at most {MAX_DEADMAN} s, not "
                f"{self.deadman_timeout}: longer, a frozen screen lets the robot run on"
            )


def twist(vx: float = 0.0, vy: float = 0.0, wz: float = 0.0) -> Any:
    """A planar ``geometry_msgs/msg/Twist``."""
    return msg(
        TWIST,
        linear=msg("geometry_msgs/msg/Vector3", x=float(vx), y=float(vy), z=0.0),
        angular=msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=float(wz)),
    )


def twist_moves(message: Any) -> bool:
    """Whether a Twist asks for any motion (NaN counts: it is not a stop)."""
    values = (
        message.linear.x,
        message.linear.y,
        message.linear.z,
        message.angular.x,
        message.angular.y,
        message.angular.z,
    )
    return any(v != 0.0 or math.isnan(v) for v in values)


@dataclass
class Stream:
    """One route's state.

    Attributes:
        route: The route.
        moving: Its last command moved something.
        last_at: When its last command was relayed.
        holds: Joint -> the command that stops it, for the joints the motion drives.
        targets: Joint -> the last position target relayed (a repeat of it is a hold).
        relayed: Commands relayed.
        deadman_stops: Stops this relay sent because the stream went silent.
        ended_stops: Stops sent because its screen let go (or the component stopped).
    """

    route: Route
    moving: bool = False
    last_at: float = -math.inf
    holds: dict[str, JointSample] = field(default_factory=dict)
    targets: dict[str, float] = field(default_factory=dict)
    relayed: int = 0
    deadman_stops: int = 0
    ended_stops: int = 0


class HumanOperatorCore(Core):
    """Relays commands route by route, with the second deadman.

    Args:
        name: The component's name (``gc1/human_operator``).
        routes: What it relays.
        config: Its parameters.
        hardware_id: The station's computer (on its status).
    """

    def __init__(
        self,
        name: str,
        routes: Sequence[Route],
        config: HumanOperatorConfig | None = None,
        hardware_id: str = "",
    ) -> None:
        super().__init__(name)
        self.config = config or HumanOperatorConfig()
        self.hardware_id = hardware_id
        self.streams: dict[str, Stream] = {r.target: Stream(r) for r in routes}
        #: Attached screens: holder (``user@host``) -> the modules held for it.
        self.operators: dict[str, tuple[str, ...]] = {}
        self._next_status = 0.0

    # ------------------------------------------------------------------ relaying
    def on_relay(self, target: str, message: Any, now: float) -> None:
        """Forward one command from an attached screen to ``target``."""
        stream = self.streams[target]
        self.publish(target, message)
        stream.relayed += 1
        stream.last_at = now
        if stream.route.kind == DRIVE:
            stream.moving = twist_moves(message)
            return
        moving = False
        for sample in joint_samples(message):
            if sample.velocity is not None and sample.velocity != 0.0:
                moving = True
                stream.holds[sample.name] = JointSample(sample.name, None, 0.0, None)
            elif sample.position is not None:
                last = stream.targets.get(sample.name)
                if last is None or abs(sample.position - last) > SAME_TARGET:
                    moving = True
                stream.targets[sample.name] = sample.position
                stream.holds[sample.name] = JointSample(sample.name, sample.position, None, None)
        stream.moving = moving
        if not moving:
            stream.holds.clear()

    def tick(self, now: float) -> None:
        """The deadman: one stop for each moving stream silent longer than the timeout."""
        for stream in self.streams.values():
            if stream.moving and now - stream.last_at > self.config.deadman_timeout:
                self._stop(stream, now)
                stream.deadman_stops += 1
        if now >= self._next_status:
            self._next_status = now + self.config.status_period
            self.publish("diagnostics", self.status(now))

    def end(self, modules: Iterable[str], now: float) -> list[str]:
        """The screen driving ``modules`` let go of them: one stop for each moving stream
        that touches them; returns the targets stopped."""
        gone = set(modules)
        stopped = []
        for stream in self.streams.values():
            if stream.moving and gone & set(stream.route.modules):
                self._stop(stream, now)
                stream.ended_stops += 1
                stopped.append(stream.route.target)
        return stopped

    def _stop(self, stream: Stream, now: float) -> None:
        if stream.route.kind == DRIVE:
            self.publish(stream.route.target, twist())
        elif stream.holds:
            # One message (two only for a module driven by velocity and position at once).
            for message in joint_state_batches(stream.holds.values(), self.stamp(now)):
                self.publish(stream.route.target, message)
        stream.moving = False
        stream.holds.clear()

    def stop(self, now: float) -> None:
        """The component stops: whatever moves gets its one stop."""
        for stream in self.streams.values():
            if stream.moving:
                self._stop(stream, now)
                stream.ended_stops += 1

    # ------------------------------------------------------------------ status
    def on_operators(self, operators: Mapping[str, Sequence[str]], now: float) -> None:
        """Who is attached now (posted by the desk), for the status."""
        del now
        self.operators = {holder: tuple(modules) for holder, modules in operators.items()}

    def status(self, now: float) -> Any:
        """Its status: who is attached, what moves, what it relayed and stopped."""
        moving = [s.route.target for s in self.streams.values() if s.moving]
        if self.operators:
            message = "; ".join(
                f"{holder} holds {', '.join(modules) or 'nothing'}"
                for holder, modules in sorted(self.operators.items())
            )
        else:
            message = "no operator attached"
        deadman = sum(s.deadman_stops for s in self.streams.values())
        values = {
            "operators": len(self.operators),
            "moving": ", ".join(moving) or "nothing",
            "relayed": sum(s.relayed for s in self.streams.values()),
            "deadman_stops": deadman,
            "ended_stops": sum(s.ended_stops for s in self.streams.values()),
            "deadman_timeout": f"{self.config.deadman_timeout:g}",
        }
        status = diagnostic_status(self.name, OK, message, self.hardware_id, values)
        return diagnostic_array([status], self.stamp(now))
