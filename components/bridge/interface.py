"""How the bridge component meets the data plane through its executor: its status, every
second, on ``diagnostics`` (relative to its station's namespace). What it relays is
subscribed and published by the relays themselves (CDR bytes), not through this spec."""

from __future__ import annotations

from components.executor.interface import Every, InterfaceSpec, Publish
from components.messages import DIAGNOSTIC_ARRAY

#: Seconds between status reports.
STATUS_PERIOD = 1.0

BRIDGE = InterfaceSpec(
    publish=(Publish("diagnostics", DIAGNOSTIC_ARRAY),),
    every=(Every(STATUS_PERIOD, "tick"),),
)
"""The bridge's static interface."""
