"""How an autonomous operator meets the data plane through its executor: its status on
``diagnostics`` (relative to its station's namespace). What its script reads and commands
it declares itself, on the component's node, through the robot it is given."""

from __future__ import annotations

from components.executor.interface import Every, InterfaceSpec, Publish
from components.messages import DIAGNOSTIC_ARRAY

#: Seconds between checks whether a status report is due.
TICK_PERIOD = 0.25

AUTONOMOUS_OPERATOR = InterfaceSpec(
    publish=(Publish("diagnostics", DIAGNOSTIC_ARRAY),),
    every=(Every(TICK_PERIOD, "tick"),),
)
"""The autonomous operator's static interface."""
