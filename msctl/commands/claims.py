"""``msctl claims``: who holds which module (the claims of :mod:`components.claims`)."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "Who drives which module: every claim, its holder, node and since."}


def command(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    timeout: float = typer.Option(
        2.0, "--timeout", help="Seconds to wait for the network's answers."
    ),
) -> None:
    """List every module's claim: the module, its holder (user@host), the node that sends
    the commands, and since when. A claim taken over a moment ago may still show beside its
    successor, marked as not holding."""
    from datetime import datetime

    from rich.table import Table

    from components.claims import Claims, holder_of
    from msctl.console import err, out, print_json
    from msctl.plane import connected

    with connected("claims") as node:
        claims = Claims(node.session, node.domain)
        try:
            found = claims.survey(timeout)
        finally:
            claims.close()
    holders = {
        module: holder_of(c for c in found if c.module == module)
        for module in dict.fromkeys(c.module for c in found)
    }
    rows = [{**c.as_dict(), "holds": holders[c.module] == c} for c in found]
    rows.sort(key=lambda r: (r["module"], not r["holds"]))
    if json_output:
        print_json({"claims": rows})
        return
    if not rows:
        err.print("no module is claimed (an operator claims one with `msctl teleop`)")
        return
    table = Table()
    for column in ("module", "holder", "node", "since"):
        table.add_column(column, overflow="fold")
    for row in rows:
        since = datetime.fromtimestamp(row["since"]).strftime("%Y-%m-%d %H:%M:%S")
        holder = row["holder"] if row["holds"] else f"[dim]{row['holder']} (taken over)[/]"
        table.add_row(row["module"], holder, row["node"], since)
    out.print(table)
