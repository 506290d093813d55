"""Re-zeroing is guarded like every service that writes to disk (issue 10, finding 2).

The finding: ``/limb1/rezero`` from anyone shifted offsets by 0.56 rad; a legal ``joint_set``
of 3.0 then drove the raw joint 0.51 rad past its original raw limit, and the change survived
restarts. Now a re-zero refuses while the module moves, is bounded per call by module data
unless forced, keeps a timestamped backup of the unit file, logs who asked, and the joint
manager keeps its commands within the raw range the last stage enforces.

The joint manager is the one of the shipped ``minimal`` assembly (hl_limb_v1, unit
hlv1-limb-01), built as the launcher builds it, saving to a copy of its unit file. Core
tests use plain calls and fake time; the caller test runs it in a real executor on Zenoh.
"""

from __future__ import annotations

import logging
import math
import shutil
import threading
import tomllib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.comm import Node, ServiceError
from components.comm.session import SessionSettings
from components.executor.executor import Executor
from components.executor.registry import apply_all
from components.joint_manager.core import JointManagerCore
from components.joint_manager.injections import REZERO
from components.joint_manager.interface import JOINT_MANAGER
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state, msg
from components.motors.base import RawLimits

J2, J3, FINGER = "limb1_joint2", "limb1_joint3", "limb1_finger_left"


def request(*joints: str, force: bool = False) -> Any:
    return msg(f"{REZERO}_Request", joints=list(joints), force=force)


class Limb:
    """limb1's joint manager of ``minimal`` with its data's rezero, saving to ``unit``."""

    def __init__(self, directory: Path) -> None:
        assembly = resolved_assembly(directory, "minimal")
        self.module = assembly.module("limb1")
        self.plan = assembly.component("limb1/joint_manager")
        self.original = Path(self.module.calibration_file)
        self.unit = directory / "units" / self.original.name
        self.unit.parent.mkdir(exist_ok=True)
        shutil.copy(self.original, self.unit)
        self.joints = self.module.actuated_joints
        self.core = JointManagerCore(
            self.plan.name,
            module=self.module.slot,
            joints=[j.spec for j in self.joints],
            calibration={j.spec.name: j.calibration for j in self.joints},
        )
        injections = [
            {**i, "calibration_file": str(self.unit)} for i in self.plan.params["injections"]
        ]
        apply_all(self.core, "joint_manager", injections=injections)
        # What the motor interface and the simulator enforce: the unit's limits at start.
        self.last_stage = {
            j.spec.name: RawLimits.of_joint(j.spec, j.calibration) for j in self.joints
        }
        self.raw = {j.spec.name: j.calibration.to_raw(0.0) for j in self.joints}

    def feed(self, now: float, velocities: dict[str, float] | None = None, **calibrated: float):
        """Feedback for every joint: where it is (calibrated, default 0), and its speed."""
        velocities = velocities or {}
        samples = []
        for j in self.joints:
            name = j.spec.name
            cal = self.core.calibration(name)
            local = j.raw_name
            raw = cal.to_raw(calibrated[local]) if local in calibrated else self.raw[name]
            self.raw[name] = raw
            samples.append(JointSample(name, raw, velocities.get(name, 0.0), 0.0))
        self.core.on_joint_states(joint_state(samples), now)

    def offsets(self, path: Path | None = None) -> dict[str, float]:
        data = tomllib.loads((path or self.unit).read_text())
        return {name: table["zero_offset"] for name, table in data["joints"].items()}

    def backups(self) -> list[Path]:
        return sorted(self.unit.parent.glob(f"{self.unit.name}.*.bak"))

    def commands(self) -> list[JointSample]:
        return [s for m in self.core.outbox.take("joint_commands") for s in joint_samples(m)]


@pytest.fixture
def limb(tmp_path: Path) -> Limb:
    return Limb(tmp_path)


def test_the_bound_comes_from_module_data(limb: Limb) -> None:
    (rezero,) = limb.plan.params["injections"]
    assert rezero == {"name": "rezero", "max_shift": 0.07, "max_shift_linear": 0.002}
    limb.feed(0.0, joint3=-0.1)  # joint3 reads -0.1: re-zeroing it shifts its offset 0.1
    refused = limb.core.on_rezero(request("joint3"), 0.1)
    assert not refused.success and "limb1_joint3 by -0.1 (bound 0.07)" in refused.message
    limb.feed(0.2, joint3=-0.05)
    done = limb.core.on_rezero(request("joint3"), 0.3)
    assert done.success, done.message
    assert list(done.joints) == [J3] and done.shifts[0] == pytest.approx(-0.05)
    # A finger (prismatic) has its own bound, in metres.
    limb.feed(0.4, finger_left=0.003)
    fingers = limb.core.on_rezero(request("finger_left"), 0.5)
    assert not fingers.success and "bound 0.002" in fingers.message


