"""``msctl bag view``: a bag's robot on rerun's timeline. A bag written with msctl's own
writer (limb1 lifting joint2 over four seconds, module health turning WARN, a tip pose, one
module's health stopping), drawn into an ``.rrd`` with ``--no-serve --save`` and read back
with rerun's own reader: the transforms at the recorded times, colours, alarms, STALE."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from components.comm.qos import QoS
from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import message_definition, qos_profiles
from components.recording.writer import BagWriter, TopicSpec
from msctl.app import app

pytest.importorskip("rerun", reason="the view extra is not installed: pip install '.[view]'")

JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
POSE = "geometry_msgs/msg/PoseStamped"
SECOND = 1_000_000_000


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An MSCTL_HOME with the dragon resolved in it, as `msctl assemble dragon` leaves it."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path / "home"
    monkeypatch.setenv("MSCTL_HOME", str(home))
    write_resolution(home / "assembly", resolve("dragon", {}))
    return home


def spec(topic: str, type_name: str) -> TopicSpec:
    return TopicSpec(
        topic,
        type_name,
        registry().type_hash(type_name),
        tuple(qos_profiles([QoS()])),
        message_definition(type_name),
    )


def health(slot: str, level: int, text: str) -> Any:
    status = msg(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=level,
        name=f"{slot}/motors",
        message=text,
        hardware_id=slot,
    )
    return msg(DIAGNOSTICS, status=[status])


def write_bag(directory: Path) -> tuple[Path, int]:
    """Four seconds of a dragon: limb1's joint2 from 0 to 1 rad, limb1 WARN after 2 s,
    wheel2's health silent after 0.5 s; a tip pose of limb1 at 1 s."""
    types = registry()
    start = time.time_ns()
    with BagWriter(directory) as writer:
        joints = writer.add_topic(spec("/limb1/joint_read", JOINT_STATE))
        limb1 = writer.add_topic(spec("/limb1/health", DIAGNOSTICS))
        wheel2 = writer.add_topic(spec("/wheel2/health", DIAGNOSTICS))
        tip = writer.add_topic(spec("/limb1/tip_pose", POSE))
        stranger = writer.add_topic(spec("/limb9/joint_read", JOINT_STATE))
        encode_joints, encode_health = types.serializer(JOINT_STATE), types.serializer(DIAGNOSTICS)
        for i in range(81):
            at = start + i * SECOND // 20
            state = msg(JOINT_STATE, name=["limb1_joint2"], position=np.array([i / 80]))
            writer.write(joints, at, encode_joints(state), at, i + 1)
            if i % 5 == 0:
                level, text = (1, "joint2 hot") if i >= 40 else (0, "")
                writer.write(limb1, at, encode_health(health("limb1", level, text)), at, i + 1)
                if i <= 10:
                    writer.write(wheel2, at, encode_health(health("wheel2", 0, "")), at, i + 1)
        pose = msg(POSE)
        pose.header.frame_id = "limb1_palm_link"
        pose.pose.orientation.w = 1.0
        writer.write(tip, start + SECOND, types.serializer(POSE)(pose), start + SECOND, 1)
        writer.write(stranger, start, encode_joints(msg(JOINT_STATE)), start, 1)
    return directory, start


def rows_of(path: Path) -> dict[str, list[Any]]:
    from rerun.chunk import RrdReader

    rows: dict[str, list[Any]] = {}
    for chunk in RrdReader(path).stream():
        rows.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return rows


def column(batches: list[Any], name: str) -> list[tuple[int, Any]]:
    """``(time ns, value)`` of one column over every batch, in time order."""
    out = []
    for batch in batches:
        if name not in batch.schema.names:
            continue
        times = batch.column("time").cast("int64").to_pylist()
        out += [(t, v) for t, v in zip(times, batch.column(name).to_pylist(), strict=True) if v]
    return sorted(out, key=lambda pair: pair[0])


def test_bag_view_draws_the_bag_on_its_own_timeline(home: Path, tmp_path: Path) -> None:
    bag, start = write_bag(tmp_path / "dragon_bag")
    rrd = tmp_path / "bag.rrd"
    result = CliRunner().invoke(app, ["bag", "view", str(bag), "--no-serve", "--save", str(rrd)])
    assert result.exit_code == 0, result.output
    assert "/limb9 was recorded but dragon has no such module" in result.output
    assert f"saved {rrd}" in result.output
    rows = rows_of(rrd)
    # The palm rises as joint2 turns, at the bag's own times (not the time it was drawn).
    palm = column(rows["/robot/limb1/limb1_palm_link"], "Transform3D:translation")
    assert len(palm) >= 10
    assert start <= palm[0][0] and palm[-1][0] <= start + 4 * SECOND
    heights = [value[0][2] for _, value in palm]
    assert abs(heights[-1] - heights[0]) > 0.3
    # limb1's shapes turned WARN's colour, after 2 s of the bag.
    warn = 0xF0BE28FF  # LEVEL_COLOURS["WARN"] as rerun's packed RGBA
    tints = column(rows["/robot/limb1/limb1_link3/visual_0"], "Cylinders3D:colors")
    assert any(value == [warn] and t >= start + 2 * SECOND for t, value in tints), tints
    alarms = " ".join(str(v) for _, v in column(rows["/alarms"], "TextLog:text"))
    assert "limb1: OK -> WARN limb1/motors: joint2 hot" in alarms
    assert "wheel2: STALE" in alarms
    assert "/targets/limb1/tip" in rows


def test_bag_view_refuses_what_it_cannot_do(home: Path, tmp_path: Path) -> None:
    from components.recording.errors import BagError
    from msctl.errors import MsctlError

    runner = CliRunner()
    missing = runner.invoke(
        app,
        ["bag", "view", str(tmp_path / "nowhere"), "--no-serve", "--save", str(tmp_path / "x.rrd")],
    )
    assert isinstance(missing.exception, BagError)
    assert "no such bag directory" in str(missing.exception)
    both = runner.invoke(app, ["bag", "view", str(tmp_path), "--rerun", "--foxglove"])
    assert isinstance(both.exception, MsctlError) and "cannot be combined" in str(both.exception)
    rrd = runner.invoke(
        app, ["bag", "view", str(tmp_path), "--foxglove", "--save", str(tmp_path / "x.rrd")]
    )
    assert isinstance(rrd.exception, MsctlError) and "not with --foxglove" in str(rrd.exception)
    nothing = runner.invoke(app, ["bag", "view", str(tmp_path), "--no-serve"])
    assert isinstance(nothing.exception, MsctlError) and "give --save" in str(nothing.exception)


def test_bag_view_foxglove_serves_the_bag_and_says_where(home: Path, tmp_path: Path) -> None:
    """The command: the bag read, its span said, the server's address on stdout, stopped
    after --for; the protocol itself is tests/test_view_bag_foxglove.py's."""
    pytest.importorskip("foxglove", reason="the view extra is not installed: pip install '.[view]'")
    bag, _ = write_bag(tmp_path / "dragon_bag")
    result = CliRunner().invoke(
        app, ["bag", "view", str(bag), "--foxglove", "--port", "0", "--for", "0.5"]
    )
    assert result.exit_code == 0, result.output
    assert "messages on 5 topics over 4.0 s" in result.output
    assert result.stdout.strip().startswith("ws://127.0.0.1:")
