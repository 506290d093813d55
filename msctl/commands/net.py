"""``msctl net``: the fleet's certificates and the per-host Zenoh configs made from them."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import typer

app = typer.Typer(
    help="Fleet security: certificate authority, identities, per-host Zenoh configs with "
    "mutual TLS and access control.",
    no_args_is_help=True,
)

JSON_OPT = typer.Option(False, "--json", help="Print one JSON document instead of a table.")
#: Certificates expiring sooner than this are flagged by ``show`` and ``doctor``.
EXPIRY_WARNING_DAYS = 7


def _fail(exc: Exception) -> None:
    from msctl.errors import InputError

    raise InputError(str(exc)) from exc


@app.command("init")
def init(
    host: list[str] = typer.Option(
        None,
        "--host",
        help="A computer to make an identity for (repeatable; default: every "
        "host of the resolved assembly, and this computer: MSCTL_HOST or the hostname).",
    ),
    operator: list[str] = typer.Option(
        None,
        "--operator",
        help="An operator to make an identity for (repeatable; default: "
        "you, as user@host like claims).",
    ),
) -> None:
    """Create the fleet CA (once) and an identity per computer and operator.

    By default the computers are the resolved assembly's and this one: a laptop that runs
    the whole assembly simulated (`msctl up --secure` off-robot) is no host of the assembly,
    and its router needs an identity of its own.
    """
    from components.assembly import AssemblyError, load_assembly
    from components.claims import default_holder
    from msctl.console import err
    from msctl.launcher.plan import this_host
    from msctl.net import pki

    hosts = list(host or [])
    if not hosts:
        try:
            hosts = list(load_assembly().hosts)
        except AssemblyError as exc:
            from msctl.errors import InputError

            raise InputError(
                f"no hosts to make identities for: {exc}", hint="or name them with --host"
            ) from exc
        here = this_host()
        try:
            hosts = list(dict.fromkeys([*hosts, pki.check_name(here, "this computer")]))
        except pki.PkiError as exc:
            # The fleet's identities do not wait on a host name a certificate cannot carry.
            err.print(
                f"no identity for this computer: {exc} (set MSCTL_HOST)",
                style="yellow",
                markup=False,
                highlight=False,
            )
    operators = list(operator or [default_holder()])
    with err.status(f"signing {len(hosts) + len(operators)} identities with the fleet CA"):
        try:
            made = pki.init_fleet(hosts, operators)
        except pki.PkiError as exc:
            _fail(exc)
    err.print(
        f"fleet CA at {pki.ca_cert()}; new identities: {', '.join(made) or 'none (all existed)'}",
        highlight=False,
    )


@app.command("add-operator")
def add_operator(
    name: str = typer.Argument(..., help="The operator (user@host, like claims)."),
) -> None:
    """Give an operator an identity signed by the fleet CA."""
    from msctl.console import err
    from msctl.net import pki

    try:
        identity = pki.issue(pki.operator_cn(pki.check_name(name, "operator")))
    except pki.PkiError as exc:
        _fail(exc)
    err.print(f"{identity.common_name}: {identity.cert} (expires {identity.expires:%Y-%m-%d})")


@app.command("revoke")
def revoke(name: str = typer.Argument(..., help="An operator name or a host name.")) -> None:
    """Delete an identity and leave it out of every config generated from now on."""
    from msctl.console import err
    from msctl.net import pki

    known = {i.common_name for i in pki.identities()}
    cn = name if name in known else pki.operator_cn(name)
    try:
        pki.revoke(cn)
    except pki.PkiError as exc:
        _fail(exc)
    err.print(
        f"revoked {cn}: regenerate and restart the routers (`msctl net config HOST -o FILE`)",
        highlight=False,
    )


@app.command("show")
def show(json_output: bool = JSON_OPT) -> None:
    """List the identities and when they expire."""
    from rich.table import Table

    from msctl.console import out, print_json
    from msctl.net import pki

    now = datetime.now(UTC)
    rows = []
    for identity in pki.identities(with_revoked=True):
        days = (identity.expires - now).days if identity.expires else None
        rows.append(
            {
                "common_name": identity.common_name,
                "role": identity.role,
                "expires": identity.expires.isoformat() if identity.expires else None,
                "days_left": days,
                "revoked": identity.revoked,
                "certificate": str(identity.cert) if not identity.revoked else None,
            }
        )
    if json_output:
        print_json({"ca": str(pki.ca_cert()), "identities": rows})
        return
    table = Table("identity", "role", "expires", "days left", "state")
    for row in rows:
        state = "revoked" if row["revoked"] else "valid"
        if row["days_left"] is not None and row["days_left"] < EXPIRY_WARNING_DAYS:
            state = "[yellow]expiring[/]" if row["days_left"] >= 0 else "[red]expired[/]"
        table.add_row(
            row["common_name"],
            row["role"],
            (row["expires"] or "-")[:10],
            "-" if row["days_left"] is None else str(row["days_left"]),
            state,
        )
    out.print(table)


@app.command("config")
def config(
    host: str = typer.Argument(None, help="The computer (default: this one, or MSCTL_HOST)."),
    output: Path = typer.Option(None, "--output", "-o", help="Write the json5 here."),
    component: bool = typer.Option(
        False, "--component", help="The config of the host's components instead of its router."
    ),
) -> None:
    """Print or write the Zenoh config of a host's router (json5)."""
    import os
    import socket

    from components.assembly import AssemblyError, load_assembly
    from msctl.console import err, out
    from msctl.errors import InputError
    from msctl.net import config as netconfig
    from msctl.net import pki

    host = host or os.environ.get("MSCTL_HOST") or socket.gethostname()
    try:
        assembly = load_assembly()
    except AssemblyError as exc:
        raise InputError(str(exc)) from exc
    if not pki.trusts():
        raise InputError(
            f"no fleet CA certificate in {pki.net_dir()}",
            hint="run `msctl net init` (on the ground station; then copy its net/ here)",
        )
    try:
        document = (
            netconfig.component_config(host)
            if component
            else netconfig.router_config(assembly, host)
        )
    except (netconfig.NetConfigError, pki.PkiError) as exc:
        _fail(exc)
    text = netconfig.dumps(document)
    if output is None:
        out.print(text, end="", markup=False, highlight=False)
        return
    output.write_text(text)
    err.print(f"wrote {output}", highlight=False)


