"""Property-based tests of the operator commands that run against a live assembly (issue 32,
"What to build" 4): ``record``, ``health`` and ``teleop``, the groups
test_properties_tools and test_net_properties leave out.

Hypothesis throws malformed topic names and regexes, sizes, durations, rates, deadman
timeouts, modes and module names at the real ``msctl`` entry point in this process, with a
resolved dragon assembly in a private MSCTL_HOME and the plane pointed at a loopback port
nothing listens on: every example either fails on its input (exit 2, one ``error:`` line) or,
valid in every way, at "no Zenoh router reachable" (exit 3) before any screen or bag is
opened. The contract: never exit 70, never a traceback, a failure said, nothing written (no
bag directory, MSCTL_HOME unchanged). The valid paths with a live assembly are the business
of test_record*, test_health* and test_teleop*.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_properties_tools import NAMES, keeps_the_contract, msctl, snapshot

pytestmark = pytest.mark.timeout(600)

#: Examples per group: enough to find the classes of bad input, few enough for seconds.
EXAMPLES = {"record": 40, "health": 30, "teleop": 30}


def _settings(group: str) -> settings:
    return settings(
        max_examples=EXAMPLES[group],
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )


@pytest.fixture(scope="module")
def resolved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A resolved dragon assembly, written once (copied into each example's home)."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    folder = tmp_path_factory.mktemp("resolved")
    write_resolution(folder / "assembly", resolve("dragon", {}))
    return folder / "assembly"


@pytest.fixture
def home(tmp_path: Path, resolved: Path) -> Iterator[Path]:
    """A private MSCTL_HOME holding dragon's lock, and a plane nothing answers on."""
    import shutil

    from conftest import free_port

    home = tmp_path / "home"
    shutil.copytree(resolved, home / "assembly")
    env = {
        "MSCTL_HOME": str(home),
        "COLUMNS": "200",
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    with mock.patch.dict(os.environ, env):
        os.environ.pop("MSCTL_DEBUG", None)
        yield home


#: Numbers as typed: usable, zero, negative, not finite, not numbers.
NUMBERS = st.one_of(
    st.sampled_from(["0", "1", "0.2", "-1", "-0.0", "nan", "inf", "-inf", "1e309", "x", ""]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
)
#: Regular expressions: usable ones and broken ones.
REGEXES = st.one_of(
    st.sampled_from(["", ".*", "/limb1/.*", "(", "[", "*", "a{2,1}", "(?P<x", "\\", "\x00"]),
    st.text(max_size=8),
)
SIZES = st.one_of(
    st.sampled_from(["0", "100M", "2G", "1k", "-1", "1.5M", "M", "10Q", "", "nan", "99999999999T"]),
    st.text(max_size=6),
)


# --------------------------------------------------------------------------- record
@_settings("record")
@given(
    topics=st.lists(NAMES, max_size=3),
    regex=REGEXES,
    exclude=REGEXES,
    size=SIZES,
    duration=NUMBERS,
    compression=st.sampled_from(["zstd", "none", "lz4", "", "ZSTD"]),
)
def test_record_takes_any_selection_and_limits_without_an_internal_error(
    home: Path,
    topics: list[str],
    regex: str,
    exclude: str,
    size: str,
    duration: str,
    compression: str,
) -> None:
    bag = home.parent / "bag"
    before = snapshot(home)
    args = ("record", *topics, "-e", regex, "-x", exclude, "-b", size, "-d", duration)
    args += ("--compression", compression, "-o", str(bag))
    # "--" keeps a generated topic that starts with '-' a topic, as an operator would type it.
    code, _, stderr = msctl(*args[len(topics) + 1 :], "--", *topics) if topics else msctl(*args)
    keeps_the_contract(code, stderr, args)
    assert code != 0, (args, "recorded with no router")
    assert not bag.exists() and snapshot(home) == before, args


# --------------------------------------------------------------------------- health
@_settings("health")
@given(
    how=st.sampled_from([("--once",), ("--watch",), ("--alarms",), ("--once", "--json")]),
    timeout=NUMBERS,
    duration=NUMBERS,
)
def test_health_takes_any_bound_without_an_internal_error(
    home: Path, how: tuple[str, ...], timeout: str, duration: str
) -> None:
    before = snapshot(home)
    args = ("health", *how, "--timeout", timeout, "--for", duration)
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)
    if code != 0:
        assert snapshot(home) == before, args


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--timeout", "nan"), ("--timeout", "inf"), ("--for", "nan"), ("--for", "inf")],
)
def test_health_refuses_bounds_that_are_no_number_of_seconds(
    home: Path, flag: str, value: str
) -> None:
    """Found by the property above: `health --once --timeout nan` was an internal error
    (exit 70, 'cannot convert float NaN to integer'); nan passed the `<= 0` check."""
    code, _, stderr = msctl("health", "--once", flag, value)
    assert code == 2, stderr
    assert stderr.startswith(f"error: {flag} must be") and f"not {value}" in stderr, stderr


def test_a_watch_that_never_connected_leaves_the_last_session_alone(home: Path) -> None:
    """Found by the property above: `health --watch` with no router recorded an empty
    session (and said "watching") before it connected, and `health --alarms` then showed
    that empty session instead of the one before it."""
    import json

    from components.data_monitor.alarms import Alarm
    from components.messages import Level
    from msctl.health.alarms import AlarmLog, alarm_path

    AlarmLog("dragon", "msctl health").append(
        [Alarm(1.0, "limb1", "limb1", Level.OK, Level.ERROR, "before")]
    )
    before = alarm_path().read_bytes()
    code, _, stderr = msctl("health", "--watch", "--for", "1")
    assert code == 3 and "no Zenoh router reachable" in stderr and "watching" not in stderr
    assert alarm_path().read_bytes() == before
    code, stdout, _ = msctl("health", "--alarms", "--json")
    assert code == 0 and json.loads(stdout)["alarms"][0]["message"] == "before", stdout


# --------------------------------------------------------------------------- teleop
MODULES = st.one_of(
    st.sampled_from(["limb1", "wheel2", "limb9", "LIMB1", "", "limb1 ", "gc1", "*"]),
    st.text(max_size=8),
)


@_settings("teleop")
@given(
    modules=st.lists(MODULES, max_size=2),
    mode=st.sampled_from(["joint", "ik", "drive", "Joint", "", "fly"]),
    rate=NUMBERS,
    first=NUMBERS,
    repeat=NUMBERS,
    cmd_vel=st.one_of(st.none(), NAMES),
    duration=NUMBERS,
)
def test_teleop_takes_any_module_mode_and_timing_without_an_internal_error(
    home: Path,
    modules: list[str],
    mode: str,
    rate: str,
    first: str,
    repeat: str,
    cmd_vel: str | None,
    duration: str,
) -> None:
    before = snapshot(home)
    args: tuple[str, ...] = ("teleop", "--mode", mode, "--rate", rate, "--first-timeout", first)
    args += ("--repeat-timeout", repeat, "--for", duration)
    for module in modules:
        args += ("-m", module)
    if cmd_vel is not None:
        args += ("--cmd-vel", cmd_vel)
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)
    assert code != 0, (args, "teleoperated with no router")
    assert snapshot(home) == before, args
