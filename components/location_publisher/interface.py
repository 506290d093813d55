"""How a Location Publisher meets the data plane (names relative to the module's namespace).

The pose topics depend on which links the publisher carries, so the interface is made per
component from that list: ``pose/<link>`` each, plus the module's ``tf``.
"""

from __future__ import annotations

from collections.abc import Sequence

from components.executor.interface import Every, InterfaceSpec, Publish, Subscribe
from components.kinematics_manager.poses import TF_MESSAGE
from components.messages import JOINT_STATE, POSE_STAMPED
from components.roles import Role


def location_interface(pose_topics: Sequence[str]) -> InterfaceSpec:
    """The interface of a publisher writing ``pose_topics`` (and ``tf``)."""
    return InterfaceSpec(
        subscribe=(Subscribe("joint_read", JOINT_STATE, "on_joint_read", role=Role.TELEMETRY),),
        publish=(
            *(Publish(topic, POSE_STAMPED) for topic in pose_topics),
            Publish("tf", TF_MESSAGE),
        ),
        every=(Every(0.05, "tick"),),
    )
