"""The gap watch: when a recorded topic was interrupted, for how long, and why (fake time)."""

from __future__ import annotations

from components.data_archiver.gaps import SILENCE_FLOOR_S, Gap, GapWatch

MS = 1_000_000
S = 1_000_000_000
T0 = 1_700_000_000 * S


def stream(watch: GapWatch, topic_id: int, start: int, period: int, count: int) -> int:
    """``count`` samples every ``period`` ns from ``start``; the time of the last."""
    now = start
    for i in range(count):
        now = start + i * period
        assert watch.sample(topic_id, now) is None
    return now


def test_a_steady_topic_with_lost_samples_has_no_gap() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")
    now = stream(watch, 0, T0, 10 * MS, 100)
    # A lossy link: samples missing here and there, well under the floor.
    assert watch.sample(0, now + 60 * MS, lost=5) is None
    assert watch.gaps == []
    assert watch.silent(now + 500 * MS) == []


def test_an_outage_is_one_gap_with_its_times_and_the_samples_it_swallowed() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")
    last = stream(watch, 0, T0, 10 * MS, 100)
    back = last + 7 * S
    gap = watch.sample(0, back, lost=699)
    assert gap == Gap("/limb1/joint_states", last, back, 699, unreachable=False)
    assert gap.seconds() == 7.0
    assert watch.gaps == [gap]
    assert watch.lost_in_gaps() == 699
    assert "silent for 7.0 s, 699 missing" in gap.describe()
    # The outage did not teach the watch that the topic is slow: a second one is seen too.
    last = stream(watch, 0, back, 10 * MS, 50)
    assert watch.sample(0, last + 2 * S) is not None


def test_the_silence_limit_follows_the_topics_own_period() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")  # 100 Hz: the floor
    watch.add_topic(1, "/limb1/health")  # 1 Hz: ten periods
    stream(watch, 0, T0, 10 * MS, 50)
    last = stream(watch, 1, T0, S, 10)
    assert watch.limit_ns(0) == int(SILENCE_FLOOR_S * S)
    assert 9.5 * S < watch.limit_ns(1) < 10.5 * S
    # Five seconds without health is not yet an interruption of a 1 Hz topic...
    assert watch.sample(1, last + 5 * S) is None
    # ...fifteen are.
    assert watch.sample(1, last + 20 * S) is not None


def test_publishers_that_left_the_graph_mark_the_gap_unreachable() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")
    last = stream(watch, 0, T0, 10 * MS, 20)
    watch.publishers(0, present=False)  # the link dropped: their tokens went with it
    watch.publishers(0, present=False)
    (open_gap,) = watch.silent(last + 3 * S)
    assert open_gap.end_ns is None and open_gap.unreachable
    assert "stopped receiving 3.0 s ago" in open_gap.describe(last + 3 * S)
    watch.publishers(0, present=True)
    gap = watch.sample(0, last + 6 * S, lost=None)
    assert gap is not None and gap.unreachable and gap.lost is None
    # The next gap starts afresh: its publishers stayed.
    later = stream(watch, 0, last + 6 * S, 10 * MS, 10)
    gap = watch.sample(0, later + 2 * S)
    assert gap is not None and not gap.unreachable


def test_a_topic_that_never_resumed_is_open_at_the_end() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")
    watch.add_topic(1, "/wheel1/joint_states")
    watch.add_topic(2, "/never")  # added, never a sample: nothing to interrupt
    last = stream(watch, 0, T0, 10 * MS, 20)
    stream(watch, 1, T0, 10 * MS, 20)
    end = stream(watch, 1, last, 10 * MS, 500)
    (silent,) = watch.silent(end)
    assert silent.topic == "/limb1/joint_states" and silent.start_ns == last
    assert silent.as_dict()["end_ns"] is None and silent.as_dict()["seconds"] is None


def test_the_graph_about_an_unknown_topic_is_ignored() -> None:
    watch = GapWatch()
    watch.publishers(7, present=False)
    assert watch.silent(T0) == []


def test_a_pause_is_not_an_interruption() -> None:
    watch = GapWatch()
    watch.add_topic(0, "/limb1/joint_states")
    last = stream(watch, 0, T0, 10 * MS, 20)
    watch.forget()
    assert watch.silent(last + 30 * S) == []
    assert watch.sample(0, last + 30 * S) is None
    assert watch.gaps == []
