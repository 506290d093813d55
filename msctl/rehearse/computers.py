"""The computers of a rehearsal: one network namespace each, and the processes inside it.

A rehearsed computer is what a real one is to msctl: its own network stack (a namespace with
loopback and one radio link), its own host name (each process it runs enters a fresh UTS
namespace and takes the computer's name), its own ``MSCTL_HOME``, and the other computers'
names in its ``/etc/hosts`` (``ip netns exec`` binds ``/etc/netns/<namespace>/hosts`` over
it), so a config that says ``tls/ground1:7448`` means what it means in the field.

It also has its own Python environment (:func:`make_python_environment`), where what its
``msctl build`` installs goes: a virtual environment under its home that sees every package
of the one msctl runs from, as a computer with msctl installed does. Without it, the five
computers' builds would pip-install into one environment at once, and into the operator's.

Every process of a computer lives in its namespace, so "every process of that computer" is
``ip netns pids``: a reboot kills them all at once, and ``down`` finds them even after the
rehearsal itself crashed.

Where the namespaces live, and how a command gets into them, is the rehearsal's privilege
mode (:mod:`msctl.rehearse.privileges`): the system's as root, or a keeper process's own user
namespace for any user. Each :class:`Computer` carries its rehearsal's, so :func:`exec_argv`
and the functions here need nothing else.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, Any

from msctl.rehearse.privilege_choice import choose, probe
from msctl.rehearse.privileges import ROOT, Privileges, RehearseError

#: The radio interface inside each computer (the emulator's TUN device).
RADIO_DEVICE = "rh0"
#: A computer's Python environment, under its home (see :func:`make_python_environment`).
PYTHON_ENV = "python"
#: The file in it that adds the packages of the environment msctl runs from.
LAYER_PTH = "_msctl_rehearse_layer.pth"


@dataclass(frozen=True)
class Computer:
    """One computer of the rehearsed deployment.

    Attributes:
        name: Its host name (``MSCTL_HOST``), as the assembly's plan names it.
        role: ``robot`` (runs modules) or ``station`` (a ground-control station).
        netns: Its network namespace.
        address: Its address on the radio link.
        home: Its ``MSCTL_HOME``.
        profile: The link profile its radio link starts with.
        privileges: Where its namespace lives and how commands enter it (its rehearsal's
            mode; the state file keeps it once, for the whole rehearsal).
    """

    name: str
    role: str
    netns: str
    address: str
    home: Path
    profile: str
    privileges: Privileges = ROOT

    @property
    def python_env(self) -> Path:
        """Its own Python environment (``VIRTUAL_ENV`` of every process run as it)."""
        return self.home / PYTHON_ENV

    def to_json(self) -> dict[str, Any]:
        """The computer as the state file keeps it (its rehearsal keeps the privileges)."""
        kept = {k: v for k, v in asdict(self).items() if k != "privileges"}
        return {**kept, "home": str(self.home)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any], privileges: Privileges = ROOT) -> Computer:
        """The computer the state file kept, in its rehearsal's ``privileges``."""
        return cls(**{**data, "home": Path(data["home"]), "privileges": privileges})


# --------------------------------------------------------------------------- privileges
def privileges_problem() -> str | None:
    """Why namespaces cannot be made here (``None``: they can, as root or in a user
    namespace of this user's; :func:`msctl.rehearse.privileges.choose` says which)."""
    return choose(probe()).problem


def need_privileges() -> type[Privileges]:
    """The privilege mode a rehearsal made now takes (root's as root, else a user
    namespace's).

    Raises:
        RehearseError: Saying what to do, when neither works here.
    """
    choice = choose(probe())
    if choice.mode is None:
        raise RehearseError(str(choice.problem))
    return choice.mode


# --------------------------------------------------------------------------- namespaces
def _ip(
    *args: str, check: bool = True, privileges: Privileges = ROOT
) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        privileges.command(["ip", *args]), capture_output=True, text=True, check=False
    )
    if check and done.returncode != 0:
        raise RehearseError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")
    return done


def namespaces(privileges: Privileges = ROOT) -> list[str]:
    """Every network namespace there is where ``privileges`` makes them (the system's, or a
    keeper's)."""
    listed = _ip("netns", "list", privileges=privileges).stdout
    return [line.split()[0] for line in listed.splitlines() if line.strip()]


def hosts_text(computers: Sequence[Computer]) -> str:
    """The ``/etc/hosts`` every computer of the rehearsal reads."""
    lines = ["127.0.0.1\tlocalhost", "::1\tlocalhost ip6-localhost ip6-loopback"]
    lines += [f"{c.address}\t{c.name}" for c in computers]
    return "\n".join(lines) + "\n"


def make_namespace(computer: Computer, computers: Sequence[Computer]) -> None:
    """The computer's namespace, with loopback up and the fleet's names in its hosts file."""
    privileges = computer.privileges
    if computer.netns in namespaces(privileges):
        raise RehearseError(
            f"network namespace {computer.netns} already exists (a rehearsal left behind?)",
            hint="remove it with `msctl rehearse down`",
        )
    _ip("netns", "add", computer.netns, privileges=privileges)
    _ip("-n", computer.netns, "link", "set", "lo", "up", privileges=privileges)
    etc = privileges.etc / computer.netns
    etc.mkdir(parents=True, exist_ok=True)
    (etc / "hosts").write_text(hosts_text(computers))
    (etc / "hostname").write_text(computer.name + "\n")


