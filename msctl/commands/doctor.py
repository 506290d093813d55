"""``msctl doctor``: the preflight of a field day, on this computer or every one."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {
    "help": "Preflight: versions, clocks, router and link, certificates, buses, disk, Python."
}


def command(
    all_hosts: bool = typer.Option(
        False,
        "--all",
        help="Every host, through its supervisor or agent, and compare them: every supervisor "
        "on the graph and every host of the resolved assembly's plan; one that does not answer "
        "is an ERROR (exit 1) naming it.",
    ),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    clock_timeout: float = typer.Option(
        3.0, "--clock-timeout", help="Seconds to wait for a timestamped sample to compare clocks."
    ),
) -> None:
    """Check this computer (or every one) is ready; exit status 1 on any ERROR."""
    import os
    import socket

    import msgspec
    from rich.markup import escape
    from rich.table import Table

    from components.comm.session import SessionConfigError, SessionSettings, open_session
    from msctl.console import err, out, print_json
    from msctl.net import doctor

    host = os.environ.get("MSCTL_HOST") or socket.gethostname()
    findings: list[doctor.Finding] = []
    with err.status("checking this computer" + (" and every host" if all_hosts else "")):
        settings = SessionSettings.from_env(mode="client")
        try:
            session = open_session(settings)
        except SessionConfigError as exc:
            # No router is the situation a preflight runs in: every other check still runs.
            findings += doctor.this_computer(
                host,
                None,
                settings.connect,
                settings.domain,
                router_error=f"{doctor.clean(exc)}: run `msctl up` or `msctl router`",
            )
            if all_hosts:
                try:
                    findings += _unasked(host)
                except Exception as exc:  # the plan unreadable: said, not the end of it
                    findings.append(
                        doctor.Finding(host, "reachable", doctor.ERROR, doctor.clean(exc))
                    )
        else:
            try:
                findings += doctor.this_computer(
                    host, session, settings.connect, settings.domain, clock_timeout
                )
                if all_hosts:
                    findings += _other_hosts(session, settings.domain, host, clock_timeout)
            finally:
                session.close()
        if all_hosts:
            for check in ("msctl version", "assembly lock"):
                findings += doctor.agreement(findings, check)
    status = doctor.worst(findings)
    if json_output:
        print_json({"status": status, "findings": [msgspec.structs.asdict(f) for f in findings]})
    else:
        colours = {doctor.OK: "green", doctor.WARN: "yellow", doctor.ERROR: "red"}
        table = Table("host", "check", "status", "detail")
        for f in findings:
            table.add_row(
                escape(f.host), escape(f.check), f"[{colours[f.status]}]{f.status}[/]",
                escape(f.detail),
            )  # fmt: skip
        out.print(table)
    if status == doctor.ERROR:
        raise typer.Exit(1)


def _other_hosts(session: object, domain: int, here: str, timeout: float) -> list:
    """Every other host's findings, asked of its supervisor or agent: every supervisor on
    the graph and every host of the resolved assembly's plan. A host that did not answer is
    an ERROR naming it, why, and what to check."""
    from components.comm.node import Node
    from components.supervision.protocol import AnswerError, doctor_answer
    from msctl.launcher.fleet import (
        NO_ANSWER,
        NO_SUPERVISOR,
        ask_hosts,
        hosts_to_ask,
        read_plan,
        supervisors,
    )
    from msctl.net import doctor

    checks = {
        NO_SUPERVISOR: "start `msctl agent` there (`systemctl status msctl-agent`) and check its "
        "router links to this one",
        NO_ANSWER: "a loaded computer or a lossy link answers late: try a longer --clock-timeout",
    }
    node = Node(session, f"msctl_doctor_{id(session)}", "/", domain=domain)
    found = []
    try:
        supervisors_now = supervisors(node)
        # This computer is checked directly (above), whether or not it runs a supervisor.
        hosts = [h for h in hosts_to_ask(node, read_plan(), supervisors_now) if h != here]
        asked = ask_hosts(node, "doctor", hosts, None, timeout + 10.0, supervisors_now)
        for namespace, answer in asked.answers.items():
            try:
                told = doctor_answer(answer, f"the supervisor {namespace}")
            except AnswerError as exc:  # a garbled or foreign answer: said, the rest goes on
                found.append(doctor.Finding(namespace, "reachable", doctor.ERROR, str(exc)))
                continue
            if told.host != here:
                found += [
                    doctor.Finding(f.host, f.check, f.status, f.detail, f.value)
                    for f in told.findings
                ]
        for silence in asked.silent.values():
            detail = silence.detail
            if silence.why in checks:
                detail += f": {checks[silence.why]}"
            found.append(doctor.Finding(silence.host, "reachable", doctor.ERROR, detail))
    finally:
        node.close()
    return found


def _unasked(here: str) -> list:
    """An ERROR for each other host of the plan, none of which could be asked (no router)."""
    from msctl.launcher.fleet import expected_hosts, read_plan
    from msctl.launcher.state import read_state
    from msctl.net import doctor

    local = read_state()
    return [
        doctor.Finding(h, "reachable", doctor.ERROR, "not asked: no router here to ask through")
        for h in expected_hosts(read_plan(), [local] if local else [])
        if h != here
    ]
