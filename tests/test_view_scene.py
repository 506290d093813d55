"""The view's Core (:mod:`msctl.view.scene`): a dragon's picture from its lock, with plain
calls: forward kinematics at the viewer, looks by health, status lines, markers, and what is
drawn again (only what changed). Also ``msctl view``'s refusals and its install hint."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
from conftest import resolved_assembly
from typer.testing import CliRunner

from msctl.app import app
from msctl.errors import MsctlError
from msctl.view.scene import LEVEL_COLOURS, Placement, Scene, SceneError, scene_of


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory):
    return resolved_assembly(tmp_path_factory.mktemp("view"), "dragon")


@pytest.fixture
def scene(dragon) -> Scene:
    return scene_of(dragon)


def test_every_link_with_visuals_is_drawn_under_its_module(scene: Scene) -> None:
    modules = {look.link: look.module for look in scene.links}
    assert modules["limb1_link3"] == "limb1"
    assert modules["wheel2_wheel_left_link"] == "wheel2"
    assert {s.kind for look in scene.links for s in look.shapes} == {"box", "cylinder"}
    first = scene.changes()
    assert set(first.poses) == set(modules), "every drawn link gets a pose at once"
    assert set(first.looks.values()) == {"UNSEEN"}
    assert set(first.status) == {"limb1", "limb2", "wheel1", "wheel2"}


def test_a_joint_moves_its_limb_and_nothing_else(scene: Scene) -> None:
    before = scene.changes()
    palm = before.poses["limb1_palm_link"]
    assert scene.set_joints("limb1", {"limb1_joint2": 0.8, "nobody_joint": 1.0})
    moved = scene.changes()
    # Links beyond joint2 moved, and wheel1 bolted to limb1's tip; limb2, wheel2 and limb1's
    # base did not.
    assert "limb1_palm_link" in moved.poses and "limb1_link3" in moved.poses
    assert {link.split("_")[0] for link in moved.poses} == {"limb1", "wheel1"}
    assert "limb1_base_link" not in moved.poses
    after = moved.poses["limb1_palm_link"]
    # The palm swung about joint2: its distance to joint2's link stays, its height changed.
    joint2 = before.poses["limb1_link2"][0]
    assert math.dist(joint2, palm[0]) == pytest.approx(math.dist(joint2, after[0]), abs=1e-6)
    assert abs(after[0][2] - palm[0][2]) > 0.3
    # A move below the tolerance, or a repeat, draws nothing.
    assert not scene.set_joints("limb1", {"limb1_joint2": 0.8 + 1e-6})
    assert not scene.changes().poses
    assert scene.link_pose("limb1_palm_link") == after


def test_health_presence_halts_and_claims_show_per_module(scene: Scene) -> None:
    scene.changes()
    scene.set_health("limb1", "WARN", "limb1/motors/joint2: hot")
    scene.set_health("wheel1", "ERROR", "wheel1/joint_manager: halted: commands refused")
    scene.set_holder("limb1", "ana@ground1")
    changes = scene.changes()
    assert changes.looks == {"limb1": "WARN", "wheel1": "ERROR"}
    assert "claimed by ana@ground1" in changes.status["limb1"]
    assert "hot" in changes.status["limb1"]
    assert "HALTED" in changes.status["wheel1"]
    assert scene.modules["wheel1"].halted
    # Leaving the graph turns the module's links to the GONE colour; nothing else changes.
    scene.set_health("limb1", "STALE", "limb1/health: no health for 3 s", present=False)
    changes = scene.changes()
    assert changes.looks == {"limb1": "GONE"}
    assert "not on the graph" in changes.status["limb1"]
    assert not scene.changes()
    assert set(LEVEL_COLOURS) >= {"OK", "WARN", "ERROR", "STALE", "UNSEEN", "GONE"}


def test_markers_are_placed_from_their_frame(scene: Scene) -> None:
    scene.set_joints("limb1", {"limb1_joint1": math.pi / 2})
    scene.changes()
    link1 = scene.link_pose("limb1_link1")
    assert link1 is not None
    scene.set_marker("limb1/tip", "limb1_link1", ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    scene.set_marker("limb1/ik_target", "", ((1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)))
    markers = scene.changes().markers
    assert markers["limb1/tip"][0] == pytest.approx(link1[0])
    assert markers["limb1/ik_target"][0] == pytest.approx((1.0, 2.0, 3.0))
    assert not scene.changes().markers, "a marker is drawn once per sample"


def test_everything_and_the_camera_take_in_the_whole_assembly(scene: Scene) -> None:
    scene.changes()
    whole = scene.everything()
    assert len(whole.poses) == len(scene.links) and len(whole.looks) == 4
    eye, target = scene.eye()
    xs = [pose[0][0] for pose in whole.poses.values()]
    assert min(xs) <= target[0] <= max(xs)
    assert eye[1] < target[1] and eye[2] > target[2], "from the side, above"


def test_a_robot_placed_in_the_world_moves_every_link(dragon) -> None:
    text = Path(dragon.urdf_path).read_text()
    modules = [(m.slot, m.kind) for m in dragon.modules]
    here = Scene(text, modules, [Placement("limb1_base_link")]).changes().poses
    there = Scene(text, modules, [Placement("limb1_base_link", (1.0, 0.0, 0.5))]).changes().poses
    for link, pose in here.items():
        assert there[link][0] == pytest.approx((pose[0][0] + 1, pose[0][1], pose[0][2] + 0.5))


def test_bad_urdf_and_missing_root_are_named(dragon) -> None:
    with pytest.raises(SceneError, match="not valid XML"):
        Scene("<robot", [], [Placement("x")])
    text = Path(dragon.urdf_path).read_text()
    with pytest.raises(SceneError, match="nowhere_link"):
        Scene(text, [], [Placement("nowhere_link")])


def test_view_without_rerun_names_the_pip_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    result = CliRunner().invoke(app, ["view", "--for", "1"])
    assert isinstance(result.exception, MsctlError) and result.exception.exit_code == 2
    assert "pip install 'msctl[view]'" in str(result.exception)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--rerun", "--foxglove"], "cannot be combined"),
        (["--foxglove", "--save", "x.rrd"], "not with --foxglove"),
        (["--save", "out.mcap"], "must end in .rrd"),
        (["--save", "/nowhere/at/all/x.rrd"], "no directory"),
        (["--no-serve"], "give --save"),
        (["--port", "70000"], "TCP port"),
        (["--for", "-1"], "--for"),
    ],
)
def test_view_refuses_contradictions(args: list[str], says: str) -> None:
    result = CliRunner().invoke(app, ["view", *args])
    assert isinstance(result.exception, MsctlError), result.output
    assert result.exception.exit_code == 2
    assert says in str(result.exception)


MESH_URDF = """<robot name="mesh_bot">
  <link name="world"/>
  <link name="arm1_base_link">
    <visual><geometry><mesh filename="{mesh}" scale="1 1 1"/></geometry></visual>
  </link>
  <link name="arm1_tip_link">
    <visual><geometry><mesh filename="package://msctl/no/such/mesh.obj"/></geometry></visual>
  </link>
  <joint name="arm1_mount" type="fixed">
    <parent link="world"/><child link="arm1_base_link"/>
  </joint>
  <joint name="arm1_joint1" type="revolute">
    <parent link="arm1_base_link"/><child link="arm1_tip_link"/>
    <origin xyz="0 0 0.5"/><axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def test_meshes_are_drawn_from_their_files_and_a_missing_one_as_a_point(tmp_path: Path) -> None:
    pytest.importorskip("rerun", reason="the view extra is not installed")
    from rerun.chunk import RrdReader

    from msctl.view.rerun_sink import RerunSink, mesh_path

    mesh = tmp_path / "base.obj"
    mesh.write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    scene = Scene(MESH_URDF.format(mesh=f"file://{mesh}"), [("arm1", "limb")], [Placement("world")])
    assert [s.kind for look in scene.links for s in look.shapes] == ["mesh", "mesh"]
    assert mesh_path(f"file://{mesh}") == mesh
    assert mesh_path("package://msctl/assemblies/modules/urdf/hl_limb_v1.urdf") is not None
    assert mesh_path("package://msctl/no/such/mesh.obj") is None
    sink = RerunSink(save=tmp_path / "mesh.rrd")
    sink.at(1.0)
    sink.draw_shapes(scene)
    sink.draw(scene, scene.everything())
    sink.close()
    columns = {
        chunk.entity_path: chunk.to_record_batch().schema.names
        for chunk in RrdReader(tmp_path / "mesh.rrd").stream()
    }
    assert any(n.startswith("Asset3D:") for n in columns["/robot/arm1/arm1_base_link/visual_0"])
    assert any(n.startswith("Points3D:") for n in columns["/robot/arm1/arm1_tip_link/visual_0"])
