"""Alarms: every level change of a row or of one of its items, recorded as its own step.

Computing a row (:meth:`~components.data_monitor.board.HealthBoard.evaluate`) records
nothing by itself; the board hands each row it judged again to :meth:`AlarmRecorder.observe`,
which compares its levels with the last ones seen and records an :class:`Alarm` for each
change.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from components.data_monitor.model import MAX_MESSAGE, MAX_NAME, Row, clip, finite, level_name
from components.messages import OK, Level

#: Alarms kept in memory.
MAX_ALARMS = 1000


@dataclass(frozen=True)
class Alarm:
    """One level change.

    Attributes:
        at: Wall-clock seconds (Unix time) of the change.
        module: Module slot or station name.
        item: Item name, or the module's name for the module's own level.
        before: The level before; ``None`` when the item was first seen at ``after``.
        after: The new level.
        message: The item's message at the change.
    """

    at: float
    module: str
    item: str
    before: Level | None
    after: Level
    message: str

    def to_json(self) -> dict[str, Any]:
        """As stored in the alarm file and printed by ``--json``."""
        return {
            "at": round(self.at, 3),
            "module": self.module,
            "item": self.item,
            "from": level_name(self.before),
            "to": self.after.name,
            "message": self.message,
        }

    @classmethod
    def from_json(cls, data: Any) -> Alarm:
        """An alarm from :meth:`to_json`'s form.

        Raises:
            ValueError: Naming the field that is missing or wrong.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"an alarm is an object, not {type(data).__name__}")
        at = finite(data.get("at"))
        if at is None:
            raise ValueError(f"alarm field 'at' must be a number, not {data.get('at')!r}")
        levels = {level.name: level for level in Level}
        before = data.get("from")
        after = data.get("to")
        if before != "-" and before not in levels:
            raise ValueError(f"alarm field 'from' must be a level name or '-', not {before!r}")
        if after not in levels:
            raise ValueError(f"alarm field 'to' must be a level name, not {after!r}")
        return cls(
            at=at,
            module=clip(data.get("module", ""), MAX_NAME),
            item=clip(data.get("item", ""), MAX_NAME),
            before=None if before == "-" else levels[before],
            after=levels[after],
            message=clip(data.get("message", ""), MAX_MESSAGE),
        )

    def line(self) -> str:
        """One line for ``--watch`` and ``--alarms``: time, module, item, from -> to, message."""
        import time as _time

        stamp = _time.strftime("%H:%M:%S", _time.localtime(self.at))
        millis = int((self.at % 1) * 1000)
        return (
            f"{stamp}.{millis:03d} {self.module} {self.item} "
            f"{level_name(self.before)} -> {self.after.name} {self.message}"
        )


class AlarmRecorder:
    """The last level of every row and item, and the alarms their changes raised (bounded).

    Attributes:
        alarms: Every alarm kept (the last :data:`MAX_ALARMS`), oldest first.
    """

    def __init__(self) -> None:
        self._levels: dict[tuple[str, str], Level] = {}
        self.alarms: deque[Alarm] = deque(maxlen=MAX_ALARMS)
        self._new: list[Alarm] = []

    def observe(self, row: Row, message: str, at: float) -> None:
        """Record the level changes of a row just judged: its items as their source reported
        them (a stale module's items keep theirs), then the row's own level.

        A first "waiting for ..." state raises no alarm, and neither does a row whose only bad
        news is such a state (it has no news yet).

        Args:
            row: The row as judged.
            message: The row's message, as long as it was judged (the row's is clipped).
            at: Wall-clock seconds of the judgement.
        """
        for item in row.items:
            if not item.pending:
                reported = item.level if item.reported is None else item.reported
                self.record(row.name, item.name, reported, item.message, at)
        bad = [i for i in row.items if i.level is not OK]
        if not (bad and all(i.pending for i in bad)):
            self.record(row.name, row.name, row.level, message, at)

    def record(self, row: str, item: str, level: Level, message: str, at: float) -> None:
        """Record an alarm if ``item`` of ``row`` changed level (first seen OK: not news)."""
        key = (row, item)
        before = self._levels.get(key)
        if before is level:
            return
        self._levels[key] = level
        if before is None and level is OK:
            return  # first seen, and fine: not news
        self._add(Alarm(at, row, item, before, level, message))

    def announce(self, row: str, item: str, level: Level, message: str, at: float) -> None:
        """Record an alarm of ``item`` at ``level`` whether or not its level changed (a report
        timed by its sender, such as an agent's rejoin)."""
        key = (row, item)
        alarm = Alarm(at, row, item, self._levels.get(key), level, message)
        self._levels[key] = level
        self._add(alarm)

    def _add(self, alarm: Alarm) -> None:
        self.alarms.append(alarm)
        self._new.append(alarm)

    def take(self) -> list[Alarm]:
        """The alarms recorded since the last call, oldest first."""
        taken, self._new = self._new, []
        return taken

    def merge_history(self, alarms: Iterable[Alarm]) -> int:
        """Add alarms recorded before this recorder started (a data monitor's history).

        Returns:
            How many were new to it.
        """
        known = {(a.at, a.module, a.item, a.after) for a in self.alarms}
        older = [a for a in alarms if (a.at, a.module, a.item, a.after) not in known]
        if not older:
            return 0
        merged = sorted([*older, *self.alarms], key=lambda a: a.at)
        self.alarms = deque(merged[-MAX_ALARMS:], maxlen=MAX_ALARMS)
        return len(older)
