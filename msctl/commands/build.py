"""``msctl build``: build what changed in the workspace, in dependency order, offline-capable.

msctl build                                   every package, changed ones only
msctl build --packages-up-to limb_control     one package and what it depends on
msctl build --list                            the packages and their dependencies
msctl build --wheelhouse wh                   fill wh with the external wheels, build
msctl build --wheelhouse wh --platform manylinux2014_aarch64 --python-version 3.11
                                              fill wh for a robot (download only)
msctl build --offline --wheelhouse wh         on the robot: no network at all
msctl build --all                             every robot computer's agent builds its own
msctl build --timeout 600                     a package still building after 600 s is stopped

SIGTERM or SIGINT (Ctrl-C) stops the build: every running step's process group is ended,
then the build exits (143 / 130) naming what it stopped, and only then is the workspace's
build lock released.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, MsctlError

COMMAND_SETTINGS = {
    "help": "Build the workspace's packages that changed (doit task graph; offline-capable)."
}


def command(
    ctx: typer.Context,
    workspace: Path = typer.Option(
        None,
        "--workspace",
        "-w",
        envvar="MSCTL_WORKSPACE",
        help="The workspace directory (env MSCTL_WORKSPACE; default: here).",
    ),
    packages_up_to: list[str] = typer.Option(
        None,
        "--packages-up-to",
        "-p",
        help="Build this package and what it depends on (repeatable).",
    ),
    jobs: int = typer.Option(None, "--jobs", "-j", help="Packages built at once (default: CPUs)."),
    offline: bool = typer.Option(
        False, "--offline", help="No network: pip installs from --wheelhouse only."
    ),
    wheelhouse: Path = typer.Option(
        None,
        "--wheelhouse",
        help="Online: download every external wheel here. Offline: install from here.",
    ),
    platform: str = typer.Option(
        None, "--platform", help="With --wheelhouse: wheels for this platform (download only)."
    ),
    python_version: str = typer.Option(
        None, "--python-version", help="With --wheelhouse: wheels for this Python (e.g. 3.11)."
    ),
    editable: bool = typer.Option(False, "--editable", help="Install Python packages editable."),
    wheels: Path = typer.Option(
        None, "--wheels", help="Build Python packages' wheels into this directory instead."
    ),
    force: bool = typer.Option(False, "--force", help="Build every package, changed or not."),
    stop_on_error: bool = typer.Option(
        False, "--stop-on-error", help="Stop at the first failure (default: build the rest)."
    ),
    list_only: bool = typer.Option(
        False, "--list", help="List the packages and their dependencies; build nothing."
    ),
    all_hosts: bool = typer.Option(
        False, "--all", help="Ask every robot computer's agent to build its own workspace."
    ),
    timeout: float = typer.Option(
        None,
        "--timeout",
        help="Seconds one package's build may take (default: no bound); it is stopped, "
        "with what it started, and fails. With --all: seconds to wait for every agent "
        "(default 1800).",
    ),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """Find the packages (pyproject.toml, package.xml, msctl-build.toml) and build them."""
    from msctl.workspace import workspace_dir
    from msctl.workspace.build import BuildOptions
    from msctl.workspace.packages import find_packages

    if jobs is not None and jobs < 1:
        raise InputError(f"--jobs must be at least 1, not {jobs}")
    if timeout is not None and not timeout > 0:
        raise InputError(f"--timeout must be a number of seconds above 0, not {timeout}")
    if all_hosts:
        from msctl.commands.update import refuse_with_all
        from msctl.workspace.remote import build_all

        on_robot = "run `msctl build` with it on the robot"
        refuse_with_all(
            ctx,
            {
                "workspace": "each robot's workspace is its agent's own setting "
                "(MSCTL_WORKSPACE where the agent runs)",
                "wheelhouse": "each robot's wheelhouse is its agent's own setting "
                "(MSCTL_WHEELHOUSE where the agent runs); fill it here with "
                "`msctl build --wheelhouse DIR --platform ...` and copy it there",
                "platform": on_robot,
                "python_version": on_robot,
                "editable": on_robot,
                "wheels": on_robot,
                "force": on_robot,
                "stop_on_error": on_robot,
                "list_only": on_robot,
                "jobs": "each agent builds with its own default (its CPUs)",
            },
        )

        build_all(list(packages_up_to or []), offline, json_output, timeout or 1800.0)
        return
    if (platform or python_version) and wheelhouse is None:
        raise InputError(
            "--platform and --python-version choose the wheels a download fetches",
            hint="give --wheelhouse DIR too",
        )
    if offline and (platform or python_version):
        raise InputError("--offline downloads nothing: --platform/--python-version do not apply")
    if editable and wheels is not None:
        raise InputError("--editable and --wheels exclude each other: install, or build wheels")
    if offline and wheelhouse is not None and not wheelhouse.is_dir():
        raise InputError(
            f"--wheelhouse {wheelhouse} does not exist on this computer",
            hint="fill it online with `msctl build --wheelhouse DIR`, then copy it here",
        )
    ws = workspace_dir(workspace)
    if not ws.is_dir():
        raise InputError(f"workspace {ws} does not exist", hint="run `msctl update` first")
    graph = find_packages(ws)
    keys = graph.up_to(packages_up_to) if packages_up_to else graph.order()
    if list_only:
        _list(graph, keys, json_output)
        return
    options = BuildOptions(
        offline=offline,
        wheelhouse=wheelhouse.absolute() if wheelhouse else None,
        platform=platform,
        python_version=python_version,
        editable=editable,
        wheels=wheels.absolute() if wheels else None,
        force=force,
        keep_going=not stop_on_error,
        timeout=timeout,
        **({"jobs": jobs} if jobs else {}),
    )
    result = _build(graph, keys, options)
    _report(result, graph, json_output)


def _build(graph: Any, keys: list[str], options: Any) -> Any:
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from msctl.console import err
    from msctl.workspace import workspace_lock
    from msctl.workspace.build import Builder

    for note in graph.notes:
        err.print(f"[dim]{escape(note)}[/]", highlight=False)
    if not keys:
        err.print(f"no packages in {graph.root} (pyproject.toml, package.xml, msctl-build.toml)")
    colour = {"built": "green", "failed": "red", "blocked": "red", "skipped": "yellow"}
    with (
        workspace_lock(graph.root, "build"),
        Progress(
            TextColumn("{task.description}"),
            BarColumn(bar_width=20),
            TextColumn("{task.fields[stage]}"),
            TimeElapsedColumn(),
            console=err,
            transient=True,
        ) as progress,
    ):
        rows: dict[str, Any] = {}

        def row(name: str) -> Any:
            if name not in rows:
                rows[name] = progress.add_task(name, total=1, stage="waiting")
            return rows[name]

        for key in keys:
            row(graph.packages[key].name)

        def event(name: str, status: str, detail: str) -> None:
            style = colour.get(status)
            shown = f"[{style}]{status}[/]" if style else status
            done = status in ("built", "up to date", "failed", "blocked", "skipped")
            progress.update(row(name), stage=shown, completed=1 if done else 0)

        builder = Builder(graph, options, event)
        with _stopped_by_signals(builder):
            return builder.run(keys)


#: Exit status of a build stopped by each signal (128 + its number, as a shell reports).
_SIGNALS = {"SIGTERM": 143, "SIGINT": 130}


@contextmanager
def _stopped_by_signals(builder: Any) -> Iterator[None]:
    """SIGTERM and SIGINT stop ``builder`` (its steps' process groups ended) instead of
    killing msctl: Python would die at SIGTERM leaving the build's children running under
    PID 1, and release the build lock while they still wrote the build state."""
    import signal

    def stop(number: int, _frame: Any) -> None:
        builder.stop(f"msctl build got {signal.Signals(number).name}")

    previous = {name: signal.signal(getattr(signal, name), stop) for name in _SIGNALS}
    try:
        yield
    finally:
        for name, handler in previous.items():
            signal.signal(getattr(signal, name), handler)


def _report(result: Any, graph: Any, json_output: bool) -> None:
    """The build's outcome: notes, the packages (a table, or JSON), then each failure, and
    an error if the build was stopped or did not build everything."""
    from rich.markup import escape

    from msctl.console import err, print_json

    for note in result.notes:
        err.print(f"[yellow]{escape(note)}[/]", highlight=False)
    if json_output:
        print_json(result.to_dict())
    elif result.nothing_done and result.packages:
        _report_up_to_date(result)
    else:
        _report_table(result)
    failed = [p for p in result.packages if p.status == "failed"]
    if result.wheelhouse is not None and result.wheelhouse.status == "failed":
        failed.insert(0, result.wheelhouse)
    for p in failed:
        err.print(
            f"[red]{escape(p.name)}[/] failed at {escape(p.step)}: {escape(p.message)}",
            highlight=False,
        )
    for message in result.errors:
        err.print(f"[red]doit:[/] {escape(message)}", highlight=False)
    _raise_unless_built(result, failed)


def _report_up_to_date(result: Any) -> None:
    """Nothing was built: say so, and name what was skipped."""
    from rich.markup import escape

    from msctl.console import err

    err.print(
        f"nothing to build: {len(result.packages)} packages up to date ({result.seconds:.2f} s)",
        highlight=False,
    )
    for p in result.packages:
        if p.status == "skipped":
            err.print(f"[yellow]skipped {p.name}: {escape(p.message)}[/]", highlight=False)


def _report_table(result: Any) -> None:
    """One row per package (the wheelhouse first): its result, time and first note line."""
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import err, out

    table = Table()
    for column in ("package", "type", "result", "time", "note"):
        table.add_column(column, overflow="fold")
    colour = {"built": "green", "failed": "red", "blocked": "red", "skipped": "yellow"}
    rows = ([result.wheelhouse] if result.wheelhouse else []) + result.packages
    for p in rows:
        style = colour.get(p.status, "")
        note = p.message.splitlines()[0] if p.message else ""
        table.add_row(
            escape(p.name),
            p.type,
            f"[{style}]{p.status}[/]" if style else p.status,
            f"{p.seconds:.1f}s" if p.seconds else "",
            escape(note),
        )
    out.print(table)
    err.print(f"[dim]{result.seconds:.1f} s[/]", highlight=False)


def _raise_unless_built(result: Any, failed: list[Any]) -> None:
    """An error naming what was stopped, failed or blocked (exit code of the signal, or 1)."""
    if result.stopped:
        name = result.stopped.rsplit(" ", 1)[-1]
        stopped = [p.name for p in result.packages if p.status == "failed"]
        raise MsctlError(
            f"build stopped: {result.stopped}; its running steps were ended"
            + (f" ({', '.join(stopped)} not built)" if stopped else ""),
            hint="build again to finish it (what was built stays built)",
            exit_code=_SIGNALS.get(name, 1),
        )
    if result.ok:
        return
    blocked = [p for p in result.packages if p.status == "blocked"]
    parts = []
    if failed:
        parts.append(f"failed: {', '.join(p.name for p in failed)}")
    if blocked:
        parts.append(f"not built (a dependency failed): {', '.join(p.name for p in blocked)}")
    if result.errors:
        parts.append("doit could not run the graph")
    raise MsctlError(
        "; ".join(parts) + " (the packages not depending on them were built)",
        hint="each failure's log is under .msctl/build/logs in the workspace",
        exit_code=1,
    )


def _list(graph: Any, keys: list[str], json_output: bool) -> None:
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import out, print_json

    document = graph.to_dict()
    document["packages"] = [p for p in document["packages"] if graph.key_of(p["name"]) in set(keys)]
    if json_output:
        print_json(document)
        return
    table = Table(title=f"packages of {graph.root}", title_justify="left")
    for column in ("package", "type", "path", "depends on", "external"):
        table.add_column(column, overflow="fold")
    for p in document["packages"]:
        table.add_row(
            escape(p["name"]),
            p["type"],
            escape(str(Path(p["path"]).relative_to(graph.root)) or "."),
            escape(", ".join(p["depends"])),
            escape(", ".join(p["external"])),
        )
    out.print(table)
