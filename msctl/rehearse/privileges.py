"""How a rehearsal gets to make network namespaces and TUN devices: as root, or without.

Two modes, one class each, chosen from what this machine allows (:func:`probe` reads it,
:func:`choose` decides, plain data in between; both in :mod:`msctl.rehearse.privilege_choice`,
importable from here):

- :class:`Root` (euid 0): the system's named network namespaces (``ip netns add``, files in
  ``/run/netns``), their ``/etc/netns/<namespace>`` files, TUN devices: what root can make.
- :class:`UserNamespace` (any user, where the kernel allows unprivileged user namespaces):
  a *keeper* process, started as ``unshare --user --map-root-user --mount --net``, lives as
  long as the rehearsal. It is root in a user namespace of its own, so what is made inside
  it (network namespaces, TUN devices, mounts) is its own to make: the kernel checks
  CAP_NET_ADMIN and CAP_SYS_ADMIN against the user namespace that owns each object, not the
  system's. Its private mount namespace has a tmpfs over ``/run/netns`` (over ``/run`` when
  that directory does not exist: a mountpoint must), so ``ip netns`` works there unchanged
  and nothing is written in the system's. Every ``ip`` call, the link emulator and every
  command of a computer enter it first with ``nsenter --target KEEPER --user --mount --net
  --preserve-credentials``. Its own network namespace is there because ``ip netns add``
  returns to the namespace it started in, which it may only do in one its user namespace
  owns. A computer's ``/etc/hosts`` is bound by its commands' shell from a file under the
  rehearsal's directory (``/etc/netns``, where ``ip netns exec`` would look, may not exist
  and only root may make it). ``down`` ends every computer's processes, then the keeper:
  its mount namespace goes with it, and with that the rehearsal's network namespaces.

Files the user namespace writes are the user's own (its root is the user, mapped), so a
rehearsal without root leaves nothing outside ``MSCTL_HOME``, ``/tmp`` and the keeper's
private mounts. ``/dev/net/tun`` must be open to the user (mode 0666, udev's default).
"""

from __future__ import annotations

import getpass
import os
import select
import signal
import subprocess
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from msctl.errors import MsctlError

# Read from here too (`privileges.choose`): the choice of a mode is its own module.
from msctl.rehearse.privilege_choice import Choice as Choice
from msctl.rehearse.privilege_choice import Probes as Probes
from msctl.rehearse.privilege_choice import choose as choose
from msctl.rehearse.privilege_choice import probe as probe

#: Where ``ip netns exec`` finds the files it binds over ``/etc`` inside a namespace.
NETNS_ETC = Path("/etc/netns")
#: How a root user keeps the caller's environment (the venv's msctl on PATH).
SUDO = "sudo -E env PATH=$PATH msctl rehearse ..."
#: What the keeper's command line holds, so ``down`` finds it after a crash.
KEEPER_MODULE = "msctl.rehearse.privileges"
#: Set to the rehearsal's directory by :func:`start_keeper`: a keeper run otherwise refuses.
KEEPER_ENV = "MSCTL_REHEARSE_KEEPER"
#: Seconds the keeper has to make its mounts and say it is ready.
KEEPER_READY_WITHIN = 20.0


class RehearseError(MsctlError):
    """A rehearsal cannot be made, found or changed; the message says what to do."""