@app.command("ros-enclave")
def ros_enclave(
    enclave: str = typer.Argument(..., help="The enclave's path (/field/viewer), also its CN."),
    router: str = typer.Option(..., "--router", help="The computer whose router it joins."),
    publish: list[str] = typer.Option(None, "--publish", help="A topic it publishes."),
    subscribe: list[str] = typer.Option(None, "--subscribe", help="A topic it reads."),
    serve: list[str] = typer.Option(None, "--serve", help="A service it serves."),
    call: list[str] = typer.Option(None, "--call", help="A service it calls."),
    output: Path = typer.Option(None, "--output", "-o", help="Write the json5 here."),
) -> None:
    """An identity for a ROS 2 enclave and its session config in rmw_zenoh's form."""
    from msctl.console import err, out
    from msctl.errors import InputError
    from msctl.net import config as netconfig
    from msctl.net import pki
    from msctl.net.ros import enclave_config, is_enclave

    if (
        not is_enclave(enclave)
        or "//" in enclave
        or not pki.check_name(enclave.strip("/").replace("/", "-"), "enclave")
    ):
        raise InputError(f"enclave {enclave!r} is not a path like /field/viewer")
    try:
        if not pki.identity_dir(enclave).is_dir():
            pki.issue(enclave)
        ports = netconfig.Ports()
        document = enclave_config(
            enclave,
            f"tls/{ports.address(router)}:{ports.tls_port(router)}",
            publish or [],
            subscribe or [],
            serve or [],
            call or [],
        )
    except (netconfig.NetConfigError, pki.PkiError) as exc:
        _fail(exc)
    text = netconfig.dumps(document)
    if output is None:
        out.print(text, end="", markup=False, highlight=False)
        return
    output.write_text(text)
    err.print(f"wrote {output}; restart the routers so their ACL names {enclave}")
