"""``msctl update``: every repository of the workspace on the current experiment's versions.

msctl update                                 the files of the last update (or workspace.repos)
msctl update ws.repos --overlay exp.repos    a workspace file and an experiment overlay
msctl update --offline                       no network: what the clones already hold
msctl update --lock exact.repos              also write the exact commits (a lock file)
msctl update --status                        branch, commit, dirty/ahead/behind, no change
msctl update --all                           every robot computer's agent updates its own
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, MsctlError

COMMAND_SETTINGS = {
    "help": "Put every repository of the workspace on its version (.repos + overlays)."
}


def command(
    ctx: typer.Context,
    repos: Path = typer.Argument(
        None,
        metavar="REPOS",
        help="The workspace's .repos file (default: the last update's, else workspace.repos).",
    ),
    overlay: list[Path] = typer.Option(
        None, "--overlay", "-o", help="An experiment overlay laid over REPOS (repeatable)."
    ),
    workspace: Path = typer.Option(
        None,
        "--workspace",
        "-w",
        envvar="MSCTL_WORKSPACE",
        help="The workspace directory (env MSCTL_WORKSPACE; default: here).",
    ),
    shallow: bool = typer.Option(False, "--shallow", help="Clone missing repositories at depth 1."),
    jobs: int = typer.Option(8, "--jobs", "-j", help="Repositories updated at once."),
    offline: bool = typer.Option(
        False, "--offline", help="No network: check out what the local clones already hold."
    ),
    retry: int = typer.Option(0, "--retry", help="Extra attempts of a failed clone or fetch."),
    lock: Path = typer.Option(
        None, "--lock", help="Also write the exact commits to this .repos file (a lock)."
    ),
    show_status: bool = typer.Option(
        False, "--status", help="Show each repository's state against the files; change nothing."
    ),
    all_hosts: bool = typer.Option(
        False, "--all", help="Ask every robot computer's agent to update its own workspace."
    ),
    timeout: float = typer.Option(
        600.0, "--timeout", help="With --all: seconds to wait for every agent."
    ),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """Clone what is missing, fetch, and check out each repository at its version."""
    from msctl.workspace import workspace_dir
    from msctl.workspace.repos import load
    from msctl.workspace.update import files_in_use

    if jobs < 1:
        raise InputError(f"--jobs must be at least 1, not {jobs}")
    if retry < 0:
        raise InputError(f"--retry must be 0 or more, not {retry}")
    if all_hosts:
        from msctl.workspace.remote import update_all

        refuse_with_all(
            ctx,
            {
                "workspace": "each robot's workspace is its agent's own setting "
                "(MSCTL_WORKSPACE where the agent runs)",
                "lock": "run `msctl update --lock OUT` on the robot",
                "show_status": "run `msctl update --status` on the robot",
                "jobs": "each agent updates with its own default",
                "retry": "each agent updates with its own default",
            },
        )

        base = repos or Path("workspace.repos")
        update_all(base, overlay or [], offline, shallow, json_output, timeout)
        return
    ws = workspace_dir(workspace)
    repos_file, overlays = files_in_use(ws, repos, overlay or [])
    repositories = load(repos_file, overlays)
    if lock is not None:
        from msctl.workspace.update import refuse_unwritable

        # Before the update: a lock that cannot be written must not cost a whole update.
        refuse_unwritable(lock, "--lock")
    if show_status:
        _show_status(ws, repos_file, overlays, repositories, lock, json_output)
        return
    from msctl.workspace.update import UpdateOptions

    options = UpdateOptions(offline=offline, shallow=shallow, jobs=jobs, retries=retry)
    _update(ws, repos_file, overlays, repositories, options, lock, json_output)


def refuse_with_all(ctx: typer.Context, reasons: dict[str, str]) -> None:
    """Refuse options given on the command line that ``--all`` does not send to the agents
    (rather than ignore them); ``reasons``: each parameter's name and what to do instead.

    Raises:
        InputError: Naming the first such option.
    """
    for name, why in reasons.items():
        # By name: typer vendors click, and its ParameterSource enum is private.
        source = ctx.get_parameter_source(name)
        if source is not None and source.name == "COMMANDLINE":
            option = next(p for p in ctx.command.params if p.name == name)
            flag = max(option.opts, key=len)
            raise InputError(f"{flag} does not apply with --all", hint=why)


def _update(
    ws: Path,
    repos_file: Path,
    overlays: list[Path],
    repositories: list[Any],
    options: Any,
    lock: Path | None,
    json_output: bool,
) -> None:
    from rich.markup import escape

    from msctl.console import err, print_json
    from msctl.workspace import workspace_lock
    from msctl.workspace.update import (
        lock_text,
        remember_files,
        update_workspace,
        write_atomically,
    )

    offline = options.offline
    names = " + ".join(str(p) for p in [repos_file, *overlays])
    err.print(
        f"updating {len(repositories)} repositories in {ws} from {names}"
        + (" [yellow](offline)[/]" if offline else ""),
        highlight=False,
    )
    with workspace_lock(ws, "update"):
        outcomes = _run_with_progress(repositories, ws, options, update_workspace)
        remember_files(ws, repos_file, overlays)
        failed = [o for o in outcomes if not o.ok]
        lock_written = None
        if lock is not None:
            if failed:
                err.print(
                    f"[yellow]--lock: {lock} not written: {len(failed)} repositories are not "
                    "on their version (a lock would not be this experiment)[/]",
                    highlight=False,
                )
            else:
                write_atomically(lock, lock_text(ws, repositories, f"from {names}"))
                lock_written = str(lock)
    if json_output:
        print_json(
            {
                "workspace": str(ws),
                "files": [str(p) for p in [repos_file, *overlays]],
                "offline": offline,
                "ok": not failed,
                "lock": lock_written,
                "repositories": [o.to_dict() for o in outcomes],
            }
        )
    else:
        _summary(outcomes)
        if lock_written:
            err.print(f"[green]wrote[/] {lock_written} (exact commits)", highlight=False)
    if failed:
        for o in failed:
            err.print(
                f"[red]{escape(o.path)}[/]: {escape(o.reason)}"
                + (f"\n    [dim]fix:[/] {escape(o.fix)}" if o.fix else ""),
                highlight=False,
            )
        raise MsctlError(
            f"{len(failed)} of {len(outcomes)} repositories not updated: "
            f"{', '.join(o.path for o in failed)} (the others were; each one failed is "
            "left as it was)",
            exit_code=1,
        )


def _run_with_progress(repositories: list[Any], ws: Path, options: Any, run: Any) -> list[Any]:
    """Run the update with a rich progress bar per repository (on stderr)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from msctl.console import err
    from msctl.workspace.update import STAGES

    steps = len(STAGES) + 1
    colour = {"refused": "red", "failed": "red", "updated": "green", "cloned": "green"}
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(bar_width=20),
        TextColumn("{task.fields[stage]}"),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    ) as progress:
        tasks = {
            r.path: progress.add_task(r.path, total=steps, stage="waiting") for r in repositories
        }

        def report(path: str, stage: str) -> None:
            index = STAGES.index(stage) if stage in STAGES else 0
            progress.update(tasks[path], completed=index, stage=stage)

        def finished(outcome: Any) -> None:
            style = colour.get(outcome.result, "")
            stage = f"[{style}]{outcome.result}[/]" if style else outcome.result
            progress.update(tasks[outcome.path], completed=steps, stage=stage)

        return run(repositories, ws, options, report, finished)


