"""``msctl rehearse``: the assembly's real multi-computer deployment on this Linux machine.

    msctl rehearse up dragon --link wifi            five computers, secure, healthy, then back
    msctl rehearse up dragon --link field-wifi --link ground1=cellular --detach
    msctl rehearse exec ground1 -- msctl health     any command, as that computer
    msctl rehearse shell ground1                    a shell on it
    msctl rehearse link hl-limb-01 --down 5         a 5 s outage of its radio link
    msctl rehearse link hl-limb-01 --profile earth-moon
    msctl rehearse reboot hl-wheel-02 --after 3     a power cut: every process, then its agent
    msctl rehearse status [--json]                  computers, processes, link counters
    msctl rehearse down                             remove everything it made

Needs root, or unprivileged user namespaces (then no sudo: the namespaces live in a user
namespace of the user's own, see ``msctl/rehearse/privileges.py``); without either it says
what to do. See ``msctl/rehearse/rehearsal.py`` for what ``up`` does, step by step: the same
commands the README's field section gives a user.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import typer

from msctl.errors import InputError

app = typer.Typer(
    help="The assembly's multi-computer deployment on this machine, over emulated radio links "
    "(root, or unprivileged user namespaces).",
    no_args_is_help=True,
)

JSON_OPT = typer.Option(False, "--json", help="Print one JSON document.")


@app.command()
def up(
    template: str = typer.Argument(..., help="The template to rehearse (dragon, two_dragons...)."),
    link: list[str] = typer.Option(
        None,
        "--link",
        "-l",
        help="PROFILE for every link, or HOST=PROFILE for one (repeatable); profiles: lan, wifi, "
        "field-wifi, cellular, earth-moon, and MSCTL_LINK_PROFILES's. Default lan.",
    ),
    use: list[str] = typer.Option(
        None, "--use", "-u", help="SLOT=UNIT: another physical unit in a slot (repeatable)."
    ),
    insecure: bool = typer.Option(
        False, "--insecure", help="Plain TCP between the computers, no access control (loud)."
    ),
    detach: bool = typer.Option(
        False, "--detach", "-d", help="Return once it is up; `msctl rehearse down` ends it."
    ),
    no_up: bool = typer.Option(
        False, "--no-up", help="Stop after the agents answer: run `msctl up --all` yourself."
    ),
    seed: int = typer.Option(1, "--seed", help="The link emulator's seed (replays its losses)."),
    timeout: float = typer.Option(
        240.0,
        "--timeout",
        help="Seconds for all of it (computers, agents, then the assembly) to come up.",
    ),
) -> None:
    """Stand the deployment up: a namespace per computer, its agent, then `msctl up --all`."""
    import time

    from msctl.assembler import parse_uses
    from msctl.console import err
    from msctl.rehearse import rehearsal as rh

    uses = parse_uses(use or [])
    if insecure:
        err.print(
            "[bold yellow]warning:[/] --insecure: the computers' routers link over plain TCP "
            "with no access control; anyone on the radio network may command the robot",
            highlight=False,
        )
    started = time.monotonic()
    with err.status("rehearse: starting") as status:
        progress = rh.Progress(
            say=lambda line: err.print(line, highlight=False),
            step=lambda line: (
                status.update(f"rehearse: {line}"),
                err.print(f"[dim]{time.monotonic() - started:6.1f} s[/] {line}", highlight=False),
            ),
        )
        rehearsal = rh.up(
            template,
            uses,
            link or [],
            secure=not insecure,
            seed=seed,
            bring_up=not no_up,
            progress=progress,
            timeout=timeout,
        )
    names = ", ".join(f"{c.name} ({c.address}, {c.profile})" for c in rehearsal.computers)
    err.print(
        f"[green]rehearsal of {rehearsal.template}[/] {'up' if not no_up else 'ready'} in "
        f"{time.monotonic() - started:.1f} s: {names}; "
        f"{'secure' if rehearsal.secure else 'plain TCP'}",
        highlight=False,
    )
    ground = rehearsal.ground.name
    err.print(
        f"next: `msctl rehearse exec {ground} -- msctl health`, `msctl rehearse status`, "
        "`msctl rehearse down`",
        highlight=False,
    )
    if detach:
        return
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        err.print("[dim]Ctrl-C takes the rehearsal down[/]", highlight=False)
        stop.wait()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        with err.status("rehearse: taking everything down"):
            rh.down(rehearsal.root)
        err.print("rehearsal down: no namespace, process or file left", highlight=False)


@app.command("exec")
def exec_command(
    host: str = typer.Argument(..., help="The computer to run as."),
    argv: list[str] = typer.Argument(..., help="The command, after `--`."),
) -> None:
    """Run a command as that computer: its namespace, host name, MSCTL_HOME and identity."""
    from msctl.rehearse.computers import exec_argv
    from msctl.rehearse.rehearsal import Rehearsal

    rehearsal = Rehearsal.load()
    computer = rehearsal.computer(host)
    command = exec_argv(computer, argv)
    sys.stdout.flush()
    sys.stderr.flush()
    # Replaced, not wrapped: the terminal, signals and the exit status are the command's own.
    os.execvpe(command[0], command, rehearsal.env(computer))


@app.command()
def shell(host: str = typer.Argument(..., help="The computer to open a shell on.")) -> None:
    """An interactive shell as that computer."""
    from msctl.rehearse.computers import exec_argv
    from msctl.rehearse.rehearsal import Rehearsal

    rehearsal = Rehearsal.load()
    computer = rehearsal.computer(host)
    env = rehearsal.env(computer)
    env["PS1"] = f"[{computer.name}] \\w \\$ "
    command = exec_argv(computer, [os.environ.get("SHELL") or "/bin/bash", "--norc", "-i"])
    os.execvpe(command[0], command, env)


@app.command()
def link(
    host: str = typer.Argument(..., help="The computer whose radio link to change."),
    profile: str = typer.Option(None, "--profile", "-p", help="Give the link this profile."),
    down_for: float = typer.Option(
        None, "--down", help="Cut the link for this many seconds (0: until --up)."
    ),
    up_again: bool = typer.Option(False, "--up", help="End an outage now."),
) -> None:
    """Change a computer's radio link while the rehearsal runs."""
    from msctl.console import err
    from msctl.rehearse.rehearsal import Rehearsal
    from msctl.rehearse.running import link_request

    chosen = [x for x in (profile is not None, down_for is not None, up_again) if x]
    if len(chosen) != 1:
        raise InputError("give exactly one of --profile P, --down [SECONDS], --up")
    rehearsal = Rehearsal.load()
    rehearsal.computer(host)
    if profile is not None:
        link_request(rehearsal, {"op": "set", "host": host, "profile": profile})
        err.print(f"{host}'s link is now {profile}", highlight=False)
    elif down_for is not None:
        if down_for < 0:
            raise InputError(f"--down takes seconds >= 0, not {down_for}")
        seconds = down_for or None
        link_request(rehearsal, {"op": "down", "host": host, "seconds": seconds})
        err.print(
            f"{host}'s link is down" + (f" for {down_for:g} s" if seconds else " until --up"),
            highlight=False,
        )
    else:
        link_request(rehearsal, {"op": "up", "host": host})
        err.print(f"{host}'s link is up", highlight=False)


