"""The data monitor kind: the assembly's health as /diagnostics_agg, and its alarm history."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="data_monitor",
    summary="aggregates module health into /diagnostics_agg, keeps alarms (msctl health)",
    placement=Placement.STATION,
    config=("components.data_monitor.core:DataMonitorConfig",),
    builder="components.data_monitor.build:build",
    interface="components.data_monitor.interface:DATA_MONITOR",
    # Shared by every data monitor; the launcher also waits for each one's node.
    healthy_output="/diagnostics_toplevel_state",
    # Health is judged over seconds; a late aggregate by milliseconds changes nothing.
    niceness=5,
    # It asks each computer's agent what runs there (the launcher's control service).
    preload=("components.supervision.wire",),
)