def test_refused_while_the_module_moves(limb: Limb) -> None:
    before = limb.unit.read_bytes()
    calibration = limb.core.calibration(J3)
    # Measured: joint5 turns (another joint than the one re-zeroed: the module moves).
    limb.feed(0.0, velocities={"limb1_joint5": 0.4}, joint3=0.01)
    moving = limb.core.on_rezero(request("joint3"), 0.1)
    assert not moving.success and "the module moves (limb1_joint5)" in moving.message
    # Commanded: a position target far away, not reached yet, even before it picks up speed.
    limb.feed(0.2, joint3=0.01)
    limb.core.on_joint_set(joint_state([JointSample(J2, 1.0, None, None)]), 0.25)
    assert limb.commands()
    commanded = limb.core.on_rezero(request("joint3"), 0.3)
    assert not commanded.success and "limb1_joint2" in commanded.message
    # A velocity command in force counts too.
    limb.feed(0.4, joint2=1.0, joint3=0.01)
    limb.core.on_joint_set(joint_state([JointSample(J2, None, 0.2, None)]), 0.45)
    assert not limb.core.on_rezero(request("joint3"), 0.46).success
    assert limb.unit.read_bytes() == before and limb.backups() == []
    assert limb.core.calibration(J3) == calibration
    # Once it stopped (held), the same request goes through.
    limb.core.on_halt(None, 0.5)
    limb.core.on_recover(None, 0.5)
    limb.feed(0.6, joint2=1.0, joint3=0.01)
    assert limb.core.on_rezero(request("joint3"), 0.7).success


def test_beyond_the_bound_only_with_force(limb: Limb, caplog) -> None:
    caplog.set_level(logging.INFO, logger="msctl.joint_manager")
    before = limb.unit.read_bytes()
    limb.feed(0.0, joint3=0.56)
    refused = limb.core.on_rezero(request(), 0.1)
    assert not refused.success and "limb1_joint3 by +0.56" in refused.message
    assert "with force" in refused.message and "nothing changed" in refused.message
    assert limb.unit.read_bytes() == before and limb.backups() == []
    forced = limb.core.on_rezero(request(force=True), 0.2)
    assert forced.success and "(forced)" in forced.message, forced.message
    shifts = dict(zip(forced.joints, forced.shifts, strict=True))
    assert shifts[J3] == pytest.approx(0.56) and shifts[J2] == pytest.approx(0.0)
    assert limb.offsets()["joint3"] == pytest.approx(0.0036 + 0.56)
    (line,) = [
        r
        for r in caplog.records
        if "rezero asked by" in r.getMessage() and r.levelno == logging.WARNING
    ]
    assert "(forced)" in line.getMessage()


def test_the_056_rad_finding_no_longer_pushes_a_raw_joint_past_its_raw_limit(limb: Limb) -> None:
    start = limb.last_stage[J3]
    limb.feed(0.0, joint3=0.56)
    # Unforced, as the finding's caller asked: refused, so nothing else can follow.
    assert not limb.core.on_rezero(request(), 0.1).success
    # Even forced (a real slip of the encoder), the joint manager keeps its commands within
    # the raw range the motors started with: joint_set 3.0 (legal) stops at the old limit.
    response = limb.core.on_rezero(request(force=True), 0.2)
    assert response.success and f"{J3} keep(s) within the raw range" in response.message
    limb.commands()
    limb.feed(0.3)
    limb.core.on_joint_set(joint_state([JointSample(J3, 3.0, None, None)]), 0.35)
    (command,) = limb.commands()
    assert start.admits(command.position, command.velocity, command.effort) is None
    assert command.position <= start.upper
    # Before the fix it sent raw 3.0 + offset + 0.56, which the last stage (the other guard)
    # refuses as well.
    before_fix = limb.core.calibration(J3).to_raw(3.0)
    assert before_fix - start.upper == pytest.approx(0.51)
    assert start.admits(before_fix, None, None) == "refused_position"
    # At that edge, a velocity outward is refused; inward is taken.
    limb.feed(0.4, joint3=limb.core.calibration(J3).to_calibrated(command.position))
    limb.core.on_joint_set(joint_state([JointSample(J3, None, 0.3, None)]), 0.45)
    assert limb.commands() == [] and limb.core.counters["refused_rezero_range"] == 1
    limb.core.on_joint_set(joint_state([JointSample(J3, None, -0.3, None)]), 0.5)
    (inward,) = limb.commands()
    assert inward.velocity == pytest.approx(-0.3)


