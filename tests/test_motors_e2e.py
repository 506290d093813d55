"""The joint manager driving real motor backends against emulated hardware, on real Zenoh.

For each motor family, a limb is resolved by the real assembler (``msctl assemble minimal``
with an H-line unit, then with a G-line unit), its joint manager and motor interface are built
from that resolved assembly and run in one Executor, and a separate test node talks to them
over a real Zenoh router, in the module's namespace, exactly as an operator's tools would:

* H-line: the CANopen CiA 402 backend (real python-can, real ``canopen``) on python-can's
  in-process ``virtual`` bus, against emulated CiA 402 drives on the same channel.
* G-line: the Dynamixel backend (real dynamixel-sdk, real pyserial) on a pseudo-terminal,
  against the emulated X-series chain.

Only the hardware is emulated. Expected motor positions are computed here from the module
data (counts per revolution, gear ratio, ticks per revolution...) and the unit's calibration,
independently of the backends' own conversion code, and compared with the emulator's state.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from conftest import wait_until

from components.assembly import JointPlan, ResolvedAssembly, load_assembly
from components.build import BuiltComponent, build_component
from components.comm.node import Node
from components.comm.qos import SENSOR
from components.comm.session import SessionSettings
from components.executor.executor import Component, Executor
from components.messages import (
    DIAGNOSTIC_ARRAY,
    ERROR,
    JOINT_STATE,
    LEVEL_NAMES,
    OK,
    TRIGGER,
    JointSample,
    joint_samples,
    joint_state,
)
from components.motors.emulation.cia402 import EmulatedCia402Bus
from components.motors.emulation.dynamixel import EmulatedDynamixelChain

pytestmark = pytest.mark.e2e

SLOT = "limb1"
UNITS = {"canopen": "hlv1-limb-01", "dynamixel": "gl-limb-01"}
#: The emulated servo chain is a Python thread: size the serial reply timeout as for a slow
#: adapter (the Dynamixel backend tests do the same).
DYNAMIXEL_OPTIONS = {"latency_timer_ms": 40.0}
#: Joint read back vs. target (calibrated space): a Dynamixel tick is 1.5e-3 rad.
TOLERANCE = 4e-3
#: Silence to ERROR on ``diagnostics``: the backend notices (CANopen: a 0.5 s heartbeat
#: timeout; Dynamixel: the next read cycle), then the motor interface's next 1 Hz report.
#: About 2 s at idle; a bound, not a figure: a loaded CI machine took more than 3 s.
DETECT_WITHIN = 30.0
#: Recovery to OK: a reboot or re-enable, then the next report (a bound, as above).
RECOVER_WITHIN = 30.0


def names_motor(plan: JointPlan, message: str) -> bool:
    """Whether a motor diagnostic's text names the joint and its motor id.

    The status itself is named after the joint's assembly name (``limb1_joint2``, which
    :meth:`Limb.wait_level` keys on); the backend's text uses the module's own joint name
    (``joint2``) and the drive or servo id, which together with the status name and the
    hardware id (the channel) say exactly which motor to look at.
    """
    return plan.raw_name in message and str(plan.motor_id) in message


# ------------------------------------------------------------------ resolved assemblies


@pytest.fixture(scope="module")
def assemblies(tmp_path_factory: pytest.TempPathFactory) -> dict[str, ResolvedAssembly]:
    """``minimal`` resolved by the real CLI, once with each family's unit in limb1."""
    resolved = {}
    for family, unit in UNITS.items():
        home = tmp_path_factory.mktemp(f"msctl-home-{family}")
        env = {**os.environ, "MSCTL_HOME": str(home)}
        command = [sys.executable, "-m", "msctl", "assemble", "minimal", "--use", f"{SLOT}={unit}"]
        done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        resolved[family] = load_assembly(home / "assembly")
    return resolved


# ------------------------------------------------------------------ the emulated hardware


