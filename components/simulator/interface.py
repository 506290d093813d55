"""How the simulator meets the data plane: every module's motor interface topics, plus its own.

The topics depend on the assembly (one set per module), so the interface is built from it
rather than declared once. Per module it mirrors
:data:`components.motor_interface.interface.MOTOR_INTERFACE` exactly (same names, types and
QoS, absolute under the module's namespace), which is what makes the simulator a drop-in.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from components.comm.qos import SENSOR
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, POSE_STAMPED, TRIGGER
from components.simulator.core import SimulatorConfig
from components.simulator.topics import (
    CLOCK,
    CLOCK_TOPIC,
    SIM_NAMESPACE,
    commands_handler,
    commands_topic,
    halt_handler,
    module_diagnostics_topic,
    pose_topics,
    recover_handler,
    states_topic,
)

if TYPE_CHECKING:
    from components.assembly import ResolvedAssembly


def simulated_slots(assembly: ResolvedAssembly) -> list[str]:
    """The slots whose motors the simulator serves (modules with an actuated joint)."""
    return [m.slot for m in assembly.modules if m.actuated_joints]


def simulator_interface(
    assembly: ResolvedAssembly, config: SimulatorConfig | None = None
) -> InterfaceSpec:
    """The simulator's interface for ``assembly``: per module, what its motor interface has.

    Per module ``/<slot>``: subscribes ``joint_commands`` (from that module's joint manager
    only, as its motor interface); publishes ``joint_states``
    (sensor QoS) and ``diagnostics``; serves ``motors/halt`` and ``motors/recover``. Its own:
    ``/sim/base_pose`` (and ``/sim/<root link>/pose`` with several robots) and
    ``/sim/diagnostics``, and the simulated time on ``/clock``. One timer drives the physics.
    """
    from components.roles import Role, senders

    config = config or SimulatorConfig()
    subscribe, publish, serve = [], [], []
    for slot in simulated_slots(assembly):
        # As a real motor interface: only the module's own joint manager commands it.
        subscribe.append(
            Subscribe(
                commands_topic(slot),
                JOINT_STATE,
                commands_handler(slot),
                senders=senders(Role.RAW, assembly, slot, commands_topic(slot)),
                role=Role.RAW,
            )
        )
        publish.append(Publish(states_topic(slot), JOINT_STATE, SENSOR))
        publish.append(Publish(module_diagnostics_topic(slot), DIAGNOSTIC_ARRAY))
        serve.append(Serve(f"/{slot}/motors/halt", TRIGGER, halt_handler(slot), role=Role.RAW))
        serve.append(
            Serve(f"/{slot}/motors/recover", TRIGGER, recover_handler(slot), role=Role.RAW)
        )
    for _, topic in pose_topics(tuple(assembly.root_links)):
        publish.append(Publish(topic, POSE_STAMPED, SENSOR))
    publish.append(Publish(CLOCK_TOPIC, CLOCK, SENSOR))
    publish.append(Publish(f"{SIM_NAMESPACE}/diagnostics", DIAGNOSTIC_ARRAY))
    return InterfaceSpec(
        subscribe=tuple(subscribe),
        publish=tuple(publish),
        serve=tuple(serve),
        every=(Every(config.tick_period, "tick"),),
    )
