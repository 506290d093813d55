"""Operator presence: a module that loses its operators holds its motors by itself.

The joint manager's watchdog stops a command stream that stops; this is the same idea for the
operators themselves. A module's operators are the assembly's ground stations and, while the
module is claimed, its claim holder. Each is seen on the robot through liveliness tokens the
robot's own router already keeps (a station's nodes and its computer's agent; the claim's
token): a cut radio link makes that router drop the far side's tokens after the session
lease (about a second), with no traffic of its own on the radio.

Rules (:class:`OperatorPresence`, pure: events and ``now`` go in, verdicts come out):

* The module is *attended* while at least one operator is visible: one station suffices
  among several, and a visible claim holder suffices alone (an operator at the robot itself,
  with the ground cut off, keeps it going by claiming it: ``msctl teleop`` does).
* Unattended for more than ``timeout`` seconds, the module is *held* (:data:`LOST`).
* The hold lifts by itself the moment any operator is visible again (:data:`BACK`): it is a
  dead-man's hold, like the watchdog's, so a returning operator's commands move the robot
  again. It never lifts a halt someone asked for (that is the joint manager's business:
  halts stay until ``recover``).
* A claim token that vanishes may have been released or cut off; the robot cannot tell the
  two apart, so either way the module is then in the stations' care (and the watchdog
  already stops whatever the vanished holder was driving).
* Start-up: the module starts as if its operators had been seen at :meth:`start`. A ground
  station that comes up a moment after the robot (within ``timeout``) causes no hold, and a
  robot nobody ever watches is held ``timeout`` seconds after it started, not allowed to run
  unwatched. In the field every station's agent is up before anything runs, so the grace is
  seldom used.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

#: :meth:`OperatorPresence.update` verdicts: the module must hold now / may move again.
LOST = "lost"
BACK = "back"


@dataclass(frozen=True)
class Station:
    """A ground station as the robot watches it.

    Attributes:
        name: The station's name (its namespace, ``gc1``).
        host: The computer it runs on (``ground1``).
    """

    name: str
    host: str

    def label(self) -> str:
        """``gc1 (ground1)``: what messages call it."""
        return f"{self.name} ({self.host})"


class OperatorPresence:
    """Whether a module's operators are visible, and when it must hold for their absence.

    Args:
        stations: The assembly's ground stations (may be empty: then only a claim holder
            attends the module).
        timeout: Seconds unattended before the module holds (the template's
            ``[safety] operator_timeout``).

    Raises:
        ValueError: If ``timeout`` is not a positive finite number, or two stations share
            a name.
    """

    def __init__(self, stations: Iterable[Station], timeout: float) -> None:
        if not (isinstance(timeout, int | float) and math.isfinite(timeout) and timeout > 0):
            raise ValueError(f"operator_timeout is {timeout!r}: give a positive number of seconds")
        self.timeout = float(timeout)
        self.stations = tuple(stations)
        names = [s.name for s in self.stations]
        if len(set(names)) != len(names):
            raise ValueError(f"stations are named twice among {names}")
        self._visible: dict[str, bool] = dict.fromkeys(names, False)
        self._holder: str | None = None
        self._started: float | None = None
        # When the last operator vanished (or the start, before any was seen); None while
        # someone is visible.
        self._alone_since: float | None = None
        self._ever_seen = False
        # The claim holder that vanished last, and when: named in the message if it went
        # shortly before the module was left alone (a link cut takes both, in any order).
        self._vanished_holder: str | None = None
        self._vanished_at = -math.inf
        self._left_by: str | None = None
        self._held = False
        self._held_since = 0.0
        self._lifted_at: float | None = None
        self._lifted_after = 0.0
        self._lifted_by = ""
        self.holds = 0

    # ------------------------------------------------------------------ events
    def start(self, now: float) -> None:
        """Start watching (the grace of one ``timeout`` counts from here); idempotent."""
        if self._started is not None:
            return
        self._started = now
        if not self.attended:
            self._alone_since = now

    def on_station(self, name: str, visible: bool, now: float) -> None:
        """Station ``name`` became visible (some node of it is on the graph) or invisible.

        Raises:
            KeyError: If the assembly has no such station.
        """
        if name not in self._visible:
            raise KeyError(f"no station {name!r}; the assembly's: {sorted(self._visible)}")
        self.start(now)
        before = self.attended
        self._visible[name] = visible
        self._changed(before, now)

    def on_holder(self, holder: str | None, now: float) -> None:
        """The module's claim holder changed (``user@host``), or the claim is gone (None)."""
        self.start(now)
        before = self.attended
        if self._holder is not None and holder is None:
            self._vanished_holder, self._vanished_at = self._holder, now
        self._holder = holder
        self._changed(before, now)

    def _changed(self, before: bool, now: float) -> None:
        after = self.attended
        if after:
            self._ever_seen = True
            self._alone_since = None
        elif before:
            self._alone_since = now
            recent = now - self._vanished_at <= self.timeout
            self._left_by = self._vanished_holder if recent else None

    # ------------------------------------------------------------------ verdicts
    @property
    def attended(self) -> bool:
        """Whether some operator is visible now."""
        return self._holder is not None or any(self._visible.values())

    @property
    def held(self) -> bool:
        """Whether the module is held for lost operators (between LOST and BACK)."""
        return self._held

    @property
    def holder(self) -> str | None:
        """The claim holder seen now (``None``: unclaimed, or its claim vanished)."""
        return self._holder

    def visible(self) -> list[str]:
        """The names of the stations visible now."""
        return [name for name, seen in self._visible.items() if seen]

    def alone_for(self, now: float) -> float:
        """Seconds since the last operator vanished (0 while one is visible)."""
        return 0.0 if self._alone_since is None else max(0.0, now - self._alone_since)

    def update(self, now: float) -> str | None:
        """The verdict at ``now``: :data:`LOST` when the module must hold from now on,
        :data:`BACK` when its hold lifts, ``None`` when nothing changes.

        Call it at every tick and after every event.
        """
        self.start(now)
        if self._held:
            if not self.attended:
                return None
            self._held = False
            self._lifted_at = now
            self._lifted_after = now - self._held_since
            self._lifted_by = self._who_is_visible()
            return BACK
        if self._alone_since is None or now - self._alone_since <= self.timeout:
            return None
        self._held = True
        self._held_since = self._alone_since
        self.holds += 1
        return LOST

    def reason(self, now: float) -> str:
        """Why the module holds (or would): for its health and for refused commands."""
        missing = [s.label() for s in self.stations]
        if self._left_by is not None and self._ever_seen:
            missing.insert(0, f"claim holder {self._left_by}")
        names = ", ".join(missing) or "no claim holder"
        alone = self.alone_for(now)
        if not self._ever_seen:
            return f"no operator since start: {names} not seen for {alone:.1f} s"
        return f"no operator: {names} unreachable for {alone:.1f} s"

    def lifted(self, now: float, window: float) -> str | None:
        """What to say in health for ``window`` seconds after a hold lifted, else None."""
        if self._lifted_at is None or self._held or now - self._lifted_at > window:
            return None
        return (
            f"operator back: {self._lifted_by} visible again after {self._lifted_after:.1f} s "
            "without one; presence hold lifted, commands accepted"
        )

    def _who_is_visible(self) -> str:
        if self._holder is not None:
            return f"claim holder {self._holder}"
        by_name = {s.name: s for s in self.stations}
        return ", ".join(by_name[name].label() for name in self.visible())
