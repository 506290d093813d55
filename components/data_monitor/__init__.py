"""Data monitor: every module's health and the supervisors' states, aggregated for the assembly.

:mod:`components.data_monitor.board` is the pure aggregation that ``msctl health`` (its TUI,
``--once`` and ``--watch``) and the ``data_monitor`` component share; the component publishes
it as ``/diagnostics_agg`` (ROS aggregator naming) and keeps the alarm history.
"""
