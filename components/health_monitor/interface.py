"""How the health monitor meets the data plane (names relative to the module namespace).

It listens to the module's main topics (``joint_states`` best-effort like every sensor stream,
so the monitor measures the rate subscribers actually get), publishes ``health``, checks for
silences ten times a second and reads the host every two seconds. Graph changes do not come
through this spec: the builder's ``on_bound`` hook watches the graph and posts them to the
core with ``Executor.call_soon``.
"""

from __future__ import annotations

from components.comm.qos import QoS
from components.executor.interface import Every, InterfaceSpec, Publish, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE
from components.roles import Role

#: Seconds between silence checks: a topic going quiet is seen within this of its threshold.
CHECK_PERIOD = 0.1
#: Seconds between host metric reads (CPU load is averaged over this interval).
HOST_PERIOD = 2.0

#: Best effort like every sensor stream, but deep enough that a 100 Hz stream is counted
#: sample by sample even when the executor thread is briefly busy (keep-last 5 would drop).
RATE_QOS = QoS(reliability="best_effort", depth=100)

HEALTH_MONITOR = InterfaceSpec(
    subscribe=(
        # It only watches: every input is telemetry to it (whoever may write a topic is the
        # stricter role another interface gives it, e.g. the joint manager's feedback).
        Subscribe(
            "joint_states", JOINT_STATE, "on_joint_states", qos=RATE_QOS, role=Role.TELEMETRY
        ),
        Subscribe("joint_read", JOINT_STATE, "on_joint_read", role=Role.TELEMETRY),
        Subscribe("diagnostics", DIAGNOSTIC_ARRAY, "on_diagnostics", role=Role.TELEMETRY),
        # What the joint manager asks the motors for, to see a joint stalled off target.
        Subscribe("joint_commands", JOINT_STATE, "on_joint_commands", role=Role.TELEMETRY),
    ),
    publish=(Publish("health", DIAGNOSTIC_ARRAY),),
    every=(Every(CHECK_PERIOD, "tick"), Every(HOST_PERIOD, "on_host_timer")),
)
"""The health monitor's static interface."""