def test_a_backup_is_kept_and_restoring_it_gives_the_original_offsets(limb: Limb) -> None:
    original = limb.offsets()
    text = limb.unit.read_bytes()
    limb.feed(0.0, joint1=0.03, joint3=-0.02)
    response = limb.core.on_rezero(request("joint1", "joint3"), 0.1)
    assert response.success, response.message
    (backup,) = limb.backups()
    assert backup.parent == limb.unit.parent and str(backup) in response.message
    assert backup.read_bytes() == text
    assert not backup.name.endswith(".toml")  # never loaded as a unit
    changed = limb.offsets()
    assert changed["joint1"] != original["joint1"] and changed["joint3"] != original["joint3"]
    assert {k: v for k, v in changed.items() if k not in ("joint1", "joint3")} == {
        k: v for k, v in original.items() if k not in ("joint1", "joint3")
    }
    # A second re-zero keeps a second, later backup: the first is never overwritten.
    limb.feed(0.2, joint3=0.01)
    assert limb.core.on_rezero(request("joint3"), 0.3).success
    first, second = limb.backups()
    assert first == backup and first.read_bytes() == text
    assert tomllib.loads(second.read_text())["joints"]["joint3"] == {
        **tomllib.loads(text.decode())["joints"]["joint3"],
        "zero_offset": changed["joint3"],
    }
    # Restoring is copying the backup back.
    shutil.copy(first, limb.unit)
    assert limb.offsets() == original
    assert limb.unit.read_bytes() == text
    # And no temporary file was left behind.
    assert sorted(p.name for p in limb.unit.parent.iterdir() if not p.name.endswith(".bak")) == [
        limb.unit.name
    ]


def test_a_refused_backup_changes_nothing(limb: Limb, monkeypatch) -> None:
    from components.joint_manager import calibration_file

    def no_backup(target: Path, text: str, mode: int) -> None:
        if target.name.endswith(".bak"):
            raise OSError(28, "No space left on device")
        raise AssertionError("the unit file must not be written without its backup")

    monkeypatch.setattr(calibration_file, "_atomic_write", no_backup)
    before, calibration = limb.unit.read_bytes(), limb.core.calibration(J3)
    limb.feed(0.0, joint3=0.01)
    response = limb.core.on_rezero(request("joint3"), 0.1)
    assert not response.success and "cannot keep a backup" in response.message
    assert limb.unit.read_bytes() == before and limb.core.calibration(J3) == calibration


# --------------------------------------------------------------------------- who asked


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


def test_the_log_names_the_caller_node(
    limb: Limb, session_settings: SessionSettings, open_sessions: Callable[[], Any], caplog
) -> None:
    caplog.set_level(logging.INFO, logger="msctl.joint_manager")
    executor = Executor(settings=session_settings)
    executor.add(limb.core, JOINT_MANAGER, namespace="/limb1", node_name="joint_manager")
    motors = Node(open_sessions(), "motor_interface", "/limb1")
    operator = Node(open_sessions(), "operator", "/ground1")
    feedback = motors.publisher("joint_states", JOINT_STATE)
    client = operator.client("/limb1/rezero", REZERO)
    stop = threading.Event()
    where = {"joint3": 0.01}

    def stream() -> None:  # the motors' joint_states, as a motor interface sends them
        while not stop.is_set():
            samples = []
            for j in limb.joints:
                cal = limb.core.calibration(j.spec.name)
                raw = cal.to_raw(where.get(j.raw_name, 0.0))
                samples.append(JointSample(j.spec.name, raw, 0.0, 0.0))
            feedback.publish(joint_state(samples))
            stop.wait(0.02)

    streamer = threading.Thread(target=stream, daemon=True)
    thread = threading.Thread(target=executor.run, daemon=True)
    thread.start()
    streamer.start()
    try:
        wait_until(lambda: limb.core.latest(J3) is not None, 10.0, "joint_states reaching it")

        def call(req: Any) -> Any:
            try:
                return client.call(req, timeout=2.0)
            except ServiceError:
                return None  # not routed yet

        done = wait_until(lambda: call(request("joint3")), 15.0, "a rezero answer")
        assert done.success, done.message
        asked = [r.getMessage() for r in caplog.records if "rezero asked by" in r.getMessage()]
        assert any("asked by /ground1/operator: re-zeroed limb1_joint3" in m for m in asked), asked
        # A refusal names the caller too.
        where["joint3"] = 0.5
        refused = wait_until(
            lambda: (r := call(request("joint3"))) and "bound" in r.message and r, 15.0, "refusal"
        )
        assert not refused.success
        asked = [r.getMessage() for r in caplog.records if "rezero asked by" in r.getMessage()]
        assert any("asked by /ground1/operator: rezero refused" in m for m in asked), asked
    finally:
        stop.set()
        streamer.join(5.0)
        executor.stop()
        thread.join(10.0)
        operator.close()
        motors.close()
    assert not thread.is_alive()


def test_rezero_is_the_srv_the_joint_manager_serves(limb: Limb) -> None:
    (serve,) = limb.core.extra_serve
    assert (serve.service, serve.srv_type) == ("rezero", REZERO)
    # A std_srvs/Trigger request (older callers) is read as: every joint, no force.
    limb.feed(0.0, joint3=0.01)
    assert limb.core.on_rezero(msg("std_srvs/srv/Trigger_Request"), 0.1).success
    limb.feed(0.2, joint3=0.5)
    assert not limb.core.on_rezero(msg("std_srvs/srv/Trigger_Request"), 0.3).success
    assert math.isclose(limb.core.latest(J3).position, 0.5, abs_tol=1e-9)
