"""Bags Foxglove opens: msctl's ``ros2msg`` schemas read by Foxglove's own parser and CDR reader.

The readers are Foxglove's npm packages (``@foxglove/rosmsg`` with ``ros2: true``, and
``@foxglove/rosmsg2-serialization``), run with node (tests/js/decode.js). They match a
dependency's ``MSG:`` name against the field's type exactly, unlike rosbags and the Python mcap
readers, which tolerate both forms. ``.ci/run`` installs node and the packages; here the test
installs the packages (``npm ci`` in tests/js) when node is there and they are not.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from components.comm.qos import QoS
from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import (
    SEPARATOR,
    fixed_definition,
    message_definition,
    needs_fixing,
    qos_profiles,
)
from components.recording.writer import BagWriter, TopicSpec
from msctl.app import app

JS = Path(__file__).parent / "js"
NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(
    NODE is None,
    reason="node is not installed: Foxglove's ros2msg reader runs on node "
    "(apt-get install nodejs npm; .ci/run does)",
)

JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
POSE = "geometry_msgs/msg/PoseStamped"


@pytest.fixture(scope="module")
def foxglove() -> Any:
    """A function reading ``[{name, definition, cdr?}]`` with Foxglove's readers."""
    if not (JS / "node_modules" / "@foxglove" / "rosmsg").is_dir():
        npm = shutil.which("npm")
        assert npm, "node is here but npm is not: apt-get install npm"
        subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund"], cwd=JS, check=True, capture_output=True
        )

    def read(items: list[dict[str, str]]) -> list[dict[str, Any]]:
        done = subprocess.run(
            [NODE, str(JS / "decode.js")],
            input=json.dumps(items),
            capture_output=True,
            text=True,
            check=True,
            timeout=60,
        )
        return json.loads(done.stdout)

    return read


def old_form(definition: str) -> str:
    """A definition as msctl wrote it before: dependencies named ``MSG: pkg/msg/Type``."""
    lines = []
    for line in definition.splitlines(keepends=True):
        if line.startswith("MSG: "):
            pkg, short = line[5:].strip().split("/")
            line = f"MSG: {pkg}/msg/{short}\n"
        lines.append(line)
    return "".join(lines)


def spec(name: str, type_name: str, definition: str | None = None) -> TopicSpec:
    return TopicSpec(
        name,
        type_name,
        registry().type_hash(type_name),
        tuple(qos_profiles([QoS()])),
        definition if definition is not None else message_definition(type_name),
    )


def samples() -> dict[str, bytes]:
    """One CDR message of each type a module publishes most."""
    types = registry()
    header = msg("std_msgs/msg/Header", frame_id="limb1/base_link")
    header.stamp.sec, header.stamp.nanosec = 17, 250
    joints = msg(
        JOINT_STATE,
        header=header,
        name=["joint1", "joint2"],
        position=np.array([0.5, -1.25]),
        velocity=np.zeros(2),
        effort=np.zeros(0),
    )
    status = msg(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=1,
        name="limb1: health",
        message="joint2 hot",
        hardware_id="hl-limb-01",
        values=[msg("diagnostic_msgs/msg/KeyValue", key="temperature", value="71")],
    )
    diagnostics = msg(DIAGNOSTICS, header=header, status=[status])
    pose = msg(POSE, header=header)
    pose.pose.position.x, pose.pose.orientation.w = 1.5, 1.0
    return {
        JOINT_STATE: types.serializer(JOINT_STATE)(joints),
        DIAGNOSTICS: types.serializer(DIAGNOSTICS)(diagnostics),
        POSE: types.serializer(POSE)(pose),
    }


def write_bag(directory: Path, old: bool = False) -> Path:
    """A bag of JointState, DiagnosticArray and PoseStamped; ``old``: schemas in the old form."""
    data = samples()
    with BagWriter(directory) as writer:
        start = time.time_ns()
        for i, (type_name, cdr) in enumerate(data.items()):
            definition = message_definition(type_name)
            assert definition is not None
            topic = writer.add_topic(
                spec(f"/limb1/t{i}", type_name, old_form(definition) if old else definition)
            )
            writer.write(topic, start + i, cdr, start + i, 1)
    return directory


