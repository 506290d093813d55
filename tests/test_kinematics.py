"""Kinematics: chain models cut from the composed URDF, the IK solver, and the Kinematics
Manager core driven with fake time and a RecordingOutbox.

Models come from the shipped ``minimal`` template resolved in memory with an H-line limb
(7 joints: position and orientation) and a G-line limb (4 joints: position only).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from components.kinematics_manager.core import KinematicsConfig, KinematicsCore
from components.kinematics_manager.ik import IkSettings, IkSolver
from components.kinematics_manager.model import ChainModel, ModelError, chain_model
from components.kinematics_manager.poses import apart
from components.messages import (
    POSE_STAMPED,
    STALE,
    WARN,
    JointSample,
    header,
    joint_samples,
    joint_state,
    msg,
)

LIMBS = {"H-line": "hlv1-limb-01", "G-line": "gl-limb-01"}
_urdfs: dict[str, str] = {}


def urdf_of(family: str) -> str:
    """The composed URDF of ``minimal`` with a limb of ``family`` (resolved once)."""
    if family not in _urdfs:
        from msctl.assembler import resolve

        _urdfs[family] = resolve("minimal", {"limb1": LIMBS[family]}).urdf
    return _urdfs[family]


def chain_of(family: str) -> ChainModel:
    return chain_model(urdf_of(family), "limb1_base_link", "limb1_tip_link")


@pytest.fixture(params=sorted(LIMBS))
def chain(request: pytest.FixtureRequest) -> ChainModel:
    return chain_of(request.param)


# ---------------------------------------------------------------------- model
def test_chain_model_has_the_limb_joints_in_order_and_no_finger() -> None:
    seven = chain_of("H-line")
    assert seven.joint_names == tuple(f"limb1_joint{i}" for i in range(1, 8))
    four = chain_of("G-line")
    assert four.joint_names == tuple(f"limb1_joint{i}" for i in range(1, 5))
    assert four.lower[0] == pytest.approx(-2.6) and four.upper[0] == pytest.approx(2.6)


def test_chain_model_refuses_joints_the_urdf_path_does_not_have() -> None:
    with pytest.raises(ModelError, match="limb1_joint9"):
        chain_model(urdf_of("G-line"), "limb1_base_link", "limb1_tip_link", ["limb1_joint9"])
    with pytest.raises(ModelError, match="not below"):
        chain_model(urdf_of("G-line"), "limb1_tip_link", "limb1_base_link")


# ---------------------------------------------------------------------- solver
def test_random_reachable_poses_are_solved_within_a_millimetre_and_a_degree(
    chain: ChainModel,
) -> None:
    solver = IkSolver(chain, seed=1)
    rng = np.random.default_rng(7)
    for _ in range(50):
        wanted = rng.uniform(solver.lower, solver.upper)
        target = chain.tip(wanted)
        start = rng.uniform(solver.lower, solver.upper)  # a different configuration
        result = solver.solve(target, start)
        assert result.reachable
        distance, angle = apart(chain.tip(result.q), target)
        assert distance < 1e-3
        if chain.nq >= 6:
            assert math.degrees(angle) < 1.0
        assert np.all(result.q >= solver.lower) and np.all(result.q <= solver.upper)


def test_a_near_target_is_solved_from_the_warm_start_without_restarts(chain: ChainModel) -> None:
    solver = IkSolver(chain)
    current = np.clip(np.full(chain.nq, 0.4), solver.lower, solver.upper)
    nudged = current + 0.05
    result = solver.solve(chain.tip(nudged), current)
    assert result.reachable and result.attempts == 1
    assert result.jump < 0.2  # the nearby solution, not another branch


def test_a_short_chain_ignores_the_target_orientation() -> None:
    chain = chain_of("G-line")
    solver = IkSolver(chain)
    assert solver.position_only
    current = np.zeros(chain.nq)
    goal = chain.tip(np.array([0.3, 0.4, -0.5, 0.2]))
    twisted = pin.SE3(pin.rpy.rpyToMatrix(1.0, -0.5, 2.0), goal.translation)
    result = solver.solve(twisted, current)
    assert result.reachable and result.position_error < 1e-3


def test_an_unreachable_target_gives_the_closest_pose_within_the_jump_bound(
    chain: ChainModel,
) -> None:
    settings = IkSettings(jump_bound=0.5)
    solver = IkSolver(chain, settings)
    current = np.clip(np.full(chain.nq, 0.3), solver.lower, solver.upper)
    here = chain.tip(current)
    far = pin.SE3(here.rotation, here.translation * 4.0)  # well beyond the limb's reach
    result = solver.solve(far, current)
    assert not result.reachable
    assert result.jump <= settings.jump_bound + 1e-9

    # Closer than where it started, and no configuration within the bound does noticeably
    # better by the solver's measure (distance + orientation_weight * angle).
    def closeness(placement: pin.SE3) -> float:
        distance, angle = apart(placement, far)
        return distance + (0.0 if solver.position_only else settings.orientation_weight * angle)

    assert closeness(result.pose) < closeness(here)
    rng = np.random.default_rng(3)
    lo = np.maximum(solver.lower, current - settings.jump_bound)
    hi = np.minimum(solver.upper, current + settings.jump_bound)
    sampled = min(closeness(chain.tip(rng.uniform(lo, hi))) for _ in range(300))
    assert closeness(result.pose) <= sampled + 1e-3


def test_far_solutions_are_taken_only_when_none_is_near(chain: ChainModel) -> None:
    # A reachable target needing a big motion is still reached (it is not a "jump" to
    # refuse, only the last resort after the restarts).
    solver = IkSolver(chain, IkSettings(jump_bound=0.1))
    current = np.zeros(chain.nq)
    wanted = np.clip(np.full(chain.nq, 1.2), solver.lower, solver.upper)
    result = solver.solve(chain.tip(wanted), current)
    assert result.reachable
    assert result.jump > 0.1


# ---------------------------------------------------------------------- core
def make_core(family: str, **config: float) -> KinematicsCore:
    chain = chain_of(family)
    return KinematicsCore(
        "limb1/kinematics_manager", "limb1", chain, KinematicsConfig.from_params(config)
    )


def read(core: KinematicsCore, q: np.ndarray, now: float) -> None:
    names = core.chain.joint_names
    samples = [JointSample(n, float(v), 0.0, 0.0) for n, v in zip(names, q, strict=True)]
    # The joint manager's joint_read also carries the fingers: they must be ignored.
    samples.append(JointSample("limb1_finger_left", 0.01, 0.0, 0.0))
    core.on_joint_read(joint_state(samples, now), now)


def target(
    x: float,
    y: float,
    z: float,
    quat: tuple[float, float, float, float] | None = None,
    frame: str = "limb1_base_link",
) -> object:
    qx, qy, qz, qw = quat if quat is not None else (math.nan,) * 4
    return msg(
        POSE_STAMPED,
        header=header(0.0, frame),
        pose=msg(
            "geometry_msgs/msg/Pose",
            position=msg("geometry_msgs/msg/Point", x=x, y=y, z=z),
            orientation=msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
        ),
    )


def sent_positions(core: KinematicsCore) -> np.ndarray:
    (message,) = core.outbox.take("joint_set")
    by_name = {s.name: s.position for s in joint_samples(message)}
    return np.array([by_name[n] for n in core.chain.joint_names])


def last_status(core: KinematicsCore) -> object:
    return core.outbox.on("diagnostics")[-1].status[0]


def test_tip_pose_follows_joint_read_rate_limited_with_keepalive() -> None:
    core = make_core("H-line")
    core.start(0.0)
    assert last_status(core).level == STALE
    q = np.full(7, 0.2)
    read(core, q, 0.0)
    (first,) = core.outbox.take("tip_pose")
    assert first.header.frame_id == "limb1_base_link"
    expected = core.chain.tip(q).translation
    assert [first.pose.position.x, first.pose.position.y, first.pose.position.z] == (
        pytest.approx(list(expected), abs=1e-9)
    )
    read(core, q + 1e-6, 0.1)  # below the threshold: nothing
    assert core.outbox.take("tip_pose") == []
    read(core, q + 0.1, 0.105)  # a real move: at once
    assert len(core.outbox.take("tip_pose")) == 1
    read(core, q + 0.2, 0.11)  # within min_period: held back ...
    assert core.outbox.take("tip_pose") == []
    core.tick(0.12)  # ... and sent on the next tick
    assert len(core.outbox.take("tip_pose")) == 1
    core.tick(0.5)
    assert core.outbox.take("tip_pose") == []
    core.tick(1.2)  # keep-alive while still
    assert len(core.outbox.take("tip_pose")) == 1


def test_ik_target_sends_joint_set_that_reaches_it() -> None:
    core = make_core("H-line")
    current = np.full(7, 0.2)
    read(core, current, 0.0)
    goal = core.chain.tip(current + np.array([0.2, -0.1, 0.1, 0.2, -0.1, 0.1, 0.05]))
    quat = pin.Quaternion(goal.rotation).coeffs()
    core.on_ik_target(target(*goal.translation, quat=tuple(quat)), 0.1)
    q = sent_positions(core)
    distance, angle = apart(core.chain.tip(q), goal)
    assert distance < 1e-3 and math.degrees(angle) < 1.0
    assert core.counters["solved"] == 1


def test_nan_parts_of_a_target_keep_the_current_value() -> None:
    core = make_core("H-line")
    current = np.array([0.3, 0.4, -0.2, 0.8, 0.1, -0.5, 0.2])
    read(core, current, 0.0)
    here = core.chain.tip(current)
    # Only x changes: y, z and the orientation are NaN, so they keep the current values.
    core.on_ik_target(target(here.translation[0] + 0.03, math.nan, math.nan), 0.1)
    reached = core.chain.tip(sent_positions(core))
    assert reached.translation[0] == pytest.approx(here.translation[0] + 0.03, abs=1e-3)
    assert reached.translation[1:] == pytest.approx(here.translation[1:], abs=1e-3)
    assert math.degrees(apart(reached, here)[1]) < 1.0


def test_an_unreachable_target_warns_and_moves_no_joint_beyond_the_bound() -> None:
    core = make_core("G-line", jump_bound=0.4)
    current = np.array([0.2, 0.3, -0.4, 0.1])
    read(core, current, 0.0)
    core.on_ik_target(target(5.0, 0.0, 0.0), 0.1)
    q = sent_positions(core)
    assert np.max(np.abs(q - current)) <= 0.4 + 1e-9
    status = last_status(core)
    assert status.level == WARN and "unreachable" in status.message
    assert core.counters["unreachable"] == 1
    # The pose commanded is closer to the target than where the tip was.
    assert core.last_result is not None and core.last_result.position_error < (
        np.linalg.norm(core.chain.tip(current).translation - [5.0, 0.0, 0.0])
    )
    read(core, current, 10.0)
    core.tick(10.0)  # the warning ages out
    assert last_status(core).level == 0


def test_targets_are_refused_before_joint_read_in_a_wrong_frame_or_when_stale() -> None:
    core = make_core("G-line")
    core.on_ik_target(target(0.2, 0.0, 0.0), 0.0)
    assert core.outbox.take("joint_set") == []
    assert "before joint_read" in last_status(core).message
    read(core, np.zeros(4), 0.1)
    core.on_ik_target(target(0.2, 0.0, 0.0, frame="world"), 0.2)
    assert core.outbox.take("joint_set") == []
    assert "frame 'world'" in last_status(core).message
    core.on_ik_target(target(0.2, 0.0, 0.0), 5.0)  # last joint_read 4.9 s ago
    assert core.outbox.take("joint_set") == []
    assert core.counters["refused"] == 3
    core.on_ik_target(target(0.2, 0.0, 0.0, quat=(0.0, 0.0, 0.0, 0.0)), 0.2)
    assert core.outbox.take("joint_set") == [] and core.counters["refused"] == 4


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="jump_bound"):
        KinematicsConfig.from_params({"jump_bound": 0})
    with pytest.raises(ValueError, match="keepalive_period"):
        KinematicsConfig(keepalive_period=0)


@pytest.mark.parametrize("x", [math.inf, -math.inf])
def test_an_infinite_target_is_refused_not_a_solver_crash(x: float) -> None:
    # NaN means "keep this coordinate"; inf used to reach the solver and fail in it
    # (AttributeError logged by the executor, nothing in diagnostics).
    core = make_core("G-line")
    read(core, np.zeros(4), 0.1)
    core.on_ik_target(target(x, 0.0, 0.0), 0.2)
    assert core.outbox.take("joint_set") == []
    assert core.counters["refused"] == 1
    assert "infinite" in last_status(core).message
