"""The simulated world: one MuJoCo model of the whole assembly, driven like real motors.

The world stands in for every motor of the assembly, so it speaks *raw* joint space, as a
motor does: each unit's calibration is applied inversely (model angle -> ``to_raw``), and the
joint manager's own calibration then brings values back to the true model (URDF) angle. That
round trip is what makes a mis-calibrated joint manager visible in simulation, as on hardware.

Each joint's actuator is a MuJoCo ``general`` actuator whose gains the world switches at run
time, the way a drive switches operating mode:

* position: ``force = kp * (setpoint - q) + kd * (v_ref - q')``, written in MuJoCo's affine
  form (``gain = kp``, ``bias = [0, -kp, -kd]``) with ``ctrl = setpoint + kd / kp * v_ref``.
  The setpoint moves toward the target at most at the joint's max velocity, like a drive's
  profile position mode, so a far target is reached at a realistic speed;
* velocity: ``gain = kv``, ``bias = [0, 0, -kv]``, ``ctrl`` = the speed;
* effort: ``gain = 1``, ``bias = 0``, ``ctrl`` = the torque (or force).

Every actuator's force range is the joint's max effort (from the MJCF); the joint limits are
the model's own limit constraints, and targets are clamped to them as a drive's software
limits would. Control values are clamped here rather than by MuJoCo's ``ctrlrange`` because
the meaningful range changes with the mode.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from components.errors import ComponentError
from components.joints import JointCalibration

if TYPE_CHECKING:
    from components.assembly import JointPlan, ResolvedAssembly

#: Control modes, as stored per joint (small ints: the per-step update is vectorised).
POSITION, VELOCITY, EFFORT = 0, 1, 2
MODE_NAMES = {POSITION: "position", VELOCITY: "velocity", EFFORT: "effort"}

#: Damping time constant used to derive missing gains (kp = kv / TIME_CONSTANT for a
#: velocity actuator asked to hold a position); the assembler tunes its servos the same way.
TIME_CONSTANT = 0.1


class SimulationError(ComponentError):
    """The model cannot be simulated as the assembly describes it (names the file and joint)."""


@dataclass(frozen=True)
class SimJoint:
    """One simulated motor: where its joint lives in the model and how it is driven.

    Attributes:
        name: Assembly joint name (``limb1_joint3``), also the actuator's name.
        module: Slot of the module the joint belongs to (``limb1``).
        calibration: The unit's calibration (raw <-> model angle).
        control: The joint's default mode at start (``position`` or ``velocity``).
        lower: Lower limit in model space (``-inf`` when unlimited).
        upper: Upper limit in model space (``inf`` when unlimited).
        max_velocity: Largest speed the drive produces (model units per second).
        max_effort: Largest torque or force (the actuator's force range).
        qpos: Address of the joint in ``qpos``.
        dof: Address of the joint in ``qvel``.
        actuator: Index of the joint's actuator.
        kp: Position gain.
        kd: Position damping (also the velocity gain when a position joint runs in velocity).
        kv: Velocity gain.
    """

    name: str
    module: str
    calibration: JointCalibration
    control: str
    lower: float
    upper: float
    max_velocity: float
    max_effort: float
    qpos: int
    dof: int
    actuator: int
    kp: float
    kd: float
    kv: float


@dataclass(frozen=True)
class RawState:
    """A module's joints in raw space, as arrays in the module's joint order."""

    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class SimWorld:
    """A MuJoCo model and its data, with one motor per actuated joint of the assembly.

    Args:
        model: The compiled model (from the assembly's MJCF).
        joints: The actuated joints, each with its module slot:
            ``(slot, JointPlan)`` pairs.
        roots: Root links of the robots (bodies whose world pose is ground truth).
        source: Where the model came from, for error messages.

    Raises:
        SimulationError: If a joint or its actuator, or a root body, is missing from the model.
    """

    def __init__(
        self,
        model: Any,
        joints: Iterable[tuple[str, JointPlan]],
        roots: Sequence[str] = (),
        source: str = "model",
    ) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.source = source
        # ctrlrange would clamp a velocity to a position range once a joint switches mode;
        # the world clamps each mode's value itself.
        model.actuator_ctrllimited[:] = 0
        self.joints: list[SimJoint] = [self._describe(slot, plan) for slot, plan in joints]
        self._index = {j.name: i for i, j in enumerate(self.joints)}
        if len(self._index) != len(self.joints):
            raise SimulationError(f"{source}: a joint is listed twice")
        self.modules: dict[str, list[int]] = {}
        for i, joint in enumerate(self.joints):
            self.modules.setdefault(joint.module, []).append(i)
        self.roots: dict[str, int] = {}
        for root in roots:
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, root)
            if body < 0:
                raise SimulationError(f"{source}: no body named {root!r} (a root link)")
            self.roots[root] = body

        n = len(self.joints)
        self._qpos = np.array([j.qpos for j in self.joints], dtype=np.intp)
        self._dof = np.array([j.dof for j in self.joints], dtype=np.intp)
        self._act = np.array([j.actuator for j in self.joints], dtype=np.intp)
        self._offset = np.array([j.calibration.zero_offset for j in self.joints])
        self._direction = np.array([float(j.calibration.direction) for j in self.joints])
        self._lower = np.array([j.lower for j in self.joints])
        self._upper = np.array([j.upper for j in self.joints])
        self._max_velocity = np.array([j.max_velocity for j in self.joints])
        self._max_effort = np.array([j.max_effort for j in self.joints])
        self._feedforward = np.array([j.kd / j.kp if j.kp > 0 else 0.0 for j in self.joints])
        self.mode = np.full(n, POSITION, dtype=np.int8)
        self.target = np.zeros(n)
        self.setpoint = np.zeros(n)
        self.resets = 0
        self._dirty = True
        self._viewer: Any = None
        self._viewer_synced = 0.0

        mujoco.mj_forward(model, self.data)
        # Drives come up enabled and holding where they are; wheels hold speed zero.
        for i, joint in enumerate(self.joints):
            if joint.control == "velocity":
                self._set_mode(i, VELOCITY)
                self.target[i] = 0.0
            else:
                self._set_mode(i, POSITION)
                here = float(self.data.qpos[joint.qpos])
                self.target[i] = self.setpoint[i] = here
        self._apply_controls(0.0)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_assembly(cls, assembly: ResolvedAssembly, mjcf: Path | None = None) -> SimWorld:
        """The world of a resolved assembly, from its MJCF (or ``mjcf`` if given).

        Raises:
            SimulationError: If the MJCF is missing or does not match the assembly.
        """
        path = Path(mjcf or assembly.mjcf_path)
        if not path.is_file():
            raise SimulationError(
                f"no MuJoCo model at {path}: run `msctl assemble {assembly.template}` again"
            )
        try:
            model = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as exc:
            raise SimulationError(f"MuJoCo cannot load {path}: {exc}") from exc
        joints = [(m.slot, j) for m in assembly.modules for j in m.actuated_joints]
        return cls(model, joints, assembly.root_links, source=str(path))

    def _describe(self, slot: str, plan: JointPlan) -> SimJoint:
        model, name = self.model, plan.spec.name
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise SimulationError(f"{self.source}: no joint named {name!r}")
        if int(model.jnt_type[jid]) not in (
            int(mujoco.mjtJoint.mjJNT_HINGE),
            int(mujoco.mjtJoint.mjJNT_SLIDE),
        ):
            raise SimulationError(f"{self.source}: joint {name!r} is not a hinge or slide")
        act = next(
            (
                a
                for a in range(model.nu)
                if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT)
                and model.actuator_trnid[a, 0] == jid
            ),
            -1,
        )
        if act < 0:
            raise SimulationError(
                f"{self.source}: joint {name!r} is actuated in the assembly but has no actuator"
            )
        if model.jnt_limited[jid]:
            lower, upper = (float(v) for v in model.jnt_range[jid])
        else:
            lower, upper = -math.inf, math.inf
        effort = plan.spec.max_effort
        if model.actuator_forcelimited[act]:
            effort = float(max(abs(v) for v in model.actuator_forcerange[act]))
        gain = float(model.actuator_gainprm[act, 0])
        bias_position, bias_velocity = (
            float(model.actuator_biasprm[act, 1]),
            float(model.actuator_biasprm[act, 2]),
        )
        if bias_position != 0.0:  # a position servo in the MJCF
            kp, kd = gain, -bias_velocity
            kv = kd
        else:  # a velocity servo: derive a position servo with the same damping
            kv = gain if gain > 0 else effort / max(plan.spec.max_velocity, 1e-6)
            kp, kd = kv / TIME_CONSTANT, kv
        return SimJoint(
            name=name,
            module=slot,
            calibration=plan.calibration,
            control=plan.control,
            lower=lower,
            upper=upper,
            max_velocity=float(plan.spec.max_velocity),
            max_effort=effort,
            qpos=int(model.jnt_qposadr[jid]),
            dof=int(model.jnt_dofadr[jid]),
            actuator=act,
            kp=kp,
            kd=kd,
            kv=kv,
        )

    # ------------------------------------------------------------------ properties
    @property
    def timestep(self) -> float:
        """Seconds of simulated time per physics step."""
        return float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        """Simulated time, seconds since the world was built."""
        return float(self.data.time)

    @property
    def joint_names(self) -> list[str]:
        """Every simulated motor's joint name."""
        return [j.name for j in self.joints]

    def joint(self, name: str) -> SimJoint:
        """A simulated motor by assembly joint name.

        Raises:
            KeyError: If no actuated joint has that name.
        """
        return self.joints[self._index[name]]

    def has_joint(self, name: str) -> bool:
        """Whether ``name`` is a simulated motor."""
        return name in self._index

    # ------------------------------------------------------------------ commands (raw space)
    def command(
        self,
        name: str,
        position: float | None = None,
        velocity: float | None = None,
        effort: float | None = None,
    ) -> None:
        """Command one motor in raw joint space, as a motor interface would.

        Position wins when both position and velocity are given (the velocity of a hold is
        zero, not a speed limit); effort alone drives the joint in torque (force) mode.
        Non-finite values are ignored.

        Raises:
            KeyError: If ``name`` is not a simulated motor.
        """
        i = self._index[name]
        cal = self.joints[i].calibration
        self._dirty = True
        if position is not None and math.isfinite(position):
            self._enter(i, POSITION)
            target = cal.to_calibrated(position)
            self.target[i] = min(max(target, self._lower[i]), self._upper[i])
        elif velocity is not None and math.isfinite(velocity):
            self._enter(i, VELOCITY)
            limit = self._max_velocity[i]
            self.target[i] = min(max(cal.rate_to_calibrated(velocity), -limit), limit)
        elif effort is not None and math.isfinite(effort):
            self._enter(i, EFFORT)
            limit = self._max_effort[i]
            self.target[i] = min(max(cal.rate_to_calibrated(effort), -limit), limit)

    def hold(self, names: Iterable[str] | None = None) -> None:
        """Hold motors where they are (all of them by default): position mode, no ramp."""
        indices = range(len(self.joints)) if names is None else [self._index[n] for n in names]
        self._dirty = True
        for i in indices:
            self._set_mode(i, POSITION)
            here = float(self.data.qpos[self._qpos[i]])
            self.target[i] = self.setpoint[i] = here

    def _enter(self, i: int, mode: int) -> None:
        if self.mode[i] == mode:
            return
        self._set_mode(i, mode)
        if mode == POSITION:
            # The profile starts where the joint is, so switching mode never jumps.
            self.setpoint[i] = float(self.data.qpos[self._qpos[i]])

    def _set_mode(self, i: int, mode: int) -> None:
        joint, model = self.joints[i], self.model
        a = joint.actuator
        model.actuator_gainprm[a, :3] = 0.0
        model.actuator_biasprm[a, :3] = 0.0
        if mode == POSITION:
            model.actuator_gainprm[a, 0] = joint.kp
            model.actuator_biasprm[a, 1] = -joint.kp
            model.actuator_biasprm[a, 2] = -joint.kd
        elif mode == VELOCITY:
            model.actuator_gainprm[a, 0] = joint.kv
            model.actuator_biasprm[a, 2] = -joint.kv
        else:
            model.actuator_gainprm[a, 0] = 1.0
        model.actuator_biastype[a] = mujoco.mjtBias.mjBIAS_AFFINE
        model.actuator_gaintype[a] = mujoco.mjtGain.mjGAIN_FIXED
        self.mode[i] = mode

    def _apply_controls(self, dt: float) -> None:
        # Controls only change after a command or while a profile moves: skip the rest of
        # the time (it costs about as much as a small model's physics step).
        if not self._dirty:
            return
        position = self.mode == POSITION
        ctrl = self.target.copy()
        moving = False
        if position.any():
            step = self._max_velocity * dt
            delta = np.where(position, np.clip(self.target - self.setpoint, -step, step), 0.0)
            self.setpoint = self.setpoint + delta
            speed = delta / dt if dt > 0 else np.zeros_like(delta)
            ctrl = np.where(position, self.setpoint + self._feedforward * speed, ctrl)
            moving = bool(delta.any())
        self.data.ctrl[self._act] = ctrl
        self._dirty = moving

    # ------------------------------------------------------------------ stepping
    def step(self, steps: int = 1) -> None:
        """Advance the physics by ``steps`` time steps (the setpoint profiles move with it)."""
        dt = self.timestep
        warning = self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC]
        before = warning.number
        viewer = self._viewer
        if viewer is not None:
            with viewer.lock():
                self._advance(steps, dt)
        else:
            self._advance(steps, dt)
        if warning.number != before:
            # MuJoCo resets the data when the acceleration blows up: the motors come back
            # holding the reset pose rather than pushing toward stale targets.
            self.resets += warning.number - before
            self.hold()

    def _advance(self, steps: int, dt: float) -> None:
        model, data = self.model, self.data
        for _ in range(steps):
            self._apply_controls(dt)
            mujoco.mj_step(model, data)

    def finite(self) -> bool:
        """Whether positions and velocities are all finite."""
        return bool(np.isfinite(self.data.qpos).all() and np.isfinite(self.data.qvel).all())

    # ------------------------------------------------------------------ reading (raw space)
    def raw_state(self, module: str) -> RawState:
        """Every motor of ``module`` in raw space (what its motor interface would report).

        Raises:
            KeyError: If the world drives no joint of that module.
        """
        idx = self.modules[module]
        q = self.data.qpos[self._qpos[idx]]
        qd = self.data.qvel[self._dof[idx]]
        tau = self.data.actuator_force[self._act[idx]]
        direction = self._direction[idx]
        return RawState(
            tuple(self.joints[i].name for i in idx),
            self._offset[idx] + direction * q,
            direction * qd,
            direction * tau,
        )

    def position(self, name: str) -> float:
        """A joint's model (calibrated, URDF) position."""
        return float(self.data.qpos[self.joints[self._index[name]].qpos])

    def velocity(self, name: str) -> float:
        """A joint's model (calibrated, URDF) velocity."""
        return float(self.data.qvel[self.joints[self._index[name]].dof])

    def mode_of(self, name: str) -> str:
        """A motor's current control mode (``position``, ``velocity`` or ``effort``)."""
        return MODE_NAMES[int(self.mode[self._index[name]])]

    def root_pose(self, root: str) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth world pose of a root link: position (m) and quaternion (w, x, y, z)."""
        body = self.roots[root]
        return self.data.xpos[body].copy(), self.data.xquat[body].copy()

    # ------------------------------------------------------------------ viewer
    def attach_viewer(self) -> bool:
        """Open MuJoCo's passive viewer when a display exists; returns whether it opened."""
        import os

        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            return False
        import mujoco.viewer

        self._viewer = mujoco.viewer.launch_passive(self.model, self.data)
        return True

    def sync_viewer(self, now: float, period: float = 1 / 30) -> None:
        """Refresh the viewer at most every ``period`` seconds (no-op without a viewer)."""
        viewer = self._viewer
        if viewer is None or now - self._viewer_synced < period:
            return
        self._viewer_synced = now
        if viewer.is_running():
            viewer.sync()

    def close(self) -> None:
        """Close the viewer, if any (idempotent)."""
        viewer, self._viewer = self._viewer, None
        if viewer is not None:
            viewer.close()


def max_real_time_factor(
    assembly: ResolvedAssembly, seconds: float = 2.0, settle: float = 0.5, repeats: int = 3
) -> float:
    """How many times faster than real time the assembly's world steps, motors holding.

    The world settles for ``settle`` simulated seconds first (a mobile robot lands on the
    ground and its contacts form), then steps ``seconds`` of simulated time as fast as it
    can, in ``repeats`` runs of which the fastest counts (as ``timeit`` does: slower runs
    measure other processes on the machine, not the world). The result is simulated seconds
    per wall-clock second of physics alone; the simulator's diagnostics report the figure
    with messages.
    """
    world = SimWorld.from_assembly(assembly)
    try:
        world.step(max(int(settle / world.timestep), 0))
        steps = max(int(seconds / world.timestep / max(repeats, 1)), 1)
        best = math.inf
        for _ in range(max(repeats, 1)):
            start = time.perf_counter()
            world.step(steps)
            best = min(best, time.perf_counter() - start)
    finally:
        world.close()
    return steps * world.timestep / best if best > 0 else math.inf