@app.command()
def reboot(
    host: str = typer.Argument(..., help="The computer to power-cycle."),
    after: float = typer.Option(0.0, "--after", help="Seconds between the power cut and the boot."),
) -> None:
    """Kill every process of that computer at once, then start its agent as at boot."""
    from msctl.console import err
    from msctl.rehearse import rehearsal as rh

    if after < 0:
        raise InputError(f"--after takes seconds >= 0, not {after}")
    rehearsal = rh.Rehearsal.load()
    with err.status(f"rebooting {host}"):
        killed = rh.reboot(rehearsal, host, after)
    err.print(f"{host}: {killed} processes killed; its agent started again", highlight=False)


@app.command()
def status(json_output: bool = JSON_OPT) -> None:
    """Computers, addresses, processes, and each link's profile and counters."""
    from rich.table import Table

    from msctl.console import err, out, print_json
    from msctl.rehearse import rehearsal as rh

    document = rh.status(rh.Rehearsal.load())
    if json_output:
        print_json(document)
        return
    where = {"root": "as root", "userns": "in a user namespace"}
    mode = document["privileges"].get("mode", "root")
    table = Table(
        title=f"rehearsal of {document['template']} "
        f"({'secure' if document['secure'] else 'plain TCP'}; links: {document['emulator']}; "
        f"{where.get(mode, mode)})"
    )
    for column in ("computer", "address", "processes", "link", "to the access point", "from it"):
        table.add_column(column)
    for computer in document["computers"]:
        link_state = computer["link"] or {}
        table.add_row(
            f"{computer['name']} ({computer['role']})",
            computer["address"],
            str(len(computer["processes"])),
            _link_cell(link_state),
            _direction_cell(link_state.get("up")),
            _direction_cell(link_state.get("down")),
        )
    out.print(table)
    if document["emulator"] != "running":
        err.print(f"[yellow]the link emulator is {document['emulator']}[/]", highlight=False)


def _link_cell(link_state: dict) -> str:
    """The profile, and an outage with how long it has left."""
    text = str(link_state.get("profile", "?"))
    for direction in ("up", "down"):
        outage = (link_state.get(direction) or {}).get("outage")
        if outage:
            left = outage.get("left_s")
            return text + (
                f" [red]outage, {left:.1f} s left[/]" if left is not None else " [red]outage[/]"
            )
    return text


def _direction_cell(counters: dict | None) -> str:
    """Packets and bytes carried, dropped by reason, the delay actually added."""
    if not counters:
        return "-"
    dropped = counters.get("dropped", {})
    drops = ", ".join(f"{n} {why}" for why, n in sorted(dropped.items()) if n) or "none dropped"
    applied = counters.get("applied", {})
    return (
        f"{counters.get('packets', 0)} pkts, {counters.get('bytes', 0) / 1024:.0f} KiB; {drops}; "
        f"+{applied.get('mean_delay_ms', 0.0):.1f} ms"
    )


@app.command()
def down() -> None:
    """Remove everything the rehearsal made: processes, links, namespaces, files."""
    from msctl.console import err
    from msctl.rehearse import rehearsal as rh

    with err.status("rehearse: taking everything down"):
        removed = rh.down()
    if removed:
        err.print(f"removed {', '.join(removed)}", highlight=False)
    err.print("no rehearsal left", highlight=False)
