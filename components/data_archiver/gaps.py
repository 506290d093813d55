"""Interruptions of a recording, per topic: when a topic went silent, for how long, why.

A recorder on a ground station hears the robots over a radio: a link that drops for five
seconds leaves a hole in every topic that crossed it. The bag must say so, per topic, with
times, not leave a reader to guess from the timestamps (and a recorder must never claim a
normal recording when it has stopped receiving). :class:`GapWatch` is the pure part of that:
the recorder's writer thread feeds it every sample's receive time, the senders' sequence
numbers say how many samples a gap swallowed, and the graph says whether the topic's
publishers were still reachable meanwhile (a radio link that drops takes their liveliness
tokens with it, after the routers' lease).

What counts as a gap: a topic that was flowing (:data:`FLOWING_SAMPLES` samples at least)
silent for longer than its silence limit, which is :data:`SILENCE_PERIODS` of its own usual
period (learned from the samples), never less than :data:`SILENCE_FLOOR_S`. Losses shorter
than that (a lossy link drops one sample in twenty) are not gaps: the recorder counts them
per topic from the sequence numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Seconds of silence below which a topic is never said to be interrupted: a 100 Hz topic
#: that skips a few samples on a lossy link has lost samples (counted), not stopped.
SILENCE_FLOOR_S = 1.0
#: A topic is interrupted after this many of its usual periods without a sample (a 1 Hz
#: health topic after 10 s, a 100 Hz joint state after the floor).
SILENCE_PERIODS = 10.0
#: Samples a topic must have had before its silence counts: one latched sample, or a
#: topic heard twice, has no rhythm to interrupt.
FLOWING_SAMPLES = 10
#: Weight of a new interval in the running estimate of a topic's period.
_PERIOD_WEIGHT = 0.05


@dataclass(frozen=True)
class Gap:
    """One interruption of one topic.

    Attributes:
        topic: The topic.
        start_ns: Receive time (ns since the epoch) of the last sample before the gap.
        end_ns: Receive time of the first sample after it; ``None``: still silent when the
            recording ended (it never resumed).
        lost: Samples the senders numbered in between (``None``: they do not number them,
            or the publisher restarted).
        unreachable: Whether the topic's publishers left the graph during the gap (their
            computer's link dropped, or they stopped).
    """

    topic: str
    start_ns: int
    end_ns: int | None
    lost: int | None
    unreachable: bool

    def seconds(self, now_ns: int | None = None) -> float:
        """Length of the gap, in seconds (an open one: until ``now_ns``)."""
        end = self.end_ns if self.end_ns is not None else (now_ns or self.start_ns)
        return (end - self.start_ns) / 1e9

    def as_dict(self) -> dict[str, object]:
        """The gap as JSON-ready data (what a bag's metadata and ``--json`` carry)."""
        return {
            "topic": self.topic,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "seconds": round(self.seconds(), 3) if self.end_ns is not None else None,
            "lost": self.lost,
            "unreachable": self.unreachable,
        }

    def describe(self, now_ns: int | None = None) -> str:
        """One line for an operator."""
        why = " (its publishers left the graph: link lost or stopped)" if self.unreachable else ""
        if self.end_ns is None:
            return f"{self.topic}: stopped receiving {self.seconds(now_ns):.1f} s ago{why}"
        lost = f", {self.lost:,} missing" if self.lost else ""
        return f"{self.topic}: silent for {self.seconds():.1f} s{lost}{why}"


class _Topic:
    __slots__ = ("last_ns", "left", "name", "period_ns", "publishers", "samples")

    def __init__(self, name: str) -> None:
        self.name = name
        self.last_ns = 0
        self.period_ns = 0.0  # 0: not known yet (fewer than two samples)
        self.publishers = True  # as far as the graph said
        self.left = False  # the publishers left since the last sample
        self.samples = 0


class GapWatch:
    """The interruptions of every recorded topic (not thread-safe: one writer thread).

    Args:
        floor_s: The shortest silence that counts as a gap.
        periods: Silence, in the topic's usual periods, that counts as a gap.
    """

    def __init__(self, floor_s: float = SILENCE_FLOOR_S, periods: float = SILENCE_PERIODS):
        self._floor_ns = int(floor_s * 1e9)
        self._periods = periods
        self._topics: dict[int, _Topic] = {}
        self.gaps: list[Gap] = []

    def add_topic(self, topic_id: int, name: str) -> None:
        """Watch topic ``topic_id`` (called before its first sample)."""
        self._topics[topic_id] = _Topic(name)

    def limit_ns(self, topic_id: int) -> int:
        """The silence, in ns, after which topic ``topic_id`` counts as interrupted."""
        topic = self._topics[topic_id]
        return max(self._floor_ns, int(topic.period_ns * self._periods))

    def sample(self, topic_id: int, now_ns: int, lost: int | None = 0) -> Gap | None:
        """A sample of ``topic_id`` received at ``now_ns``; the gap it ends, if any.

        Args:
            topic_id: The topic.
            now_ns: Its receive time.
            lost: Samples its sender numbered since its previous one (``None``: unknown).
        """
        topic = self._topics[topic_id]
        topic.samples += 1
        last, topic.last_ns = topic.last_ns, now_ns
        if not last:
            return None
        interval = now_ns - last
        limit = max(self._floor_ns, int(topic.period_ns * self._periods))
        if interval > limit and topic.samples > FLOWING_SAMPLES:
            gap = Gap(topic.name, last, now_ns, lost, topic.left)
            topic.left = False
            self.gaps.append(gap)
            return gap
        topic.left = False
        # The usual period, from the intervals that were not gaps (an outage must not teach
        # the watch that the topic is slow).
        if topic.period_ns:
            topic.period_ns += (interval - topic.period_ns) * _PERIOD_WEIGHT
        else:
            topic.period_ns = float(interval)
        return None

    def publishers(self, topic_id: int, present: bool) -> None:
        """What the graph says now: whether topic ``topic_id`` has a reachable publisher."""
        topic = self._topics.get(topic_id)
        if topic is None:
            return
        if topic.publishers and not present:
            topic.left = True
        topic.publishers = present

    def forget(self) -> None:
        """Forget when each topic was last heard (a paused recording: a pause is not an
        interruption, and the first sample after it starts afresh)."""
        for topic in self._topics.values():
            topic.last_ns = 0
            topic.left = False

    def silent(self, now_ns: int) -> list[Gap]:
        """The gaps open at ``now_ns``: topics that were flowing and are silent past their
        limit (``end_ns`` is ``None``)."""
        found = []
        for topic_id, topic in self._topics.items():
            if (
                topic.samples >= FLOWING_SAMPLES
                and topic.last_ns
                and now_ns - topic.last_ns > self.limit_ns(topic_id)
            ):
                found.append(
                    Gap(topic.name, topic.last_ns, None, None, topic.left or not topic.publishers)
                )
        return found

    def lost_in_gaps(self) -> int:
        """Samples the closed gaps swallowed (those whose count is known)."""
        return sum(g.lost for g in self.gaps if g.lost)
