"""``msctl logs``: the output of a component's process on this computer."""

from __future__ import annotations

import re
import time
from datetime import datetime, timedelta
from pathlib import Path

import typer

from msctl.errors import InputError, NetworkError, NotFoundError, did_you_mean

COMMAND_SETTINGS = {"help": "Show (or follow) a component's log."}

_STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d)")
_SINCE = re.compile(r"^(\d+(?:\.\d+)?)([smhd]?)$")


def _since_seconds(text: str) -> float:
    match = _SINCE.match(text.strip())
    if not match:
        raise InputError(f"--since {text!r}: write it like 30s, 5m, 2h")
    value, unit = float(match.group(1)), match.group(2) or "s"
    return value * {"s": 1, "m": 60, "h": 3600, "d": 86400}[unit]


def _log_file(component: str | None) -> list[Path]:
    from msctl.launcher import state

    document = state.read_state()
    logs = state.log_dir()
    if component is None:
        return sorted(logs.glob("*.log"))
    if document:
        for process in document.get("processes", []):
            if component == process["name"] or component in process.get("components", []):
                return [Path(process["log"])]
    candidate = logs / f"{component.replace('/', '_')}.log"
    if candidate.exists():
        return [candidate]
    raise _unknown(component, document)


def _unknown(component: str, document: dict | None) -> NotFoundError:
    """The one wording of "no such log", with or without ``--follow``."""
    known = _local_names(document)
    near = did_you_mean(component, known)
    if near:
        hint = f"{near} (`msctl ps` shows what runs where)"
    elif known:
        hint = f"known here: {', '.join(known)}; `msctl ps` shows where each runs"
    else:
        hint = "nothing ran on this computer; `msctl ps` shows where each runs"
    return NotFoundError(f"no log for {component!r} on this computer", hint=hint)


def _local_names(document: dict | None) -> list[str]:
    """The components and processes this computer's last run knew."""
    known = [c["name"] for c in (document or {}).get("components", [])]
    return known + [p["name"] for p in (document or {}).get("processes", [])]


def _remote_lines(component: str, lines: int, follow: bool) -> list[str]:
    """The last lines of ``component``'s log from the supervisor (agent) of its host.

    Raises:
        NotFoundError: If no running supervisor knows it.
        InputError: With ``follow``: it runs on another computer (followed there only).
        NetworkError: If no other computer can be asked, or its supervisor does not answer.
    """
    from components.comm.services import ServiceTimeout
    from components.supervision.protocol import logs_answer
    from msctl.launcher.control import RequestError, call_supervisor
    from msctl.launcher.remote import host_of
    from msctl.plane import connected

    with connected("logs") as node:
        host = host_of(component, node)
        if follow:
            raise InputError(
                f"{component} runs on {host}: `msctl logs -f` follows this computer's logs",
                hint=f"run it on {host}, or `msctl logs {component}` from here for its last lines",
            )
        try:
            answer = call_supervisor(node, host, "logs", {"component": component, "lines": lines})
        except (ServiceTimeout, RequestError) as exc:
            raise NetworkError(f"cannot get the log of {component} from {host}: {exc}") from exc
    told = logs_answer(answer, f"the supervisor of {host}")
    return [line for process_lines in told.values() for line in process_lines]


def command(
    component: str = typer.Argument(None, help="Component or process (default: all)."),
    follow: bool = typer.Option(False, "--follow", "-f", help="Keep printing new lines."),
    since: str = typer.Option(None, "--since", help="Only lines newer than this (30s, 5m, 2h)."),
    lines: int = typer.Option(200, "--lines", "-n", help="Show at most this many lines each."),
) -> None:
    """Print a component's log (its whole process's output)."""
    from msctl.console import out
    from msctl.launcher import state

    cutoff = None
    if since:
        cutoff = datetime.now() - timedelta(seconds=_since_seconds(since))
    try:
        files = _log_file(component)
    except NotFoundError as local:
        if component is None:
            raise
        if did_you_mean(component, _local_names(state.read_state())):
            raise  # a slip of the keyboard on a name from here: no other computer to ask
        # Not on this computer: ask the supervisor (agent) of the host that runs it. The
        # same with --follow, so that an unknown name reads the same either way.
        try:
            remote = _remote_lines(component, lines, follow)
        except NotFoundError as nowhere:
            # Nobody anywhere knows it: the nearest name another computer runs, if any.
            near = (nowhere.hint or "").startswith("did you mean")
            raise (nowhere if near else local) from None
        except NetworkError as exc:
            raise NetworkError(
                f"{local.message}, and no other computer can be asked: {exc.message}",
                hint=exc.hint,
            ) from exc
        for line in remote:
            out.print(line, highlight=False, markup=False)
        return
    if not files:
        raise NotFoundError("no logs on this computer yet", hint="start something with `msctl up`")
    for path in files:
        text = path.read_text(encoding="utf-8", errors="replace").splitlines()
        if cutoff is not None:
            keep, kept = [], False
            for line in text:
                stamp = _STAMP.match(line)
                if stamp:
                    kept = datetime.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S") >= cutoff
                if kept:
                    keep.append(line)
            text = keep
        if len(files) > 1:
            out.print(f"==> {path.name} <==", highlight=False, markup=False)
        for line in text[-lines:]:
            out.print(line, highlight=False, markup=False)
    if follow:
        positions = {p: p.stat().st_size for p in files}
        try:
            while True:
                for path in files:
                    size = path.stat().st_size if path.exists() else 0
                    if size < positions[path]:
                        positions[path] = 0  # rotated
                    if size > positions[path]:
                        with path.open(encoding="utf-8", errors="replace") as handle:
                            handle.seek(positions[path])
                            chunk = handle.read()
                            positions[path] = handle.tell()
                        for line in chunk.splitlines():
                            out.print(line, highlight=False, markup=False)
                time.sleep(0.2)
        except KeyboardInterrupt:
            return
