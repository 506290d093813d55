"""``msctl ps``: every component of the assembly on every host, with its state."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "What runs where: state, pid, uptime, restarts, last error."}


def command(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    timeout: float = typer.Option(2.0, "--timeout", help="Seconds to wait for each host."),
) -> None:
    """List every component on every reachable host (and this computer's from its state file)."""
    from rich.table import Table

    from msctl.console import err, out, print_json
    from msctl.launcher.fleet import fleet_state

    documents, notes = fleet_state(timeout)
    # A supervisor that cannot write its logs or state file (a full disk) says so here.
    notes = [*notes, *(f"{d['host']}: {fault}" for d in documents for fault in d.get("faults", []))]
    rows = [
        {**c, "host": d["host"], "template": d.get("template")}
        for d in documents
        for c in d.get("components", [])
    ]
    if json_output:
        print_json({"components": rows, "hosts": [d["host"] for d in documents], "notes": notes})
        return
    for note in notes:
        err.print(f"[yellow]{note}[/]", highlight=False)
    if not rows:
        err.print("nothing is running (start with `msctl up dragon`)")
        return
    table = Table()
    for column in ("component", "kind", "host", "state", "pid", "uptime", "restarts", "last error"):
        table.add_column(column, overflow="fold")
    for r in rows:
        style = {
            "running": "green",
            "failed": "red",
            "unresponsive": "red",
            "restarting": "yellow",
        }.get(r["state"], "")
        table.add_row(
            r["name"],
            r["kind"],
            r["host"],
            f"[{style}]{r['state']}[/]" if style else r["state"],
            str(r["pid"] or "-"),
            f"{r['uptime']:.0f}s",
            str(r["restarts"]),
            r["last_error"] or "",
        )
    out.print(table)
