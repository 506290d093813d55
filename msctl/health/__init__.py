"""``msctl health``: the operator's view of every module, component, joint and alarm.

:mod:`msctl.health.live` feeds a :class:`~components.data_monitor.board.HealthBoard` from the
data plane (every module's health, the graph, the supervisors); :mod:`msctl.health.alarms`
keeps the alarm file; :mod:`msctl.health.app` is the textual screen on top of them.
"""
