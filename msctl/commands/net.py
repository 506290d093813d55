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
    lift: bool = typer.Option(
        False,
        "--lift",
        help="Lift the revocation of the names given with --host/--operator and issue them "
        "new identities (their revoked certificates stay refused).",
    ),
) -> None:
    """Create the fleet CA (once) and an identity per computer and operator.

    By default the computers are the resolved assembly's and this one: a laptop that runs
    the whole assembly simulated (`msctl up --secure` off-robot) is no host of the assembly,
    and its router needs an identity of its own. An existing CA is verified first. A revoked
    name is never issued again here unless named with --lift: named without it, the command
    refuses; implied (the assembly's), it is skipped and said.
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
    try:
        revoked = pki.revoked_names()
    except pki.PkiError as exc:
        _fail(exc)
    if lift and not (host or operator):
        from msctl.errors import InputError

        raise InputError("--lift lifts the revocation of names given: name them with --host "
                         "or --operator")  # fmt: skip
    # A revoked name the assembly (or the default) implies is skipped and said; one asked
    # for by name is refused by init_fleet, before anything is written.
    skipped = []
    if not lift and not host:
        skipped += [h for h in hosts if h in revoked]
        hosts = [h for h in hosts if h not in revoked]
    if not lift and not operator:
        skipped += [pki.operator_cn(o) for o in operators if pki.operator_cn(o) in revoked]
        operators = [o for o in operators if pki.operator_cn(o) not in revoked]
    with err.status(f"signing {len(hosts) + len(operators)} identities with the fleet CA"):
        try:
            made = pki.init_fleet(hosts, operators, lift=lift)
        except pki.PkiError as exc:
            _fail(exc)
    for cn in skipped:
        err.print(
            f"{cn}: revoked, not issued again (`msctl net unrevoke {pki.cli_name(cn)}` to lift it)",
            style="yellow",
            markup=False,
            highlight=False,
        )
    err.print(
        f"fleet CA at {pki.ca_cert()} (verified); new identities: "
        f"{', '.join(made) or 'none (all existed)'}",
        highlight=False,
    )


@app.command("add-operator")
def add_operator(
    name: str = typer.Argument(..., help="The operator (user@host, like claims)."),
    lift: bool = typer.Option(
        False,
        "--lift",
        help="The operator was revoked: lift the revocation and issue a new identity (the "
        "revoked certificate stays refused).",
    ),
) -> None:
    """Give an operator an identity signed by the fleet CA (a new one replaces the old, which
    every config generated from then on refuses)."""
    from msctl.console import err
    from msctl.net import pki

    try:
        identity = pki.issue(pki.operator_cn(pki.check_name(name, "operator")), lift=lift)
    except pki.PkiError as exc:
        _fail(exc)
    err.print(
        f"{identity.common_name}: {identity.cert} (CN {identity.certificate_cn}, expires "
        f"{identity.expires:%Y-%m-%d}): regenerate and restart the routers to admit it",
        highlight=False,
        markup=False,
    )


def _revocable(name: str) -> str:
    """The identity ``name`` means: a host or enclave by its name, else an operator."""
    from msctl.net import pki

    known = set(pki.common_names()) | pki.revoked_names()
    return name if name in known else pki.operator_cn(name)


@app.command("revoke")
def revoke(name: str = typer.Argument(..., help="An operator name or a host name.")) -> None:
    """Delete an identity and refuse its certificate in every config generated from now on;
    the name is not issued again until `msctl net unrevoke` lifts the revocation."""
    from msctl.console import err
    from msctl.net import pki

    try:
        cn = _revocable(name)
        pki.revoke(cn)
    except pki.PkiError as exc:
        _fail(exc)
    err.print(
        f"revoked {cn}: regenerate and restart the routers (`msctl net config HOST -o FILE`); "
        f"it stays revoked until `msctl net unrevoke {pki.cli_name(cn)}`",
        highlight=False,
        markup=False,
    )


@app.command("unrevoke")
def unrevoke(name: str = typer.Argument(..., help="An operator name or a host name.")) -> None:
    """Lift a revocation so the name can be issued a new identity; the revoked certificate
    stays refused."""
    from msctl.console import err
    from msctl.net import pki

    try:
        cn = _revocable(name)
        when = pki.unrevoke(cn)
    except pki.PkiError as exc:
        _fail(exc)
    again = (
        f"`msctl net add-operator {pki.cli_name(cn)}`"
        if pki.role_of(cn) == "operator"
        else f"`msctl net init --host {cn}`"
    )
    err.print(
        f"lifted the revocation of {cn} (revoked {when}); its revoked certificate stays "
        f"refused; issue a new identity with {again}",
        highlight=False,
        markup=False,
    )


@app.command("show")
def show(json_output: bool = JSON_OPT) -> None:
    """List the identities and when they expire; exit 1 when one cannot be read or a private
    key is open to others (each said on its own line, with the fix)."""
    from rich.table import Table

    from msctl.console import err, out, print_json
    from msctl.net import pki

    now = datetime.now(UTC)
    try:
        found, broken = pki.scan()
        revoked = sorted(pki.revoked_names())
        loose = dict(pki.loose_keys())
    except pki.PkiError as exc:
        _fail(exc)
    rows = []
    for identity in found:
        days = (identity.expires - now).days if identity.expires else None
        rows.append(
            {
                "common_name": identity.common_name,
                "role": identity.role,
                "expires": identity.expires.isoformat() if identity.expires else None,
                "days_left": days,
                "revoked": False,
                "certificate": str(identity.cert),
                "certificate_cn": identity.certificate_cn,
                "problem": loose.get(identity.key),
            }
        )
    for cn in revoked:
        rows.append(
            {
                "common_name": cn,
                "role": pki.role_of(cn),
                "expires": None,
                "days_left": None,
                "revoked": True,
                "certificate": None,
                "certificate_cn": None,
                "problem": None,
            }
        )
    for cert, why in broken:
        rows.append(
            {
                "common_name": cert.parent.name,
                "role": None,
                "expires": None,
                "days_left": None,
                "revoked": False,
                "certificate": str(cert),
                "certificate_cn": None,
                "problem": why,
            }
        )
    ca_key = pki.net_dir() / "ca" / "ca.key"
    problems = [r["problem"] for r in rows if r["problem"]]
    if ca_key in loose:
        problems.insert(0, loose[ca_key])
    if json_output:
        print_json({"ca": str(pki.ca_cert()), "identities": rows, "problems": problems})
    else:
        table = Table("identity", "role", "expires", "days left", "state")
        for row in rows:
            state = "revoked" if row["revoked"] else "valid"
            if row["days_left"] is not None and row["days_left"] < EXPIRY_WARNING_DAYS:
                state = "[yellow]expiring[/]" if row["days_left"] >= 0 else "[red]expired[/]"
            if row["problem"]:
                state = "[red]unreadable[/]" if row["role"] is None else "[red]key open[/]"
            table.add_row(
                row["common_name"],
                row["role"] or "-",
                (row["expires"] or "-")[:10],
                "-" if row["days_left"] is None else str(row["days_left"]),
                state,
            )
        out.print(table)
    for problem in problems:
        err.print(f"error: {problem}", style="red", markup=False, highlight=False)
    if problems:
        raise typer.Exit(1)


def _write(output: Path, text: str) -> None:
    """Write a generated config, or fail in one line naming the file."""
    from msctl.errors import InputError

    try:
        output.write_text(text)
    except OSError as exc:
        raise InputError(
            f"cannot write {output}: {exc.strerror or exc}",
            hint="name a file in a directory that exists and that you may write (-o FILE)",
        ) from None


def _check_output(output: Path | None) -> None:
    """Refuse an ``-o`` that cannot be written before anything is made for it."""
    import os

    from msctl.errors import InputError

    if output is None:
        return
    parent = output.parent if str(output.parent) else Path(".")
    if output.is_dir() or not parent.is_dir() or not os.access(parent, os.W_OK):
        why = "is a directory" if output.is_dir() else f"{parent} is no writable directory"
        raise InputError(
            f"cannot write {output}: {why}",
            hint="name a file in a directory that exists and that you may write (-o FILE)",
        )


@app.command("config")
def config(
    host: str = typer.Argument(None, help="The computer (default: this one, or MSCTL_HOST)."),
    output: Path = typer.Option(None, "--output", "-o", help="Write the json5 here."),
    component: bool = typer.Option(
        False, "--component", help="The config of the host's components instead of its router."
    ),
) -> None:
    """Print or write the Zenoh config of a host's router (json5).

    Refuses a router whose own private key others may read, and warns of any other.
    """
    import os
    import socket

    from components.assembly import AssemblyError, load_assembly
    from msctl.console import err, out
    from msctl.errors import InputError
    from msctl.net import config as netconfig
    from msctl.net import pki

    host = host or os.environ.get("MSCTL_HOST") or socket.gethostname()
    _check_output(output)
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
        loose = pki.loose_keys()
    except (netconfig.NetConfigError, pki.PkiError) as exc:
        _fail(exc)
    for _key, why in loose:
        err.print(f"warning: {why}", style="yellow", markup=False, highlight=False)
    text = netconfig.dumps(document)
    if output is None:
        out.print(text, end="", markup=False, highlight=False)
        return
    _write(output, text)
    err.print(f"wrote {output}", highlight=False)


def _enclave_path(enclave: str) -> str:
    """``enclave`` if it is a ROS enclave path (``/field/viewer``)."""
    from components.comm.names import NameError_, normalize_namespace
    from msctl.errors import InputError

    try:
        path = normalize_namespace(enclave)
    except NameError_ as exc:
        raise InputError(f"enclave {enclave!r} is not a path like /field/viewer: {exc}") from None
    if not enclave.startswith("/") or path == "/" or path != enclave:
        raise InputError(
            f"enclave {enclave!r} is not a path like /field/viewer",
            hint="a '/', then names of letters, digits and '_' separated by '/'",
        )
    return path


def _router_hosts() -> list[str]:
    """The computers whose routers an enclave may join: the resolved assembly's, else every
    host with an identity here."""
    from components.assembly import AssemblyError, load_assembly
    from msctl.net import pki

    try:
        return list(load_assembly().hosts)
    except AssemblyError:
        return [n for n in pki.common_names() if pki.role_of(n) == "host"]


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
    """An identity for a ROS 2 enclave and its session config in rmw_zenoh's form.

    Every name is checked before the identity is made: nothing is written for a bad one.
    """
    from components.comm.names import NameError_, qualify
    from msctl.console import err, out
    from msctl.errors import InputError, nearest
    from msctl.net import config as netconfig
    from msctl.net import pki
    from msctl.net.ros import enclave_config

    enclave = _enclave_path(enclave)
    topics: dict[str, list[str]] = {}
    for flag, given in (
        ("--publish", publish),
        ("--subscribe", subscribe),
        ("--serve", serve),
        ("--call", call),
    ):
        try:
            topics[flag] = [qualify(t, "/") for t in given or []]
        except NameError_ as exc:
            raise InputError(f"{flag}: {exc}") from None
    try:
        hosts = _router_hosts()
    except pki.PkiError as exc:
        _fail(exc)
    if router not in hosts:
        close = nearest(router, hosts)
        raise InputError(
            f"--router {router!r} is no computer of the fleet (its computers: "
            f"{', '.join(hosts) or 'none'})",
            hint=f"did you mean {close[0]}?"
            if close
            else "name the computer whose router it joins",
        )
    _check_output(output)
    try:
        pki.refuse_revoked(enclave)
        if not pki.identity_dir(enclave).is_dir():
            pki.issue(enclave)
        ports = netconfig.Ports()
        document = enclave_config(
            enclave,
            f"tls/{ports.address(router)}:{ports.tls_port(router)}",
            topics["--publish"],
            topics["--subscribe"],
            topics["--serve"],
            topics["--call"],
        )
    except (netconfig.NetConfigError, pki.PkiError) as exc:
        _fail(exc)
    text = netconfig.dumps(document)
    if output is None:
        out.print(text, end="", markup=False, highlight=False)
        return
    _write(output, text)
    err.print(f"wrote {output}; restart the routers so their ACL names {enclave}")
