"""``msctl health``: every module, component, joint and alarm of the running assembly.

Without options, a textual screen. ``--once`` takes one snapshot for scripts and CI (exit 0
when the worst level is OK or WARN, 1 when something is ERROR or STALE); ``--watch`` prints
level changes as lines; ``--alarms`` prints the last session's alarms from the alarm file.
"""

from __future__ import annotations

import time

import typer

from msctl.errors import InputError, NotFoundError

COMMAND_SETTINGS = {
    "help": "Every module, component, joint and alarm: a live screen, --once, --watch, --alarms."
}


def _assembly():
    from components.assembly import AssemblyError, load_assembly

    try:
        return load_assembly()
    except AssemblyError as exc:
        raise NotFoundError(str(exc)) from exc


def command(
    once: bool = typer.Option(False, "--once", help="Print one snapshot; exit 1 on ERROR/STALE."),
    watch: bool = typer.Option(False, "--watch", help="Print level changes as lines, no screen."),
    alarms: bool = typer.Option(False, "--alarms", help="Print the last session's alarms."),
    json_output: bool = typer.Option(
        False, "--json", help="JSON: one document (--once, --alarms), one line each (--watch)."
    ),
    timeout: float = typer.Option(
        3.0, "--timeout", help="--once: seconds to wait for every module's health."
    ),
    duration: float = typer.Option(
        0.0, "--for", help="--watch or the screen: stop after this many seconds (0: Ctrl-C/q)."
    ),
) -> None:
    """Show the health of the running assembly (reads module health directly; a data
    monitor's alarm history is merged in when one runs)."""
    modes = (("--once", once), ("--watch", watch), ("--alarms", alarms))
    chosen = [name for name, on in modes if on]
    if len(chosen) > 1:
        raise InputError(f"{' and '.join(chosen)} cannot be combined: pick one")
    # Written so that nan fails too (every comparison with it is false).
    if not timeout > 0 or timeout == float("inf"):
        raise InputError(f"--timeout must be positive (finite seconds), not {timeout}")
    if not duration >= 0 or duration == float("inf"):
        raise InputError(
            f"--for must be 0 or more (finite seconds; 0: until stopped), not {duration}"
        )
    if json_output and not (once or watch or alarms):
        raise InputError("--json goes with --once, --watch or --alarms (the screen is not JSON)")
    if alarms:
        _print_alarms(json_output)
        return
    assembly = _assembly()
    if once:
        _once(assembly, json_output, timeout)
    elif watch:
        _watch(assembly, json_output, duration)
    else:
        from msctl.health.app import run_app

        run_app(assembly, duration=duration or None)


def _once(assembly, json_output: bool, timeout: float) -> None:
    from components.messages import ERROR, STALE
    from msctl.console import print_json
    from msctl.health.live import LiveHealth
    from msctl.plane import connected

    started = time.monotonic()
    # The whole snapshot within about --timeout: the router's handshake included.
    with (
        connected("health", open_timeout=timeout) as node,
        LiveHealth(node, assembly, grace=timeout) as live,
    ):
        live.wait_first_news(max(0.1, timeout - (time.monotonic() - started)))
        snapshot = live.evaluate()
    if json_output:
        print_json(snapshot.to_json())
    else:
        _print_table(snapshot)
    if snapshot.level in (ERROR, STALE):
        raise typer.Exit(1)


def _print_table(snapshot) -> None:
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import out

    colours = {"OK": "green", "WARN": "yellow", "ERROR": "red", "STALE": "magenta"}
    level = snapshot.level.name
    table = Table(
        title=f"{snapshot.assembly}: [{colours[level]}]{level}[/]",
        title_justify="left",
    )
    for column in ("level", "module", "host", "components", "message"):
        table.add_column(column, overflow="fold")
    for row in (*snapshot.modules, *snapshot.stations):
        name = row.level.name
        table.add_row(
            f"[{colours[name]}]{name}[/]",
            row.name + (" (station)" if row.station else ""),
            row.host,
            f"{row.components_ok}/{row.components_expected}",
            escape(row.message),
        )
    out.print(table)


def _watch(assembly, json_output: bool, duration: float) -> None:
    import json
    import sys
    import time

    from msctl.console import err
    from msctl.health.alarms import AlarmLog
    from msctl.health.live import LiveHealth
    from msctl.plane import connected

    modules = sum(not s.station for s in _specs(assembly))
    with connected("health") as node, LiveHealth(node, assembly) as live:
        # Recorded and said once it can watch: a session that never connected would stand,
        # empty, as the last session `health --alarms` shows, hiding the one before.
        log = AlarmLog(assembly.template, "msctl health --watch")
        err.print(
            f"watching {assembly.template}: {modules} modules (level changes below; Ctrl-C "
            f"stops; saved to {log.path})",
            highlight=False,
        )
        deadline = None if not duration else time.monotonic() + duration
        live.fetch_history()
        while deadline is None or time.monotonic() < deadline:
            live.evaluate()
            fresh = live.take_alarms()
            if fresh:
                # Saved before shown: whoever reads a line and then presses Ctrl-C finds it in
                # the file (shown first, a KeyboardInterrupt in between lost it).
                log.append(fresh)
                for alarm in fresh:
                    line = json.dumps(alarm.to_json()) if json_output else alarm.line()
                    sys.stdout.write(line + "\n")
                sys.stdout.flush()
            time.sleep(0.2)  # the evaluation rate: level changes are timed to 0.2 s


def _specs(assembly):
    from components.data_monitor.plan import watched

    return watched(assembly)


def _print_alarms(json_output: bool) -> None:
    from rich.markup import escape

    from msctl.console import err, out, print_json
    from msctl.health.alarms import alarm_path, last_session

    path = alarm_path()
    try:
        session = last_session(path)
    except OSError as exc:
        raise InputError(f"cannot read the alarm file {path}: {exc}") from exc
    if session is None:
        raise NotFoundError(
            f"no alarms recorded in {path}",
            hint="`msctl health` and `msctl health --watch` record them",
        )
    if json_output:
        print_json(session.to_json())
        return
    import time

    started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(session.started))
    err.print(
        f"{session.source} on {session.assembly}, started {started}: "
        f"{len(session.alarms)} alarms"
        + (f" ({session.skipped} unreadable lines skipped)" if session.skipped else ""),
        highlight=False,
    )
    for alarm in session.alarms:
        out.print(escape(alarm.line()), highlight=False)
