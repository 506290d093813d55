"""``msctl doctor``: the preflight of a field day, on this computer."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {
    "help": "Preflight: versions, clocks, router and link, certificates, "
    "buses, disk, Python environment."
}


def command(
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    clock_timeout: float = typer.Option(
        3.0, "--clock-timeout", help="Seconds to wait for a timestamped sample to compare clocks."
    ),
) -> None:
    """Check this computer is ready; exit status 1 on any ERROR."""
    import dataclasses
    import os
    import socket
    import time

    from rich.table import Table

    from components.assembly import AssemblyError, load_assembly, lock_path, state_dir
    from components.comm.session import SessionConfigError, SessionSettings, open_session
    from msctl.console import err, out, print_json
    from msctl.net import doctor

    host = os.environ.get("MSCTL_HOST") or socket.gethostname()
    findings: list[doctor.Finding] = []
    try:
        assembly = load_assembly()
    except AssemblyError:
        assembly = None
    findings += doctor.version(host, lock_path() if assembly else None)
    simulated = assembly is None or host not in {m.host for m in assembly.modules}
    with err.status("checking the router and the clock"):
        settings = SessionSettings.from_env(mode="client")
        try:
            session = open_session(settings)
        except SessionConfigError as exc:
            findings.append(
                doctor.Finding(
                    host, "router", doctor.ERROR, f"{exc}: run `msctl up` or `msctl router`"
                )
            )
        else:
            try:
                findings.append(doctor.router(host, session, settings.connect))
                offset, source = doctor.measure_clock_offset(
                    session, f"{settings.domain}/**", time.time_ns, clock_timeout
                )
                findings.append(doctor.clock_offset(host, offset, source))
            finally:
                session.close()
    findings += doctor.certificates(host, None)
    if assembly is not None:
        findings += doctor.devices(host, assembly, simulated)
    findings.append(doctor.disk(host, state_dir()))
    findings += doctor.python_env(host, simulated)
    status = doctor.worst(findings)
    if json_output:
        print_json({"status": status, "findings": [dataclasses.asdict(f) for f in findings]})
    else:
        colours = {doctor.OK: "green", doctor.WARN: "yellow", doctor.ERROR: "red"}
        table = Table("host", "check", "status", "detail")
        for f in findings:
            table.add_row(f.host, f.check, f"[{colours[f.status]}]{f.status}[/]", f.detail)
        out.print(table)
    if status == doctor.ERROR:
        raise typer.Exit(1)
