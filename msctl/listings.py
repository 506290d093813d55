"""What ``msctl ps`` and ``msctl topic list`` print, with nothing of the CLI framework.

The typer commands call these, and so does :mod:`msctl.quick`, which answers the plain forms
of both commands before typer (and the pydantic it brings, about 0.25 s together) is
imported. Only what a listing needs is imported here, inside the functions: no rich for
JSON or plain lines, no message codec.
"""

from __future__ import annotations

import sys


def show_ps(json_output: bool = False, timeout: float = 5.0) -> None:
    """Print every component on every reachable host (and this computer's from its state
    file): a table, or one JSON document.

    Args:
        json_output: Print one JSON document instead of a table.
        timeout: Seconds to wait for the hosts (asked at once).
    """
    from msctl.console import print_json
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
    if notes:
        from msctl.console import err

        for note in notes:
            err.print(f"[yellow]{note}[/]", highlight=False)
    if not rows:
        sys.stderr.write("nothing is running (start with `msctl up dragon`)\n")
        return
    from msctl.console import print_table

    colours = {"running": "green", "failed": "red", "unresponsive": "red", "restarting": "yellow"}
    print_table(
        ("component", "kind", "host", "state", "pid", "uptime", "restarts", "last error"),
        [
            [
                (r["name"], ""),
                (r["kind"], ""),
                (r["host"], ""),
                (r["state"], colours.get(r["state"], "")),
                (str(r["pid"] or "-"), ""),
                (f"{r['uptime']:.0f}s", ""),
                (str(r["restarts"]), ""),
                (r["last_error"] or "", ""),
            ]
            for r in rows
        ],
    )


def show_topics(show_types: bool = False, verbose: bool = False, json_output: bool = False) -> None:
    """Print every topic on the network, one per line, or one JSON document.

    Args:
        show_types: Show each topic's types.
        verbose: Show the types and the publisher and subscriber counts.
        json_output: Print one JSON document.
    """
    from components.comm.graph import snapshot
    from msctl.console import print_json, print_line
    from msctl.plane import connected

    with connected("topic_list") as node:
        topics = snapshot(node.session, node.domain).topics()
    if json_output:
        print_json(
            [
                {
                    "name": t.name,
                    "types": sorted(t.types),
                    "publishers": t.publishers,
                    "subscribers": t.subscribers,
                }
                for t in topics.values()
            ]
        )
        return
    for t in topics.values():
        line = t.name
        if show_types or verbose:
            line += f" [{', '.join(sorted(t.types))}]"
        if verbose:
            line += f" {t.publishers} publisher(s), {t.subscribers} subscriber(s)"
        print_line(line)
