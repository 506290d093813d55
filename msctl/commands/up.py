"""``msctl up``: start this computer's part of the resolved assembly, and watch it come up."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from msctl.errors import InputError, MsctlError, NotFoundError, OperationTimeout

if TYPE_CHECKING:
    from components.supervision.protocol import ProcessRow

#: Where the router `msctl up` or `msctl agent` starts listens and links: their `--help`'s
#: epilog.
ROUTER_EPILOG = (
    "Unless a router answers on MSCTL_ZENOH_CONNECT (default tcp/localhost:7447), this command "
    "starts this computer's router, on loopback only; MSCTL_ROUTER_LISTEN adds endpoints "
    "(comma-separated, e.g. tcp/0.0.0.0:7448; one on the loopback listener's own port, "
    "tcp/0.0.0.0:7447, replaces it) and MSCTL_ROUTER_CONNECT links it to other routers "
    "(comma-separated, e.g. tcp/ground1:7448). Plain TCP beyond this computer is warned of; "
    "--secure (MSCTL_SECURE=1) takes mutual TLS and access control from `msctl net` instead."
)
COMMAND_SETTINGS = {
    "help": "Start this computer's part of the assembly (simulated off-robot).",
    "epilog": ROUTER_EPILOG,
}

_DAEMON_ENV = "MSCTL_UP_DAEMON"


def load_resolved(template: str | None, uses: list[str], defaults: bool = False) -> Any:
    """Resolve ``template`` first when given, then load the resolved assembly.

    Without a template, say which units of the resolution in use are not the defaults (when
    resolving, the assembler says it).
    """
    from components.assembly import AssemblyError, load_assembly
    from msctl.commands.assemble import note_off_defaults, resolve_and_write

    if template:
        resolve_and_write(template, uses, defaults)
    elif uses or defaults:
        raise InputError(
            "--use and --defaults apply when resolving: name the TEMPLATE too",
            hint="e.g. `msctl up dragon --use limb1=hlv1-limb-03`",
        )
    try:
        assembly = load_assembly()
    except AssemblyError as exc:
        raise NotFoundError(str(exc)) from exc  # the message already says what to run
    if not template:
        note_off_defaults(assembly.template, dict(assembly.units))
    return assembly


def command(
    template: str = typer.Argument(None, help="Resolve this template first (e.g. dragon)."),
    sim: bool = typer.Option(None, "--sim/--real", help="Force simulation on or off."),
    duration: float = typer.Option(None, "--for", help="Run this many seconds, then stop."),
    detach: bool = typer.Option(False, "--detach", help="Return once up; keep running."),
    host: str = typer.Option(None, "--host", help="Act as this computer (default MSCTL_HOST)."),
    all_hosts: bool = typer.Option(False, "--all", help="Start every host's part via agents."),
    insecure: bool = typer.Option(
        False, "--insecure", help="With --all: allow agents over a link that is not TLS."
    ),
    secure: bool = typer.Option(
        False,
        "--secure",
        envvar="MSCTL_SECURE",
        help="Run the embedded router from `msctl net config`: mutual TLS and access control "
        "(env MSCTL_SECURE).",
    ),
    use: list[str] = typer.Option(None, "--use", help="SLOT=UNIT when resolving TEMPLATE."),
    defaults: bool = typer.Option(
        False, "--defaults", help="When resolving TEMPLATE: every other slot on its default unit."
    ),
    speed: float = typer.Option(1.0, "--speed", help="Simulation speed factor."),
    timeout: float = typer.Option(60.0, "--timeout", help="Seconds to wait for all-healthy."),
    kill_unresponsive: float = typer.Option(
        5.0,
        "--kill-unresponsive-after",
        envvar="MSCTL_KILL_UNRESPONSIVE_AFTER",
        help="Seconds a component process may stay unresponsive (no heartbeat) before it is "
        "killed and restarted [env MSCTL_KILL_UNRESPONSIVE_AFTER].",
    ),
) -> None:
    """Start the components of this computer, wait until every one is healthy, then run.

    The router it starts when none answers is the epilog of ``COMMAND_SETTINGS``.
    """
    from msctl.launcher import state
    from msctl.launcher.plan import plan_host, this_host

    if speed <= 0:
        raise InputError(f"--speed must be positive, not {speed}")
    if not kill_unresponsive > 0:
        raise InputError(f"--kill-unresponsive-after must be positive, not {kill_unresponsive}")
    if secure:
        # The embedded router, started by the supervisor (maybe detached), reads it.
        os.environ["MSCTL_SECURE"] = "1"
    if all_hosts:
        from msctl.launcher.remote import refuse_plain_links, up_all

        if not insecure:
            refuse_plain_links()
        up_all(load_resolved(template, use or [], defaults), sim, speed, timeout)
        return
    host = host or this_host()
    # Before anything looks at the state: of two `up` started together, one goes on and the
    # other is refused here, naming the first (the state file cannot tell them apart yet).
    lock = _run_lock(template, host)
    server = None
    try:
        previous = state.read_state()
        if state.supervisor_alive(previous) and os.environ.get(_DAEMON_ENV) != "1":
            raise MsctlError(
                f"{previous.get('template')} is already up on {previous.get('host')} "
                f"(supervisor pid {previous.get('supervisor_pid')})",
                hint="see it with `msctl ps`, stop it with `msctl down`",
                exit_code=3,
            )
        if not detach or os.environ.get(_DAEMON_ENV) == "1":
            # This process runs the launch: its fork server imports while it resolves.
            server = _early_forkserver()
        try:
            assembly = load_resolved(template, use or [], defaults)
        except OSError as exc:  # writing the resolution into MSCTL_HOME
            raise state.home_not_writable(Path(exc.filename or state.state_dir()), exc) from exc
        lock.note(template=assembly.template)
        if assembly.secure:
            # `[network] secure = true` says what --secure does: the embedded router (maybe
            # started by a detached supervisor, which inherits this) runs the generated config.
            os.environ["MSCTL_SECURE"] = "1"
        if os.environ.get(_DAEMON_ENV) != "1":
            _refuse_if_agent_serves(host)
        plan = plan_host(assembly, host, sim)
        if not plan.processes:
            raise InputError(
                f"{host} runs nothing of {assembly.template}",
                hint="use --host to act as one of its computers, or --sim to run it all here",
            )
        if detach and os.environ.get(_DAEMON_ENV) != "1":
            # Said here, before detaching: the detached supervisor's own lines go to its log.
            _check_router(plan)
            _detach(plan, sim, duration, host, speed, timeout, kill_unresponsive, lock)
            return
        _run_foreground(assembly, plan, duration, speed, timeout, kill_unresponsive, server)
    finally:
        if server is not None:
            server.close()  # after the run's workers (idempotent), or unused: a refusal
        lock.release()


def _check_router(plan: Any) -> None:
    """The router the run will start, checked now: a setting that cannot work (a port taken,
    an address not this computer's, an identity missing) fails here in one line, and what
    to warn of (plain TCP beyond this computer, an identity made) is said.

    Raises:
        RouterStartError: Naming the endpoint, file or host, and the fix.
    """
    from rich.markup import escape

    from components.comm.session import SessionSettings
    from msctl.console import err
    from msctl.launcher.router import EmbeddedRouter, router_reachable

    settings = SessionSettings.from_env()
    if not settings.connect:
        return
    router = EmbeddedRouter.from_env(settings.connect[0], plan.host, plan.off_robot)
    lines = [router.not_applied()] if router_reachable(router.endpoint) else router.check()
    for line in filter(None, lines):
        err.print(f"[bold yellow]{escape(line)}[/]", highlight=False)


def _early_forkserver() -> Any:
    """The run's fork server, started now (``None``: workers start as new interpreters)."""
    from components.assembly import lock_path
    from msctl.launcher import forkserver

    try:
        return forkserver.for_run(lock_path())
    except OSError:
        return None  # the launch says why when it tries again


#: The descriptor of the run lock a detached supervisor inherits from the `up` that started it.
_LOCK_FD_ENV = "MSCTL_UP_LOCK_FD"


def _run_lock(template: str | None, host: str) -> Any:
    """Take this MSCTL_HOME's run lock, or keep the one a detaching `up` handed down.

    Raises:
        AlreadyRunning: If another supervisor holds it (named).
        HomeNotWritable: If MSCTL_HOME cannot be written (named).
    """
    from msctl.launcher.state import RunLock

    inherited = os.environ.pop(_LOCK_FD_ENV, None)
    if inherited and os.environ.get(_DAEMON_ENV) == "1":
        return RunLock.adopt(int(inherited), host=host, by="msctl up --detach")
    return RunLock.acquire(template=template, host=host, by="msctl up")


def _refuse_if_agent_serves(host: str) -> None:
    """Two supervisors for one host would answer the same requests: refuse the second."""
    from components.comm.session import SessionSettings
    from msctl.launcher.control import host_namespace
    from msctl.launcher.router import router_reachable

    settings = SessionSettings.from_env()
    if not settings.connect or not router_reachable(settings.connect[0]):
        return  # no router yet: no agent can be serving through it
    from msctl.launcher.fleet import supervisors
    from msctl.plane import connected

    with connected("up_check") as node:
        serving = host_namespace(host) in supervisors(node)
    if serving:
        raise MsctlError(
            f"a supervisor (an agent, or another `msctl up`) already serves {host}",
            hint="start through it with `msctl up --all` from a ground station, or see `msctl ps`",
        )


def _run_foreground(
    assembly: Any,
    plan: Any,
    duration: float | None,
    speed: float,
    timeout: float,
    kill_unresponsive: float,
    server: Any = None,
) -> None:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from msctl.console import err
    from msctl.launcher.run import Launch
    from msctl.launcher.supervisor import LivenessPolicy

    launch = Launch(
        assembly,
        plan,
        speed=speed,
        liveness=LivenessPolicy(kill_after=kill_unresponsive),
        forkserver=server,
    )
    signals: list[int] = []  # the stop signals received, first first

    def on_signal(signum: int, _frame: Any) -> None:
        signals.append(signum)
        launch.request_stop()

    previous = {
        s: signal.signal(s, on_signal)
        # SIGHUP: the operator's terminal or SSH link went away; stop as for Ctrl-C, or
        # every process group would be left running with a state file naming a dead pid.
        for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    }
    daemon = os.environ.get(_DAEMON_ENV) == "1"
    interrupted_starting = False
    try:
        mode = "simulation" if plan.simulated else "hardware"
        err.print(
            f"[bold]{assembly.template}[/] on {plan.host} ({mode}"
            + (", off-robot" if plan.off_robot else "")
            + f"): {len(plan.components)} components in {len(plan.processes)} processes",
            highlight=False,
        )
        if plan.not_built:
            err.print(
                f"[dim]not started ({len(plan.not_built)}, kinds not implemented yet): "
                + ", ".join(sorted({k for _, k in plan.not_built}))
                + "[/]",
                highlight=False,
            )
        started = time.monotonic()
        try:
            launch.start()
        except RuntimeError as exc:
            raise MsctlError(
                str(exc), hint="free the port or point MSCTL_ZENOH_CONNECT elsewhere"
            ) from exc
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} healthy"),
            TimeElapsedColumn(),
            console=err,
            transient=True,
            disable=daemon,
        ) as progress:
            task = progress.add_task("starting", total=len(plan.components))
            while not launch._stop and not launch.all_healthy():
                launch.step()
                views = launch.components()
                healthy = sum(v.state == "running" for v in views)
                waiting = [v.name for v in views if v.state != "running"]
                progress.update(
                    task, completed=healthy, description=f"waiting for {', '.join(waiting[:3])}"
                )
                if launch.failed():
                    _report_failure(launch, "failed")
                if time.monotonic() - started > timeout:
                    _report_failure(launch, f"not healthy after {timeout:g} s")
                if launch._stop:
                    break
                time.sleep(0.05)
        elapsed = time.monotonic() - started
        if not launch._stop:
            launch.write_state()
            _print_summary(launch, elapsed)
            launch.run(None if duration is None else max(0.0, duration - elapsed), _print_events)
        else:
            # A Ctrl-C before the run was up: it never did what was asked, so the command
            # ends as every interrupted msctl command does (one line, 130), and a script's
            # `msctl up dragon && ...` goes no further. Once up, Ctrl-C is how a foreground
            # run ends: 0, as for SIGTERM and SIGHUP at any time.
            interrupted_starting = bool(signals) and signals[0] == signal.SIGINT
    finally:
        launch.shutdown()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        err.print(f"{assembly.template} stopped on {plan.host}", highlight=False)
    if interrupted_starting:
        raise KeyboardInterrupt


