"""``msctl stop COMPONENT``: stop one component's process (it stays stopped)."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "Stop one component (its process) and keep it stopped."}


def command(component: str = typer.Argument(..., help="Component or process name.")) -> None:
    """Stop the process that runs COMPONENT."""
    from msctl.launcher.remote import control_component

    control_component("stop", component)
