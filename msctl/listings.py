"""What ``msctl ps`` and ``msctl topic list`` print, with nothing of the CLI framework.

The typer commands call these, and so does :mod:`msctl.quick`, which answers the plain forms
of both commands before typer (and the pydantic it brings, about 0.25 s together) is
imported. Only what a listing needs is imported here, inside the functions: no rich for
JSON or plain lines, no message codec.
"""

from __future__ import annotations

import sys
from typing import Any


def show_ps(json_output: bool = False, timeout: float = 5.0, all_hosts: bool = False) -> None:
    """Print every component on every host that answers (and this computer's from its state
    file): a table, or one JSON document; then fail if a host that was asked did not answer.

    The hosts asked: every supervisor the graph shows, and with ``all_hosts`` every host of
    the resolved assembly's plan as well. A host that should have answered and did not is a
    row ``unreachable`` (or ``refused``) in the table and an entry of the document's
    ``unreachable`` list, with why. A plan host that was not asked (no ``all_hosts``, and no
    supervisor of it on the graph) is named on stderr and in that list with ``asked``
    false, and does not fail the command: plain ``ps`` lists what the graph shows.

    Args:
        json_output: Print one JSON document instead of a table.
        timeout: Seconds to wait for the hosts (asked at once).
        all_hosts: Ask every host of the plan, even those the graph does not show.

    Raises:
        MsctlError: Exit status 1, naming every host that was asked and did not answer and
            what to check, after the listing is printed.
    """
    from msctl.console import print_json
    from msctl.launcher.fleet import describe, fleet_state

    fleet = fleet_state(timeout, every_host=all_hosts)
    documents = fleet.documents
    # A supervisor that cannot write its logs or state file (a full disk) says so here.
    notes = [
        *fleet.notes,
        *(f"{d['host']}: {fault}" for d in documents for fault in d.get("faults", [])),
    ]
    rows = [
        {**c, "host": d["host"], "template": d.get("template")}
        for d in documents
        for c in d.get("components", [])
    ]
    failed = [s for s in fleet.silent if s.asked]
    if json_output:
        print_json(
            {
                "components": rows,
                "hosts": [d["host"] for d in documents],
                "unreachable": [s._asdict() for s in fleet.silent],
                "notes": notes,
            }
        )
    else:
        for note in notes:
            _warn(note)
        _print_ps_table(rows, failed, documents, all_hosts)
    _warn_unasked(fleet, all_hosts)
    if failed:
        from msctl.errors import MsctlError

        raise MsctlError(
            f"{len(failed)} host(s) did not answer: {describe(failed)}",
            hint=_what_to_check(failed),
        )


#: The colour of a component's state in the table.
_STATE_COLOURS = {
    "running": "green",
    "failed": "red",
    "unresponsive": "red",
    "restarting": "yellow",
}


def _print_ps_table(rows: list, failed: list, documents: list, all_hosts: bool) -> None:
    """The table of ``msctl ps``: a row per component, one per host that did not answer."""
    from msctl.launcher.fleet import REFUSED

    if not (rows or failed):
        sys.stderr.write("nothing is running (start with `msctl up dragon`)\n")
        return
    from msctl.console import print_table

    print_table(
        ("component", "kind", "host", "state", "pid", "uptime", "restarts", "last error"),
        [
            [
                (r["name"], ""),
                (r["kind"], ""),
                (r["host"], ""),
                (r["state"], _STATE_COLOURS.get(r["state"], "")),
                (str(r["pid"] or "-"), ""),
                (f"{r['uptime']:.0f}s", ""),
                (str(r["restarts"]), ""),
                (r["last_error"] or "", ""),
            ]
            for r in rows
        ]
        + [
            [
                ("-", ""),
                ("-", ""),
                (s.host, ""),
                ("refused" if s.why == REFUSED else "unreachable", "red"),
                ("-", ""),
                ("-", ""),
                ("-", ""),
                (s.detail, ""),
            ]
            for s in failed
        ],
    )
    idle = [d["host"] for d in documents if not d.get("components")]
    if all_hosts and idle:
        # Every host of the plan is accounted for: those that answered with nothing to
        # list too.
        _warn(f"answered, running nothing: {', '.join(idle)}")


def _warn_unasked(fleet: Any, all_hosts: bool) -> None:
    """Say which hosts of the plan were not asked, or that there is no plan to ask by."""
    from msctl.launcher.fleet import NO_NETWORK

    if all_hosts and fleet.plan is None:
        from msctl.launcher.fleet import plan_path

        _warn(
            f"no resolved assembly here ({plan_path()}): asked only the supervisors on the "
            "graph; `msctl assemble TEMPLATE` names every host to ask"
        )
    not_asked = [s for s in fleet.silent if not s.asked]
    if not_asked:
        # Said in both forms: a JSON reader has the list, a person at a terminal this line.
        template = fleet.plan.template if fleet.plan else "the assembly"
        how = "no router" if not_asked[0].why == NO_NETWORK else "not on the graph"
        _warn(
            f"not asked ({how}): {', '.join(s.host for s in not_asked)}, host(s) of "
            f"{template}'s plan: their components are not listed (`msctl ps --all` asks each)"
        )


def _what_to_check(silent: list) -> str:
    """What an operator checks for hosts that did not answer, by why."""
    from msctl.launcher.fleet import NO_ANSWER, NO_NETWORK, NO_SUPERVISOR

    whys = {s.why for s in silent}
    checks = []
    if NO_NETWORK in whys:
        checks.append("start this computer's router (`msctl router` or `msctl agent`)")
    if NO_SUPERVISOR in whys:
        checks.append(
            "check that `msctl agent` runs on each (`systemctl status msctl-agent`) and that "
            "its router links to this one (`msctl doctor --all`)"
        )
    if NO_ANSWER in whys:
        checks.append("a loaded computer or a lossy link answers late: try a longer --timeout")
    if len(checks) < len(whys):  # refused: the reason is in the message
        checks.append("see each one's reason")
    return "; ".join(checks)


def _warn(text: str) -> None:
    """One human line on stderr, yellow on a terminal: written as it is, without rich (70 ms
    to import, and a note such as ``[Errno 111]`` is not markup)."""
    import os

    if sys.stderr.isatty() and not os.environ.get("NO_COLOR"):
        text = f"\x1b[33m{text}\x1b[0m"
    sys.stderr.write(text + "\n")
    sys.stderr.flush()


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