_printed_events = 0


def _print_events(launch: Any) -> None:
    global _printed_events
    from msctl.console import err

    for event in launch.events[_printed_events:]:
        err.print(f"[yellow]{event}[/]", highlight=False)
    _printed_events = len(launch.events)


def _report_failure(launch: Any, what: str) -> None:
    """Say why the run did not come up, and raise: a FAILED process by its cause alone (once,
    on the last line); otherwise every component not healthy yet, with its process's log."""
    from msctl.console import err

    failed = [p for p in launch.supervisor.snapshot() if p.state == "failed"]
    if failed:
        shown: set[str] = set()  # processes crashing alike show their traceback once
        for process in launch.failed():
            if process.final_exits:
                continue  # its one line says it all
            # A crash loop: the lines before the cause (a traceback) are worth seeing, once.
            context = [
                line
                for line in list(process.log.tail)[-8:]
                if line.strip()
                and not line.startswith("--- msctl:")
                and line.strip() not in process.last_error
                and line.strip() not in shown
            ]
            shown.update(line.strip() for line in context)
            for line in context:
                err.print(f"    {process.name}: {line}", highlight=False, markup=False)
        raise _failure_error(failed)
    bad = [v for v in launch.components() if v.state != "running"]
    by_process: dict[str, list[Any]] = {}
    for view in bad:
        by_process.setdefault(view.process, []).append(view)
    for name, views in by_process.items():
        process = launch.supervisor.processes[name]
        if process.last_error:
            err.print(f"[red]process {name}[/]: {process.last_error}", highlight=False)
        for view in views:
            why = "its node never appeared" if not view.node_seen else "it never published"
            err.print(f"[red]{view.name}[/] ({view.kind}, process {name}): {why}", highlight=False)
        for line in list(process.log.tail)[-8:]:
            err.print(f"    {line}", highlight=False, markup=False)
    names = ", ".join(v.name for v in bad[:5])
    raise OperationTimeout(
        f"{names} {what}",
        hint=f"logs in {launch.supervisor.log_dir}; see `msctl logs <component>`",
    )


