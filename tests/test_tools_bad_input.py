"""Bad input to ``msctl topic``, ``msctl service`` and ``msctl bag``, as a hostile but fair
operator gives it (issue 32, case 9): one line naming what is wrong, a non-zero exit that is
not 70 (internal error), no traceback, nothing written.

Real ``msctl`` subprocesses against a real router on a random loopback port; bags written
with the ``mcap`` library and msctl's own writer.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.writer import Writer

from components.comm.qos import LATCHED
from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import message_definition, qos_profiles
from components.recording.metadata import read_metadata
from components.recording.writer import BagWriter, TopicSpec
from msctl.recorder.bag import inspect

pytestmark = pytest.mark.timeout(300)

STRING = "std_msgs/msg/String"
#: Names ROS 2 refuses, each for another reason.
ILLEGAL = ["bad topic!", "/limb1//joint_set", "/1limb/joint_set", "~private", "/limb-1/x"]


def _msctl(env: dict[str, str], cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env={**os.environ, **env, "MSCTL_HOME": str(cwd / "home"), "COLUMNS": "200"},
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _one_clear_line(result: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert result.returncode not in (0, 70), result.stderr
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr
    said = " ".join(result.stderr.split())
    for needle in needles:
        assert needle in said, said


def test_illegal_topic_and_service_names_are_one_line(
    tmp_path: Path, net_env: dict[str, str]
) -> None:
    # One subprocess per command, each with another illegal name (the property tests throw
    # many more names at the same check in-process).
    for args, name in [
        (("topic", "echo", ILLEGAL[0], STRING, "--timeout", "1"), ILLEGAL[0]),
        (("topic", "hz", ILLEGAL[1], STRING, "--for", "1"), ILLEGAL[1]),
        (("topic", "pub", ILLEGAL[2], STRING, "{data: x}", "--once"), ILLEGAL[2]),
        (("topic", "echo", ILLEGAL[4], "--timeout", "1"), ILLEGAL[4]),
    ]:
        result = _msctl(net_env, tmp_path, *args)
        _one_clear_line(result, f"topic {name!r} is not a legal ROS 2 topic name")
        assert result.returncode == 2
    call = _msctl(net_env, tmp_path, "service", "call", ILLEGAL[3], "std_srvs/srv/Trigger")
    _one_clear_line(call, f"service {ILLEGAL[3]!r} is not a legal ROS 2 service name")
    assert call.returncode == 2


def test_negative_counts_and_durations_are_refused(tmp_path: Path, net_env: dict[str, str]) -> None:
    for args, needle in [
        (("topic", "echo", "/chatter", STRING, "--times", "-1"), "--times must be 0"),
        (("topic", "echo", "/chatter", STRING, "--timeout", "-2"), "--timeout must be"),
        (("topic", "pub", "/chatter", STRING, "{data: x}", "--times", "-3"), "--times must be 0"),
        (("topic", "hz", "/chatter", STRING, "--for", "-1"), "--for must be"),
    ]:
        result = _msctl(net_env, tmp_path, *args)
        _one_clear_line(result, needle)
        assert result.returncode == 2


def _string_bag(directory: Path, count: int) -> Path:
    serialize = registry().serializer(STRING)
    with BagWriter(directory) as writer:
        topic = writer.add_topic(
            TopicSpec(
                "/chatter",
                STRING,
                registry().type_hash(STRING),
                tuple(qos_profiles([LATCHED])),
                message_definition(STRING),
            )
        )
        start = time.time_ns()
        for i in range(count):
            writer.write(topic, start + i * 10_000_000, serialize(msg(STRING, data=f"m{i}")))
    return directory


@pytest.mark.parametrize(
    "garbage",
    ["topics: [\n  - name: /chatter\n    type", "\x00\x01binary", "just a string\n", ""],
)
def test_recover_rebuilds_a_malformed_metadata_from_an_intact_mcap(
    tmp_path: Path, garbage: str
) -> None:
    bag = _string_bag(tmp_path / "bag", 20)
    good = read_metadata(bag)
    (bag / "metadata.yaml").write_text(garbage)
    result = _msctl({}, tmp_path, "bag", "recover", str(bag))
    assert result.returncode == 0, result.stderr
    said = " ".join(result.stderr.split())
    assert "metadata.yaml" in said and "rebuilt from the MCAP files" in said, said
    assert (bag / "metadata.yaml.unreadable").read_text() == garbage
    rebuilt = read_metadata(bag)
    assert rebuilt.message_count == 20
    assert [(t.name, t.type, t.type_hash) for t in rebuilt.topics] == [
        (t.name, t.type, t.type_hash) for t in good.topics
    ]
    assert not inspect(bag).needs_recovery


def test_recover_takes_a_mcap_path_as_its_help_says(tmp_path: Path) -> None:
    bag = _string_bag(tmp_path / "bag", 12)
    (mcap,) = bag.glob("*.mcap")
    part = _msctl({}, tmp_path, "bag", "recover", str(mcap))
    assert part.returncode == 0, part.stderr
    assert f"{mcap.name} is part of the bag {bag}: recovered the bag" in " ".join(
        part.stderr.split()
    )
    # A file alone, cut short as a crash leaves it: rebuilt in place, nothing else written.
    alone = tmp_path / "loose" / "field.mcap"
    alone.parent.mkdir()
    data = mcap.read_bytes()
    alone.write_bytes(data[: len(data) - 200])
    before = sorted(p.name for p in alone.parent.iterdir())
    result = _msctl({}, tmp_path, "bag", "recover", str(alone), "--json")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in alone.parent.iterdir()) == before
    assert inspect(alone).metadata.message_count == 12
    assert not inspect(alone).needs_recovery
    text = tmp_path / "notes.txt"
    text.write_text("not a bag")
    refused = _msctl({}, tmp_path, "bag", "recover", str(text))
    _one_clear_line(refused, "not a bag")
    assert text.read_text() == "not a bag"


def test_playing_a_topic_without_schema_names_it_and_fails(
    tmp_path: Path, net_env: dict[str, str]
) -> None:
    bag = tmp_path / "bare"
    bag.mkdir()
    with open(bag / "bare_0.mcap", "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        channel = writer.register_channel("/chatter", "cdr", 0)
        serialize = registry().serializer(STRING)
        start = time.time_ns()
        for i in range(3):
            writer.add_message(channel, start + i, serialize(msg(STRING, data=f"m{i}")), start + i)
        writer.finish()
    result = _msctl(net_env, tmp_path, "bag", "play", str(bag))
    _one_clear_line(result, "/chatter: the bag names no type for it", "not played: /chatter")
    assert "no definition of  " not in result.stderr


@pytest.fixture(autouse=True)
def _no_strays(tmp_path: Path) -> None:
    yield
    shutil.rmtree(tmp_path / "home", ignore_errors=True)
