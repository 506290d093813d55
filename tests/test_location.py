"""Location publisher core: per-link poses in the module's root frame from ``joint_read``,
``tf`` for ROS tools, rate limits; built from the shipped ``dragon`` assembly."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import resolved_assembly

from components.assembly import (
    ResolvedAssembly,
)
from components.build import BuiltComponent, build_component
from components.kinematics_manager.model import chain_model
from components.location_publisher.core import LocationCore
from components.messages import JointSample, joint_state


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    """The shipped ``dragon`` template, resolved with its default units."""
    return resolved_assembly(tmp_path_factory.mktemp("dragon"), "dragon")


def built(assembly: ResolvedAssembly, name: str) -> BuiltComponent:
    component = build_component(assembly.component(name), assembly)
    assert isinstance(component.core, LocationCore)
    return component


def read(core: LocationCore, positions: dict[str, float], now: float) -> None:
    samples = [JointSample(n, v, 0.0, 0.0) for n, v in positions.items()]
    core.on_joint_read(joint_state(samples, now), now)


def test_tip_pose_is_the_chain_fk_in_the_module_base_frame(dragon: ResolvedAssembly) -> None:
    tip = built(dragon, "limb2/location_tip")
    core = tip.core
    assert tip.namespace == "/limb2" and core.topics == ["pose/tip_link"]
    core.start(0.0)
    assert core.outbox.sent == []  # the tip hangs from joints not read yet
    q = np.array([0.3, -0.4, 0.5, 0.6, -0.2, 0.1, 0.7])
    names = [f"limb2_joint{i}" for i in range(1, 8)]
    read(core, dict(zip(names, q, strict=True)) | {"limb2_finger_left": 0.01}, 0.1)
    (pose,) = core.outbox.take("pose/tip_link")
    assert pose.header.frame_id == "limb2_base_link"
    chain = chain_model(dragon.urdf_path.read_text(), "limb2_base_link", "limb2_tip_link")
    expected = chain.tip(q).translation
    got = [pose.pose.position.x, pose.pose.position.y, pose.pose.position.z]
    assert got == pytest.approx(list(expected), abs=1e-9)
    (tf,) = core.outbox.take("tf")
    (edge,) = tf.transforms
    assert (edge.header.frame_id, edge.child_frame_id) == ("limb2_base_link", "limb2_tip_link")
    assert edge.transform.translation.x == pytest.approx(expected[0])


def test_changes_are_rate_limited_and_still_poses_kept_alive(dragon: ResolvedAssembly) -> None:
    core = built(dragon, "limb1/location_tip").core
    names = [f"limb1_joint{i}" for i in range(1, 8)]
    read(core, dict.fromkeys(names, 0.1), 0.0)
    assert len(core.outbox.take("pose/tip_link")) == 1
    read(core, dict.fromkeys(names, 0.1 + 1e-7), 0.5)  # below the thresholds
    assert core.outbox.take("pose/tip_link") == []
    read(core, dict.fromkeys(names, 0.2), 0.51)
    read(core, dict.fromkeys(names, 0.3), 0.52)  # within min_period: held back
    assert len(core.outbox.take("pose/tip_link")) == 1
    core.tick(0.55)
    assert len(core.outbox.take("pose/tip_link")) == 1
    core.tick(1.0)
    assert core.outbox.take("pose/tip_link") == []
    core.tick(1.6)  # a second after the last publication
    assert len(core.outbox.take("pose/tip_link")) == 1


def test_root_publisher_carries_the_mount_edge_or_the_fixed_connectors(
    dragon: ResolvedAssembly,
) -> None:
    # limb2 hangs from limb1's base connector: its base publisher says so on tf, at start.
    base2 = built(dragon, "limb2/location_base").core
    base2.start(0.0)
    (pose,) = base2.outbox.take("pose/base_link")
    assert pose.pose.orientation.w == pytest.approx(1.0)  # the root in its own frame
    (tf,) = base2.outbox.take("tf")
    edges = {(t.header.frame_id, t.child_frame_id) for t in tf.transforms}
    assert edges == {("limb1_connector_base", "limb2_base_link")}
    # limb1 is the robot's root: it has no mount, so it carries its fixed connectors.
    base1 = built(dragon, "limb1/location_base").core
    base1.start(0.0)
    (tf,) = base1.outbox.take("tf")
    edges = {(t.header.frame_id, t.child_frame_id) for t in tf.transforms}
    assert ("limb1_base_link", "limb1_connector_base") in edges
    assert all(parent == "limb1_base_link" for parent, _ in edges)
    assert ("limb1_base_link", "limb1_connector_tip") not in edges  # it moves with the joints


def test_a_wheel_module_publishes_its_own_links(dragon: ResolvedAssembly) -> None:
    mount = built(dragon, "wheel1/location_mount")
    assert mount.namespace == "/wheel1" and mount.core.topics == ["pose/connector_mount"]
    mount.core.start(0.0)  # fixed to the body: known without any joint
    (pose,) = mount.core.outbox.take("pose/connector_mount")
    assert pose.header.frame_id == "wheel1_body_link"
    assert pose.pose.position.x == pytest.approx(-0.1)
    # Another module's joints are not this module's business.
    read(mount.core, {"limb1_joint1": 1.0}, 0.1)
    assert mount.core.outbox.take("pose/connector_mount") == []
