"""What a radio link is asked to do: the profile of each direction, validated when built.

A :class:`LinkProfile` names one :class:`DirectionProfile` per direction; a direction's
bursty loss is a :class:`GilbertElliott` model. These are plain values: the link's Core
(:mod:`msctl.rehearse.link`) applies them, :mod:`msctl.rehearse.profiles` reads them from
TOML. A value that breaks a rule raises :class:`ProfileError` naming the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

#: The queue limit of a rate-limited direction that gives neither ``queue_ms`` nor
#: ``queue_bytes``: about what a Wi-Fi access point's queue holds at a few Mb/s.
DEFAULT_QUEUE_MS = 200.0

#: The default token bucket: one full-size Ethernet frame passes without waiting.
DEFAULT_BUCKET_BYTES = 1500


class ProfileError(ValueError):
    """A profile value that breaks a rule.

    Attributes:
        field: The field at fault (``loss``, ``gilbert_elliott.p`` ...).
        rule: What the value must be (``must be between 0 and 1``).
        value: The value given.
    """

    def __init__(self, field: str, rule: str, value: object):
        super().__init__(f"{field} {rule}, got {value!r}")
        self.field = field
        self.rule = rule
        self.value = value


def _number(name: str, value: object, low: float | None = None, high: float | None = None) -> None:
    """Check that ``value`` is a real number in ``[low, high]`` (either bound optional)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ProfileError(name, "must be a number", value)
    if low is not None and high is not None and not low <= value <= high:
        raise ProfileError(name, f"must be between {low:g} and {high:g}", value)
    if low is not None and value < low:
        raise ProfileError(name, f"must be at least {low:g}", value)
    if high is not None and value > high:
        raise ProfileError(name, f"must be at most {high:g}", value)


def _positive(name: str, value: object) -> None:
    _number(name, value)
    if value <= 0:  # type: ignore[operator]
        raise ProfileError(name, "must be greater than 0", value)


@dataclass(frozen=True)
class GilbertElliott:
    """The two-state Gilbert-Elliott loss model, stepped once per packet.

    The link is either *good* or *bad*; a packet is lost with probability ``loss_good`` or
    ``loss_bad`` in that state, then the state changes (good -> bad with probability ``p``,
    bad -> good with ``r``). The stationary share of bad packets is ``p / (p + r)``.

    Attributes:
        p: P(good -> bad) per packet.
        r: P(bad -> good) per packet.
        loss_good: Loss probability in the good state.
        loss_bad: Loss probability in the bad state.
    """

    p: float
    r: float
    loss_good: float = 0.0
    loss_bad: float = 1.0

    def __post_init__(self) -> None:
        _number("gilbert_elliott.p", self.p, 0, 1)
        _number("gilbert_elliott.r", self.r, 0, 1)
        if self.r == 0:
            raise ProfileError("gilbert_elliott.r", "must be greater than 0", self.r)
        _number("gilbert_elliott.loss_good", self.loss_good, 0, 1)
        _number("gilbert_elliott.loss_bad", self.loss_bad, 0, 1)

    @classmethod
    def from_mean(cls, loss: float, burst: float) -> GilbertElliott:
        """The model with a mean loss fraction and a mean loss burst length.

        Every packet is lost in the bad state and none in the good one (the Gilbert model),
        so a burst is a stay in the bad state, geometric with mean ``1 / r``, and the loss
        fraction is the share of bad packets ``p / (p + r)``. Hence::

            r = 1 / burst
            p = r * loss / (1 - loss)

        Args:
            loss: Mean loss fraction, ``0 <= loss < 1``.
            burst: Mean burst length in packets, ``>= 1`` and ``>= loss / (1 - loss)``
                (else ``p`` would exceed 1).

        Raises:
            ProfileError: For a value out of range, naming ``loss`` or ``burst``.
        """
        _number("loss", loss, 0, 1)
        if loss >= 1:
            raise ProfileError("loss", "must be below 1 with a burst length", loss)
        _number("burst", burst, 1)
        r = 1.0 / burst
        p = r * loss / (1.0 - loss)
        if p > 1:
            raise ProfileError(
                "burst", f"must be at least loss / (1 - loss) = {loss / (1 - loss):g}", burst
            )
        return cls(p=p, r=r)

    @property
    def bad_share(self) -> float:
        """The stationary probability of the bad state, ``p / (p + r)``."""
        return self.p / (self.p + self.r)

    @property
    def mean_loss(self) -> float:
        """The long-run loss fraction."""
        bad = self.bad_share
        return (1 - bad) * self.loss_good + bad * self.loss_bad


