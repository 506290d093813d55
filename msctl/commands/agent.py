"""``msctl agent``: run this robot computer's agent; ``msctl agent install``: make it a service.

    msctl agent                      serve /msctl/<host>/request until Ctrl-C / SIGTERM
    msctl agent install              write /etc/systemd/system/msctl-agent.service
    msctl agent install --user       write ~/.config/systemd/user/msctl-agent.service
    msctl agent install -o FILE      write the unit to FILE (to copy elsewhere)

Once an agent runs on every robot computer, ``msctl up --all`` on a ground station starts the
whole assembly, and ``ps / logs / restart / stop / down --all`` reach every computer, with no
SSH.
"""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import typer

from msctl.commands.up import ROUTER_EPILOG
from msctl.errors import InputError, MsctlError

app = typer.Typer(
    help="This computer's agent: starts its part of an assembly when `msctl up --all` asks.",
    epilog=ROUTER_EPILOG,
)

UNIT_NAME = "msctl-agent.service"
SYSTEM_UNIT_DIR = Path("/etc/systemd/system")
#: Passed from the installing shell into the unit, so the agent joins the same network.
_ENV_PREFIXES = (
    "MSCTL_ZENOH_",
    # Where its router listens and links, and whether it is secure: without them in the
    # unit, the agent started at boot would be a loopback-only router no station reaches.
    "MSCTL_ROUTER_",
    "MSCTL_SECURE",
    "MSCTL_NET_TLS_PORT",
    "MSCTL_HOME",
    "MSCTL_DOMAIN",
    "ROS_DOMAIN_ID",
    "MSCTL_WORKSPACE",
    "MSCTL_WHEELHOUSE",
)


@app.callback(invoke_without_command=True)
def run(
    ctx: typer.Context,
    host: str = typer.Option(
        None, "--host", envvar="MSCTL_HOST", help="This computer's name (env MSCTL_HOST)."
    ),
    secure: bool = typer.Option(
        False,
        "--secure",
        envvar="MSCTL_SECURE",
        help="Run the agent's router from `msctl net config`: mutual TLS and access control "
        "(env MSCTL_SECURE).",
    ),
) -> None:
    """Run the agent: idle until `msctl up --all` sends it an assembly; Ctrl-C stops all.

    Its router (when it starts one) is the app's epilog.
    """
    if secure:
        import os

        os.environ["MSCTL_SECURE"] = "1"  # read where the agent starts its router
    if ctx.invoked_subcommand is not None:
        return
    from msctl.launcher.agent import Agent
    from msctl.launcher.control import RequestError

    try:
        agent = Agent(host)
    except RequestError as exc:
        raise InputError(
            str(exc), hint="set MSCTL_HOST to the host named in the unit's calibration"
        ) from None
    previous = {
        s: signal.signal(s, lambda *_: agent.request_stop())
        # SIGHUP (terminal or SSH link gone) stops the run as SIGTERM does: nothing orphaned.
        for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    }
    from msctl.workspace.service import WorkspaceAgent

    # `msctl update --all` / `build --all`: its own service and thread, so a long git or pip
    # run never holds up the agent's loop.
    workspace = WorkspaceAgent.from_env(agent.host, log=agent.log)
    try:
        try:
            agent.start()
        except MsctlError:
            raise  # its own line says what and how to fix it
        except RuntimeError as exc:
            raise MsctlError(
                str(exc), hint="free the port or point MSCTL_ZENOH_CONNECT at the router"
            ) from exc
        workspace.serve(agent.session, agent.settings.domain)
        agent.run()
    finally:
        workspace.close()
        agent.shutdown()
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def msctl_executable() -> list[str]:
    """How systemd should start this msctl: the script next to this interpreter, else
    ``python -m msctl`` with this interpreter (both absolute, so the unit needs no PATH)."""
    script = Path(sys.executable).parent / "msctl"
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [str(Path(sys.executable).absolute()), "-m", "msctl"]


def _quote(value: str) -> str:
    # systemd reads C-style escapes inside double quotes; a newline would end the setting.
    if "\n" in value or "\r" in value:
        raise InputError(f"{value!r} contains a line break; it cannot go into a systemd unit")
    value = value.replace("%", "%%")  # systemd expands %-specifiers, even inside quotes
    if value and not any(c in value for c in " \t\"'\\$;"):
        return value
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


