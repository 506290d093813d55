"""geometry_msgs poses <-> Pinocchio SE3, and how far apart two poses are.

Shared by the kinematics manager and the location publisher so both write poses the same way
(meters, unit quaternions, ``header.frame_id`` naming the frame the pose is in).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pinocchio as pin

from components.messages import POSE_STAMPED, header, msg

TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def pose_msg(placement: pin.SE3) -> Any:
    """A ``geometry_msgs/Pose`` for a placement."""
    x, y, z = (float(v) for v in placement.translation)
    qx, qy, qz, qw = (float(v) for v in pin.Quaternion(placement.rotation).coeffs())
    return msg(
        "geometry_msgs/msg/Pose",
        position=msg("geometry_msgs/msg/Point", x=x, y=y, z=z),
        orientation=msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )


def pose_stamped(placement: pin.SE3, stamp: float, frame_id: str) -> Any:
    """A ``geometry_msgs/PoseStamped`` of ``placement`` in ``frame_id``."""
    return msg(POSE_STAMPED, header=header(stamp, frame_id), pose=pose_msg(placement))


def transform_stamped(placement: pin.SE3, stamp: float, parent: str, child: str) -> Any:
    """A ``geometry_msgs/TransformStamped``: ``child``'s placement in ``parent``."""
    x, y, z = (float(v) for v in placement.translation)
    qx, qy, qz, qw = (float(v) for v in pin.Quaternion(placement.rotation).coeffs())
    return msg(
        "geometry_msgs/msg/TransformStamped",
        header=header(stamp, parent),
        child_frame_id=child,
        transform=msg(
            "geometry_msgs/msg/Transform",
            translation=msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z),
            rotation=msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
        ),
    )


def tf_message(transforms: list[Any]) -> Any:
    """A ``tf2_msgs/TFMessage``."""
    return msg(TF_MESSAGE, transforms=transforms)


def partial_target(pose: Any, current: pin.SE3) -> pin.SE3 | None:
    """The placement a (possibly partial) ``geometry_msgs/Pose`` asks for.

    NaN in a position coordinate keeps that coordinate of ``current``; NaN in any quaternion
    component keeps ``current``'s orientation (a quaternion is only meaningful whole).

    Returns:
        The target, or None if the quaternion is finite but has no length (not a rotation).
    """
    position = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=float)
    position = np.where(np.isnan(position), current.translation, position)
    o = pose.orientation
    quat = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if np.isnan(quat).any():
        rotation = current.rotation
    else:
        norm = float(np.linalg.norm(quat))
        if not norm > 1e-9 or not math.isfinite(norm):
            return None
        quat /= norm
        rotation = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
    return pin.SE3(rotation, position)


def apart(a: pin.SE3, b: pin.SE3) -> tuple[float, float]:
    """Distance (m) and rotation angle (rad) between two placements."""
    distance = float(np.linalg.norm(a.translation - b.translation))
    angle = float(np.linalg.norm(pin.log3(a.rotation.T @ b.rotation)))
    return distance, angle
