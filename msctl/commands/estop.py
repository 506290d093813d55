"""``msctl estop [MODULE...]``: halt every module of the running assembly at once.

Each module's joint manager is asked to ``halt`` (hold every joint, refuse commands until
``msctl recover``); every request leaves before any answer is awaited. The modules are those
the graph shows serving a joint manager's ``halt``, with those of this computer's resolved
assembly (a module planned but silent is named as not acknowledging, never skipped).
A claim never blocks a halt.
"""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {
    "help": "Halt every module of the running assembly (or those named) at once; "
    "`msctl recover` undoes it."
}

#: Seconds for the graph to say which joint managers run.
GRAPH_TIMEOUT = 1.0


def command(
    modules: list[str] = typer.Argument(None, help="Modules to halt (default: every one)."),
    timeout: float = typer.Option(2.0, "--timeout", help="Seconds to wait for each module."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """Halt MODULES (default: every module) through their joint managers, all at once; print
    each module's time to acknowledge; exit non-zero naming any that did not."""
    trigger("halt", modules or [], timeout, json_output)


def trigger(verb: str, named: list[str], timeout: float, json_output: bool) -> None:
    """Call ``verb`` (``halt`` or ``recover``) on the modules, report, fail on silence.

    Raises:
        InputError: If a named module is not one the assembly or the graph knows.
        NotFoundError: If no module is known at all (nothing runs, no resolved assembly).
        OperationTimeout: If a module did not acknowledge (the message names each).
    """
    import time

    from components.estop import Estop
    from msctl.console import err, print_json
    from msctl.errors import InputError, NotFoundError, OperationTimeout, did_you_mean
    from msctl.plane import connected

    with connected(verb) as node:
        spaces, notes = modules_to_reach(node)
        if not spaces:
            raise NotFoundError(
                "no module to reach: the graph shows no joint manager and this computer has "
                "no resolved assembly",
                hint="start one with `msctl up <template>`, or check MSCTL_ZENOH_CONNECT",
            )
        unknown = [m for m in named if m not in spaces]
        if unknown:
            near = did_you_mean(unknown[0], list(spaces))
            raise InputError(
                f"no module {', '.join(unknown)} in the running assembly",
                hint=f"{near + ' ' if near else ''}modules: {', '.join(spaces)}",
            )
        chosen = {m: spaces[m] for m in (named or spaces)}
        with Estop(node, chosen) as estop:
            started = time.monotonic()
            answers = (
                estop.halt(timeout=timeout) if verb == "halt" else estop.recover(timeout=timeout)
            )
            total = time.monotonic() - started
    silent = [a for a in answers if not a.ok]
    if json_output:
        print_json(
            {
                "verb": verb,
                "modules": [a.as_dict() for a in answers],
                "seconds": total,
                "acknowledged": not silent,
                "notes": notes,
            }
        )
    else:
        for note in notes:
            err.print(f"[yellow]{note}[/]", highlight=False)
        report(verb, answers, total)
    if silent:
        raise OperationTimeout(
            f"{verb}: {', '.join(a.module for a in silent)} did not acknowledge: "
            + "; ".join(f"{a.module}: {a.message}" for a in silent),
            hint=(
                "they may still be moving: stop them at the robot (power, the drive's own "
                "stop), then check with `msctl ps`"
                if verb == "halt"
                else "check them with `msctl ps` and `msctl health`"
            ),
        )


def report(verb: str, answers: list, total: float) -> None:
    """One line per module on stdout: acknowledged or not, its time, what it said."""
    from rich.markup import escape

    from msctl.console import out

    done = "halted" if verb == "halt" else "recovered"
    width = max(len(a.module) for a in answers)
    for a in answers:
        took = "-" if a.seconds is None else f"{a.seconds * 1000:.1f} ms"
        state = f"[green]{done}[/]" if a.ok else "[bold red]NO ACK[/]"
        out.print(
            f"{a.module:<{width}}  {state:<8}  {took:>9}  {escape(a.message)}", highlight=False
        )
    out.print(f"{len(answers)} module(s) in {total * 1000:.1f} ms", highlight=False)


def modules_to_reach(node: object) -> tuple[dict[str, str], list[str]]:
    """Module slot -> namespace: the joint managers the graph shows serving ``halt``, and
    those this computer's resolved assembly plans (when it is the one running); notes on
    what did not agree."""
    from components.assembly import AssemblyError, load_assembly
    from components.comm.liveliness import PREFIX, Entity, EntityKind, TokenError, ask_tokens
    from components.joint_manager.kind import KIND as JOINT_MANAGER

    found: dict[str, str] = {}
    key = f"{PREFIX}/{node.domain}/*/*/*/{EntityKind.SERVICE.value}/**"
    for token in ask_tokens(node.session, key, GRAPH_TIMEOUT):
        try:
            entity = Entity.parse(token)
        except TokenError:
            continue
        if entity.node_name != JOINT_MANAGER.name or entity.topic is None:
            continue
        namespace, _, service = entity.topic.rpartition("/")
        if service == "halt" and namespace == entity.namespace.rstrip("/"):
            found[namespace.strip("/").replace("/", "_")] = namespace or "/"
    planned: dict[str, str] = {}
    notes: list[str] = []
    try:
        assembly = load_assembly()
    except AssemblyError:
        assembly = None
    if assembly is not None:
        planned = {
            p.module: p.namespace
            for p in assembly.components
            if p.kind == JOINT_MANAGER.name and p.module is not None
        }
    if found and planned and not set(found) & set(planned):
        # This computer's lock is of another assembly than the one running.
        notes.append(
            f"the resolved assembly here ({assembly.template}) is not the one running: "
            "reaching the modules the graph shows"
        )
        planned = {}
    spaces = dict(planned)
    spaces.update({m: n for m, n in found.items() if m not in spaces})
    missing = [m for m in planned if m not in found]
    if planned and not found:
        notes.append("the graph shows no joint manager: asking the resolved assembly's modules")
    if found and missing:
        notes.append(f"not on the graph: {', '.join(missing)} (asked all the same)")
    return spaces, notes