def unit_text(host: str, user_unit: bool, env: dict[str, str] | None = None) -> str:
    """The systemd unit running ``msctl agent`` as ``host``.

    Args:
        host: The computer's name, as the calibration files spell it (MSCTL_HOST).
        user_unit: A ``systemctl --user`` unit (no ``User=``, wanted by ``default.target``).
        env: The environment to take network settings from (default: this process's).
    """
    env = os.environ if env is None else env
    environment = {"MSCTL_HOST": host, "PYTHONUNBUFFERED": "1"}
    for key in sorted(env):
        if key.startswith(_ENV_PREFIXES) and key != "MSCTL_HOST":
            environment[key] = env[key]
    lines = [
        "# Written by `msctl agent install`; run it again rather than editing by hand.",
        "[Unit]",
        f"Description=msctl agent of {host}: starts its part of an assembly on request",
        "Wants=network-online.target",
        "After=network-online.target",
        "",
        "[Service]",
        "Type=simple",
        "ExecStart=" + " ".join(_quote(a) for a in [*msctl_executable(), "agent"]),
        *(f"Environment={_quote(f'{k}={v}')}" for k, v in environment.items()),
    ]
    if not user_unit:
        # Motors hang on the installer's serial ports and CAN links: run as that user, not root.
        lines.append(f"User={os.environ.get('SUDO_USER') or getpass.getuser()}")
    lines += [
        "Restart=always",
        "RestartSec=2",
        # The agent stops its process groups itself; the control group catches any leftover.
        "KillMode=control-group",
        "KillSignal=SIGTERM",
        "TimeoutStopSec=10",
        "",
        "[Install]",
        f"WantedBy={'default.target' if user_unit else 'multi-user.target'}",
        "",
    ]
    return "\n".join(lines)


def _user_unit_dir() -> Path:
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "systemd" / "user"


@app.command()
def install(
    user: bool = typer.Option(False, "--user", help="A user unit (~/.config/systemd/user)."),
    output: Path = typer.Option(None, "--output", "-o", help="Write the unit to this file."),
    enable: bool = typer.Option(
        False, "--enable", help="Also run systemctl daemon-reload and enable --now."
    ),
    host: str = typer.Option(
        None, "--host", envvar="MSCTL_HOST", help="The computer's name (env MSCTL_HOST)."
    ),
) -> None:
    """Write a systemd unit that runs `msctl agent` at boot and restarts it if it stops."""
    from msctl.assembler.store import write_file
    from msctl.console import err
    from msctl.launcher.plan import this_host

    if enable and output is not None:
        raise InputError(
            "--enable works with the systemd unit directories only, not --output",
            hint="copy the file into /etc/systemd/system (or use --user), then enable it",
        )
    host = host or this_host()
    path = output or ((_user_unit_dir() if user else SYSTEM_UNIT_DIR) / UNIT_NAME)
    try:
        write_file(path, unit_text(host, user))
    except PermissionError as exc:
        raise MsctlError(
            f"cannot write {path}: permission denied",
            hint="run it with sudo, or use --user (a user unit) or --output FILE",
        ) from exc
    except OSError as exc:
        raise MsctlError(f"cannot write {path}: {exc.strerror or exc}") from exc
    err.print(f"[green]wrote[/] {path} (agent of {host})", highlight=False)
    systemctl = ["systemctl", "--user"] if user else ["systemctl"]
    steps = [[*systemctl, "daemon-reload"], [*systemctl, "enable", "--now", "msctl-agent"]]
    shown = " && ".join(("" if user else "sudo ") + " ".join(s) for s in steps)
    if output is not None:
        err.print(
            f"next: copy it to {SYSTEM_UNIT_DIR / UNIT_NAME} (or {_user_unit_dir() / UNIT_NAME}), "
            f"then `{shown}`",
            highlight=False,
        )
        return
    if not enable:
        err.print(f"next: `{shown}`", highlight=False)
        if user:
            err.print(
                "[dim]to start it at boot without a login: `sudo loginctl enable-linger "
                f"{getpass.getuser()}`[/]",
                highlight=False,
            )
        return
    if shutil.which("systemctl") is None:
        raise MsctlError(
            f"systemctl is not on this computer; {path} was written",
            hint="start `msctl agent` with this computer's init system instead",
        )
    for step in steps:
        result = subprocess.run(step, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            raise MsctlError(
                f"`{' '.join(step)}` failed ({result.returncode}): "
                f"{(result.stderr or result.stdout).strip()}"
            )
    err.print("[green]enabled[/] msctl-agent: `systemctl status msctl-agent`", highlight=False)
