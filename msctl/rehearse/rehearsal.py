"""One rehearsal: a template's deployment stood up on this machine, and taken down again.

``up`` does what a field team does on real computers, in the same order and with the same
commands, each computer in its own namespace:

1. resolve the template here to learn its computers (robot computers and ground stations);
2. one namespace per computer, linked to the simulated access point by the link emulator,
   and its own home and Python environment (what its builds install goes there);
3. on every computer, ``msctl assemble TEMPLATE`` from its own data (as each real computer
   resolves for itself);
4. secure (the default): ``msctl net init`` on the first ground station, and its
   ``MSCTL_HOME/net`` copied to every computer but for the CA's key, as the README tells a user;
5. ``msctl agent`` on every computer (robot computers with their real motor backends against
   emulated hardware: ``MSCTL_EMULATE_HARDWARE=1``), each starting its computer's router
   linked as the generated configs say (plain TCP links only with ``--insecure``);
6. from the ground station, ``msctl up --all``.

Everything it makes is written down in ``$MSCTL_HOME/rehearse/rehearsal.json`` before it is
made, and every namespace is named after that directory, so ``down`` removes all of it even
after the rehearsal itself crashed midway.

As root, the namespaces are the system's; as any other user, where the kernel allows
unprivileged user namespaces, they live in a keeper process's own user namespace
(:mod:`msctl.rehearse.privileges`), with no sudo: every step above is the same.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from components.paths import state_dir
from msctl.rehearse.computers import (
    Computer,
    RehearseError,
    environment,
    kill_all,
    namespaces,
    need_privileges,
    remove_namespace,
    spawn,
)
from msctl.rehearse.privileges import ROOT, Privileges, find_keepers
from msctl.rehearse.privileges import from_json as privileges_from_json

# The CLI and the tests reach these as `rehearsal.reboot` and `rehearsal.status`.
from msctl.rehearse.running import reboot as reboot
from msctl.rehearse.running import status as status
from msctl.rehearse.start import make_computers, up_all

#: Robot computers from .11 up, ground stations from .201 up.
FIRST_ROBOT, FIRST_STATION = 11, 201
#: The state file's name under ``$MSCTL_HOME/rehearse``.
STATE_FILE = "rehearsal.json"
#: The ports the field uses: each computer has its own network stack, as a real one does.
LOCAL_PORT, TLS_PORT = 7447, 7448


def rehearsal_dir() -> Path:
    """``$MSCTL_HOME/rehearse``: the rehearsal's state, logs and its computers' homes."""
    # Absolute: the state names files the computers' processes read from other directories.
    return (state_dir() / "rehearse").absolute()


def namespace_prefix(root: Path | None = None) -> str:
    """``msr-<6 hex>-``: the namespaces of the rehearsal kept in ``root`` (named after its
    path, so rehearsals of two MSCTL_HOMEs never share one, and a crash leaves them findable)."""
    root = (root or rehearsal_dir()).resolve()
    return "msr-" + hashlib.sha1(str(root).encode()).hexdigest()[:6] + "-"


@dataclass
class Rehearsal:
    """What a rehearsal made, as its state file keeps it.

    Attributes:
        root: Its directory (``$MSCTL_HOME/rehearse``).
        template: The template rehearsed.
        uses: The slot=unit choices it was resolved with.
        secure: Mutual TLS and access control (the field default), else plain TCP links.
        computers: Its computers, robots first.
        operator: The operator identity the stations' commands use (``user@station``).
        emulator_pid: The link emulator's process.
        seed: The link emulator's seed (the same seed replays the same losses).
        created: When it was made (epoch seconds).
        privileges: Where its namespaces live (the system's as root, else a keeper's user
            namespace); its computers carry the same.
    """

    root: Path
    template: str
    uses: dict[str, str]
    secure: bool
    computers: list[Computer] = field(default_factory=list)
    operator: str = ""
    emulator_pid: int | None = None
    seed: int = 1
    created: float = field(default_factory=time.time)
    privileges: Privileges = ROOT

    # ------------------------------------------------------------------ state
    @property
    def state_file(self) -> Path:
        """Where this rehearsal is written down."""
        return self.root / STATE_FILE

    @property
    def control_socket(self) -> Path:
        """The link emulator's control socket."""
        return self.root / "links.sock"

    @property
    def logs(self) -> Path:
        """Where the agents' and the emulator's output goes."""
        return self.root / "logs"

    def save(self) -> None:
        """Write the state file atomically."""
        from msctl.assembler.store import write_file

        document = {
            "template": self.template,
            "uses": self.uses,
            "secure": self.secure,
            "operator": self.operator,
            "emulator_pid": self.emulator_pid,
            "seed": self.seed,
            "created": self.created,
            "privileges": self.privileges.to_json(),
            "computers": [c.to_json() for c in self.computers],
        }
        write_file(self.state_file, json.dumps(document, indent=2) + "\n")

    @classmethod
    def load(cls, root: Path | None = None) -> Rehearsal:
        """The rehearsal kept in ``root``.

        Raises:
            RehearseError: If none is there.
        """
        root = root or rehearsal_dir()
        path = root / STATE_FILE
        try:
            data = json.loads(path.read_text())
            privileges = privileges_from_json(data.get("privileges"))
            return cls(
                root=root,
                template=data["template"],
                uses=dict(data.get("uses", {})),
                secure=bool(data["secure"]),
                computers=[Computer.from_json(c, privileges) for c in data["computers"]],
                operator=data.get("operator", ""),
                emulator_pid=data.get("emulator_pid"),
                seed=int(data.get("seed", 1)),
                created=float(data.get("created", 0.0)),
                privileges=privileges,
            )
        except FileNotFoundError:
            raise RehearseError(
                f"no rehearsal in {root}", hint="start one with `msctl rehearse up TEMPLATE`"
            ) from None
        except (ValueError, KeyError, TypeError) as exc:
            raise RehearseError(
                f"{path} is not a rehearsal's state ({exc})",
                hint="`msctl rehearse down` removes whatever it can find of it",
            ) from exc

    def use(self, privileges: Privileges) -> None:
        """Make its namespaces with ``privileges`` (every computer's with them)."""
        self.privileges = privileges
        self.computers = [replace(c, privileges=privileges) for c in self.computers]

    def computer(self, name: str) -> Computer:
        """The computer called ``name``.

        Raises:
            RehearseError: Naming the computers there are.
        """
        for computer in self.computers:
            if computer.name == name:
                return computer
        from msctl.errors import did_you_mean

        near = did_you_mean(name, [c.name for c in self.computers])
        raise RehearseError(
            f"the {self.template} rehearsal has no computer {name!r} "
            f"(its computers: {', '.join(c.name for c in self.computers)})",
            hint=near or None,
        )

    @property
    def stations(self) -> list[Computer]:
        """The ground stations."""
        return [c for c in self.computers if c.role == "station"]

    @property
    def ground(self) -> Computer:
        """The computer operators work from: the first ground station (else the first robot)."""
        return (self.stations or self.computers)[0]

    # ------------------------------------------------------------------ running as a computer
    def env(self, computer: Computer, base: Mapping[str, str] | None = None) -> dict[str, str]:
        """The environment of a command run as ``computer``: its host name and home, and on a
        secure ground station the operator's identity, so `msctl` commands reach the fleet
        (on the first robot computer of an assembly without one: operators work there)."""
        extra: dict[str, str] = {}
        operated = computer.role == "station" or computer.name == self.ground.name
        if self.secure and operated and self.operator:
            extra["MSCTL_IDENTITY"] = self.operator
        return environment(computer, extra, base)

    def agent_env(self, computer: Computer) -> dict[str, str]:
        """The environment ``msctl agent`` runs with on ``computer`` (a systemd unit's)."""
        extra = {"MSCTL_ZENOH_CONNECT": f"tcp/localhost:{LOCAL_PORT}"}
        if self.secure:
            extra["MSCTL_SECURE"] = "1"
        else:
            extra.update(plain_links(self, computer))
        if computer.role == "robot":
            from components.motors.emulation import EMULATE_ENV

            extra[EMULATE_ENV] = "1"
        return environment(computer, extra)

    def run(
        self, computer: Computer, argv: Sequence[str], timeout: float = 120.0
    ) -> subprocess.CompletedProcess[str]:
        """Run ``argv`` as ``computer`` to its end; its output captured.

        Raises:
            OperationTimeout: If it ran longer than ``timeout`` seconds (it is killed; the
                message names the computer, the command and the last line it wrote).
        """
        from msctl.errors import OperationTimeout
        from msctl.rehearse.computers import exec_argv

        try:
            return subprocess.run(
                exec_argv(computer, argv),
                env=self.env(computer),
                capture_output=True,
                text=True,
                timeout=timeout,
                stdin=subprocess.DEVNULL,
                check=False,
            )
        except subprocess.TimeoutExpired as exc:
            said = exc.stderr or exc.output or ""
            said = said.decode(errors="replace") if isinstance(said, bytes) else said
            last = next((line for line in reversed(said.splitlines()) if line.strip()), "")
            raise OperationTimeout(
                f"{computer.name}: `{' '.join(argv)}` did not finish within {timeout:g} s"
                + (f"; its last line: {last.strip()}" if last else ""),
                hint="its links may be too slow for the bound (`msctl rehearse status`); "
                "give `msctl rehearse up` a longer --timeout",
            ) from None

    def start_agent(self, computer: Computer) -> int:
        """Start ``msctl agent`` on ``computer``, as systemd does at boot; its pid."""
        argv = [sys.executable, "-m", "msctl", "agent"]
        process = spawn(
            computer, argv, self.agent_env(computer), self.logs / f"{computer.name}.log"
        )
        return process.pid


