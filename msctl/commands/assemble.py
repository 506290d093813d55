"""``msctl assemble``: pick a template and the physical units -> one resolved assembly.

One command with a positional word, so ``msctl assemble dragon --use limb1=hlv1-limb-04`` and
``msctl assemble show`` both read naturally; ``show``, ``urdf`` and ``mjcf`` are therefore
reserved and no template may be named like them.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError, NotFoundError

ACTIONS = ("show", "urdf", "mjcf")

app = typer.Typer(
    invoke_without_command=True,
    no_args_is_help=False,
    add_completion=False,
    subcommand_metavar="",
    context_settings={"allow_interspersed_args": True},
)


@app.callback()
def assemble(
    target: str = typer.Argument(
        None,
        metavar="TEMPLATE|show|urdf|mjcf",
        help="A template to resolve (dragon, two_dragons...), or: show (the current resolution), "
        "urdf / mjcf (print the generated model).",
        show_default=False,
    ),
    use: list[str] = typer.Option(
        None,
        "--use",
        "-u",
        metavar="SLOT=UNIT",
        help="Put unit UNIT in slot SLOT (repeatable). Every other slot keeps its previous unit.",
    ),
    defaults: bool = typer.Option(
        False,
        "--defaults",
        help="Put every slot not named by --use back on the template's default unit.",
    ),
    list_: bool = typer.Option(
        False, "--list", "-l", help="List templates, module types and units, with what fits where."
    ),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
    output: Path = typer.Option(
        None, "--output", "-o", help="With urdf/mjcf: write the model to this file instead."
    ),
) -> None:
    """Resolve an assembly: template + physical units -> lock file, URDF, MJCF, per-host plan.

    \b
    msctl assemble dragon
        resolve (the defaults, or the previous resolution's units)
    msctl assemble dragon --use limb1=hlv1-limb-04
        swap one unit, keep the others
    msctl assemble dragon --defaults
        every slot back on the template's default unit
    msctl assemble --list
        templates, module types and units, and what fits where
    msctl assemble show
        the current resolution and its per-host plan
    msctl assemble urdf -o /tmp/dragon.urdf
        write the composed URDF (mjcf: the MuJoCo model)

    The resolution lives in $MSCTL_HOME/assembly (default ~/.local/state/msctl/assembly).
    """
    if list_:
        _refuse(target is not None, "--list takes no TEMPLATE")
        _list(json_output)
        return
    if target is None:
        raise InputError(
            "name a template to resolve, or show / urdf / mjcf",
            hint="see `msctl assemble --list` for the templates",
            exit_code=2,
        )
    if target in ACTIONS:
        _refuse(bool(use), f"--use applies when resolving a template, not with {target}")
        _refuse(defaults, f"--defaults applies when resolving a template, not with {target}")
        if target == "show":
            _refuse(output is not None, "-o applies to urdf and mjcf")
            _show(json_output)
        else:
            _refuse(json_output, f"{target} prints XML; --json does not apply")
            _artifact(target, output)
        return
    _refuse(output is not None, "-o applies to `msctl assemble urdf` and `mjcf`")
    _resolve(target, use or [], json_output, defaults)


def _refuse(condition: bool, message: str) -> None:
    if condition:
        raise InputError(message, hint="see `msctl assemble --help`")


def _previous_units() -> dict[str, str]:
    """Slot -> unit of the current resolution, if any (a broken one is ignored, with a note)."""
    from components.assembly import lock_path
    from msctl.console import err

    path = lock_path()
    try:
        units = json.loads(path.read_text(encoding="utf-8")).get("units", {})
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, AttributeError) as exc:
        err.print(f"[yellow]note:[/] ignoring unreadable {path} ({exc})", highlight=False)
        return {}
    return {str(k): str(v) for k, v in units.items()} if isinstance(units, dict) else {}


def _picker():
    """A chooser for slots with several fitting units, or None without a terminal."""
    if not (sys.stdin.isatty() and sys.stderr.isatty()):
        return None
    from rich.prompt import IntPrompt

    from msctl.assembler import data
    from msctl.console import err

    def choose(slot: str, candidates: list[str]) -> str:
        err.print(f"[bold]{len(candidates)} units fit slot {slot}:[/]")
        for i, serial in enumerate(candidates, 1):
            unit = data.load_unit(serial)
            err.print(f"  {i}) {serial:<16} {unit.module_type:<12} host {unit.host}")
        pick = IntPrompt.ask(
            f"unit for {slot}",
            choices=[str(i) for i in range(1, len(candidates) + 1)],
            console=err,
        )
        return candidates[pick - 1]

    return choose


def resolve_and_write(
    template: str, uses: list[str], defaults: bool = False
) -> tuple[dict[str, Any], Path, list[str]]:
    """Resolve ``template`` (with ``--use`` choices) and write the assembly atomically.

    Args:
        template: The template to resolve.
        uses: ``SLOT=UNIT`` choices.
        defaults: Ignore the previous resolution: every other slot takes its default unit.

    Returns:
        The lock document, the directory written, and the slots whose unit changed.
    """
    from components.assembly import assembly_dir
    from msctl.assembler import parse_uses, resolve
    from msctl.assembler.store import write_resolution

    if template in ACTIONS:  # pragma: no cover - dispatched before
        raise InputError(f"{template!r} is reserved")
    _refuse_while_running()
    previous = _previous_units()
    chosen = parse_uses(uses)
    resolution = resolve(template, chosen, {} if defaults else previous, _picker())
    target = write_resolution(assembly_dir(), resolution)
    document = resolution.document
    changed = [s for s, u in document["units"].items() if previous.get(s) not in (None, u)]
    kept = {s: u for s, u in document["units"].items() if s not in chosen and previous.get(s) == u}
    note_off_defaults(template, kept)
    return document, target, changed


def _refuse_while_running() -> None:
    """A running assembly's workers read the lock file when they (re)start: never replace it
    under them."""
    from msctl.launcher.state import read_state, run_lock_holder, supervisor_alive

    hint = "stop it with `msctl down` first, then assemble and `msctl up` again"
    running = read_state()
    if supervisor_alive(running):
        assert running is not None
        raise InputError(
            f"assembly {running.get('template', '?')} is running (supervisor pid "
            f"{running.get('supervisor_pid')} on {running.get('host', 'this computer')}); "
            "resolving again now would replace the lock file under it",
            hint=hint,
        )
    # Still starting: its state file is not written yet, its workers read the lock file now.
    holder = run_lock_holder()
    if holder is not None:
        raise InputError(
            f"assembly {holder.get('template') or '?'} is starting (pid {holder.get('pid')}: "
            f"{holder.get('by') or 'msctl up'} on {holder.get('host') or 'this computer'}); "
            "resolving again now would replace the lock file under it",
            hint=hint,
        )


def note_off_defaults(template: str, units: dict[str, str]) -> None:
    """Say which of ``units`` (kept from before, not chosen now) are not the template's
    defaults: a unit swapped in for one experiment stays until told otherwise."""
    from msctl.assembler.resolve import off_defaults
    from msctl.console import err

    differ = off_defaults(template, units)
    if not differ:
        return
    slots = ", ".join(f"{slot}={unit} (default {default})" for slot, unit, default in differ)
    err.print(
        f"[yellow]note:[/] kept from the previous resolution, not the defaults: {slots}; "
        f"`msctl assemble {template} --defaults` puts them back",
        highlight=False,
    )


def _resolve(template: str, uses: list[str], json_output: bool, defaults: bool = False) -> None:
    from components.assembly import LOCK_NAME
    from msctl.console import err, print_json

    start = time.perf_counter()
    document, target, changed = resolve_and_write(template, uses, defaults)
    elapsed = (time.perf_counter() - start) * 1000
    if json_output:
        print_json(document)
    else:
        _print_summary(document)
    note = f" (changed: {', '.join(changed)})" if changed else ""
    err.print(
        f"[green]resolved[/] {template}{note} -> {target / LOCK_NAME} in {elapsed:.0f} ms",
        highlight=False,
    )


def _load():
    from components.assembly import AssemblyError, load_assembly

    try:
        return load_assembly()
    except AssemblyError as exc:
        raise NotFoundError(str(exc)) from None


def _show(json_output: bool) -> None:
    from msctl.console import print_json

    assembly = _load()
    if json_output:
        print_json(dict(assembly.document))
        return
    _print_summary(dict(assembly.document))


def _print_summary(document: dict[str, Any]) -> None:
    from rich.table import Table

    from msctl.console import out

    units = Table(
        title=f"{document['template']}: {document.get('description', '')}", title_justify="left"
    )
    for column in ("slot", "unit", "type", "host", "bus", "joints"):
        units.add_column(column)
    # Overrides now live in the parameters of the component they change (the joint manager).
    overrides_of: dict[str, list[str]] = {}
    for c in document["components"]:
        if c["module"] is not None:
            names = [o["name"] for o in c["params"].get("overrides", ())]
            overrides_of.setdefault(c["module"], []).extend(names)
    for m in document["modules"]:
        bus = m["bus"]
        rate = bus.get("bitrate") or bus.get("baudrate")
        overrides = ", ".join(overrides_of.get(m["slot"], ()))
        units.add_row(
            m["slot"],
            m["unit"],
            m["module_type"],
            m["host"],
            f"{bus['kind']} {bus['channel']} @{rate}",
            f"{len(m['joints'])}" + (f" (overrides: {overrides})" if overrides else ""),
        )
    out.print(units)
    hosts = Table(title="per-host plan", title_justify="left")
    hosts.add_column("host")
    hosts.add_column("role")
    hosts.add_column("components")
    for host in document["hosts"]:
        plan = document["host_plans"][host]
        hosts.add_row(host, plan["role"], ", ".join(plan["components"]))
    out.print(hosts)
    counts = ", ".join(f"{k} {v}" for k, v in document["component_counts"].items())
    total = sum(document["component_counts"].values())
    out.print(f"{total} components: {counts}", highlight=False)


def _artifact(kind: str, output: Path | None) -> None:
    from msctl.assembler.store import write_file
    from msctl.console import err

    assembly = _load()
    path = assembly.urdf_path if kind == "urdf" else assembly.mjcf_path
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise NotFoundError(
            f"{path}: cannot read the {kind.upper()} ({exc.strerror})",
            hint=f"run `msctl assemble {assembly.template}` again",
        ) from None
    if output is None:
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    parent = output.parent if str(output.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(
            f"-o {output}: no directory {parent}",
            hint="create it first, or write somewhere that exists",
        )
    if output.is_dir():
        raise InputError(f"-o {output} is a directory; give a file name, e.g. {output}/x.{kind}")
    try:
        write_file(output, text)
    except OSError as exc:
        raise InputError(f"-o {output}: cannot write ({exc.strerror})") from None
    err.print(f"wrote {output}", highlight=False)


def _list(json_output: bool) -> None:
    from msctl.assembler import data
    from msctl.console import out, print_json
    from msctl.errors import MsctlError

    templates: dict[str, Any] = {}
    fits_where: dict[str, list[str]] = {}
    for name in data.template_names():
        try:
            t = data.load_template(name)
        except MsctlError as exc:
            templates[name] = {"error": str(exc)}
            continue
        templates[name] = {
            "description": t.description,
            "mobile": t.mobile,
            "slots": {s.name: {"fits": list(s.fits), "default": s.default} for s in t.slots},
            "stations": [s.name for s in t.stations],
        }
        for s in t.slots:
            for key in s.fits:
                fits_where.setdefault(key, []).append(f"{name}.{s.name}")
    modules: dict[str, Any] = {}
    for key in data.module_type_names():
        try:
            m = data.load_module_type(key)
        except MsctlError as exc:
            modules[key] = {"error": str(exc)}
            continue
        modules[key] = {
            "description": m.description,
            "family": m.family,
            "kind": m.kind,
            "revision": m.revision,
            "bus": m.bus["kind"],
            "joints": len(m.joints),
            "connectors": list(m.connectors),
        }
    units: dict[str, Any] = {}
    for serial in data.unit_serials():
        try:
            u = data.load_unit(serial)
        except MsctlError as exc:
            units[serial] = {"error": str(exc)}
            continue
        units[serial] = {
            "module_type": u.module_type,
            "host": u.host,
            "channel": u.bus.get("channel"),
            "fits": fits_where.get(u.module_type, []),
        }
    if json_output:
        print_json({"templates": templates, "module_types": modules, "units": units})
        return
    from rich.table import Table

    def table(title: str, columns: list[str], rows: list[list[str]]) -> None:
        t = Table(title=title, title_justify="left")
        for c in columns:
            t.add_column(c)
        for r in rows:
            t.add_row(*r)
        out.print(t)

    table(
        f"templates ({data.assemblies_dir()})",
        ["template", "slots (fits)", "description"],
        [
            [n, v["error"], ""]
            if "error" in v
            else [
                n,
                "\n".join(f"{s}: {', '.join(d['fits'])}" for s, d in v["slots"].items()),
                v["description"],
            ]
            for n, v in templates.items()
        ],
    )
    table(
        "module types",
        ["type", "family", "kind", "rev", "bus", "joints", "description"],
        [
            [k, v["error"], "", "", "", "", ""]
            if "error" in v
            else [
                k,
                v["family"],
                v["kind"],
                str(v["revision"]),
                v["bus"],
                str(v["joints"]),
                v["description"],
            ]
            for k, v in modules.items()
        ],
    )
    table(
        f"units ({data.calibration_dir()})",
        ["unit", "type", "host", "channel", "fits"],
        [
            [k, v["error"], "", "", ""]
            if "error" in v
            else [k, v["module_type"], v["host"], str(v["channel"]), ", ".join(v["fits"])]
            for k, v in units.items()
        ],
    )
