"""``msctl ps``: every component of the assembly on every host, with its state."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "What runs where: state, pid, uptime, restarts, last error."}


def command(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    timeout: float = typer.Option(
        5.0, "--timeout", help="Seconds to wait for the hosts (asked at once)."
    ),
) -> None:
    """List every component on every reachable host (and this computer's from its state file)."""
    from msctl.listings import show_ps

    show_ps(json_output=json_output, timeout=timeout)
