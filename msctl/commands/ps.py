"""``msctl ps``: every component of the assembly on every host, with its state."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {
    "help": "What runs where: state, pid, uptime, restarts, last error.",
    "epilog": "Asked: every supervisor the graph shows; with --all also every host of the "
    "resolved assembly's plan (its robot computers and ground stations). Exit status 1 when a "
    "host that was asked did not answer: it is listed as unreachable, with why (no supervisor "
    "on the graph, or no answer within --timeout). Without --all, a host of the plan the graph "
    "does not show is not asked: it is named on stderr and does not change the exit status. "
    "A computer that runs the whole assembly off-robot stands for every host of the plan.",
}


def command(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    timeout: float = typer.Option(
        5.0, "--timeout", help="Seconds to wait for the hosts (asked at once)."
    ),
    all_hosts: bool = typer.Option(
        False,
        "--all",
        help="Ask every host of the resolved assembly's plan too, even one the graph does not "
        "show; list each that does not answer as unreachable, and exit 1.",
    ),
) -> None:
    """List every component on every host that answers (and this computer's from its state
    file); the rule of what is asked and when it fails is the epilog above."""
    from msctl.listings import show_ps

    show_ps(json_output=json_output, timeout=timeout, all_hosts=all_hosts)
