"""Data monitor: every module's health and the supervisors' states, aggregated for the assembly.

:mod:`components.data_monitor.board` is the pure aggregation that ``msctl health`` (its TUI,
``--once`` and ``--watch``) and the ``data_monitor`` component share (what it shows:
:mod:`~components.data_monitor.model`; its alarms: :mod:`~components.data_monitor.alarms`;
live rates: :mod:`~components.data_monitor.measures`); the component publishes it as
``/diagnostics_agg`` (ROS aggregator naming) and keeps the alarm history.
"""
