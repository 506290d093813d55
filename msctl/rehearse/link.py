"""The radio link between one computer and the access point, as a pure Core.

A :class:`LinkDirection` decides, for each packet offered to it, when the packet leaves the
link or that it is dropped, and why. It owns no clock (``now`` in seconds is passed in, from
any monotonic origin) and no I/O; its randomness is a seeded :class:`random.Random`, so the
same seed and the same offers give the same outcome and a run can be replayed. A
:class:`Link` is the two directions of one computer's link (``up``: computer -> access point,
``down``: access point -> computer), changed together.

A packet goes through these stages, in order:

1. **Outage.** While the link is down (scripted with :meth:`LinkDirection.down`, or a random
   on/off process with exponential up and down times) every packet is dropped (``outage``).
   The decision is taken when the packet enters: a packet already in flight still arrives.
2. **Loss.** Independent (Bernoulli) loss with probability ``loss``, or bursty
   Gilbert-Elliott loss (:class:`~msctl.rehearse.link_profile.GilbertElliott`) when a mean
   burst length is given or the model's parameters are (``loss``). Loss comes before the
   rate limit, so the loss fraction is exactly the one asked whatever the load.
3. **Rate.** A token bucket of ``rate_kbit`` (1000 bit/s units) holding at most
   ``bucket_bytes``, with a FIFO queue in front: a packet waits until the bucket holds its
   size (tokens may go negative: that debt is the queue's backlog). A packet that would wait
   longer than ``queue_ms``, or would make the backlog exceed ``queue_bytes``, is dropped
   (``queue``). The wait (the packet's serialization behind the ones before it) adds to its
   delay.
4. **Delay.** ``delay_ms`` plus a jitter drawn uniformly from ``[-jitter_ms, +jitter_ms]``,
   the sum clamped at zero (so when ``jitter_ms > delay_ms`` the mean is a little above
   ``delay_ms``). Packets stay in order, as Wi-Fi's link-layer retransmissions keep them: a
   packet never leaves before the one offered before it,
   ``leave = max(now + wait + delay + jitter, previous leave)``.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

from msctl.rehearse.link_profile import DirectionProfile, LinkProfile

#: Why a packet was dropped; the keys of :attr:`LinkDirection.dropped`.
DROP_REASONS = ("loss", "outage", "queue")


@dataclass(frozen=True)
class Outage:
    """An outage in force.

    Attributes:
        since: When it began (the caller's clock, seconds).
        until: When it ends, or None until :meth:`LinkDirection.up`.
        cause: ``scripted``, ``random`` or ``scripted+random``.
    """

    since: float
    until: float | None
    cause: str

    def as_dict(self, now: float | None = None) -> dict[str, Any]:
        """JSON-ready; with ``now``, also how long it has lasted and how long is left."""
        out: dict[str, Any] = {"since": self.since, "until": self.until, "cause": self.cause}
        if now is not None:
            out["down_for_s"] = now - self.since
            out["left_s"] = None if self.until is None else max(0.0, self.until - now)
        return out


@dataclass(slots=True)
class _Applied:
    """What a direction did since its profile was set: the figures to compare with it."""

    since: float
    reached: int = 0  # packets that reached the loss stage (offered while up)
    lost: int = 0
    bursts: int = 0
    delivered: int = 0
    delay_sum: float = 0.0
    delay_max: float = 0.0


class LinkDirection:
    """One direction of a link: offered packets, when they leave or why they are dropped.

    The counters run from the start; the applied figures (:attr:`mean_delay`,
    :attr:`loss_fraction`, :attr:`mean_burst`) cover the packets offered since the profile
    in force was set, so that they compare with what it asks.

    Attributes:
        profile: The profile in force.
        packets: Packets offered.
        bytes: Bytes offered.
        delivered: Packets let through.
        delivered_bytes: Bytes let through.
        dropped: Packets dropped, by reason (:data:`DROP_REASONS`).
        delayed: Packets let through with any added delay (leaving later than offered).
    """

    def __init__(
        self,
        profile: DirectionProfile,
        seed: int | str = 0,
        now: float = 0.0,
        outage_seed: int | str | None = None,
    ):
        """Start the direction at ``now``, up, with a full token bucket.

        Args:
            profile: How it behaves.
            seed: Seeds the packet decisions.
            now: The caller's clock, seconds.
            outage_seed: Seeds the random outages, apart from the packets so that outage
                times do not depend on the traffic (two directions seeded alike have theirs
                at the same times); None: derived from ``seed``.
        """
        self.profile = profile
        self._rng = random.Random(f"{seed}:packets")
        self._outage_rng = random.Random(
            f"{seed}:outages" if outage_seed is None else f"{outage_seed}:outages"
        )
        self._bad = False
        self._rate: float | None = None
        self._now = now
        self.packets = 0
        self.bytes = 0
        self.delivered = 0
        self.delivered_bytes = 0
        self.dropped = dict.fromkeys(DROP_REASONS, 0)
        self.delayed = 0
        self._applied = _Applied(since=now)
        self._in_burst = False
        self._last_leave = -math.inf
        # Scripted outage: [since, until or None] while down.
        self._scripted: tuple[float, float | None] | None = None
        # Random outages: state, since when, and when it changes next (None: not in use).
        self._random_down = False
        self._random_since = now
        self._random_next: float | None = None
        self._apply(profile, now, keep_state=False)

    # ------------------------------------------------------------------ profile
    def set_profile(self, profile: DirectionProfile, now: float) -> None:
        """Change the profile of a running direction; counters, queue and outages carry on.

        The token bucket keeps its level (capped at the new bucket size); the loss model
        keeps its state when it stays bursty; random outages start a new up period unless
        one is in force and the new profile has them too (then it ends as it would have).

        Args:
            profile: The new profile.
            now: The caller's clock, seconds.
        """
        now = self._tick(now)
        self._apply(profile, now, keep_state=True)
        self._applied = _Applied(since=now)
        self._in_burst = False

    def _apply(self, profile: DirectionProfile, now: float, keep_state: bool) -> None:
        old_rate = self._rate if keep_state else None
        old_model = self.profile.loss_model if keep_state else None
        if old_rate is not None:
            # The bucket fills at the old rate up to now (a backlog drains at the new one).
            self._tokens = min(self._bucket, self._tokens + (now - self._tokens_at) * old_rate)
        self.profile = profile
        self._delay = profile.delay_ms / 1000.0
        self._jitter = profile.jitter_ms / 1000.0
        self._loss = profile.loss
        self._model = profile.loss_model
        if self._model is None:
            self._bad = False
        elif old_model is None:
            # Start from the stationary distribution, so a short run is not biased.
            self._bad = self._rng.random() < self._model.bad_share
        self._rate = None if profile.rate_kbit is None else profile.rate_kbit * 1000.0 / 8.0
        self._bucket = float(profile.bucket_bytes)
        limit_ms = profile.queue_limit_ms
        self._queue_s = math.inf if limit_ms is None else limit_ms / 1000.0
        self._queue_bytes = math.inf if profile.queue_bytes is None else profile.queue_bytes
        if not keep_state or old_rate is None:
            self._tokens = self._bucket
        else:
            self._tokens = min(self._tokens, self._bucket)
        self._tokens_at = now
        if profile.mean_up_s is None:
            self._random_down = False
            self._random_next = None
        elif not (keep_state and self._random_down):
            self._random_down = False
            self._random_since = now
            self._random_next = now + self._outage_rng.expovariate(1.0 / profile.mean_up_s)

    # ------------------------------------------------------------------ outages
    def down(self, now: float, seconds: float | None = None) -> None:
        """Take the direction down: every packet offered is dropped until it is up again.

        Args:
            now: The caller's clock, seconds.
            seconds: How long; None: until :meth:`up`.

        Raises:
            ValueError: For ``seconds`` not greater than 0.
        """
        if seconds is not None and not seconds > 0:
            raise ValueError(f"an outage lasts more than 0 seconds, got {seconds!r}")
        now = self._tick(now)
        since = self._scripted[0] if self._scripted is not None else now
        self._scripted = (since, None if seconds is None else now + seconds)

    def up(self, now: float) -> None:
        """End any outage now, scripted or random (random outages then start a new up period).

        Args:
            now: The caller's clock, seconds.
        """
        now = self._tick(now)
        self._scripted = None
        if self._random_down:
            self._random_down = False
            self._random_since = now
            self._random_next = now + self._outage_rng.expovariate(1.0 / self.profile.mean_up_s)

    def outage(self, now: float) -> Outage | None:
        """The outage in force at ``now``, or None when the direction is up."""
        now = self._tick(now)
        scripted = self._scripted
        if scripted is None and not self._random_down:
            return None
        if scripted is None:
            return Outage(self._random_since, self._random_next, "random")
        if not self._random_down:
            return Outage(scripted[0], scripted[1], "scripted")
        until = scripted[1]
        if until is not None and self._random_next is not None:
            until = max(until, self._random_next)
        return Outage(min(scripted[0], self._random_since), until, "scripted+random")

    def _tick(self, now: float) -> float:
        """Advance the outage state to ``now``; time never runs backwards inside."""
        if now < self._now:
            now = self._now
        self._now = now
        scripted = self._scripted
        if scripted is not None and scripted[1] is not None and now >= scripted[1]:
            self._scripted = None
        nxt = self._random_next
        while nxt is not None and now >= nxt:
            self._random_down = not self._random_down
            self._random_since = nxt
            mean = self.profile.mean_down_s if self._random_down else self.profile.mean_up_s
            nxt = nxt + self._outage_rng.expovariate(1.0 / mean)  # type: ignore[operator]
            self._random_next = nxt
        return now

    # ------------------------------------------------------------------ packets
    def offer(self, size_bytes: int, now: float) -> float | None:
        """Offer one packet: when it leaves the link, or None if it is dropped.

        Args:
            size_bytes: The packet's size (the whole IP packet).
            now: The caller's clock, seconds; earlier than a previous call counts as that
                previous time.

        Returns:
            The time the packet leaves (``>= now``), or None when dropped (counted in
            :attr:`dropped` under its reason).
        """
        now = self._tick(now)
        self.packets += 1
        self.bytes += size_bytes
        if self._scripted is not None or self._random_down:
            self.dropped["outage"] += 1
            return None
        applied = self._applied
        applied.reached += 1
        if self._lose():
            self.dropped["loss"] += 1
            applied.lost += 1
            if not self._in_burst:
                self._in_burst = True
                applied.bursts += 1
            return None
        self._in_burst = False
        leave = now
        rate = self._rate
        if rate is not None:
            tokens = self._tokens + (now - self._tokens_at) * rate
            if tokens > self._bucket:
                tokens = self._bucket
            self._tokens_at = now
            wait = (size_bytes - tokens) / rate if tokens < size_bytes else 0.0
            backlog = -tokens if tokens < 0 else 0.0
            if wait > self._queue_s or backlog + size_bytes > self._queue_bytes:
                self._tokens = tokens
                self.dropped["queue"] += 1
                return None
            self._tokens = tokens - size_bytes
            leave += wait
        if self._jitter:
            leave += max(0.0, self._delay + self._rng.uniform(-self._jitter, self._jitter))
        else:
            leave += self._delay
        if leave < self._last_leave:
            leave = self._last_leave
        self._last_leave = leave
        self.delivered += 1
        self.delivered_bytes += size_bytes
        applied.delivered += 1
        added = leave - now
        if added > 0:
            self.delayed += 1
            applied.delay_sum += added
            if added > applied.delay_max:
                applied.delay_max = added
        return leave

    def _lose(self) -> bool:
        model = self._model
        if model is None:
            return self._loss > 0 and self._rng.random() < self._loss
        rng = self._rng
        lost = rng.random() < (model.loss_bad if self._bad else model.loss_good)
        if self._bad:
            if rng.random() < model.r:
                self._bad = False
        elif rng.random() < model.p:
            self._bad = True
        return lost

    def discard(self, size_bytes: int, reason: str = "queue") -> None:
        """Count a packet this direction let through as dropped after all.

        For the emulator, when the receiving device refuses a packet the link delivered
        (its queue is full): the counters then say what the receiver saw. The applied
        figures, which describe the link's own decisions, are not changed.

        Args:
            size_bytes: The packet's size.
            reason: One of :data:`DROP_REASONS`.
        """
        if reason not in self.dropped:
            raise ValueError(f"unknown drop reason {reason!r}; reasons: {', '.join(DROP_REASONS)}")
        self.delivered -= 1
        self.delivered_bytes -= size_bytes
        self.dropped[reason] += 1

    # ------------------------------------------------------------------ figures
    def queued_bytes(self, now: float) -> int:
        """Bytes waiting in the queue before the rate limit at ``now``."""
        if self._rate is None:
            return 0
        now = max(now, self._now)
        tokens = self._tokens + (now - self._tokens_at) * self._rate
        return round(-tokens) if tokens < 0 else 0

    @property
    def mean_delay(self) -> float:
        """Mean delay added to the packets let through since the profile was set, seconds
        (0 before any)."""
        applied = self._applied
        return applied.delay_sum / applied.delivered if applied.delivered else 0.0

    @property
    def loss_fraction(self) -> float:
        """Packets lost (``loss``) over the packets that reached the loss stage (offered
        while up) since the profile was set (0 before any)."""
        applied = self._applied
        return applied.lost / applied.reached if applied.reached else 0.0

    @property
    def mean_burst(self) -> float:
        """Mean length of a run of consecutive ``loss`` drops since the profile was set,
        packets (0 before any)."""
        applied = self._applied
        return applied.lost / applied.bursts if applied.bursts else 0.0

    def status(self, now: float) -> dict[str, Any]:
        """The counters, the figures asked and the figures applied, JSON-ready."""
        outage = self.outage(now)
        return {
            "packets": self.packets,
            "bytes": self.bytes,
            "delivered": self.delivered,
            "delivered_bytes": self.delivered_bytes,
            "dropped": dict(self.dropped),
            "delayed": self.delayed,
            "queued_bytes": self.queued_bytes(now),
            "outage": None if outage is None else outage.as_dict(now),
            "asked": self.profile.asked(),
            "applied": {
                "for_s": now - self._applied.since,
                "packets": self._applied.reached,
                "delivered": self._applied.delivered,
                "mean_delay_ms": self.mean_delay * 1000.0,
                "max_delay_ms": self._applied.delay_max * 1000.0,
                "loss_fraction": self.loss_fraction,
                "mean_burst": self.mean_burst,
            },
        }


class Link:
    """The two directions of one computer's link to the access point.

    Both directions' random outages are seeded alike, so with the same outage figures they
    go down and up together, as a radio does.

    Attributes:
        profile: The profile in force.
        up: Computer -> access point.
        down: Access point -> computer.
    """

    def __init__(self, profile: LinkProfile, seed: int | str = 0, now: float = 0.0):
        """Start the link at ``now``.

        Args:
            profile: How it behaves.
            seed: Seeds both directions (their packet decisions apart).
            now: The caller's clock, seconds.
        """
        self.profile = profile
        self.up = LinkDirection(profile.up, seed=f"{seed}:up", now=now, outage_seed=seed)
        self.down = LinkDirection(profile.down, seed=f"{seed}:down", now=now, outage_seed=seed)

    def set_profile(self, profile: LinkProfile, now: float) -> None:
        """Change both directions' profiles; counters carry on."""
        self.profile = profile
        self.up.set_profile(profile.up, now)
        self.down.set_profile(profile.down, now)

    def take_down(self, now: float, seconds: float | None = None) -> None:
        """Take both directions down (see :meth:`LinkDirection.down`)."""
        self.up.down(now, seconds)
        self.down.down(now, seconds)

    def bring_up(self, now: float) -> None:
        """End any outage in both directions (see :meth:`LinkDirection.up`)."""
        self.up.up(now)
        self.down.up(now)
