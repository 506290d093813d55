"""Which privilege mode this machine allows: :func:`probe` reads it, :func:`choose` decides.

Plain data in between (:class:`Probes`, :class:`Choice`), so tests make their own probes. The
modes themselves (:class:`~msctl.rehearse.privileges.Root`,
:class:`~msctl.rehearse.privileges.UserNamespace`) are in :mod:`msctl.rehearse.privileges`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from msctl.rehearse.privileges import Privileges

#: The device the link emulator opens for every computer's radio.
TUN = Path("/dev/net/tun")
#: The commands (util-linux) a rehearsal without root runs besides ``ip``.
USERNS_COMMANDS = ("unshare", "nsenter", "mount")


@dataclass(frozen=True)
class Sysctl:
    """A kernel setting that turns unprivileged user namespaces off.

    Attributes:
        name: Its name (``sysctl NAME``).
        off: The value that turns them off.
        why: Whose setting it is, for the message.
        fix: The command that turns them on.
    """

    name: str
    off: str
    why: str
    fix: str

    @property
    def path(self) -> Path:
        """Its file under ``/proc/sys``."""
        return Path("/proc/sys") / self.name.replace(".", "/")


#: The settings that turn unprivileged user namespaces off, by distribution.
USERNS_SYSCTLS = (
    Sysctl(
        "kernel.unprivileged_userns_clone",
        "0",
        "the kernel's switch on Debian and older Ubuntu",
        "sudo sysctl -w kernel.unprivileged_userns_clone=1",
    ),
    Sysctl(
        "user.max_user_namespaces",
        "0",
        "no user namespace may be made",
        "sudo sysctl -w user.max_user_namespaces=15000",
    ),
    Sysctl(
        "kernel.apparmor_restrict_unprivileged_userns",
        "1",
        "Ubuntu's AppArmor takes every capability from them",
        "sudo sysctl -w kernel.apparmor_restrict_unprivileged_userns=0",
    ),
)


@dataclass(frozen=True)
class Probes:
    """What this machine allows, as :func:`probe` reads it (plain data: tests make their own).

    Attributes:
        platform: ``sys.platform``.
        euid: This process's effective user id.
        commands: Which of ``ip`` and :data:`USERNS_COMMANDS` are on PATH.
        tun: ``ok`` (``/dev/net/tun`` is open to this user), ``missing``, or ``denied``.
        tun_mode: Its permission bits (for the message), ``None`` when missing.
        userns: ``None`` when an unprivileged user namespace with a network namespace
            worked here; else what the try said.
        sysctls: The values of :data:`USERNS_SYSCTLS` this kernel has.
    """

    platform: str
    euid: int
    commands: frozenset[str]
    tun: str
    tun_mode: int | None = None
    userns: str | None = None
    sysctls: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Choice:
    """The mode :func:`choose` picked, or why none works here (the message says what to do).

    Attributes:
        mode: The mode's class; ``None`` when none works.
        problem: Why none works (``None`` when one does).
    """

    mode: type[Privileges] | None
    problem: str | None = None


def probe() -> Probes:
    """Read what this machine allows; tries an unprivileged user namespace (a few ms)
    only when this process is not root and has the commands for one."""
    commands = frozenset(c for c in ("ip", *USERNS_COMMANDS) if shutil.which(c))
    tun, tun_mode = "missing", None
    if TUN.exists():
        tun_mode = TUN.stat().st_mode & 0o777
        tun = "ok" if os.access(TUN, os.R_OK | os.W_OK) else "denied"
    sysctls = {}
    for setting in USERNS_SYSCTLS:
        try:
            sysctls[setting.name] = setting.path.read_text().strip()
        except OSError:
            continue
    euid = os.geteuid() if hasattr(os, "geteuid") else -1
    userns: str | None = "not tried"
    if sys.platform == "linux" and euid != 0 and {"ip", "unshare"} <= commands:
        userns = try_user_namespace()
    return Probes(sys.platform, euid, commands, tun, tun_mode, userns, sysctls)


def try_user_namespace() -> str | None:
    """Make a user namespace with a network namespace and bring its loopback up, as the
    keeper will; ``None`` if that worked, else what failed (AppArmor's restriction lets
    the namespace be made, without the capabilities: only using them tells)."""
    argv = ["unshare", "--user", "--map-root-user", "--mount", "--net", "--"]
    argv += ["ip", "link", "set", "lo", "up"]
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=20, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return str(exc)
    if done.returncode == 0:
        return None
    lines = (done.stderr or done.stdout).strip().splitlines()
    return lines[-1] if lines else f"exit status {done.returncode}"


def choose(probes: Probes) -> Choice:
    """The mode this machine allows: root's when root, else a user namespace's when the
    kernel allows one; else exactly why not and what to do."""
    # On use, not at import: privileges imports this module to re-export its names.
    from msctl.rehearse.privileges import SUDO, Root, UserNamespace

    if probes.platform != "linux":
        return Choice(None, "msctl rehearse needs Linux (network namespaces and TUN devices)")
    if "ip" not in probes.commands:
        return Choice(
            None, "the `ip` command (iproute2) is not installed: `sudo apt-get install iproute2`"
        )
    if probes.tun == "missing":
        return Choice(None, f"{TUN} is missing: load the tun module (`sudo modprobe tun`)")
    if probes.euid == 0:
        return Choice(Root)
    why: list[str] = []
    fixes: list[str] = []
    missing = [c for c in USERNS_COMMANDS if c not in probes.commands]
    if missing:
        why.append(f"`{'`, `'.join(missing)}` (util-linux) not installed")
        fixes.append("install them: `sudo apt-get install util-linux`")
    elif probes.userns is not None:
        off = [s for s in USERNS_SYSCTLS if probes.sysctls.get(s.name) == s.off]
        for setting in off:
            why.append(
                f"unprivileged user namespaces are off ({setting.name} = {setting.off}: "
                f"{setting.why})"
            )
            fixes.append(f"turn them on: `{setting.fix}`")
        if not off:
            why.append(f"an unprivileged user namespace cannot be made here ({probes.userns})")
    if probes.tun == "denied":
        mode = f"mode {probes.tun_mode:04o}" if probes.tun_mode is not None else "its mode"
        why.append(f"{TUN} is not open to you ({mode})")
        fixes.append(f"`sudo chmod 0666 {TUN}` (udev's default on most distributions)")
    if not why:
        return Choice(UserNamespace)
    problem = (
        "msctl rehearse makes network namespaces and TUN devices, which needs root or "
        f"unprivileged user namespaces, and neither is available: you are not root, and "
        f"{'; '.join(why)}. Run it with sudo (`{SUDO}` keeps this environment)"
    )
    if fixes:
        problem += ", or, to run it as yourself, " + " and ".join(fixes)
        if any("sysctl" in f for f in fixes):
            problem += " (a file in /etc/sysctl.d/ keeps a setting across boots)"
    return Choice(None, problem)