def plain_links(rehearsal: Rehearsal, computer: Computer) -> dict[str, str]:
    """The router settings of an insecure rehearsal: robots link to every station over plain
    TCP (the README's `--insecure` field setup), stations listen for them."""
    stations = [c.name for c in rehearsal.stations]
    if computer.role == "station" or not stations:
        # A station-less assembly: robots link to the first robot's router.
        first = rehearsal.computers[0].name
        if computer.role == "station" or computer.name == first:
            return {"MSCTL_ROUTER_LISTEN": f"tcp/0.0.0.0:{TLS_PORT}"}
        stations = [first]
    return {"MSCTL_ROUTER_CONNECT": ",".join(f"tcp/{s}:{TLS_PORT}" for s in stations)}


# --------------------------------------------------------------------------- planning
def plan_computers(
    assembly: Any, root: Path, profile: str, per_host: Mapping[str, str]
) -> list[Computer]:
    """One :class:`Computer` per host of the resolved assembly: robots, then stations."""
    robots = list(dict.fromkeys(m.host for m in assembly.modules))
    stations = [h for h in assembly.hosts if h not in robots]
    unknown = sorted(set(per_host) - set(robots) - set(stations))
    if unknown:
        raise RehearseError(
            f"--link names {', '.join(unknown)}, not a computer of {assembly.template} "
            f"(its computers: {', '.join([*robots, *stations])})"
        )
    prefix = namespace_prefix(root)
    computers = []
    for role, names, first in (
        ("robot", robots, FIRST_ROBOT),
        ("station", stations, FIRST_STATION),
    ):
        for index, name in enumerate(names):
            computers.append(
                Computer(
                    name=name,
                    role=role,
                    netns=(prefix + name)[:48],
                    address=f"10.77.0.{first + index}",
                    home=root / "computers" / name,
                    profile=per_host.get(name, profile),
                )
            )
    return computers