def bag_items(directory: Path) -> list[dict[str, str]]:
    """Each message of a bag with its channel's schema, as the node reader takes them."""
    items = []
    for path in sorted(directory.glob("*.mcap")):
        with open(path, "rb") as stream:
            for schema, _, message in make_reader(stream).iter_messages():
                assert schema is not None
                items.append(
                    {
                        "name": schema.name,
                        "definition": schema.data.decode(),
                        "cdr": base64.b64encode(message.data).decode(),
                    }
                )
    return items


def test_every_message_definition_parses_with_foxglove(foxglove: Any) -> None:
    names = [n for n in registry().message_names() if "/msg/" in n]
    items = [{"name": n, "definition": message_definition(n) or ""} for n in names]
    failed = [(r["name"], r.get("error")) for r in foxglove(items) if not r["ok"]]
    assert not failed, failed


def test_the_old_form_fails_in_foxglove_as_the_issue_says(foxglove: Any) -> None:
    # The reader is strict: the test above would catch a regression to the old form.
    definition = message_definition(JOINT_STATE)
    assert definition is not None
    (result,) = foxglove([{"name": JOINT_STATE, "definition": old_form(definition)}])
    assert not result["ok"]
    assert "std_msgs/Header" in result["error"]


def test_definition_is_what_rosbag2_writes() -> None:
    # rosbag2_cpp's test_local_message_definition_source: the type's text, then per dependency
    # an empty line, 80 '=', 'MSG: pkg/Type' as the field names it; depth first, sorted.
    definition = message_definition(DIAGNOSTICS)
    assert definition is not None
    expected_order = [
        "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ]
    names = [line[5:] for line in definition.splitlines() if line.startswith("MSG: ")]
    assert names == expected_order
    assert definition.startswith(
        "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n\n"
        f"{SEPARATOR}\nMSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\n"
    )
    assert definition.endswith(
        f"\n\n{SEPARATOR}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    )
    assert not needs_fixing(definition)
    assert fixed_definition(old_form(definition)) == definition


def test_a_bag_msctl_writes_decodes_in_foxglove(foxglove: Any, tmp_path: Path) -> None:
    results = foxglove(bag_items(write_bag(tmp_path / "bag")))
    assert [r["ok"] for r in results] == [True, True, True], results
    by_name = {r["name"]: r["message"] for r in results}
    joints = by_name[JOINT_STATE]
    assert joints["name"] == ["joint1", "joint2"]
    assert joints["position"] == [0.5, -1.25]
    assert joints["header"]["frame_id"] == "limb1/base_link"
    assert joints["header"]["stamp"] == {"sec": 17, "nanosec": 250}
    status = by_name[DIAGNOSTICS]["status"][0]
    assert (status["level"], status["hardware_id"]) == (1, "hl-limb-01")
    assert status["values"] == [{"key": "temperature", "value": "71"}]
    assert by_name[POSE]["pose"]["position"]["x"] == 1.5


def test_bag_recover_fix_schemas_makes_an_old_bag_readable(foxglove: Any, tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "old", old=True)
    before = bag_items(bag)
    assert not any(r["ok"] for r in foxglove(before))
    # Without the option a finished bag is left as it is.
    plain = CliRunner().invoke(app, ["bag", "recover", str(bag), "--json"])
    assert plain.exit_code == 0, plain.output
    assert json.loads(plain.stdout)["files"][0]["action"] == "kept"
    fixed = CliRunner().invoke(app, ["bag", "recover", str(bag), "--fix-schemas", "--json"])
    assert fixed.exit_code == 0, fixed.output
    (report,) = json.loads(fixed.stdout)["files"]
    assert (report["action"], report["fixed_schemas"], report["messages"]) == (
        "schemas fixed",
        3,
        3,
    )
    after = bag_items(bag)
    assert [a["cdr"] for a in after] == [b["cdr"] for b in before]
    assert all(r["ok"] for r in foxglove(after))
    # Once fixed, a second pass has nothing to do.
    again = CliRunner().invoke(app, ["bag", "recover", str(bag), "--fix-schemas", "--json"])
    assert json.loads(again.stdout)["files"][0]["action"] == "kept"