class Hardware:
    """What the test needs from an emulated bus, in raw joint terms."""

    channel: str
    options: dict[str, Any]

    def __init__(self, assembly: ResolvedAssembly) -> None:
        self.module = assembly.module(SLOT)

    def joint(self, name: str) -> JointPlan:
        return self.module.joint(name)

    def goal(self, name: str) -> float:
        """The motor's current target, converted to raw joint units by this test."""
        raise NotImplementedError

    def position(self, name: str) -> float:
        """The motor's position, converted to raw joint units by this test."""
        raise NotImplementedError

    def silence(self, name: str) -> None:
        raise NotImplementedError

    def resume(self, name: str) -> None:
        raise NotImplementedError

    def overheat(self, name: str) -> None:
        raise NotImplementedError

    def cool_down(self, name: str) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class Cia402Hardware(Hardware):
    """Emulated CiA 402 drives on a fresh python-can virtual channel."""

    def __init__(self, assembly: ResolvedAssembly) -> None:
        super().__init__(assembly)
        self.channel = f"e2e-{uuid.uuid4().hex[:12]}"
        self.options = {"channel": self.channel, "bus_options": {"interface": "virtual"}}
        counts = {
            j.motor_id: int(j.motor_params.get("counts_per_rev", 4096))
            for j in self.module.actuated_joints
        }
        self.bus = EmulatedCia402Bus(self.channel, counts, counts_per_rev=counts).start()

    def _drive(self, name: str) -> Any:
        return self.bus.drive(self.joint(name).motor_id)

    def _counts_per_rad(self, name: str) -> float:
        # Encoder counts per motor revolution, motor revolutions per output revolution, and
        # for a linear joint (a finger) metres per output radian.
        params = self.joint(name).motor_params
        per_rad = params["counts_per_rev"] * params["gear_ratio"] / (2 * math.pi)
        return per_rad / float(params.get("meters_per_rad", 1.0))

    def goal(self, name: str) -> float:
        return self._drive(name).read_object(0x607A) / self._counts_per_rad(name)

    def position(self, name: str) -> float:
        return self._drive(name).position / self._counts_per_rad(name)

    def silence(self, name: str) -> None:
        self._drive(name).silence()

    def resume(self, name: str) -> None:
        self._drive(name).resume()

    def overheat(self, name: str) -> None:
        drive = self._drive(name)
        drive.set_temperature(drive.temperature_limit + 15.0)

    def cool_down(self, name: str) -> None:
        self._drive(name).set_temperature(40.0)

    def close(self) -> None:
        self.bus.stop()


class DynamixelHardware(Hardware):
    """An emulated X-series chain (each servo the model the module data names) on a pty."""

    def __init__(self, assembly: ResolvedAssembly) -> None:
        super().__init__(assembly)
        joints = self.module.actuated_joints
        self.chain = EmulatedDynamixelChain(
            ids=[j.motor_id for j in joints], models={j.motor_id: j.motor_model for j in joints}
        )
        self.channel = self.chain.port
        self.options = {"channel": self.channel, "bus_options": dict(DYNAMIXEL_OPTIONS)}

    def _ticks_to_raw(self, name: str, ticks: int) -> float:
        # X-series: 4096 ticks per output revolution, 0 rad at the middle tick (2048); a
        # linear joint's motor_params say how far one radian of the horn moves it.
        plan = self.joint(name)
        per_rad = float(plan.motor_params.get("meters_per_rad", 1.0))
        return (ticks - 2048) * 2 * math.pi / 4096 * per_rad

    def goal(self, name: str) -> float:
        sid = self.joint(name).motor_id
        return self._ticks_to_raw(name, self.chain.register(sid, "goal_position"))

    def position(self, name: str) -> float:
        sid = self.joint(name).motor_id
        return self._ticks_to_raw(name, self.chain.register(sid, "present_position"))

    def silence(self, name: str) -> None:
        self.chain.silence(self.joint(name).motor_id)

    def resume(self, name: str) -> None:
        self.chain.resume(self.joint(name).motor_id)  # power-cycled: torque off, RAM reset

    def overheat(self, name: str) -> None:
        sid = self.joint(name).motor_id
        self.chain.set_temperature(sid, self.chain.register(sid, "temperature_limit") + 10)

    def cool_down(self, name: str) -> None:
        self.chain.set_temperature(self.joint(name).motor_id, 40)

    def close(self) -> None:
        self.chain.close()


HARDWARE: dict[str, type[Hardware]] = {"canopen": Cia402Hardware, "dynamixel": DynamixelHardware}


# ------------------------------------------------------------------ the operator's side


