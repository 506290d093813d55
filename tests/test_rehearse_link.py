"""The link emulator's Core (:mod:`msctl.rehearse.link`) with fake time, and its profiles.

Statistical checks use a fixed seed, so they are deterministic; their tolerances are still
derived from the standard deviation of the estimate (:func:`sd_bernoulli`, ...) and set at
five of them or more, so that any other seed passes too (a 5-sigma miss is a 1-in-1.7-million
event for a normal estimate).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from msctl.errors import InputError, NotFoundError
from msctl.rehearse.link import Link, LinkDirection
from msctl.rehearse.link_profile import (
    DEFAULT_QUEUE_MS,
    DirectionProfile,
    GilbertElliott,
    LinkProfile,
    ProfileError,
)
from msctl.rehearse.profiles import PROFILES_ENV, find_profile, load_profiles

SIGMAS = 5.0


def sd_bernoulli(p: float, n: int) -> float:
    """Standard deviation of the loss fraction of ``n`` independent trials."""
    return math.sqrt(p * (1 - p) / n)


def sd_markov(model: GilbertElliott, n: int) -> float:
    """Standard deviation of the loss fraction of ``n`` packets of a Gilbert model.

    With every bad packet lost and no good one, the loss indicator is a two-state Markov
    chain whose second eigenvalue is ``lam = 1 - p - r``; the variance of its mean over ``n``
    steps is about ``pi (1 - pi) / n * (1 + lam) / (1 - lam)``.
    """
    pi = model.bad_share
    lam = 1 - model.p - model.r
    return math.sqrt(pi * (1 - pi) / n * (1 + lam) / (1 - lam))


def offers(direction: LinkDirection, count: int, size: int, step: float, start: float = 0.0):
    """Offer ``count`` packets of ``size`` bytes, one every ``step`` seconds: (now, leave)."""
    return [(start + i * step, direction.offer(size, start + i * step)) for i in range(count)]


# --------------------------------------------------------------------------- delay, jitter
def test_delay_with_jitter_stays_within_the_asked_bounds_and_in_order() -> None:
    profile = DirectionProfile(delay_ms=30, jitter_ms=20)
    # Sparse offers (100 ms apart, more than the jitter span): no packet is held back.
    sparse = LinkDirection(profile, seed=1)
    added = [leave - now for now, leave in offers(sparse, 10_000, 100, 0.1)]
    assert min(added) >= 0.010 - 1e-12 and max(added) <= 0.050 + 1e-12
    # Uniform on [10, 50] ms: sd 20/sqrt(3) ms per packet.
    tolerance = SIGMAS * 0.020 / math.sqrt(3) / math.sqrt(len(added))
    assert abs(sum(added) / len(added) - 0.030) < tolerance
    assert abs(sparse.mean_delay - 0.030) < tolerance
    assert sparse.delayed == sparse.delivered == 10_000
    # Dense offers (1 ms apart): a packet never overtakes the one before it, and since the
    # one before left by its own bound, the bounds still hold.
    dense = LinkDirection(profile, seed=2)
    result = offers(dense, 10_000, 100, 0.001)
    leaves = [leave for _, leave in result]
    assert leaves == sorted(leaves)
    assert all(0.010 - 1e-12 <= leave - now <= 0.050 + 1e-12 for now, leave in result)
    # Holding back raises the mean above the asked 30 ms, and status says so.
    assert dense.mean_delay > 0.030


def test_jitter_wider_than_the_delay_never_gives_a_negative_delay() -> None:
    direction = LinkDirection(DirectionProfile(delay_ms=2, jitter_ms=5), seed=3)
    for now, leave in offers(direction, 5000, 100, 0.05):
        assert leave >= now


def test_no_impairment_leaves_at_once_and_counts_nothing_delayed() -> None:
    direction = LinkDirection(DirectionProfile(), seed=0)
    assert all(leave == now for now, leave in offers(direction, 100, 1400, 0.001))
    assert direction.delayed == 0 and direction.delivered == 100
    assert direction.bytes == direction.delivered_bytes == 140_000


# --------------------------------------------------------------------------- loss
def test_bernoulli_loss_fraction_is_the_asked_one() -> None:
    n = 200_000
    direction = LinkDirection(DirectionProfile(loss=0.01), seed=4)
    lost = sum(leave is None for _, leave in offers(direction, n, 100, 0.0001))
    assert direction.dropped["loss"] == lost
    assert abs(lost / n - 0.01) < SIGMAS * sd_bernoulli(0.01, n)
    assert direction.loss_fraction == lost / n
    # Independent losses: runs geometric with mean 1 / (1 - p), sd sqrt(p) / (1 - p).
    runs = lost / direction.mean_burst
    assert abs(direction.mean_burst - 1 / 0.99) < SIGMAS * math.sqrt(0.01) / 0.99 / math.sqrt(runs)


def test_gilbert_elliott_from_mean_loss_and_burst() -> None:
    model = GilbertElliott.from_mean(0.05, 4)
    assert model.r == pytest.approx(0.25)
    assert model.p == pytest.approx(0.25 * 0.05 / 0.95)
    assert model.mean_loss == pytest.approx(0.05)
    n = 200_000
    direction = LinkDirection(DirectionProfile(loss=0.05, burst=4), seed=5)
    result = offers(direction, n, 100, 0.0001)
    lost = [leave is None for _, leave in result]
    assert abs(sum(lost) / n - 0.05) < SIGMAS * sd_markov(model, n)
    # Burst lengths are geometric with mean 1 / r: sd sqrt(1 - r) / r per burst.
    bursts = sum(1 for i, x in enumerate(lost) if x and (i == 0 or not lost[i - 1]))
    mean_burst = sum(lost) / bursts
    assert abs(mean_burst - 4) < SIGMAS * math.sqrt(1 - model.r) / model.r / math.sqrt(bursts)
    assert direction.mean_burst == pytest.approx(mean_burst)
    # Bursty, unlike independent loss of the same mean (bursts of 1 / 0.95 = 1.05).
    assert mean_burst > 3


def test_gilbert_elliott_given_directly_with_loss_in_both_states() -> None:
    model = GilbertElliott(p=0.02, r=0.1, loss_good=0.01, loss_bad=0.5)
    expected = (0.1 / 0.12) * 0.01 + (0.02 / 0.12) * 0.5
    assert model.mean_loss == pytest.approx(expected)
    n = 200_000
    direction = LinkDirection(DirectionProfile(gilbert_elliott=model), seed=6)
    offers(direction, n, 100, 0.0001)
    # Loose bound: at most the variance of a chain that loses every bad packet, times the
    # largest state loss, plus the per-packet coin (sd_bernoulli).
    bound = SIGMAS * (
        math.sqrt(model.bad_share * (1 - model.bad_share) / n * (2 - 0.12) / 0.12)
        + sd_bernoulli(expected, n)
    )
    assert abs(direction.loss_fraction - expected) < bound


def test_gilbert_elliott_rules() -> None:
    with pytest.raises(ProfileError, match="burst must be at least loss / \\(1 - loss\\)"):
        GilbertElliott.from_mean(0.8, 1.5)
    with pytest.raises(ProfileError, match=r"gilbert_elliott.r must be greater than 0"):
        GilbertElliott(p=0.1, r=0)
    with pytest.raises(ProfileError, match=r"burst must be at least 1, got 0.5"):
        DirectionProfile(loss=0.1, burst=0.5)


# --------------------------------------------------------------------------- rate, queue
def test_token_bucket_back_to_back_leaves_at_the_asked_rate() -> None:
    # 1000 kbit/s = 125 000 bytes/s; the bucket (1500 bytes) passes at once.
    direction = LinkDirection(DirectionProfile(rate_kbit=1000, queue_ms=100_000), seed=0)
    leaves = [direction.offer(1000, 0.0) for _ in range(1000)]
    assert leaves[0] == 0.0 and leaves[1] == pytest.approx(500 / 125_000)
    assert leaves[-1] == pytest.approx((1000 * 1000 - 1500) / 125_000)
    assert direction.queued_bytes(0.0) == 1000 * 1000 - 1500
    assert direction.queued_bytes(leaves[-1]) == 0


def test_token_bucket_output_rate_under_overload_is_the_asked_rate() -> None:
    # 8 Mb/s offered into a 1 Mb/s link for 20 s: the queue overflows, the output is 1 Mb/s.
    direction = LinkDirection(DirectionProfile(rate_kbit=1000, delay_ms=10, queue_ms=100), seed=0)
    result = offers(direction, 20_000, 1000, 0.001)
    leaves = [leave for _, leave in result if leave is not None]
    assert direction.dropped["queue"] > 0
    assert direction.dropped["queue"] + direction.delivered == 20_000
    # Steady state: bytes delivered after the first over the time between first and last.
    rate_bps = (len(leaves) - 1) * 1000 * 8 / (leaves[-1] - leaves[0])
    assert rate_bps == pytest.approx(1_000_000, rel=0.001)
    # Nobody waited longer than the limit: delay 10 ms + queue 100 ms.
    assert all(leave - now <= 0.110 + 1e-9 for now, leave in result if leave is not None)


def test_a_packet_that_would_wait_longer_than_the_queue_limit_is_dropped() -> None:
    # 1000-byte packets all at t=0 into 125 000 bytes/s with a 1500-byte bucket: packet k
    # waits (1000 k - 500) / 125 000 s, within 100 ms for k <= 13.
    direction = LinkDirection(DirectionProfile(rate_kbit=1000, queue_ms=100), seed=0)
    result = [direction.offer(1000, 0.0) for _ in range(20)]
    assert [leave is not None for leave in result] == [True] * 14 + [False] * 6
    assert direction.dropped == {"loss": 0, "outage": 0, "queue": 6}
    # The queue drains: later, packets pass again.
    assert direction.offer(1000, 1.0) == 1.0


def test_queue_limit_in_bytes() -> None:
    # Backlog 500 bytes after the second packet, 1500 after the third ...: 4000 bytes hold
    # the first five (backlog + size <= 4000 up to 3500 + ... see below).
    direction = LinkDirection(DirectionProfile(rate_kbit=1000, queue_bytes=4000), seed=0)
    passed = [direction.offer(1000, 0.0) is not None for _ in range(10)]
    # Backlog before packet k is max(0, 1000 k - 1500): k passes while that + 1000 <= 4000.
    expected = [max(0, 1000 * k - 1500) + 1000 <= 4000 for k in range(10)]
    assert passed == expected and passed.count(True) == 5
    assert direction.profile.queue_limit_ms is None  # a byte limit alone: no time limit


def test_a_new_rate_drains_the_backlog_and_keeps_the_refill_so_far() -> None:
    direction = LinkDirection(DirectionProfile(rate_kbit=1000, queue_ms=10_000), seed=0)
    assert direction.offer(1000, 0.0) == 0.0  # bucket 1500 -> 500
    # 1 s later the bucket is full again, whatever the new profile says.
    direction.set_profile(DirectionProfile(rate_kbit=8000, queue_ms=10_000), 1.0)
    assert direction.offer(1500, 1.0) == 1.0
    # A backlog of 100 000 bytes at 1 000 000 bytes/s (8000 kbit/s): 0.1 s.
    for _ in range(100):
        direction.offer(1000, 1.0)
    assert direction.queued_bytes(1.0) == 100_000
    direction.set_profile(DirectionProfile(rate_kbit=800, queue_ms=10_000), 1.05)
    # Half drained at the old rate, the rest at 100 000 bytes/s.
    assert direction.queued_bytes(1.05) == 50_000
    assert direction.offer(1, 1.05) == pytest.approx(1.05 + 50_001 / 100_000)


def test_the_default_queue_limit_applies_when_none_is_given() -> None:
    direction = LinkDirection(DirectionProfile(rate_kbit=100), seed=0)
    assert direction.profile.queue_limit_ms == DEFAULT_QUEUE_MS
    # 12 500 bytes/s: a packet waiting more than 200 ms (2500 bytes of backlog) is dropped.
    results = [direction.offer(500, 0.0) for _ in range(20)]
    assert all(leave <= 0.2 + 1e-9 for leave in results if leave is not None)
    assert direction.dropped["queue"] > 0


# --------------------------------------------------------------------------- outages
def test_scripted_outage_for_a_time_and_until_up() -> None:
    direction = LinkDirection(DirectionProfile(delay_ms=5), seed=0)
    assert direction.offer(100, 0.0) == pytest.approx(0.005)
    direction.down(1.0, 2.0)
    outage = direction.outage(1.5)
    assert outage is not None and (outage.since, outage.until, outage.cause) == (
        1.0,
        3.0,
        "scripted",
    )
    assert direction.offer(100, 1.5) is None and direction.offer(100, 2.99) is None
    assert direction.offer(100, 3.0) == pytest.approx(3.005)
    assert direction.outage(3.0) is None
    direction.down(4.0)
    assert direction.offer(100, 1000.0) is None
    assert direction.outage(1000.0).until is None  # type: ignore[union-attr]
    direction.up(1001.0)
    assert direction.offer(100, 1001.0) is not None
    assert direction.dropped == {"loss": 0, "outage": 3, "queue": 0}
    assert direction.packets == 6 and direction.delivered == 3
    with pytest.raises(ValueError, match="more than 0 seconds"):
        direction.down(1002.0, 0)


def test_random_outages_take_the_asked_share_of_time() -> None:
    mean_up, mean_down = 1.0, 0.25
    direction = LinkDirection(DirectionProfile(mean_up_s=mean_up, mean_down_s=mean_down), seed=7)
    step, horizon = 0.05, 5000.0
    down = 0
    outages: dict[float, float] = {}
    samples = int(horizon / step)
    for i in range(samples):
        outage = direction.outage(i * step)
        if outage is not None:
            down += 1
            assert outage.cause == "random" and outage.until is not None
            outages[outage.since] = outage.until
    share = mean_down / (mean_up + mean_down)
    cycles = horizon / (mean_up + mean_down)
    # Renewal-reward estimate of the down share over n cycles: by the delta method its sd
    # is sqrt((1 - f)^2 md^2 + f^2 mu^2) / (mu + md) / sqrt(n).
    sd = math.sqrt((1 - share) ** 2 * mean_down**2 + share**2 * mean_up**2) / (
        (mean_up + mean_down) * math.sqrt(cycles)
    )
    assert abs(down / samples - share) < SIGMAS * sd + step / (mean_up + mean_down)
    # Outage lengths are exponential: sd of their mean is mean_down / sqrt(count); those
    # shorter than a sampling step are missed, so the bound allows half a step more.
    lengths = [until - since for since, until in outages.items()]
    assert len(lengths) > 0.8 * cycles
    mean_length = sum(lengths) / len(lengths)
    assert abs(mean_length - mean_down) < SIGMAS * mean_down / math.sqrt(len(lengths)) + step / 2
    # A packet offered during one is dropped as an outage (the same seed: the same times).
    since, until = next(iter(outages.items()))
    fresh = LinkDirection(DirectionProfile(mean_up_s=mean_up, mean_down_s=mean_down), seed=7)
    assert fresh.offer(100, (since + until) / 2) is None
    assert fresh.dropped["outage"] == 1


def test_both_directions_of_a_link_go_down_together() -> None:
    # Different packet figures each way, the same outage figures.
    profile = LinkProfile(
        "flaky",
        up=DirectionProfile(mean_up_s=2, mean_down_s=0.5, loss=0.1),
        down=DirectionProfile(mean_up_s=2, mean_down_s=0.5),
    )
    link = Link(profile, seed=9)
    for i in range(20_000):
        now = i * 0.01
        up, down = link.up.outage(now), link.down.outage(now)
        assert (up is None) == (down is None)
        link.up.offer(100, now)  # packets do not shift the outage times
    link.take_down(300.0, 1.0)
    assert link.up.offer(100, 300.5) is None and link.down.offer(100, 300.5) is None
    link.bring_up(300.6)
    assert link.up.outage(300.6) is None and link.down.outage(300.6) is None


def test_up_ends_a_random_outage_too() -> None:
    direction = LinkDirection(DirectionProfile(mean_up_s=1, mean_down_s=1000), seed=1)
    now = 0.0
    while direction.outage(now) is None:
        now += 0.1
    direction.up(now)
    assert direction.outage(now) is None
    assert direction.offer(100, now) == now


# --------------------------------------------------------------------------- replay, changes
def field_wifi() -> DirectionProfile:
    return find_profile(load_profiles(), "field-wifi").up


def test_the_same_seed_and_offers_replay_the_same_outcome() -> None:
    profile = field_wifi()

    def run(seed: int) -> list[float | None]:
        direction = LinkDirection(profile, seed=seed)
        return [leave for _, leave in offers(direction, 20_000, 700, 0.002)]

    first = run(11)
    assert run(11) == first
    assert run(12) != first
    assert any(leave is None for leave in first) and any(leave is not None for leave in first)


def test_set_profile_keeps_counters_and_applies_the_new_figures() -> None:
    direction = LinkDirection(DirectionProfile(delay_ms=50), seed=0)
    offers(direction, 100, 100, 0.1)
    direction.down(10.0, 1.0)
    assert direction.offer(100, 10.5) is None
    direction.set_profile(DirectionProfile(loss=1.0), 10.6)
    assert direction.packets == 101 and direction.delivered == 100
    assert direction.dropped == {"loss": 0, "outage": 1, "queue": 0}
    assert direction.outage(10.7) is not None  # a scripted outage outlives a profile change
    assert direction.offer(100, 12.0) is None
    assert direction.dropped["loss"] == 1
    # The applied figures start again with each profile, the counters do not.
    assert direction.loss_fraction == 1.0
    direction.set_profile(DirectionProfile(delay_ms=20), 13.0)
    assert direction.loss_fraction == 0.0 and direction.mean_delay == 0.0
    assert direction.offer(100, 13.0) == pytest.approx(13.02)
    assert direction.mean_delay == pytest.approx(0.02)
    assert direction.delivered == 101 and direction.delayed == 101
    assert direction.status(14.0)["applied"]["for_s"] == pytest.approx(1.0)


def test_status_is_json_and_compares_asked_with_applied() -> None:
    direction = LinkDirection(field_wifi(), seed=3)
    offers(direction, 5000, 500, 0.001)
    status = direction.status(5.0)
    json.dumps(status)
    assert status["packets"] == 5000
    assert status["delivered"] + sum(status["dropped"].values()) == 5000
    assert status["asked"]["delay_ms"] == 30 and status["asked"]["mean_loss"] == pytest.approx(0.05)
    assert status["asked"]["gilbert_elliott"]["r"] == pytest.approx(0.25)
    assert status["applied"]["mean_delay_ms"] >= 10
    assert 0 <= status["applied"]["loss_fraction"] < 0.2
    direction.discard(500)
    assert direction.status(5.0)["dropped"]["queue"] == status["dropped"]["queue"] + 1


# --------------------------------------------------------------------------- profiles
def test_every_builtin_profile_loads_with_its_documented_figures() -> None:
    profiles = load_profiles(None)
    assert list(profiles)[:5] == ["lan", "wifi", "field-wifi", "cellular", "earth-moon"]
    for profile in profiles.values():
        assert profile.description
        Link(profile, seed=0).up.offer(1000, 0.0)
    lan = profiles["lan"]
    assert lan.up == lan.down == DirectionProfile()
    wifi = profiles["wifi"].up
    assert (wifi.delay_ms, wifi.jitter_ms, wifi.loss, wifi.loss_model) == (3, 2, 0.01, None)
    field = profiles["field-wifi"].down
    assert field.mean_loss == pytest.approx(0.05) and field.loss_model.r == pytest.approx(0.25)  # type: ignore[union-attr]
    assert (field.rate_kbit, field.mean_up_s, field.mean_down_s) == (4000, 60, 1.5)
    cellular = profiles["cellular"]
    assert (cellular.up.rate_kbit, cellular.down.rate_kbit) == (5000, 20000)
    moon = profiles["earth-moon"].up
    assert moon.delay_ms == 1280 and moon.rate_kbit == 256
    # The queue holds a round trip's worth of bytes at the link's rate.
    bdp_bytes = 256_000 / 8 * 2 * 1.28
    assert moon.queue_limit_ms / 1000 * 256_000 / 8 >= bdp_bytes  # type: ignore[operator]


def write(tmp_path: Path, text: str, name: str = "links.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_bad_value_names_the_file_profile_field_and_rule(tmp_path: Path) -> None:
    path = write(tmp_path, "[x]\nloss = 2\n")
    with pytest.raises(InputError) as caught:
        load_profiles(path)
    assert str(caught.value) == f"{path}: profile 'x': loss must be between 0 and 1, got 2"
    path = write(tmp_path, "[x]\nup.rate_kbit = -5\n")
    with pytest.raises(
        InputError, match=r"profile 'x': up.rate_kbit must be greater than 0, got -5"
    ):
        load_profiles(path)
    path = write(tmp_path, '[x]\ndelay_ms = "soon"\n')
    with pytest.raises(InputError, match="profile 'x': delay_ms must be a number, got 'soon'"):
        load_profiles(path)
    path = write(tmp_path, "[x]\nmean_up_s = 10\n")
    with pytest.raises(InputError, match="mean_up_s needs mean_down_s too"):
        load_profiles(path)
    path = write(tmp_path, "[x]\ngilbert_elliott = { p = 0.1, r = 2 }\n")
    with pytest.raises(InputError, match=r"'x': gilbert_elliott.r must be between 0 and 1, got 2"):
        load_profiles(path)
    path = write(tmp_path, "[x]\nloss = 0.1\ngilbert_elliott = { p = 0.1, r = 0.5 }\n")
    with pytest.raises(InputError, match="loss cannot be given with gilbert_elliott"):
        load_profiles(path)


def test_unknown_fields_are_refused_with_a_did_you_mean(tmp_path: Path) -> None:
    path = write(tmp_path, "[x]\ndelay = 3\n")
    with pytest.raises(InputError, match=r"profile 'x': unknown field 'delay' \(did you mean "):
        load_profiles(path)
    path = write(tmp_path, "[x]\ndown.jiter_ms = 3\n")
    with pytest.raises(
        InputError, match=r"unknown field 'down.jiter_ms' .did you mean 'down.jitter_ms'"
    ):
        load_profiles(path)
    path = write(tmp_path, "[x]\ngilbert_elliott = { p = 0.1, r = 0.5, los_bad = 1 }\n")
    with pytest.raises(InputError, match=r"did you mean 'gilbert_elliott.loss_bad'"):
        load_profiles(path)
    path = write(tmp_path, "x = 3\n")
    with pytest.raises(InputError, match="profile 'x' must be a table, got 3"):
        load_profiles(path)


def test_bases_resolve_and_unknown_bases_are_named(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        '[slow-wifi]\nbase = "wifi"\nrate_kbit = 500\n\n'
        '[slower]\nbase = "slow-wifi"\ndescription = "slower still"\nup.rate_kbit = 100\n',
    )
    profiles = load_profiles(path)
    slow, slower = profiles["slow-wifi"], profiles["slower"]
    assert slow.up.delay_ms == 3 and slow.up.loss == 0.01 and slow.up.rate_kbit == 500
    assert slow.description == profiles["wifi"].description
    assert (slower.up.rate_kbit, slower.down.rate_kbit) == (100, 500)
    assert slower.description == "slower still"
    path = write(tmp_path, '[x]\nbase = "wfi"\n')
    with pytest.raises(
        InputError,
        match=r"profile 'x': base must be a known profile, got 'wfi' \(did you mean 'wifi'",
    ):
        load_profiles(path)
    path = write(tmp_path, '[x]\nbase = "y"\n[y]\nbase = "x"\n')
    with pytest.raises(InputError, match="must not lead back to itself"):
        load_profiles(path)
    # A burst given over a Gilbert-Elliott base replaces the base's loss model.
    path = write(
        tmp_path,
        "[ge]\ngilbert_elliott = { p = 0.01, r = 0.5 }\n[mean]\n"
        'base = "ge"\nloss = 0.1\nburst = 2\n',
    )
    assert load_profiles(path)["mean"].up.loss_model.r == pytest.approx(0.5)  # type: ignore[union-attr]


def test_a_user_file_adds_and_replaces_profiles(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = write(
        tmp_path,
        '[wifi]\nbase = "wifi"\nloss = 0.2\n\n[lan]\ndelay_ms = 1\n\n[mine]\nrate_kbit = 64\n',
    )
    profiles = load_profiles(path)
    assert list(profiles) == [
        "lan",
        "wifi",
        "field-wifi",
        "cellular",
        "earth-moon",
        "degraded",
        "mine",
    ]
    # Its own name as base: the built-in it replaces, then changed.
    assert profiles["wifi"].up.loss == 0.2 and profiles["wifi"].up.delay_ms == 3
    assert profiles["lan"].up.delay_ms == 1
    assert profiles["mine"].down.rate_kbit == 64
    # The environment names the file when none is given.
    monkeypatch.setenv(PROFILES_ENV, str(path))
    assert load_profiles()["mine"].up.rate_kbit == 64
    monkeypatch.setenv(PROFILES_ENV, str(tmp_path / "missing.toml"))
    with pytest.raises(NotFoundError, match=f"missing.toml \\(from \\${PROFILES_ENV}\\): no such"):
        load_profiles()
    monkeypatch.delenv(PROFILES_ENV)
    bad = write(tmp_path, "[x\n", "bad.toml")
    with pytest.raises(InputError, match=r"bad.toml: not valid TOML"):
        load_profiles(bad)


def test_find_profile_names_the_known_ones() -> None:
    profiles = load_profiles()
    assert find_profile(profiles, "wifi").name == "wifi"
    with pytest.raises(
        NotFoundError,
        match=r"no link profile 'feld-wifi' \(did you mean 'field-wifi'\?\); profiles: lan, wifi",
    ):
        find_profile(profiles, "feld-wifi")
