"""How the data monitor meets the data plane.

Its outputs and service are absolute or private (two data monitors of one station must not
serve one name): ``/diagnostics_agg`` and ``/diagnostics_toplevel_state`` as ROS's aggregator
names them, and ``~/alarms`` (``/gc1/data_monitor/alarms``). What it reads depends on the
assembly, one ``/<slot>/health`` per module and one ``/<station>/diagnostics`` per station
(where its data archivers report), so :func:`data_monitor_interface` adds those to the static
part :data:`DATA_MONITOR`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from components.data_monitor.core import DIAGNOSTIC_STATUS, GET_ALARMS, health_handler
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import DIAGNOSTIC_ARRAY
from components.roles import Role

if TYPE_CHECKING:
    from components.data_monitor.model import WatchedSpec

#: Seconds between evaluations: a level change is published within this (and min_period).
TICK_PERIOD = 0.2

DATA_MONITOR = InterfaceSpec(
    publish=(
        Publish("/diagnostics_agg", DIAGNOSTIC_ARRAY),
        Publish("/diagnostics_toplevel_state", DIAGNOSTIC_STATUS),
    ),
    serve=(Serve("~/alarms", GET_ALARMS, "on_get_alarms", role=Role.QUERY),),
    every=(Every(TICK_PERIOD, "tick"),),
)
"""The data monitor's static interface (without the per-module health subscriptions)."""


def data_monitor_interface(watched: list[WatchedSpec]) -> InterfaceSpec:
    """:data:`DATA_MONITOR` plus one subscription per watched module (``/<slot>/health``)
    and station (``/<station>/diagnostics``, where its data archivers report)."""
    subscribe = tuple(
        Subscribe(
            spec.health_topic, DIAGNOSTIC_ARRAY, health_handler(spec.name), role=Role.TELEMETRY
        )
        for spec in watched
    )
    return InterfaceSpec(
        subscribe=subscribe,
        publish=DATA_MONITOR.publish,
        serve=DATA_MONITOR.serve,
        every=DATA_MONITOR.every,
    )
