"""The computers of a rehearsal: one network namespace each, and the processes inside it.

A rehearsed computer is what a real one is to msctl: its own network stack (a namespace with
loopback and one radio link), its own host name (each process it runs enters a fresh UTS
namespace and takes the computer's name), its own ``MSCTL_HOME``, and the other computers'
names in its ``/etc/hosts`` (``ip netns exec`` binds ``/etc/netns/<namespace>/hosts`` over
it), so a config that says ``tls/ground1:7448`` means what it means in the field.

Every process of a computer lives in its namespace, so "every process of that computer" is
``ip netns pids``: a reboot kills them all at once, and ``down`` finds them even after the
rehearsal itself crashed.
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

from msctl.errors import MsctlError

#: Where ``ip netns exec`` finds the files it binds over ``/etc`` inside a namespace.
NETNS_ETC = Path("/etc/netns")
#: The radio interface inside each computer (the emulator's TUN device).
RADIO_DEVICE = "rh0"


class RehearseError(MsctlError):
    """A rehearsal cannot be made, found or changed; the message says what to do."""


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
    """

    name: str
    role: str
    netns: str
    address: str
    home: Path
    profile: str

    def to_json(self) -> dict[str, Any]:
        """The computer as the state file keeps it."""
        return {**asdict(self), "home": str(self.home)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Computer:
        """The computer the state file kept."""
        return cls(**{**data, "home": Path(data["home"])})


# --------------------------------------------------------------------------- privileges
def privileges_problem() -> str | None:
    """Why namespaces cannot be made here (``None``: they can).

    Root is needed: the namespaces, the TUN devices and ``/etc/netns`` are the system's.
    """
    if sys.platform != "linux":
        return "msctl rehearse needs Linux (network namespaces and TUN devices)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed: `sudo apt-get install iproute2`"
    if os.geteuid() != 0:
        return (
            "msctl rehearse makes network namespaces and TUN devices, which needs root: run it "
            "with sudo (`sudo -E env PATH=$PATH msctl rehearse ...` keeps this environment)"
        )
    if not Path("/dev/net/tun").exists():
        return "/dev/net/tun is missing: load the tun module (`sudo modprobe tun`)"
    return None


def need_privileges() -> None:
    """Raise :class:`RehearseError` saying what to do when namespaces cannot be made."""
    problem = privileges_problem()
    if problem is not None:
        raise RehearseError(problem)


# --------------------------------------------------------------------------- namespaces
def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if check and done.returncode != 0:
        raise RehearseError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")
    return done


def namespaces() -> list[str]:
    """Every network namespace of this machine."""
    return [line.split()[0] for line in _ip("netns", "list").stdout.splitlines() if line.strip()]


def hosts_text(computers: Sequence[Computer]) -> str:
    """The ``/etc/hosts`` every computer of the rehearsal reads."""
    lines = ["127.0.0.1\tlocalhost", "::1\tlocalhost ip6-localhost ip6-loopback"]
    lines += [f"{c.address}\t{c.name}" for c in computers]
    return "\n".join(lines) + "\n"


def make_namespace(computer: Computer, computers: Sequence[Computer]) -> None:
    """The computer's namespace, with loopback up and the fleet's names in its hosts file."""
    if computer.netns in namespaces():
        raise RehearseError(
            f"network namespace {computer.netns} already exists (a rehearsal left behind?)",
            hint="remove it with `msctl rehearse down`",
        )
    _ip("netns", "add", computer.netns)
    _ip("-n", computer.netns, "link", "set", "lo", "up")
    etc = NETNS_ETC / computer.netns
    etc.mkdir(parents=True, exist_ok=True)
    (etc / "hosts").write_text(hosts_text(computers))
    (etc / "hostname").write_text(computer.name + "\n")


def remove_namespace(netns: str) -> None:
    """Delete the namespace and its files (nothing if it is gone already)."""
    if netns in namespaces():
        _ip("netns", "delete", netns, check=False)
    shutil.rmtree(NETNS_ETC / netns, ignore_errors=True)


# --------------------------------------------------------------------------- processes
def environment(
    computer: Computer,
    extra: Mapping[str, str] | None = None,
    base: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """The environment of a process run as ``computer``.

    It keeps the caller's (PATH, the terminal), takes the computer's identity and home, and
    drops what would point it at another computer's settings.
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
        env["PATH"] = bin_dir + (os.pathsep + path if path else "")
    env.update({"MSCTL_HOST": computer.name, "MSCTL_HOME": str(computer.home)})
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


def exec_argv(computer: Computer, argv: Sequence[str]) -> list[str]:
    """``argv`` run inside ``computer``: its namespace, and a UTS namespace of its name."""
    # `hostname` inside a fresh UTS namespace changes this process's view only.
    script = 'hostname "$0" && exec "$@"'
    return [
        "ip",
        "netns",
        "exec",
        computer.netns,
        "unshare",
        "--uts",
        "--",
        "sh",
        "-c",
        script,
        computer.name,
        *argv,
    ]


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


def pids(netns: str) -> list[int]:
    """Every process inside the namespace."""
    done = _ip("netns", "pids", netns, check=False)
    return [int(p) for p in done.stdout.split() if p.isdigit()]


def describe_processes(netns: str) -> list[dict[str, Any]]:
    """The namespace's processes: pid and command line (for ``status``)."""
    import psutil

    found = []
    for pid in pids(netns):
        try:
            argv = psutil.Process(pid).cmdline()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        found.append({"pid": pid, "command": " ".join(argv)})
    return found


def kill_all(netns: str, grace: float = 5.0) -> int:
    """End every process of the namespace: SIGTERM, then SIGKILL after ``grace`` seconds
    (``grace`` 0: SIGKILL at once, as a power cut). Returns how many there were."""
    first = pids(netns)
    if not first:
        return 0
    signals = [signal.SIGKILL] if grace <= 0 else [signal.SIGTERM, signal.SIGKILL]
    for sig in signals:
        for pid in pids(netns):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + (grace if sig == signal.SIGTERM else 5.0)
        while pids(netns) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not pids(netns):
            break
    return len(first)