@dataclass
class Operator:
    """A separate test node in the module's namespace: what it sees and what it sends."""

    node: Node
    lock: threading.Lock = field(default_factory=threading.Lock)
    #: Calibrated joint name -> latest joint_read position.
    read: dict[str, float] = field(default_factory=dict)
    #: Every raw command the joint manager sent (joint_commands).
    commands: list[JointSample] = field(default_factory=list)
    #: Joint name -> monotonic times joint_states (motor interface) carried it.
    states_at: dict[str, list[float]] = field(default_factory=dict)
    #: Status name -> (level, message) of the latest diagnostics carrying it.
    status: dict[str, tuple[int, str]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        node = self.node
        node.subscription("joint_read", JOINT_STATE, self._on_read)
        node.subscription("joint_commands", JOINT_STATE, self._on_commands)
        node.subscription("joint_states", JOINT_STATE, self._on_states, SENSOR)
        node.subscription("diagnostics", DIAGNOSTIC_ARRAY, self._on_diagnostics)
        self.joint_set = node.publisher("joint_set", JOINT_STATE)
        self.recover_client = node.client("motors/recover", TRIGGER)

    def _on_read(self, message: Any) -> None:
        with self.lock:
            for sample in joint_samples(message):
                if sample.position is not None:
                    self.read[sample.name] = sample.position

    def _on_commands(self, message: Any) -> None:
        with self.lock:
            self.commands.extend(joint_samples(message))

    def _on_states(self, message: Any) -> None:
        now = time.monotonic()
        with self.lock:
            for sample in joint_samples(message):
                self.states_at.setdefault(sample.name, []).append(now)

    def _on_diagnostics(self, message: Any) -> None:
        with self.lock:
            for status in message.status:
                self.status[status.name] = (int(status.level), status.message)

    def send(self, name: str, position: float) -> None:
        """Publish a calibrated position target on ``joint_set``."""
        self.joint_set.publish(joint_state([JointSample(name, position)], time.time()))

    def position(self, name: str) -> float | None:
        with self.lock:
            return self.read.get(name)

    def level(self, name: str) -> tuple[int, str] | None:
        with self.lock:
            return self.status.get(name)

    def states_since(self, name: str, since: float) -> int:
        with self.lock:
            return sum(t >= since for t in self.states_at.get(name, ()))

    def recover_motors(self) -> Any:
        return self.recover_client.call(self.recover_client.request_type()(), timeout=5.0)


@dataclass
class Limb:
    """One limb's joint manager and motor interface, running, and the hardware under them."""

    family: str
    hardware: Hardware
    operator: Operator
    components: list[Component]
    built: list[BuiltComponent]

    @property
    def joints(self) -> list[str]:
        return [j.name for j in self.hardware.module.actuated_joints]

    def plan(self, name: str) -> JointPlan:
        return self.hardware.joint(name)

    def errors(self) -> dict[str, int]:
        return {c.name: c.errors for c in self.components}

    def move(
        self, name: str, target: float, timeout: float = 6.0, tolerance: float = TOLERANCE
    ) -> float:
        """Command a calibrated target (re-sent while waiting) until joint_read reaches it."""

        def arrived() -> bool:
            self.operator.send(name, target)
            position = self.operator.position(name)
            return position is not None and abs(position - target) < tolerance

        try:
            wait_until(arrived, timeout, f"{name} read back at {target}")
        except AssertionError as exc:
            cal = self.plan(name).calibration
            raise AssertionError(
                f"{exc}; joint_read {self.operator.position(name)}, motor "
                f"{cal.to_calibrated(self.hardware.position(name))} (calibrated), "
                f"{self.operator.level(name)}"
            ) from None
        return self.operator.position(name)

    def wait_level(self, name: str, level: int, timeout: float) -> str:
        """Wait until the motor interface's diagnostics give joint ``name`` this level."""

        def reached() -> str | None:
            seen = self.operator.level(name)
            return seen[1] if seen is not None and seen[0] == level else None

        return wait_until(
            reached, timeout, f"{name} {LEVEL_NAMES[level]} (last: {self.operator.level(name)})"
        )


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """Every emulator, bus and executor thread is gone after a test, every pty closed."""
    ptys_before = _open_ptys()
    yield
    ours = ("cia402-emulator", "dynamixel-emulator", "canopen-", "executor-")
    deadline = time.monotonic() + 2.0
    while True:
        leaked = [t.name for t in threading.enumerate() if t.name.startswith(ours)]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked
    assert _open_ptys() <= ptys_before


def _open_ptys() -> set[str]:
    # Only pseudo-terminals: Zenoh's runtime keeps its own descriptors for the process.
    found = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(("/dev/pts/", "/dev/ptmx")):
            found.add(f"{fd}:{target}")
    return found


@pytest.fixture(params=sorted(HARDWARE))
def limb(
    request: pytest.FixtureRequest,
    assemblies: dict[str, ResolvedAssembly],
    session_settings: SessionSettings,
    open_sessions: Callable[[], Any],
) -> Iterator[Limb]:
    """Emulated hardware, the limb's two components in one Executor, an operator node."""
    family = request.param
    assembly = assemblies[family]
    hardware = HARDWARE[family](assembly)
    built: list[BuiltComponent] = []
    executor: Executor | None = None
    runner: threading.Thread | None = None
    operator_node: Node | None = None
    try:
        for kind in ("motor_interface", "joint_manager"):
            plan = assembly.component(f"{SLOT}/{kind}")
            built.append(build_component(plan, assembly, hardware.options))
        executor = Executor(session_settings)
        components = [executor.add(b.core, b.spec, b.namespace, b.node_name) for b in built]
        operator_node = Node(open_sessions(), "e2e_operator", f"/{SLOT}")
        operator = Operator(operator_node)
        runner = threading.Thread(target=executor.run, name=f"executor-{family}", daemon=True)
        runner.start()
        limb = Limb(family, hardware, operator, components, built)
        # Up: every joint reported by the motor interface and OK.
        for name in limb.joints:
            limb.wait_level(name, OK, RECOVER_WITHIN)
        yield limb
        assert limb.errors() == {c.name: 0 for c in components}
    finally:
        if executor is not None:
            executor.stop()
            if runner is not None:
                runner.join(timeout=10.0)
                assert not runner.is_alive(), "the executor did not stop"
            executor.close()
        if operator_node is not None:
            operator_node.close()
        for b in built:
            b.close()
        hardware.close()
    # Stopping ran every core's stop handler: still no exception reached the executor.
    assert limb.errors() == {c.name: 0 for c in components}


# ------------------------------------------------------------------ the tests


def test_calibrated_target_reaches_the_motor(limb: Limb) -> None:
    """joint_set -> calibration -> joint_commands -> backend -> motor -> joint_read agree."""
    name = f"{SLOT}_joint2"
    plan = limb.plan(name)
    cal = plan.calibration
    assert cal.zero_offset != 0.0  # a real unit calibration is in play
    target = 0.4
    limb.move(name, target)
    raw = cal.to_raw(target)
    hw = limb.hardware
    wait_until(lambda: abs(hw.position(name) - raw) < TOLERANCE, 30.0, f"motor at raw {raw}")
    assert hw.goal(name) == pytest.approx(raw, abs=TOLERANCE)
    # joint_read reports the motor's position in calibrated space once the motor settled (the
    # read that first came within tolerance of the target may be from a moment before: a
    # busy machine showed the motor 4.5 mrad further on).
    wait_until(
        lambda: (
            abs(limb.operator.position(name) - cal.to_calibrated(hw.position(name))) < TOLERANCE
        ),
        30.0,
        "joint_read agreeing with the motor",
    )
    # The joint manager sent raw (motor) space, not the calibrated target.
    sent = [c.position for c in limb.operator.commands if c.name == name]
    assert sent and sent[-1] == pytest.approx(raw, abs=1e-9)
    # The other joints were left where they were.
    other = f"{SLOT}_joint3"
    assert hw.position(other) == pytest.approx(0.0, abs=TOLERANCE)


def test_finger_target_in_metres_reaches_the_motor(limb: Limb) -> None:
    """A prismatic joint (rack-and-pinion finger): metres in joint_set, metres in joint_read."""
    # finger_right: gl-limb-01's finger_left calibration puts its whole range beyond the
    # servo's single-turn position range (see the report), so it cannot be used here.
    name = f"{SLOT}_finger_right"
    plan = limb.plan(name)
    assert plan.spec.type == "prismatic" and "meters_per_rad" in plan.motor_params
    target = round(0.5 * plan.spec.upper, 4)
    limb.move(name, target, tolerance=1e-4)
    raw = plan.calibration.to_raw(target)
    hw = limb.hardware
    wait_until(lambda: abs(hw.position(name) - raw) < 1e-4, 30.0, f"finger at raw {raw} m")
    assert hw.goal(name) == pytest.approx(raw, abs=1e-4)


def test_silent_motor_is_an_error_naming_it_then_picked_up_again(limb: Limb) -> None:
    """A motor that stops answering: ERROR naming it, the rest keeps going, and it comes back."""
    silent, other = f"{SLOT}_joint2", f"{SLOT}_joint4"
    limb.move(silent, 0.2)
    limb.hardware.silence(silent)
    message = limb.wait_level(silent, ERROR, DETECT_WITHIN)
    assert names_motor(limb.plan(silent), message)
    assert limb.errors() == {c.name: 0 for c in limb.components}

    # The other joints keep reporting, are OK, and still obey commands. Waited for, not
    # sampled once: the emulated chain is a thread of this process, and on a loaded machine it
    # can miss a reply window of a servo that is not the silent one (seen in a full run).
    limb.move(other, -0.3)
    now = time.monotonic()
    wait_until(lambda: limb.operator.states_since(other, now) >= 5, 10.0, f"{other} reporting")
    others = [name for name in limb.joints if name != silent]
    wait_until(
        lambda: all(limb.operator.level(name)[0] == OK for name in others),
        10.0,
        "every other joint OK",
    )
    assert limb.operator.states_since(silent, now) == 0

    # Back: picked up without any call, OK again, and it moves when told.
    limb.hardware.resume(silent)
    limb.wait_level(silent, OK, RECOVER_WITHIN)
    limb.move(silent, -0.25)
    raw = limb.plan(silent).calibration.to_raw(-0.25)
    wait_until(
        lambda: abs(limb.hardware.position(silent) - raw) < TOLERANCE, 3.0, "moved after resume"
    )
    assert limb.errors() == {c.name: 0 for c in limb.components}


def test_over_temperature_is_an_error_naming_the_joint_until_recover(limb: Limb) -> None:
    """An over-temperature flag: ERROR naming the joint; motors/recover clears it."""
    hot = f"{SLOT}_joint3"
    limb.move(hot, 0.1)
    limb.hardware.overheat(hot)
    message = limb.wait_level(hot, ERROR, DETECT_WITHIN)
    assert names_motor(limb.plan(hot), message)
    assert "temperature" in message or "overheating" in message, message
    for name in limb.joints:
        if name != hot:
            assert limb.operator.level(name)[0] == OK, (name, limb.operator.level(name))

    limb.hardware.cool_down(hot)
    response = limb.operator.recover_motors()
    assert response.success, response.message
    limb.wait_level(hot, OK, RECOVER_WITHIN)
    limb.move(hot, 0.3)
    assert limb.errors() == {c.name: 0 for c in limb.components}


# Hardware error status is a Dynamixel register: this one runs on the G-line limb only.
@pytest.mark.parametrize("limb", ["dynamixel"], indirect=True)
def test_hardware_error_flag_then_recover(limb: Limb) -> None:
    """Dynamixel: a hardware-error flag (overload) shuts the servo down; recover reboots it."""
    name = f"{SLOT}_joint1"
    limb.move(name, 0.2)
    hardware = limb.hardware
    assert isinstance(hardware, DynamixelHardware)
    sid = limb.plan(name).motor_id
    hardware.chain.set_hardware_error(sid, 1 << 5)
    message = limb.wait_level(name, ERROR, DETECT_WITHIN)
    assert names_motor(limb.plan(name), message) and "overload" in message
    assert hardware.chain.register(sid, "torque_enable") == 0

    response = limb.operator.recover_motors()
    assert response.success, response.message
    limb.wait_level(name, OK, RECOVER_WITHIN)
    assert hardware.chain.register(sid, "hardware_error_status") == 0
    assert hardware.chain.register(sid, "torque_enable") == 1
    limb.move(name, -0.2)
    assert limb.errors() == {c.name: 0 for c in limb.components}


def test_out_of_limit_target_never_reaches_the_motor(limb: Limb) -> None:
    """An out-of-limit joint_set is clamped inside the URDF limit before any motor sees it."""
    name = f"{SLOT}_joint2"
    plan = limb.plan(name)
    spec, cal = plan.spec, plan.calibration
    for beyond in (spec.upper + 1.0, spec.lower - 1.0):
        inside = min(max(beyond, spec.lower), spec.upper)

        def near_limit(beyond: float = beyond, inside: float = inside) -> bool:
            # Streamed like an operator holding a key: the watchdog stops a joint whose
            # commands stop while it moves.
            limb.operator.send(name, beyond)
            position = limb.operator.position(name)
            return position is not None and abs(position - inside) < 0.05

        # It stops short of the limit (the manager keeps a margin) and stays there.
        wait_until(near_limit, 8.0, f"{name} near its limit {inside}")
        time.sleep(0.2)
        position = limb.operator.position(name)
        assert spec.lower < position < spec.upper
        goal = cal.to_calibrated(limb.hardware.goal(name))
        assert spec.lower < goal < spec.upper, (goal, spec)
    raw_bounds = sorted((cal.to_raw(spec.lower), cal.to_raw(spec.upper)))
    sent = [c.position for c in limb.operator.commands if c.name == name]
    assert sent
    assert all(raw_bounds[0] < p < raw_bounds[1] for p in sent), (sent, raw_bounds)