def remove_namespace(netns: str, privileges: Privileges = ROOT) -> None:
    """Delete the namespace and its files (nothing if it is gone already)."""
    if netns in namespaces(privileges):
        _ip("netns", "delete", netns, check=False, privileges=privileges)
    shutil.rmtree(privileges.etc / netns, ignore_errors=True)


# --------------------------------------------------------------------------- Python
def make_python_environment(computer: Computer) -> Path:
    """The computer's own Python environment, layered over the one msctl runs from.

    A virtual environment (no pip of its own: ``venv``'s bundled pip takes tens of seconds
    to install) whose site-packages holds a ``.pth`` file adding every site directory of
    this interpreter with :func:`site.addsitedir` (so their own ``.pth`` files, an editable
    msctl's among them, work there too). Its own site-packages come first: what the
    computer's builds install there is what its processes import, and is gone with its
    home. ``python -m pip`` there is msctl's environment's pip, installing there.

    Returns:
        Its directory (:attr:`Computer.python_env`).
    """
    import site
    import venv

    where = computer.python_env
    venv.EnvBuilder(symlinks=True, with_pip=False).create(where)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    own = where / "lib" / version / "site-packages"
    layers = [d for d in site.getsitepackages() if Path(d).is_dir()]
    user = site.getusersitepackages() if site.ENABLE_USER_SITE else None
    if user and Path(user).is_dir():
        layers.append(user)
    lines = [f"site.addsitedir({d!r})" for d in layers if Path(d).resolve() != own.resolve()]
    # One line: a .pth file runs lines that start with `import`, one statement list each.
    (own / LAYER_PTH).write_text("import site; " + "; ".join(lines or ["pass"]) + "\n")
    return where


# --------------------------------------------------------------------------- processes
def environment(
    computer: Computer,
    extra: Mapping[str, str] | None = None,
    base: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """The environment of a process run as ``computer``.

    It keeps the caller's (PATH, the terminal), takes the computer's identity, home and
    Python environment (``VIRTUAL_ENV``, its ``bin`` first on PATH: ``python`` is the
    computer's, and builds install there), and drops what would point it at another
    computer's settings.
    """
    env = {
        k: v
        for k, v in (os.environ if base is None else base).items()
        if not k.startswith(("MSCTL_ZENOH_", "MSCTL_ROUTER_", "MSCTL_IDENTITY", "MSCTL_SECURE"))
    }
    bin_dir = str(Path(sys.executable).parent)
    path = env.get("PATH", "")
    if bin_dir not in path.split(os.pathsep):
        # `msctl` (this one) first on PATH, so `rehearse exec HOST -- msctl ...` runs it.
        path = bin_dir + (os.pathsep + path if path else "")
    own_bin = str(computer.python_env / "bin")
    env["PATH"] = own_bin + os.pathsep + path if path else own_bin
    env["VIRTUAL_ENV"] = str(computer.python_env)
    env.update({"MSCTL_HOST": computer.name, "MSCTL_HOME": str(computer.home)})
    env.update(computer.privileges.environment(env))
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


def exec_argv(computer: Computer, argv: Sequence[str]) -> list[str]:
    """``argv`` run inside ``computer``: its namespace, its ``/etc/hosts``, and a UTS
    namespace of its name; exec all the way down, so the pid is the command's.

    Raises:
        RehearseError: If the rehearsal's user namespace is gone (its keeper died).
    """
    return computer.privileges.enter(computer.netns, computer.name, argv)


def spawn(
    computer: Computer,
    argv: Sequence[str],
    env: Mapping[str, str],
    log: Path,
) -> subprocess.Popen[bytes]:
    """Start ``argv`` as ``computer`` in a session of its own, output appended to ``log``."""
    log.parent.mkdir(parents=True, exist_ok=True)
    out: IO[bytes]
    with open(log, "ab") as out:
        out.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} {' '.join(argv)}\n".encode())
        out.flush()
        return subprocess.Popen(
            exec_argv(computer, argv),
            env=dict(env),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def pids(netns: str, privileges: Privileges = ROOT) -> list[int]:
    """Every process inside the namespace."""
    done = _ip("netns", "pids", netns, check=False, privileges=privileges)
    return [int(p) for p in done.stdout.split() if p.isdigit()]


def describe_processes(netns: str, privileges: Privileges = ROOT) -> list[dict[str, Any]]:
    """The namespace's processes: pid and command line (for ``status``)."""
    import psutil

    found = []
    for pid in pids(netns, privileges):
        try:
            argv = psutil.Process(pid).cmdline()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        found.append({"pid": pid, "command": " ".join(argv)})
    return found


def kill_all(netns: str, grace: float = 5.0, privileges: Privileges = ROOT) -> int:
    """End every process of the namespace: SIGTERM, then SIGKILL after ``grace`` seconds
    (``grace`` 0: SIGKILL at once, as a power cut). Returns how many there were."""
    first = pids(netns, privileges)
    if not first:
        return 0
    signals = [signal.SIGKILL] if grace <= 0 else [signal.SIGTERM, signal.SIGKILL]
    for sig in signals:
        for pid in pids(netns, privileges):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + (grace if sig == signal.SIGTERM else 5.0)
        while pids(netns, privileges) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not pids(netns, privileges):
            break
    return len(first)