def _summary(outcomes: list[Any]) -> None:
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import out

    table = Table()
    for column in ("repository", "from", "to", "result", "note"):
        table.add_column(column, overflow="fold")
    colour = {"refused": "red", "failed": "red", "updated": "green", "cloned": "green"}
    for o in outcomes:
        style = colour.get(o.result, "")
        note = o.reason if not o.ok else "; ".join(o.notes)
        table.add_row(
            escape(o.path),
            o.before,
            o.after if o.after != o.before else "=",
            f"[{style}]{o.result}[/]" if style else o.result,
            escape(note),
        )
    out.print(table)


def _show_status(
    ws: Path,
    repos_file: Path,
    overlays: list[Path],
    repositories: list[Any],
    lock: Path | None,
    json_output: bool,
) -> None:
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import err, out, print_json
    from msctl.workspace.status import status, unlisted_clones
    from msctl.workspace.update import lock_text, write_atomically

    rows = status(repositories, ws)
    extra = unlisted_clones(ws, repositories)
    names = " + ".join(str(p) for p in [repos_file, *overlays])
    if lock is not None:
        write_atomically(lock, lock_text(ws, repositories, f"status of {names}"))
    if json_output:
        print_json(
            {
                "workspace": str(ws),
                "files": [str(p) for p in [repos_file, *overlays]],
                "repositories": [r.to_dict() for r in rows],
                "not_in_files": extra,
                "lock": str(lock) if lock else None,
            }
        )
        return
    table = Table(title=f"{ws} against {names}", title_justify="left")
    for column in ("repository", "wants", "branch", "commit", "state", "note"):
        table.add_column(column, overflow="fold")
    for r in rows:
        if not r.present:
            state = "[red]absent[/]"
        elif r.on_version:
            state = "[green]on version[/]" + (" [yellow]dirty[/]" if r.dirty else "")
        else:
            state = "[yellow]off version[/]" if r.on_version is False else "[yellow]unknown[/]"
        table.add_row(
            escape(r.path),
            escape(r.version or "(default branch)"),
            escape(r.branch or ("(detached)" if r.present else "-")),
            (r.commit or "-")[:10],
            state,
            escape(r.note),
        )
    out.print(table)
    if extra:
        err.print(
            f"[yellow]clones not in the files (left alone): {', '.join(extra)}[/]",
            highlight=False,
        )
    if lock is not None:
        err.print(f"[green]wrote[/] {lock} (exact commits)", highlight=False)