def _names(text: str, component: str) -> bool:
    """Whether ``text`` names ``component`` (``limb1/joint`` is not named by ``limb1/joint2``)."""
    import re

    return re.search(rf"(?<![\w/]){re.escape(component)}(?![\w/])", text) is not None


def _failure_error(failed: list[ProcessRow]) -> MsctlError:
    """The one error naming each FAILED process (rows of a run document's ``processes``), the
    component its cause names, and the cause; the others of its process are listed first.

    The cause is printed on this line only, and each cause once: a newcomer reads the last
    line first, and processes failing alike (every worker refusing MSCTL_TRANSPORT=rclpy
    without ROS) are named together before their one cause.
    """
    from msctl.console import err

    alike: dict[str, list[ProcessRow]] = {}
    for process in failed:
        alike.setdefault(process.last_error or "no error printed", []).append(process)
    causes = []
    for cause, processes in alike.items():
        if len(processes) > 1:
            count = sum(len(p.components) for p in processes)
            names = ", ".join(p.name for p in processes)
            causes.append(f"processes {names} ({count} components) failed, each: {cause}")
            continue
        process = processes[0]
        components = list(process.components)
        named = [c for c in components if _names(process.last_error or "", c)] or components
        others = [c for c in components if c not in named]
        if others:
            err.print(
                f"[dim]not started with it (process {process.name}): {', '.join(others)}[/]",
                highlight=False,
            )
        who = f"{', '.join(named)} (process {process.name})" if named else process.name
        causes.append(f"{who} failed: {cause}")
    if len(failed) == 1:
        where = f"log {failed[0].log}; see `msctl logs {failed[0].name}`"
    else:
        where = f"logs in {Path(failed[0].log).parent}; see `msctl logs <component>`"
    return MsctlError("; ".join(causes), hint=where, exit_code=3)