def parse_links(links: Sequence[str]) -> tuple[str | None, dict[str, str]]:
    """``--link`` values: ``PROFILE`` for every link, ``HOST=PROFILE`` for one.

    Raises:
        RehearseError: If two values give every link a profile.
    """
    every: str | None = None
    per_host: dict[str, str] = {}
    for value in links:
        host, sep, profile = value.partition("=")
        if not sep:
            if every is not None and every != value:
                raise RehearseError(
                    f"--link {every} and --link {value} both set every link",
                    hint="give one PROFILE, and HOST=PROFILE for the links that differ",
                )
            every = value
        elif not host or not profile:
            raise RehearseError(f"--link {value!r}: write PROFILE or HOST=PROFILE")
        else:
            per_host[host] = profile
    return every, per_host


# --------------------------------------------------------------------------- up
@dataclass
class Progress:
    """Where ``up`` says what it does (a rich status line in the CLI, a list in tests)."""

    say: Callable[[str], None] = lambda _line: None
    step: Callable[[str], None] = lambda _line: None


def up(
    template: str,
    uses: Mapping[str, str],
    links: Sequence[str],
    secure: bool,
    seed: int = 1,
    bring_up: bool = True,
    progress: Progress | None = None,
    timeout: float = 180.0,
) -> Rehearsal:
    """Stand the template's deployment up on this machine (see the module's docstring).

    Raises:
        RehearseError: If it cannot be made (privileges, a rehearsal already there, a
            profile unknown); whatever was made is taken down again first.
    """
    from components.assembly import from_document
    from msctl.assembler import resolve
    from msctl.rehearse import profiles as link_profiles

    progress = progress or Progress()
    mode = need_privileges()
    root = rehearsal_dir()
    if (root / STATE_FILE).exists() or _leftovers(root):
        raise RehearseError(
            f"a rehearsal is already in {root}",
            hint="see it with `msctl rehearse status`; `msctl rehearse down` removes it",
        )
    every, per_host = parse_links(links)
    known = link_profiles.load_profiles()
    for name in {every or "lan", *per_host.values()}:
        if name not in known:
            from msctl.errors import did_you_mean

            raise RehearseError(
                f"unknown link profile {name!r} (known: {', '.join(sorted(known))})",
                hint=did_you_mean(name, known) or "add it to a profiles file (MSCTL_LINK_PROFILES)",
            )
    resolution = resolve(template, dict(uses))
    assembly = from_document(resolution.document)
    rehearsal = Rehearsal(
        root=root,
        template=assembly.template,
        uses=dict(assembly.units),
        secure=secure,
        seed=seed,
        computers=plan_computers(assembly, root, every or "lan", per_host),
    )
    root.mkdir(parents=True, exist_ok=True)
    try:
        # Its keeper, without root, is found by its command line if a crash comes first.
        rehearsal.use(mode.start(root))
        rehearsal.save()  # before anything is made: `down` finds it all after a crash
        # One budget for every step, as --timeout says.
        deadline = time.monotonic() + timeout
        make_computers(rehearsal, progress, deadline, timeout)
        if bring_up:
            progress.step(f"{rehearsal.ground.name}: msctl up --all")
            up_all(rehearsal, deadline, timeout)
    except BaseException:
        progress.say("[red]rehearsal failed; taking down what was made[/]")
        down(root)
        raise
    return rehearsal


