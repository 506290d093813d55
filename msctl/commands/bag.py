"""``msctl bag``: info, play and recover of rosbag2 (MCAP) bags, msctl's and ROS 2's; pull of a
computer's own bags (robot-side recording) to this one, over the fleet."""

from __future__ import annotations

import signal
import threading
from datetime import datetime
from pathlib import Path
from typing import Any

import typer

from msctl.errors import MsctlError

app = typer.Typer(help="Bags: describe, replay, recover after a crash.", no_args_is_help=True)

BAG_ARG = typer.Argument(..., help="The bag directory (or one .mcap file).")
JSON_OPT = typer.Option(False, "--json", help="Print one JSON document instead of text.")


@app.command("info")
def info(bag: Path = BAG_ARG, json_output: bool = JSON_OPT) -> None:
    """Describe a bag as `ros2 bag info` does (an unrecovered bag is scanned)."""
    from msctl.console import err, out, print_json
    from msctl.recorder.bag import inspect

    described = inspect(bag)
    metadata = described.metadata
    if json_output:
        print_json(
            {
                "path": str(described.path),
                "files": [
                    {
                        "path": f.path.name,
                        "size": f.size,
                        "complete": f.complete,
                        "message_count": f.message_count,
                    }
                    for f in described.files
                ],
                "size": described.size,
                "storage_identifier": metadata.storage_identifier,
                "ros_distro": metadata.ros_distro,
                "duration_ns": metadata.duration,
                "starting_time_ns": metadata.starting_time,
                "end_time_ns": described.end_time,
                "message_count": metadata.message_count,
                "topics": [
                    {
                        "name": t.name,
                        "type": t.type,
                        "count": t.message_count,
                        "serialization_format": t.serialization_format,
                        "type_description_hash": t.type_hash,
                    }
                    for t in metadata.topics
                ],
                "needs_recovery": described.needs_recovery,
                "reasons": described.reasons,
            }
        )
    else:
        rows = [
            ("Files", "\n".join(f.path.name for f in described.files)),
            ("Bag size", _size(described.size)),
            ("Storage id", metadata.storage_identifier),
            ("ROS Distro", metadata.ros_distro),
            ("Duration", f"{metadata.duration / 1e9:.9f}s"),
            ("Start", _when(metadata.starting_time)),
            ("End", _when(described.end_time)),
            ("Messages", str(metadata.message_count)),
            (
                "Topic information",
                "\n".join(
                    f"Topic: {t.name} | Type: {t.type} | Count: {t.message_count} | "
                    f"Serialization Format: {t.serialization_format}"
                    for t in metadata.topics
                ),
            ),
            ("Services", "0"),
        ]
        for label, value in rows:
            lines = value.splitlines() or [""]
            out.print(f"{label + ':':<19}{lines[0]}", highlight=False, markup=False)
            for line in lines[1:]:
                out.print(f"{'':<19}{line}", highlight=False, markup=False)
    if described.needs_recovery:
        err.print(
            f"[yellow]this bag needs recovery:[/] {'; '.join(described.reasons)} — the counts "
            f"above come from scanning it; `msctl bag recover {bag}` completes it",
            highlight=False,
        )