# --------------------------------------------------------------------------- the modes
class Privileges(ABC):
    """Where a rehearsal's namespaces live, and how its commands get into them."""

    #: The mode's name, as the state file keeps it.
    mode: ClassVar[str]

    @property
    @abstractmethod
    def etc(self) -> Path:
        """The directory holding each namespace's ``/etc`` files (``<etc>/<namespace>/hosts``)."""

    @abstractmethod
    def command(self, argv: Sequence[str], wd: str | None = None) -> list[str]:
        """``argv`` run where the rehearsal's namespaces are (``ip`` sees them there).

        Args:
            argv: The command.
            wd: Its working directory, when it matters (the caller's otherwise kept).
        """

    @abstractmethod
    def enter(self, netns: str, hostname: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside network namespace ``netns``, in a UTS namespace of its own
        named ``hostname``, the namespace's ``/etc`` files over the system's, exec all the
        way down (its pid is the command's)."""

    @classmethod
    @abstractmethod
    def start(cls, root: Path) -> Privileges:
        """Make what the mode needs for the rehearsal in ``root`` before its namespaces."""

    def alive(self) -> bool:
        """Whether the rehearsal's namespaces can still be reached this way."""
        return True

    def environment(self, env: Mapping[str, str]) -> dict[str, str]:
        """What a computer's process needs added to ``env`` in this mode."""
        return {}

    def need(self) -> None:
        """Raise :class:`RehearseError` when this caller cannot change a rehearsal made so."""

    def close(self) -> list[str]:
        """Undo what the mode made (after the namespaces' processes ended); what it ended."""
        return []

    @abstractmethod
    def to_json(self) -> dict[str, Any]:
        """The mode as the state file keeps it (``mode``: its name)."""

    @classmethod
    @abstractmethod
    def from_json(cls, data: Mapping[str, Any]) -> Privileges:
        """The mode the state file kept (what :meth:`to_json` wrote)."""


#: The shell that names a computer's command's UTS namespace, then becomes the command
#: (``hostname`` inside a fresh UTS namespace changes this process's view only).
UTS_SCRIPT = 'hostname "$0" && exec "$@"'


@dataclass(frozen=True)
class Root(Privileges):
    """The system's namespaces, as root makes them."""

    mode: ClassVar[str] = "root"

    @classmethod
    def start(cls, root: Path) -> Privileges:
        """Nothing to make: the system's namespaces are root's."""
        return ROOT

    @property
    def etc(self) -> Path:
        """``/etc/netns``, which ``ip netns exec`` binds from."""
        return NETNS_ETC

    def command(self, argv: Sequence[str], wd: str | None = None) -> list[str]:
        """``argv`` itself: root sees the system's namespaces."""
        return list(argv)

    def enter(self, netns: str, hostname: str, argv: Sequence[str]) -> list[str]:
        """``ip netns exec`` (which binds ``/etc/netns/<netns>``), then a UTS namespace."""
        return [
            "ip",
            "netns",
            "exec",
            netns,
            "unshare",
            "--uts",
            "--",
            "sh",
            "-c",
            UTS_SCRIPT,
            hostname,
            *argv,
        ]

    def need(self) -> None:
        """Only root changes what root made."""
        if os.geteuid() != 0:
            raise RehearseError(
                "this rehearsal was made by root (the system's network namespaces)",
                hint=f"run it with sudo: `{SUDO}`",
            )

    def to_json(self) -> dict[str, Any]:
        """``{"mode": "root"}``."""
        return {"mode": self.mode}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Privileges:
        """:data:`ROOT`."""
        return ROOT


#: The one :class:`Root` (it holds nothing).
ROOT = Root()


@dataclass(frozen=True)
class UserNamespace(Privileges):
    """The namespaces of a keeper process's own user namespace (see the module's docstring).

    Attributes:
        keeper: The keeper's pid.
        userns: The inode of its user namespace (``/proc/<keeper>/ns/user``): a pid reused by
            another process is never taken for it, and after the keeper died, the
            rehearsal's processes still in that namespace are found by it.
        root: The rehearsal's directory.
    """

    mode: ClassVar[str] = "userns"

    keeper: int
    userns: int
    root: Path

    @classmethod
    def start(cls, root: Path) -> Privileges:
        """The keeper (see :func:`start_keeper`), its error output in ``<root>/logs``."""
        return start_keeper(root, root / "logs" / "keeper.log")

    @property
    def etc(self) -> Path:
        """``<root>/etc``: the user's own (``/etc/netns`` is root's to make)."""
        return self.root / "etc"

    def alive(self) -> bool:
        """Whether the keeper still runs (the very one: its user namespace is the same)."""
        try:
            same = os.stat(f"/proc/{self.keeper}/ns/user").st_ino == self.userns
            # A keeper that exited unreaped keeps its user namespace, not its mount one.
            os.stat(f"/proc/{self.keeper}/ns/mnt")
        except OSError:
            return False
        return same

    def command(self, argv: Sequence[str], wd: str | None = None) -> list[str]:
        """``argv`` entered into the keeper's user, mount and network namespaces.

        Raises:
            RehearseError: If the keeper is gone (the rehearsal's namespaces went with it).
        """
        if not self.alive():
            raise RehearseError(
                f"the rehearsal's keeper (pid {self.keeper}) is gone, and its namespaces with it",
                hint="`msctl rehearse down` removes what is left; then up again",
            )
        # --preserve-credentials: nsenter would set uid 0 and groups, which a user namespace
        # made by --map-root-user refuses (setgroups is denied there); the user is root there.
        enter = ["nsenter", f"--target={self.keeper}", "--user", "--mount", "--net"]
        enter.append("--preserve-credentials")
        if wd is not None:
            # Entering a mount namespace moves to its root: the command's directory is the
            # caller's (the same path: the keeper's mounts hide only /run's).
            enter.append(f"--wd={wd}")
        return [*enter, "--", *argv]

    def enter(self, netns: str, hostname: str, argv: Sequence[str]) -> list[str]:
        """``ip netns exec``, then the namespace's ``/etc`` files bound over the system's
        by the shell (in the mount namespace ``ip netns exec`` made for this command)."""
        script = (
            'for f in "$1"/*; do t="/etc/${f##*/}"; '
            'if [ -e "$t" ]; then mount --bind "$f" "$t" || exit 1; fi; done; '
            'shift && hostname "$0" && exec "$@"'
        )
        inside = ["ip", "netns", "exec", netns, "unshare", "--uts", "--", "sh", "-c", script]
        return self.command([*inside, hostname, str(self.etc / netns), *argv], wd=_cwd())

    def environment(self, env: Mapping[str, str]) -> dict[str, str]:
        """The user's name, when ``env`` does not say it: the user is root in there, and
        ``msctl net init`` names its operator after the user (as this process does)."""
        if any(env.get(k) for k in ("LOGNAME", "USER", "LNAME", "USERNAME")):
            return {}
        name = _user_name()
        return {"LOGNAME": name, "USER": name}

    def close(self) -> list[str]:
        """End the keeper (and so the rehearsal's namespaces), then any of its processes
        left in its user namespace (a keeper that died first leaves them running)."""
        ended = []
        if self.alive():
            _end([self.keeper], grace=5.0)
            ended.append(f"keeper {self.keeper}")
        # Its processes by their namespace *and* their home: after the namespace is gone,
        # another one (a browser's sandbox) may be given its number.
        stray = [p for p in processes_in(self.userns) if _of_rehearsal(p, self.root)]
        if stray:
            _end(stray, grace=5.0)
            ended.append(f"{len(stray)} processes left in its user namespace")
        return ended

    def to_json(self) -> dict[str, Any]:
        """Mode, keeper, user namespace and the ``/etc`` files' directory."""
        return {
            "mode": self.mode,
            "keeper": self.keeper,
            "userns": self.userns,
            "root": str(self.root),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Privileges:
        """Keeper, user namespace and directory as kept."""
        return cls(keeper=int(data["keeper"]), userns=int(data["userns"]), root=Path(data["root"]))


#: Every mode by its name in the state file.
MODES: dict[str, type[Privileges]] = {Root.mode: Root, UserNamespace.mode: UserNamespace}


def from_json(data: Mapping[str, Any] | None) -> Privileges:
    """The mode a state file kept (none kept: root's, as every rehearsal was before).

    Raises:
        RehearseError: If the mode is not one msctl knows.
    """
    data = data or {"mode": Root.mode}
    mode = MODES.get(str(data.get("mode")))
    if mode is None:
        raise RehearseError(
            f"unknown privilege mode {data.get('mode')!r} (known: {', '.join(MODES)})",
            hint="`msctl rehearse down` removes whatever it can find of it",
        )
    return mode.from_json(data)


def _cwd() -> str:
    try:
        return os.getcwd()
    except FileNotFoundError:  # removed under the caller: any directory does then
        return "/"


def _user_name() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no name for this uid in a bare container
        return str(os.getuid())


# --------------------------------------------------------------------------- the keeper
def start_keeper(root: Path, log: Path) -> UserNamespace:
    """Start the keeper of the rehearsal in ``root`` and wait until its mounts are made.

    Args:
        root: The rehearsal's directory (on the keeper's command line: ``down`` finds it
            by that after a crash).
        log: Where its error output goes.

    Raises:
        RehearseError: If it exited or did not say it was ready in time.
    """
    argv = ["unshare", "--user", "--map-root-user", "--mount", "--net", "--"]
    argv += [sys.executable, "-m", KEEPER_MODULE, "keep", str(root)]
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as err:
        # A session of its own: Ctrl-C in the terminal of `rehearse up` is for `up`.
        keeper = subprocess.Popen(
            argv,
            env={**os.environ, KEEPER_ENV: str(root)},
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=err,
            start_new_session=True,
            cwd="/",
        )
    assert keeper.stdout is not None
    deadline = time.monotonic() + KEEPER_READY_WITHIN
    ready = b""
    while not ready.endswith(b"\n") and time.monotonic() < deadline:
        readable, _, _ = select.select([keeper.stdout], [], [], 0.1)
        if readable:
            chunk = os.read(keeper.stdout.fileno(), 64)
            if not chunk:
                break
            ready += chunk
    keeper.stdout.close()
    if ready.strip() != b"ready":
        if keeper.poll() is None:
            keeper.kill()
        code = keeper.wait(5)
        tail = log.read_text(errors="replace").strip().splitlines()[-1:] if log.exists() else []
        raise RehearseError(
            f"the rehearsal's user namespace could not be made (keeper exit status {code}): "
            f"{tail[0] if tail else 'no output'}",
            hint=f"see {log}",
        )
    userns = os.stat(f"/proc/{keeper.pid}/ns/user").st_ino
    return UserNamespace(keeper=keeper.pid, userns=userns, root=root)


def find_keepers(root: Path) -> list[UserNamespace]:
    """The keepers running for the rehearsal in ``root`` (by their command line: a crash
    may come before the state file kept one)."""
    import psutil

    found = []
    for process in psutil.process_iter(["pid", "cmdline"]):
        argv = process.info.get("cmdline") or []
        if KEEPER_MODULE in argv and "keep" in argv and str(root) in argv:
            try:
                userns = os.stat(f"/proc/{process.info['pid']}/ns/user").st_ino
            except OSError:
                continue
            found.append(UserNamespace(process.info["pid"], userns, root))
    return found


def processes_in(userns: int) -> list[int]:
    """Every process this user may see in user namespace ``userns`` (by its inode)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            if os.stat(f"/proc/{entry}/ns/user").st_ino == userns:
                found.append(int(entry))
        except OSError:  # gone, or another user's
            continue
    return found


def _of_rehearsal(pid: int, root: Path) -> bool:
    """Whether process ``pid`` is one of the rehearsal in ``root``'s: run as one of its
    computers (``MSCTL_HOME`` under it) or naming it on its command line."""
    import psutil

    try:
        process = psutil.Process(pid)
        if str(root) in " ".join(process.cmdline()):
            return True
        return Path(process.environ().get("MSCTL_HOME", "/")).is_relative_to(root)
    except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
        return False


def _end(pids: Sequence[int], grace: float) -> None:
    """SIGTERM, then SIGKILL after ``grace`` seconds, every one of ``pids``."""
    import psutil

    def running(process: psutil.Process) -> bool:
        # Not this process's children: one that exited stays a zombie until init reaps it.
        try:
            return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
        except psutil.Error:
            return False

    processes = []
    for pid in pids:
        try:
            processes.append(psutil.Process(pid))
        except psutil.Error:
            continue
    for signum, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 5.0)):
        left = [p for p in processes if running(p)]
        for process in left:
            try:
                process.send_signal(signum)
            except psutil.Error:
                pass
        deadline = time.monotonic() + wait
        while any(running(p) for p in left) and time.monotonic() < deadline:
            time.sleep(0.05)


def keep(root: Path) -> int:
    """The keeper's life, inside its new namespaces: a private ``/run/netns``, ``ready`` on
    its output, then nothing until SIGTERM. ``root`` is only for its command line."""
    if os.environ.get(KEEPER_ENV) != str(root) or own_user_namespace() is not True:
        # Run by hand as root, its tmpfs would hide the system's namespaces from everyone.
        print(
            f"keeper of {root}: not in a user namespace of its own: it is started by "
            "`msctl rehearse up` (through unshare), never by hand",
            file=sys.stderr,
        )
        return 2
    os.chdir("/")
    # A mountpoint must exist, and only root may make /run/netns: over /run when it is not there.
    run = Path("/run/netns") if Path("/run/netns").is_dir() else Path("/run")
    options = "mode=0755,size=8m"
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "msctl-rehearse", str(run)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        why = done.stderr.strip() or f"exit status {done.returncode}"
        print(f"keeper of {root}: cannot mount a tmpfs on {run}: {why}", file=sys.stderr)
        return 3
    for signum in (signal.SIGINT, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    print("ready", flush=True)
    # Nobody reads on after "ready": its output is closed, so no write ever blocks it.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
    while True:
        signal.pause()


def own_user_namespace() -> bool | None:
    """Whether this process is in a user namespace other than the system's (whose uid map
    is the identity over every id); ``None`` when it cannot tell (no /proc)."""
    try:
        mapping = Path("/proc/self/uid_map").read_text().split()
    except OSError:
        return None
    return mapping != ["0", "0", "4294967295"]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m msctl.rehearse.privileges keep ROOT`` (the keeper; see :func:`keep`)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2 or args[0] != "keep":
        print(f"usage: python -m {KEEPER_MODULE} keep ROOT", file=sys.stderr)
        return 2
    return keep(Path(args[1]))


if __name__ == "__main__":
    sys.exit(main())
