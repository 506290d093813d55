"""Real joint managers for teleop tests, in this process, over emulated motors.

:class:`ModulesRig` builds the joint managers of some modules of a resolved assembly through
the component registry and runs them in one :class:`~components.executor.executor.Executor`
on a thread, as ``msctl up`` runs them. Only the hardware below them is emulated
(:class:`EmulatedMotors`): each module's motors follow their ``joint_commands`` at once
(position) or at the commanded speed (velocity) and report ``joint_states`` at 100 Hz.
"""

from __future__ import annotations

import threading
from typing import Any

from components.assembly import ResolvedAssembly
from components.build import BuiltComponent, build_component
from components.comm.node import Node
from components.comm.qos import SENSOR
from components.comm.session import SessionSettings, open_session
from components.executor.executor import Executor
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state

#: Seconds between two ``joint_states`` of the emulated motors.
MOTOR_PERIOD = 0.01


class EmulatedMotors:
    """One module's motors: raw positions that follow the joint manager's commands.

    Args:
        session: An open session (the caller closes it).
        assembly: The resolved assembly.
        slot: The module.
    """

    def __init__(self, session: Any, assembly: ResolvedAssembly, slot: str) -> None:
        module = assembly.module(slot)
        self.names = [j.spec.name for j in module.actuated_joints]
        self.position = dict.fromkeys(self.names, 0.0)
        self.velocity = dict.fromkeys(self.names, 0.0)
        self.commands: list[JointSample] = []
        self._lock = threading.Lock()
        # As the module's motor interface: the joint manager takes feedback from it only.
        self.node = Node(session, "motor_interface", module.namespace)
        self._states = self.node.publisher("joint_states", JOINT_STATE, SENSOR)
        self.node.subscription("joint_commands", JOINT_STATE, self._on_commands)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"motors-{slot}", daemon=True)
        self._thread.start()

    def _on_commands(self, message: Any) -> None:
        with self._lock:
            for sample in joint_samples(message):
                if sample.name not in self.position:
                    continue
                self.commands.append(sample)
                if sample.position is not None:
                    self.position[sample.name] = sample.position
                    self.velocity[sample.name] = 0.0
                elif sample.velocity is not None:
                    self.velocity[sample.name] = sample.velocity

    def _run(self) -> None:
        while not self._stop.wait(MOTOR_PERIOD):
            with self._lock:
                for name, speed in self.velocity.items():
                    self.position[name] += speed * MOTOR_PERIOD
                rows = [JointSample(n, self.position[n], self.velocity[n], 0.0) for n in self.names]
            self._states.publish(joint_state(rows))

    def close(self) -> None:
        """Stop reporting and undeclare (idempotent)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.node.close()


class ModulesRig:
    """Joint managers of ``slots`` on a thread, over emulated motors.

    Args:
        assembly: The resolved assembly.
        slots: The modules to run.
        settings: Session settings joining the test's router.
    """

    def __init__(
        self, assembly: ResolvedAssembly, slots: list[str], settings: SessionSettings
    ) -> None:
        self.assembly = assembly
        self.managers: dict[str, BuiltComponent] = {
            slot: build_component(assembly.component(f"{slot}/joint_manager"), assembly)
            for slot in slots
        }
        self.executor = Executor(settings=settings)
        for built in self.managers.values():
            self.executor.add(built.core, built.spec, built.namespace, built.node_name)
        self._runner = threading.Thread(target=self.executor.run, name="executor", daemon=True)
        self._runner.start()
        self.session = open_session(settings)
        self.motors = {slot: EmulatedMotors(self.session, assembly, slot) for slot in slots}

    def close(self) -> None:
        """Stop everything and close both sessions."""
        for motors in self.motors.values():
            motors.close()
        self.executor.stop()
        self._runner.join(timeout=10.0)
        for built in self.managers.values():
            built.close()
        self.session.close()