@app.command("recover")
def recover(
    bag: Path = BAG_ARG,
    fix_schemas: bool = typer.Option(
        False,
        "--fix-schemas",
        help="Also rewrite message definitions written by msctl before it followed rosbag2 "
        "('MSG: pkg/msg/Type', which Foxglove cannot decode) as 'MSG: pkg/Type'.",
    ),
    json_output: bool = JSON_OPT,
) -> None:
    """Complete a bag a crash left unfinished: rebuild file summaries and metadata.yaml
    (an unreadable metadata.yaml is rebuilt from the MCAP files)."""
    from rich.markup import escape
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn

    from msctl.console import err, print_json
    from msctl.recorder.recover import recover as run

    with Progress(
        TextColumn("recovering {task.description}"),
        BarColumn(),
        DownloadColumn(),
        console=err,
        transient=True,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task(str(bag), total=None)

        def advance(name: str, done: int, total: int) -> None:
            progress.update(task, description=name, completed=done, total=total)

        report = run(bag, progress=advance, fix_schemas=fix_schemas)
    if json_output:
        print_json(
            {
                "directory": str(report.directory),
                "files": [
                    {
                        "path": f.path.name,
                        "action": f.action,
                        "messages": f.messages,
                        "salvaged": f.salvaged,
                        "lost_bytes": f.lost_bytes,
                        "damaged_chunks": f.damaged_chunks,
                        "orphans": f.orphans,
                        "fixed_schemas": f.fixed_schemas,
                        "problems": f.problems,
                    }
                    for f in report.files
                ],
                "message_count": report.metadata.message_count,
                "lost_anything": report.lost_anything,
                "notes": report.notes,
            }
        )
        return
    for note in report.notes:
        err.print(f"[yellow]{escape(note)}[/]", highlight=False)
    for outcome in report.files:
        line = f"{outcome.path.name}: {outcome.action}, {outcome.messages:,} messages"
        if outcome.salvaged:
            line += f" ({outcome.salvaged:,} read out of a cut-short chunk)"
        if outcome.fixed_schemas:
            line += f", {outcome.fixed_schemas} schema(s) rewritten in rosbag2's form"
        err.print(line, highlight=False)
        for problem in outcome.problems:
            err.print(f"  [yellow]{problem}[/]", highlight=False)
    alone = bag.is_file() and not (report.directory / "metadata.yaml").exists()
    if not report.rebuilt and not any(f.action == "schemas fixed" for f in report.files):
        err.print(
            f"{bag}: every file was complete"
            + ("" if alone else "; metadata.yaml rewritten from the files"),
            highlight=False,
        )
    verdict = "some data was lost (above)" if report.lost_anything else "nothing lost"
    err.print(
        f"recovered {bag}: {report.metadata.message_count:,} messages on "
        f"{len(report.metadata.topics)} topic(s); {verdict}",
        highlight=False,
    )


@app.command("view")
def view(
    bag: Path = BAG_ARG,
    rerun: bool = typer.Option(False, "--rerun", help="rerun's web viewer (the default)."),
    foxglove: bool = typer.Option(
        False, "--foxglove", help="A Foxglove server playing the bag (its playback bar seeks)."
    ),
    port: int | None = typer.Option(
        None, "--port", help="Web viewer (9090) or Foxglove server (8765) port; 0: any free one."
    ),
    grpc_port: int = typer.Option(9876, "--grpc-port", help="Data port (0: any free one)."),
    save: Path | None = typer.Option(None, "--save", help="Also write an .rrd file."),
    serve: bool = typer.Option(True, "--serve/--no-serve", help="--no-serve: only --save."),
    window: bool | None = typer.Option(
        None,
        "--window/--web",
        help="rerun's desktop window or its web viewer (default: the window with a display).",
        show_default=False,
    ),
    duration: float = typer.Option(0.0, "--for", help="Serve this many seconds (0: Ctrl-C)."),
) -> None:
    """The robot of a bag in 3D, on rerun's timeline (scrub it) or played to Foxglove (its
    playback bar): joints, health, tips."""
    from msctl.commands.view import check_options, view_bag, view_bag_foxglove

    check_options(rerun, foxglove, save, bag=True)
    if foxglove:
        view_bag_foxglove(bag, 8765 if port is None else port, duration)
        return
    view_bag(bag, save, 9090 if port is None else port, grpc_port, serve, duration, window)


@app.command("play")
def play(
    bag: Path = BAG_ARG,
    rate: float = typer.Option(1.0, "--rate", "-r", help="Speed factor (2: twice as fast)."),
    loop: bool = typer.Option(False, "--loop", "-l", help="Start over at the end, until Ctrl-C."),
    topics: list[str] = typer.Option(None, "--topics", help="Only these topics (repeatable)."),
    start_offset: float = typer.Option(
        0.0, "--start-offset", help="Seconds into the bag to start at."
    ),
    remap: list[str] = typer.Option(
        None,
        "--remap",
        "-m",
        help="Publish OLD on NEW: OLD:=NEW (repeatable; OLD must be a topic of the bag).",
    ),
    allow_commands: bool = typer.Option(
        False,
        "--allow-commands",
        help="Play commands, halts and control requests (joint_set, cmd_vel...) onto a "
        "running assembly too; never a module's feedback or raw motor commands (remap those).",
    ),
    json_output: bool = JSON_OPT,
) -> None:
    """Republish a bag's messages with their original timing, through msctl's publishers."""
    from components.comm.graph import snapshot
    from msctl.console import err, print_json
    from msctl.plane import connected
    from msctl.recorder.bag import inspect
    from msctl.recorder.player import Player, parse_remaps

    described = inspect(bag)
    if described.needs_recovery:
        err.print(
            f"[yellow]playing an unrecovered bag[/] ({'; '.join(described.reasons)})",
            highlight=False,
        )
    remaps = parse_remaps(remap or [])
    stop = threading.Event()
    with connected("bag_play") as node:
        player = Player(
            node,
            described,
            rate=rate,
            topics=topics or (),
            start_offset=start_offset,
            remap=remaps,
            loop=loop,
            allow_commands=allow_commands,
        )
        graph = snapshot(node.session, node.domain).topics()
        player.check_commands(lambda t: t in graph and graph[t].subscribers > 0)
        previous = {s: signal.signal(s, lambda *_: stop.set()) for s in _STOPS}
        try:
            report = _play_with_progress(player, stop, described)
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
    for name, why in sorted(report.skipped.items()):
        err.print(f"[yellow]not played:[/] {name}: {why}", highlight=False)
    if json_output:
        print_json(
            {
                "published": report.published,
                "topics": report.topics,
                "skipped": report.skipped,
                "loops": report.loops,
            }
        )
    else:
        err.print(
            f"published {report.published:,} messages on {len(report.topics)} topic(s)",
            highlight=False,
        )
    if report.skipped:
        # A topic asked for and not played is a failure, even when the rest played.
        raise MsctlError(
            f"{len(report.skipped)} topic(s) not played: {', '.join(sorted(report.skipped))}",
            hint="see why above; `msctl bag info` shows each topic's type",
        )


_STOPS = (signal.SIGINT, signal.SIGTERM)


def _play_with_progress(player: Any, stop: threading.Event, described: Any) -> Any:
    from rich.progress import BarColumn, Progress, TextColumn

    from msctl.console import err

    total = max(described.metadata.duration / 1e9 - player.start_offset, 0.0)
    with Progress(
        TextColumn("playing"),
        BarColumn(),
        TextColumn("{task.completed:.1f}/{task.total:.1f} s  {task.fields[sent]} msgs"),
        console=err,
        transient=True,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task("play", total=total or None, sent=0)

        def update(report: Any, played: float) -> None:
            progress.update(task, completed=played, sent=report.published)

        return player.play(stop, update)


def _size(size: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.1f} {unit}" if unit != "B" else f"{size} B"
        size /= 1024  # type: ignore[assignment]
    return f"{size} B"


def _when(stamp: int) -> str:
    if not stamp:
        return "-"
    moment = datetime.fromtimestamp(stamp / 1e9)
    return f"{moment:%b %d %Y %H:%M:%S}.{stamp % 1_000_000_000:09d} ({stamp / 1e9:.9f})"


@app.command("pull")
def pull(
    host: str = typer.Argument(..., help="The computer whose own bags to copy here."),
    into: Path = typer.Option(
        None, "--into", help="Directory the bags go to (default: $MSCTL_HOME/pulled/HOST)."
    ),
    limit: float = typer.Option(
        0.0, "--limit", help="kB/s at most, leaving the radio room for the rest (0: no limit)."
    ),
    patience: float = typer.Option(
        30.0, "--patience", help="Seconds with no answer from HOST before giving up."
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="List what would be pulled, skipped and left; fetch nothing."
    ),
    chunk: int = typer.Option(
        64, "--chunk", help="KiB asked per request (1 to 256).", min=1, max=256
    ),
    window: int = typer.Option(8, "--window", help="Requests in flight at most.", min=1, max=32),
    json_output: bool = JSON_OPT,
) -> None:
    """Copy HOST's own bags (robot-side recording) here over the fleet, chunk by chunk.

    Resumes after a cut (run it again: nothing already here is fetched again), verifies every
    file's SHA-256, and exits non-zero naming any file not verified or a host that did not
    answer.
    """
    from components.paths import state_dir
    from msctl.console import print_json
    from msctl.errors import InputError, NetworkError
    from msctl.launcher.plan import SAFE_NAME
    from msctl.plane import connected
    from msctl.recorder.pull import HostSilent, Puller, PullReport

    if not SAFE_NAME.match(host) or "/" in host or ".." in host:
        raise InputError(
            f"{host!r} is not a computer's name", hint="e.g. `msctl bag pull hl-limb-01`"
        )
    if limit < 0 or patience <= 0:
        raise InputError("--limit must be 0 or more and --patience more than 0")
    target = into if into is not None else state_dir() / "pulled" / host
    with (
        connected("bag_pull") as node,
        Puller(
            node,
            host,
            target,
            chunk=chunk * 1024,
            window=window,
            patience=patience,
            limit=limit * 1000,
        ) as puller,
    ):
        try:
            files = puller.listing()
        except HostSilent as exc:
            if json_output:
                silent = f"{host} gave no answer for {patience:g} s ({exc})"
                print_json(PullReport(host, target, silent=silent).as_dict())
            raise NetworkError(
                f"{host} did not answer within {patience:g} s: {exc}",
                hint=f"check `msctl ps --all` shows {host}'s agent, and its link; then pull again",
            ) from None
        actions = puller.plan(files)
        if dry_run:
            _print_plan(host, target, actions, json_output)
            return
        report = _pull_with_progress(puller, actions)
    _print_report(report, json_output)
    _judge(report)


def _print_plan(host: str, target: Path, actions: list, json_output: bool) -> None:
    from msctl.console import err, print_json

    if json_output:
        print_json(
            {
                "host": host,
                "into": str(target),
                "files": [
                    {
                        "path": a.file.path,
                        "action": a.kind,
                        "size": a.file.size,
                        "abandoned": a.file.abandoned,
                        "offset": a.offset,
                        "why": a.why,
                    }
                    for a in actions
                ],
            }
        )
        return
    for a in actions:
        err.print(f"{a.kind:<8} {a.file.path} ({_size(a.file.size)}) {a.why}", highlight=False)
    err.print(f"{len(actions)} file(s) on {host}; nothing fetched (--dry-run)", highlight=False)


def _pull_with_progress(puller: Any, actions: list) -> Any:
    from rich.progress import (
        BarColumn,
        DownloadColumn,
        Progress,
        TextColumn,
        TransferSpeedColumn,
    )

    from msctl.console import err
    from msctl.recorder.pull import FETCH

    total = sum(a.file.size - a.offset for a in actions if a.kind == FETCH)
    with Progress(
        TextColumn("pulling {task.description}"),
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
        console=err,
        transient=True,
        disable=not err.is_terminal,
    ) as progress:
        task = progress.add_task(puller.host, total=total or None)

        def advance(path: str, size: int) -> None:
            progress.update(task, description=path, advance=size)

        puller.progress = advance
        return puller.pull(actions)


def _print_report(report: Any, json_output: bool) -> None:
    from rich.markup import escape

    from msctl.console import err, print_json
    from msctl.recorder.pull import FAILED, NOT_READY, PULLED, SKIPPED

    if json_output:
        print_json(report.as_dict())
        return
    for f in report.having(PULLED):
        resumed = f" (resumed at {f.resumed_from:,} bytes)" if f.resumed_from else ""
        note = f": [yellow]{escape(f.why)}[/]" if f.why else ""
        err.print(
            f"[green]pulled[/]   {escape(f.path)} {_size(f.size)}{resumed}{note}", highlight=False
        )
    for f in report.having(NOT_READY):
        err.print(f"[yellow]left[/]     {escape(f.path)}: {escape(f.why)}", highlight=False)
    for f in report.having(FAILED):
        err.print(f"[bold red]failed[/]   {escape(f.path)}: {escape(f.why)}", highlight=False)
    err.print(
        f"{report.host}: {len(report.having(PULLED))} pulled and verified, "
        f"{len(report.having(SKIPPED))} already here (verified), "
        f"{len(report.having(NOT_READY))} left (not finished there), "
        f"{len(report.having(FAILED))} failed; {_size(report.fetched)} in "
        f"{report.seconds:.1f} s ({report.rate / 1000:.1f} kB/s) into {report.into}",
        highlight=False,
    )


def _judge(report: Any) -> None:
    from msctl.errors import MsctlError, NetworkError
    from msctl.recorder.pull import FAILED

    failed = report.having(FAILED)
    if report.silent:
        raise NetworkError(
            f"{report.silent}; not verified: {', '.join(f.path for f in failed)}",
            hint=f"`msctl bag pull {report.host}` again once the link is back resumes where "
            "this one stopped",
        )
    if failed:
        raise MsctlError(
            f"not verified: {'; '.join(f'{f.path} ({f.why})' for f in failed)}",
            hint="pull again; a file that fails twice is named above with why",
        )