@dataclass(frozen=True)
class DirectionProfile:
    """How one direction of a link behaves. Validated when built.

    Attributes:
        delay_ms: Added one-way delay.
        jitter_ms: Half-width of the uniform jitter added to ``delay_ms`` (total never < 0).
        loss: Mean loss fraction. Independent per packet unless ``burst`` is given.
        burst: Mean loss burst length in packets: makes the loss a Gilbert-Elliott model
            derived by :meth:`GilbertElliott.from_mean`.
        gilbert_elliott: The Gilbert-Elliott model given directly (then ``loss`` is 0 and
            ``burst`` is None).
        rate_kbit: Token-bucket rate in kbit/s (1000 bit/s); None: unlimited.
        bucket_bytes: Token-bucket size: bytes that may pass at once after a quiet time.
        queue_ms: Longest wait in the queue before the rate limit; None with ``queue_bytes``
            None means :data:`DEFAULT_QUEUE_MS`.
        queue_bytes: Largest backlog of the queue, in bytes; None: no byte limit.
        mean_up_s: Mean time between random outages (exponential); None: no random outages.
        mean_down_s: Mean length of a random outage (exponential).
    """

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    burst: float | None = None
    gilbert_elliott: GilbertElliott | None = None
    rate_kbit: float | None = None
    bucket_bytes: int = DEFAULT_BUCKET_BYTES
    queue_ms: float | None = None
    queue_bytes: int | None = None
    mean_up_s: float | None = None
    mean_down_s: float | None = None

    def __post_init__(self) -> None:
        _number("delay_ms", self.delay_ms, 0)
        _number("jitter_ms", self.jitter_ms, 0)
        _number("loss", self.loss, 0, 1)
        if self.burst is not None:
            GilbertElliott.from_mean(self.loss, self.burst)
        if self.gilbert_elliott is not None:
            if not isinstance(self.gilbert_elliott, GilbertElliott):
                raise ProfileError("gilbert_elliott", "must be a table", self.gilbert_elliott)
            if self.burst is not None:
                raise ProfileError("burst", "cannot be given with gilbert_elliott", self.burst)
            if self.loss:
                raise ProfileError("loss", "cannot be given with gilbert_elliott", self.loss)
        if self.rate_kbit is not None:
            _positive("rate_kbit", self.rate_kbit)
        if isinstance(self.bucket_bytes, bool) or not isinstance(self.bucket_bytes, int):
            raise ProfileError("bucket_bytes", "must be a whole number of bytes", self.bucket_bytes)
        if self.bucket_bytes < 1:
            raise ProfileError("bucket_bytes", "must be at least 1", self.bucket_bytes)
        if self.queue_ms is not None:
            _number("queue_ms", self.queue_ms, 0)
        if self.queue_bytes is not None:
            if isinstance(self.queue_bytes, bool) or not isinstance(self.queue_bytes, int):
                raise ProfileError(
                    "queue_bytes", "must be a whole number of bytes", self.queue_bytes
                )
            if self.queue_bytes < 1:
                raise ProfileError("queue_bytes", "must be at least 1", self.queue_bytes)
        if (self.mean_up_s is None) != (self.mean_down_s is None):
            given, missing = (
                ("mean_up_s", "mean_down_s")
                if self.mean_down_s is None
                else ("mean_down_s", "mean_up_s")
            )
            raise ProfileError(given, f"needs {missing} too (random outages need both)", None)
        if self.mean_up_s is not None:
            _positive("mean_up_s", self.mean_up_s)
            _positive("mean_down_s", self.mean_down_s)

    @property
    def loss_model(self) -> GilbertElliott | None:
        """The Gilbert-Elliott model of this direction, or None for independent loss."""
        if self.gilbert_elliott is not None:
            return self.gilbert_elliott
        if self.burst is not None:
            return GilbertElliott.from_mean(self.loss, self.burst)
        return None

    @property
    def mean_loss(self) -> float:
        """The long-run loss fraction asked (of the packets that reach the loss stage)."""
        model = self.loss_model
        return model.mean_loss if model is not None else self.loss

    @property
    def queue_limit_ms(self) -> float | None:
        """The queue's time limit in force (the default when no limit is given)."""
        if self.queue_ms is None and self.queue_bytes is None:
            return DEFAULT_QUEUE_MS
        return self.queue_ms

    def asked(self) -> dict[str, Any]:
        """The figures asked, JSON-ready, for ``status`` to show beside the applied ones."""
        out: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self)}
        model = self.loss_model
        out["gilbert_elliott"] = (
            None
            if model is None
            else {
                "p": model.p,
                "r": model.r,
                "loss_good": model.loss_good,
                "loss_bad": model.loss_bad,
            }
        )
        out["mean_loss"] = self.mean_loss
        if self.rate_kbit is not None:
            out["queue_ms"] = self.queue_limit_ms
        return out


@dataclass(frozen=True)
class LinkProfile:
    """A named link profile: one :class:`DirectionProfile` per direction.

    Attributes:
        name: The profile's name (``wifi``).
        up: Computer -> access point.
        down: Access point -> computer.
        description: What the profile stands for.
    """

    name: str
    up: DirectionProfile = field(default_factory=DirectionProfile)
    down: DirectionProfile = field(default_factory=DirectionProfile)
    description: str = ""
