"""Quality of service, as ROS 2 states it and as rmw_zenoh writes it into liveliness tokens.

Token form (rmw_zenoh, Jazzy):
``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:``
``<liveliness>,<lease s>,<ns>``
where every field equal to rmw_zenoh's baseline (reliable, volatile, keep-last 42, infinite
durations, automatic liveliness) is left empty. Enum values are the rmw ones: reliability
1 reliable / 2 best effort; durability 1 transient local / 2 volatile; history 1 keep last /
2 keep all.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

Reliability = Literal["reliable", "best_effort"]
Durability = Literal["volatile", "transient_local"]
History = Literal["keep_last", "keep_all"]

_RELIABILITY = {"reliable": 1, "best_effort": 2}
_DURABILITY = {"transient_local": 1, "volatile": 2}
_HISTORY = {"keep_last": 1, "keep_all": 2}
_BASELINE_DEPTH = 42


class _QoSFields(NamedTuple):
    reliability: Reliability
    durability: Durability
    history: History
    depth: int


class QoS(_QoSFields):
    """A topic's quality of service (the subset msctl honours).

    Attributes:
        reliability: ``reliable`` (resend, never drop on our side) or ``best_effort``.
        durability: ``transient_local`` keeps the last ``depth`` samples for late subscribers.
        history: ``keep_last`` (bounded by ``depth``) or ``keep_all``.
        depth: Queue depth for ``keep_last``.
    """

    # A named tuple checked as it is made (not a dataclass: see components.comm.graph).
    __slots__ = ()

    def __new__(
        cls,
        reliability: Reliability = "reliable",
        durability: Durability = "volatile",
        history: History = "keep_last",
        depth: int = 10,
    ) -> QoS:
        if reliability not in _RELIABILITY:
            raise ValueError(f"reliability must be one of {list(_RELIABILITY)}")
        if durability not in _DURABILITY:
            raise ValueError(f"durability must be one of {list(_DURABILITY)}")
        if history not in _HISTORY:
            raise ValueError(f"history must be one of {list(_HISTORY)}")
        if history == "keep_last" and depth < 1:
            raise ValueError("depth must be at least 1 for keep_last")
        return super().__new__(cls, reliability, durability, history, depth)

    @property
    def latched(self) -> bool:
        """Whether late subscribers get the last samples (transient local)."""
        return self.durability == "transient_local"

    def encode(self) -> str:
        """The QoS field of an rmw_zenoh liveliness token."""
        reliability = "" if self.reliability == "reliable" else str(_RELIABILITY[self.reliability])
        durability = "" if self.durability == "volatile" else str(_DURABILITY[self.durability])
        history = "" if self.history == "keep_last" else str(_HISTORY[self.history])
        depth = ""
        if self.history == "keep_last" and self.depth != _BASELINE_DEPTH:
            depth = str(self.depth)
        return f"{reliability}:{durability}:{history},{depth}:,:,:,,"

    @classmethod
    def decode(cls, text: str) -> QoS:
        """Parse the QoS field of a token (ours or another rmw_zenoh implementation's).

        Raises:
            ValueError: If the text is not in the token form.
        """
        parts = text.split(":")
        if len(parts) != 6:
            raise ValueError(f"malformed QoS {text!r}: expected 6 ':'-separated fields")
        reliability = {"": "reliable", "0": "reliable", "1": "reliable", "2": "best_effort"}.get(
            parts[0], "reliable"
        )
        durability = {"1": "transient_local"}.get(parts[1], "volatile")
        history_kind, _, depth_text = parts[2].partition(",")
        history = "keep_all" if history_kind == "2" else "keep_last"
        depth = int(depth_text) if depth_text else _BASELINE_DEPTH
        return cls(reliability, durability, history, max(depth, 1))  # type: ignore[arg-type]


#: Sensor streams: newest wins, never block the sender.
SENSOR = QoS(reliability="best_effort", depth=5)
#: Latched state (robot description, plans): a late subscriber gets the last one.
LATCHED = QoS(durability="transient_local", depth=1)
