"""``msctl teleop``: drive the running assembly from the keyboard, with a deadman.

The modules are claimed first: refused while another operator holds one, naming them and
since when; ``--take`` takes the claims over, and the other operator's screen says so. Joint
mode jogs one joint through its joint manager; IK mode moves a limb's tip with the IK syncer's
bounded steps; drive mode publishes Twists on the assembly's ``cmd_vel``. Motion continues
only while key events keep coming; whatever ends it sends exactly one stop.
"""

from __future__ import annotations

import typer

from msctl.errors import InputError, NotFoundError

COMMAND_SETTINGS = {
    "help": "Keyboard teleoperation with a deadman: jog joints, move limb tips, drive."
}


def command(
    module: list[str] = typer.Option(
        [], "--module", "-m", help="A module to command (repeat; default: every module)."
    ),
    mode: str = typer.Option("joint", "--mode", help="Starting mode: joint, ik or drive."),
    take: bool = typer.Option(
        False, "--take", help="Take over the modules' claims from whoever holds them."
    ),
    rate: float = typer.Option(20.0, "--rate", help="Motion commands per second while held."),
    first_timeout: float = typer.Option(
        0.6,
        "--first-timeout",
        help="Deadman seconds after a key's first event (above the OS's key-repeat delay).",
    ),
    repeat_timeout: float = typer.Option(
        0.15, "--repeat-timeout", help="Deadman seconds after each key repeat."
    ),
    cmd_vel: str | None = typer.Option(
        None, "--cmd-vel", help="Drive mode's topic (default: the assembly's cmd_vel)."
    ),
    stamped: bool = typer.Option(
        False, "--stamped", help="Drive mode publishes geometry_msgs/msg/TwistStamped."
    ),
    duration: float = typer.Option(
        0.0, "--for", help="Stop and quit after this many seconds (0: on Esc/Ctrl-C)."
    ),
) -> None:
    """Teleoperate the running assembly from this terminal (needs its lock file here)."""
    from msctl.teleop.core import TeleopSettings
    from msctl.teleop.keys import MODES

    if mode not in MODES:
        raise InputError(f"--mode must be one of {', '.join(MODES)}, not {mode!r}")
    if duration < 0:
        raise InputError(f"--for must be 0 or more seconds, not {duration}")
    try:
        settings = TeleopSettings(
            rate=rate, first_timeout=first_timeout, repeat_timeout=repeat_timeout
        )
    except ValueError as exc:
        raise InputError(str(exc).replace("TeleopSettings.", "--").replace("_", "-")) from exc
    assembly = _assembly()
    from msctl.teleop.link import check_modules, unavailable_modes

    # From the assembly's data alone, before the network: a mistake fails at once.
    slots = check_modules(assembly, module)
    why = unavailable_modes(assembly, slots, cmd_vel).get(mode)
    if why:
        raise InputError(f"--mode {mode}: {why}")
    from msctl.teleop.app import run_app

    run_app(
        assembly,
        modules=module,
        mode=mode,
        settings=settings,
        cmd_vel=cmd_vel,
        stamped=stamped,
        duration=duration or None,
        take=take,
    )


def _assembly():
    from components.assembly import AssemblyError, load_assembly

    try:
        return load_assembly()
    except AssemblyError as exc:
        raise NotFoundError(str(exc)) from exc
