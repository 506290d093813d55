"""Closed-form first guesses for limb chains of a known shape (the shipped limb families).

Damped least squares from an unrelated configuration wanders: it reaches some solution, often
far from where the limb is, and finding the one nearest the current angles takes many
restarts. A chain whose shape has a closed-form inverse instead lists its solutions directly,
and the solver polishes the nearest one (:attr:`components.kinematics_manager.ik.IkSolver.guess`).

Two shapes are known, read from the chain's Pinocchio model (never from the family's name):

* **roll-pitch-pitch-roll** (G-line, 4 joints, position only): a roll about the base's x axis,
  two pitches, and a last roll whose axis carries the tip (it turns the tip in place). Up to
  four solutions (roll or roll + half a turn, elbow up or down); the last roll keeps its
  current angle.
* **shoulder-elbow-wrist** (H-line, 7 joints): roll-pitch-roll shoulder whose axes meet in one
  point, a pitch elbow, roll-pitch-roll wrist whose axes meet in one point, tip on the last
  roll axis. The redundant degree of freedom is the elbow's swivel about the shoulder-wrist
  line, sampled at ``samples`` angles; each sample has eight solutions (elbow, shoulder and
  wrist branches).

In both, every link runs along its parent joint's x axis (joint origins are pure x offsets,
no rotation), which is how the shipped URDFs are drawn. A chain of another shape is refused
with the joint that does not fit.

Guesses are exact for the geometry but know nothing of limits or jumps: the solver drops those
outside the limits and picks the nearest.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import pinocchio as pin

from components.kinematics_manager.model import ChainModel


class Guess(Protocol):
    """Joint-angle solutions of a target: ``guess(target, current)`` -> array (k, nq)."""

    def __call__(self, target: pin.SE3, current: np.ndarray) -> np.ndarray:
        """Solutions putting the tip at ``target`` (k >= 0 rows; none: out of reach)."""
        ...


#: Swivel angles sampled by the shoulder-elbow-wrist guess (every 5 degrees). On 450 targets
#: drawn near and far, the nearest of 72 samples was within a 1 rad jump bound for 1 target
#: fewer than a warm-started descent (and for about 45 more); 36 samples missed 6.
DEFAULT_SAMPLES = 72

_STRAIGHT = 1e-12  # |cos| within this of 1: an Euler decomposition at its singularity


def closed_form(chain: ChainModel, samples: int = DEFAULT_SAMPLES) -> Guess:
    """The closed-form guess for ``chain``'s shape.

    Args:
        chain: The chain model.
        samples: Swivel angles sampled (shoulder-elbow-wrist chains only).

    Raises:
        ValueError: If the chain matches no known shape (the message names the joint).
    """
    axes, lengths = _shape(chain)
    if axes == "XYYX":
        return RollPitchPitch(lengths)
    if axes == "XYXYXYX":
        return ShoulderElbowWrist(lengths, samples)
    raise ValueError(
        f"chain {chain.base_link} -> {chain.tip_link} has joint axes {axes}; closed forms "
        "exist for XYYX (roll-pitch-pitch-roll) and XYXYXYX (shoulder-elbow-wrist)"
    )


def _shape(chain: ChainModel) -> tuple[str, list[float]]:
    """Joint axes (``"XYYX"``) and the x offsets: base -> joint 1, joint i -> i+1, last -> tip.

    Raises:
        ValueError: If a joint is not a plain revolute joint about x or y, or a link does not
            run along its parent's x axis.
    """
    model = chain.model
    axes = ""
    lengths = []
    placements = [model.jointPlacements[j] for j in range(1, model.njoints)]
    placements.append(model.frames[chain.tip_frame].placement)
    names = [*chain.joint_names, chain.tip_link]
    for j in range(1, model.njoints):
        joint_type = model.joints[j].shortname()
        if joint_type not in ("JointModelRX", "JointModelRY"):
            raise ValueError(
                f"joint {model.names[j]} is {joint_type}; the closed forms need revolute joints "
                "about x or y"
            )
        axes += joint_type[-1]
    if model.frames[chain.tip_frame].parentJoint != model.njoints - 1:
        raise ValueError(f"{chain.tip_link} does not hang from the chain's last joint")
    for name, placement in zip(names, placements, strict=True):
        offset = placement.translation
        if not np.allclose(placement.rotation, np.eye(3), atol=1e-9) or not np.allclose(
            offset[1:], 0.0, atol=1e-9
        ):
            raise ValueError(
                f"{name} is not placed along its parent's x axis (origin {offset.tolist()}, "
                "or a rotated origin); the closed forms need straight links"
            )
        lengths.append(float(offset[0]))
    return axes, lengths


class RollPitchPitch:
    """Position-only closed form of a roll-pitch-pitch-roll chain (tip on the last roll axis).

    Args:
        lengths: x offsets base -> joint 1 -> joint 2 -> joint 3 -> joint 4 -> tip.
    """

    def __init__(self, lengths: list[float]) -> None:
        to_j1, j1_j2, j2_j3, j3_j4, j4_tip = lengths
        self.shoulder = np.array([to_j1 + j1_j2, 0.0, 0.0])  # on the first roll's axis
        self.upper = j2_j3
        self.lower = j3_j4 + j4_tip  # the last roll does not move the tip

    def __call__(self, target: pin.SE3, current: np.ndarray) -> np.ndarray:
        """Up to four joint vectors putting the tip at ``target.translation``."""
        x, y, z = target.translation - self.shoulder
        rho = math.hypot(y, z)
        upper, lower = self.upper, self.lower
        # In the plane the first roll turns, the two pitches reach (x, w): w = -/+ rho.
        cos_elbow = (x * x + rho * rho - upper * upper - lower * lower) / (2.0 * upper * lower)
        if abs(cos_elbow) > 1.0 + 1e-9:
            return np.empty((0, 4))
        elbow = math.acos(min(1.0, max(-1.0, cos_elbow)))
        out = []
        for w in (rho, -rho):
            if rho < 1e-12:
                roll = float(current[0])  # on the roll axis: any roll does
            elif w > 0:
                roll = math.atan2(-y, z)
            else:
                roll = math.atan2(y, -z)
            # R_y(pitch) takes (l, 0, 0) to (l cos, 0, -l sin): the plane's height is -w.
            for bend in (elbow, -elbow):
                pitch = math.atan2(-w, x) - math.atan2(
                    lower * math.sin(bend), upper + lower * math.cos(bend)
                )
                out.append((roll, pitch, bend, float(current[3])))
        return np.array(out)


class ShoulderElbowWrist:
    """Closed form of a roll-pitch-roll / pitch / roll-pitch-roll chain, swivel sampled.

    Args:
        lengths: x offsets base -> joint 1 -> ... -> joint 7 -> tip.
        samples: Swivel angles sampled around the shoulder-wrist line.
    """

    def __init__(self, lengths: list[float], samples: int = DEFAULT_SAMPLES) -> None:
        if samples < 1:
            raise ValueError(f"samples is {samples}; give at least 1")
        self.shoulder = np.array([lengths[0] + lengths[1], 0.0, 0.0])
        self.upper = lengths[2] + lengths[3]  # shoulder centre -> elbow
        self.fore = lengths[4] + lengths[5]  # elbow -> wrist centre
        self.hand = lengths[6] + lengths[7]  # wrist centre -> tip
        swivel = np.linspace(-math.pi, math.pi, samples, endpoint=False)
        self._sin = np.sin(swivel)[:, None, None]
        self._versine = (1.0 - np.cos(swivel))[:, None, None]

    def __call__(self, target: pin.SE3, current: np.ndarray) -> np.ndarray:
        """Eight joint vectors per swivel sample putting the tip at ``target``."""
        goal = target.rotation
        wrist = target.translation - self.hand * goal[:, 0]
        x, y, z = (float(v) for v in wrist - self.shoulder)
        distance = math.sqrt(x * x + y * y + z * z)
        upper, fore = self.upper, self.fore
        cos_elbow = (distance * distance - upper * upper - fore * fore) / (2.0 * upper * fore)
        if abs(cos_elbow) > 1.0 + 1e-9 or distance < 1e-12:
            return np.empty((0, 7))
        elbow = math.acos(min(1.0, max(-1.0, cos_elbow)))
        x, y, z = x / distance, y / distance, z / distance
        # Rotations about the shoulder-wrist line keep the wrist where it is: the swivel.
        k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
        swivels = np.eye(3) + self._sin * k + self._versine * (k @ k)  # (n, 3, 3)
        # With the shoulder at zero the wrist lies along ``bent`` (elbow bent either way); any
        # shoulder rotation taking it onto the shoulder-wrist line puts the wrist there.
        c4, s4 = math.cos(elbow), math.sin(elbow)
        reach = math.hypot(upper + fore * c4, fore * s4)
        bent_x, bent_z = (upper + fore * c4) / reach, fore * s4 / reach
        aligning = np.stack(
            [
                _aligning((bent_x, 0.0, -bent_z), (x, y, z)),
                _aligning((bent_x, 0.0, bent_z), (x, y, z)),
            ]
        )
        shoulders = swivels @ aligning[:, None]  # (elbow branch, n, 3, 3)
        s1, s2, s3 = _roll_pitch_roll(shoulders, float(current[0]))  # (2, 2, n)
        # Both shoulder branches make the same rotation: what the wrist must turn is
        # (shoulder * elbow)^T * goal.
        bends = np.array([[[c4, 0.0, s4], [0.0, 1.0, 0.0], [-s4, 0.0, c4]],
                          [[c4, 0.0, -s4], [0.0, 1.0, 0.0], [s4, 0.0, c4]]])  # fmt: skip
        hands = np.swapaxes(shoulders @ bends[:, None], -1, -2) @ goal
        w1, w2, w3 = _roll_pitch_roll(hands, float(current[4]))  # (2, 2, n)
        # (wrist branch, shoulder branch, elbow branch, sample, joint)
        q = np.empty((2, 2, 2, len(self._sin), 7))
        q[..., 0] = s1
        q[..., 1] = s2
        q[..., 2] = s3
        q[..., 3] = np.array([elbow, -elbow])[:, None]
        q[..., 4] = w1[:, None]
        q[..., 5] = w2[:, None]
        q[..., 6] = w3[:, None]
        return q.reshape(-1, 7)


def _aligning(a: tuple[float, float, float], b: tuple[float, float, float]) -> np.ndarray:
    """A rotation taking unit vector ``a`` onto unit vector ``b`` (the shortest one)."""
    (ax, ay, az), (bx, by, bz) = a, b
    kx, ky, kz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx  # a x b
    sine2 = kx * kx + ky * ky + kz * kz
    cosine = ax * bx + ay * by + az * bz
    if sine2 < 1e-24:
        if cosine > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis perpendicular to a.
        other = (0.0, 1.0, 0.0) if abs(ay) < 0.9 else (0.0, 0.0, 1.0)
        axis = np.cross(a, other)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])
    return np.eye(3) + k + (k @ k) * ((1.0 - cosine) / sine2)


def _roll_pitch_roll(
    rotations: np.ndarray, roll_now: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both decompositions ``R = Rx(a) Ry(b) Rx(c)`` of each rotation (leading axis added).

    With ``R = Rx(a) Ry(b) Rx(c)``: ``R00 = cos b``, ``(R10, R20) = sin b (sin a, -cos a)``,
    ``(R01, R02) = sin b (sin c, cos c)``. At the singularity (``sin b = 0``) only ``a + c``
    (b = 0) or ``c - a`` (b = pi) is fixed: ``a`` keeps the current angle ``roll_now``.
    """
    r00 = np.clip(rotations[..., 0, 0], -1.0, 1.0)
    pitch = np.arccos(r00)
    first = np.arctan2(rotations[..., 1, 0], -rotations[..., 2, 0])
    last = np.arctan2(rotations[..., 0, 1], rotations[..., 0, 2])
    straight = np.abs(r00) > 1.0 - _STRAIGHT
    if straight.any():
        # b = 0: R = Rx(a + c); b = pi: R = Ry(pi) Rx(c - a), so Rx(c - a) = diag(-1, 1, -1) R.
        r11, r21 = rotations[..., 1, 1], rotations[..., 2, 1]
        together = np.where(r00 > 0, np.arctan2(r21, r11), np.arctan2(-r21, r11))
        first = np.where(straight, roll_now, first)
        last = np.where(straight, np.where(r00 > 0, together - roll_now, together + roll_now), last)
    # The other branch: -b, with a and c half a turn further (kept within (-pi, pi]).
    a = np.stack([first, np.where(first > 0.0, first - math.pi, first + math.pi)])
    b = np.stack([pitch, -pitch])
    c = np.stack([last, np.where(last > 0.0, last - math.pi, last + math.pi)])
    return a, b, c
