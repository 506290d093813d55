"""Rigid transforms as plain tuples: enough to join modules at their connectors.

Pure Python on purpose: a handful of 3x3 products per connection is faster than importing numpy
on the resolution path. Rotations follow URDF: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

import math

Vec = tuple[float, float, float]
Mat = tuple[Vec, Vec, Vec]
Transform = tuple[Mat, Vec]

IDENTITY: Mat = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def rpy_matrix(roll: float, pitch: float, yaw: float) -> Mat:
    """Rotation matrix of URDF roll/pitch/yaw angles (radians)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )


def matrix_rpy(r: Mat) -> Vec:
    """URDF roll/pitch/yaw of a rotation matrix (yaw is zero at the pitch singularity)."""
    sp = max(-1.0, min(1.0, -r[2][0]))
    pitch = math.asin(sp)
    if abs(sp) > 1.0 - 1e-12:
        # Gimbal lock: only roll +- yaw is defined; put it all in roll.
        return (math.atan2(-r[1][2], r[1][1]), pitch, 0.0)
    return (math.atan2(r[2][1], r[2][2]), pitch, math.atan2(r[1][0], r[0][0]))


def matmul(a: Mat, b: Mat) -> Mat:
    """Product of two 3x3 matrices."""
    return tuple(  # type: ignore[return-value]
        tuple(sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)) for i in range(3)
    )


def transpose(a: Mat) -> Mat:
    """Transpose (the inverse of a rotation)."""
    return tuple(tuple(a[j][i] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def apply(a: Mat, v: Vec) -> Vec:
    """Matrix times vector."""
    return tuple(sum(a[i][k] * v[k] for k in range(3)) for i in range(3))  # type: ignore[return-value]


def from_xyz_rpy(xyz: Vec, rpy: Vec) -> Transform:
    """A transform from a URDF origin."""
    return rpy_matrix(*rpy), (float(xyz[0]), float(xyz[1]), float(xyz[2]))


def compose(a: Transform, b: Transform) -> Transform:
    """``a`` then ``b`` (b expressed in a's frame)."""
    ra, ta = a
    rb, tb = b
    moved = apply(ra, tb)
    return matmul(ra, rb), (ta[0] + moved[0], ta[1] + moved[1], ta[2] + moved[2])


def inverse(a: Transform) -> Transform:
    """Inverse of a rigid transform."""
    rt = transpose(a[0])
    t = apply(rt, a[1])
    return rt, (-t[0], -t[1], -t[2])


def to_xyz_rpy(a: Transform) -> tuple[Vec, Vec]:
    """A transform as a URDF origin, with round-off noise removed."""
    xyz = tuple(_clean(v) for v in a[1])
    rpy = tuple(_clean(v) for v in matrix_rpy(a[0]))
    return xyz, rpy  # type: ignore[return-value]


def _clean(value: float) -> float:
    # 1e-17 instead of 0 makes the URDF noisy and diffs of lock files unreadable.
    rounded = round(value, 12)
    return 0.0 if rounded == 0 else rounded


def mating(angle_deg: float) -> Transform:
    """The child connector's frame in the parent connector's frame.

    Mating faces oppose each other: the child's z points back into the parent, obtained by a
    half turn about the connector's y axis, then the child turns by ``angle_deg`` about its own z.
    """
    flip = rpy_matrix(0.0, math.pi, 0.0)
    turn = rpy_matrix(0.0, 0.0, math.radians(angle_deg))
    return matmul(flip, turn), (0.0, 0.0, 0.0)