def _print_summary(launch: Any, elapsed: float) -> None:
    from rich.table import Table

    from msctl.console import err

    table = Table(title=f"{launch.assembly.template} up in {elapsed:.2f} s", title_justify="left")
    for column in ("component", "kind", "process", "pid", "state"):
        table.add_column(column)
    for c in launch.document().components:
        table.add_row(c.name, c.kind, c.process, str(c.pid), c.state)
    err.print(table)
    err.print(
        "[dim]Ctrl-C stops everything; `msctl ps`, `msctl logs`, `msctl down` from another shell[/]"
    )


def _detach(
    plan: Any,
    sim: bool | None,
    duration: float | None,
    host: str,
    speed: float,
    timeout: float,
    kill_unresponsive: float,
    lock: Any,
) -> None:
    from components.supervision.protocol import run_document
    from msctl.console import err
    from msctl.launcher import state

    argv = [
        sys.executable,
        "-m",
        "msctl",
        "up",
        "--host",
        host,
        "--speed",
        repr(speed),
        "--timeout",
        repr(timeout),
        "--kill-unresponsive-after",
        repr(kill_unresponsive),
    ]
    if sim is not None:
        argv.append("--sim" if sim else "--real")
    if duration is not None:
        argv += ["--for", repr(duration)]
    log_path = state.run_dir() / "supervisor.log"
    try:
        log = log_path.open("a")
    except OSError as exc:
        raise state.home_not_writable(log_path.parent, exc) from exc
    with log:
        # The supervisor inherits the run lock (the same open file) and holds it to its end.
        daemon = subprocess.Popen(
            argv,
            env={**os.environ, _DAEMON_ENV: "1", _LOCK_FD_ENV: str(lock.fd)},
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            pass_fds=(lock.fd,),
        )
    lock.note(pid=daemon.pid, by="msctl up --detach")
    deadline = time.monotonic() + timeout + 15
    while time.monotonic() < deadline:
        document = state.read_state()
        if daemon.poll() is not None:
            # Its last word, written as it stopped.
            last = run_document(state.read_state() or {})
            failed = [
                p
                for p in (last.processes if last is not None else [])
                if p.state == "failed" and last.supervisor_pid == daemon.pid
            ]
            if failed:
                raise _failure_error(failed)
            raise MsctlError(
                f"the supervisor exited with code {daemon.returncode}",
                hint=f"see {log_path}",
            )
        if (
            document
            and document.get("supervisor_pid") == daemon.pid
            and document["components"]
            and all(c["state"] == "running" for c in document["components"])
        ):
            err.print(
                f"[green]up[/] {document['template']} on {host}: "
                f"{len(document['components'])} components healthy (supervisor pid {daemon.pid}); "
                "`msctl ps`, `msctl down`",
                highlight=False,
            )
            return
        time.sleep(0.1)
    raise OperationTimeout(
        f"not healthy after {timeout:g} s", hint=f"see {log_path} and `msctl ps`"
    )