# --------------------------------------------------------------------------- down
def _leftover_namespaces(root: Path, privileges: Privileges = ROOT) -> list[str]:
    prefix = namespace_prefix(root)
    return [n for n in namespaces(privileges) if n.startswith(prefix)]


def _leftovers(root: Path) -> list[str]:
    """What a rehearsal in ``root`` left running without its state file: the system's
    namespaces named after it, and keepers of its user namespace."""
    keepers = [f"keeper {k.keeper}" for k in find_keepers(root)]
    return _leftover_namespaces(root) + keepers


def _places(root: Path, rehearsal: Rehearsal | None) -> list[Privileges]:
    """Where the rehearsal in ``root`` has namespaces: the mode its state kept, the
    system's when namespaces named after it are there, every keeper found running for it
    (a crash may come before the state kept one)."""
    places: list[Privileges] = [rehearsal.privileges] if rehearsal else []
    if _leftover_namespaces(root):
        places.append(ROOT)
    places += find_keepers(root)
    return list(dict.fromkeys(places))


def down(root: Path | None = None) -> list[str]:
    """Remove everything the rehearsal in ``root`` made: every process of its computers,
    the link emulator, the namespaces and their files, its keeper (without root), its
    directory. Works from what is left after a crash (the namespaces are named after
    ``root``, a keeper has it on its command line). Returns what it removed.

    Raises:
        RehearseError: If root made it and this is not root.
    """
    root = root or rehearsal_dir()
    removed: list[str] = []
    try:
        rehearsal: Rehearsal | None = Rehearsal.load(root)
    except RehearseError:
        rehearsal = None
    places = _places(root, rehearsal)
    for privileges in places:
        privileges.need()
    from msctl.launcher.fanout import at_once

    kept = {c.netns for c in rehearsal.computers} if rehearsal else set()
    # A keeper that died took its namespaces with it: nothing of them to reach.
    reachable = [p for p in places if p.alive()]
    found = {p: sorted(kept | set(_leftover_namespaces(root, p))) for p in reachable}
    for privileges, names in found.items():
        # Every computer's processes at once: each gets its SIGTERM grace in parallel.
        counts = at_once(lambda n, p=privileges: kill_all(n, privileges=p), names)
        for netns, count in zip(names, counts, strict=True):
            removed.append(f"{netns} ({count} processes)")
    # By its spec file, not only the pid kept: a crash may come before the pid was written.
    for pid in _emulators(root):
        _stop_pid(pid, "msctl.rehearse.emulator")
    for privileges, names in found.items():
        for netns in names:
            remove_namespace(netns, privileges)
    for privileges in places:
        removed += privileges.close()
    if root.exists():
        shutil.rmtree(root, ignore_errors=True)
    return removed


def _emulators(root: Path) -> list[int]:
    """The link emulators running for the rehearsal in ``root``."""
    import psutil

    spec = str(root / "links.json")
    found = []
    for process in psutil.process_iter(["pid", "cmdline"]):
        argv = process.info.get("cmdline") or []
        if "msctl.rehearse.emulator" in argv and spec in argv:
            found.append(process.info["pid"])
    return found


def _stop_pid(pid: int, marker: str) -> None:
    """SIGTERM, then SIGKILL, ``pid`` if it still runs ``marker`` (never a reused pid)."""
    import psutil

    try:
        process = psutil.Process(pid)
        if marker not in " ".join(process.cmdline()):
            return
        process.terminate()
        process.wait(5.0)
    except psutil.TimeoutExpired:
        process.kill()
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        pass
