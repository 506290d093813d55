"""``msctl rehearse`` without root: every verb as user ``nobody``, in a user namespace.

CI runs as root, so each command here runs as ``nobody`` (``setpriv``), with a home of its
own under /tmp. Two things a desktop user has that ``nobody`` on a CI machine may not are
given to it in a private mount namespace of the command (``unshare --mount``), changing
nothing of this machine: a ``/dev/net/tun`` open to everyone (udev's default; a container's
is often 0600) and a path to the interpreter (a directory only root may enter, as
``/root/.pyenv`` under ``/root``, is covered by a tmpfs holding only the way through).
The rehearsal's keeper is made inside that namespace, so its own mount namespace, which
every later command enters, has the same.

Skipped, saying why, when this is not root, a command is missing, the interpreter cannot be
made usable by ``nobody``, or the kernel refuses unprivileged user namespaces.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until

import components
import msctl
from msctl.rehearse.computers import namespaces
from msctl.rehearse.privilege_choice import TUN
from msctl.rehearse.privileges import KEEPER_MODULE
from msctl.rehearse.rehearsal import namespace_prefix

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(600)]

#: The unprivileged user the commands run as.
NOBODY = 65534
#: The one computer of ``minimal`` (its module's host; operators work there too).
HOST = "hl-limb-01"


def _not_usable_by_others(path: Path) -> bool:
    return not os.stat(path).st_mode & stat.S_IXOTH


def _ways_through(paths: list[Path]) -> dict[Path, set[str]] | str:
    """Per directory ``nobody`` may not enter, the children on the way to ``paths``; or why
    that is not enough (two such directories on one way)."""
    blocked: dict[Path, set[str]] = {}
    for path in paths:
        closed = [p for p in reversed(path.parents) if _not_usable_by_others(p)]
        if len(closed) > 1:
            return f"{closed[0]} and {closed[1]}, on the way to {path}, are closed to others"
        if closed:
            blocked.setdefault(closed[0], set()).add(path.relative_to(closed[0]).parts[0])
    return blocked


class Nobody:
    """Commands run as user ``nobody`` with its own ``HOME`` and ``MSCTL_HOME``.

    Args:
        base: Its home (owned by it); ``MSCTL_HOME`` is ``base/home``.
        stage: A directory of root's for the private mounts' tmpfs.
        ways: What :func:`_ways_through` found.
    """

    def __init__(self, base: Path, stage: Path, ways: dict[Path, set[str]]) -> None:
        self.base = base
        self.home = base / "home"
        self.stage = stage
        self.ways = ways
        keep = ("PATH", "LANG", "LC_ALL", "TERM", "TZ")
        self.env = {k: os.environ[k] for k in keep if k in os.environ}
        # No USER or LOGNAME: msctl names the operator from the account, as nobody's shell would.
        self.env.update(
            {
                "HOME": str(base),
                "MSCTL_HOME": str(self.home),
                "COLUMNS": "200",
                "PYTHONPYCACHEPREFIX": str(base / "pyc"),
                "CYDR_CACHE_DIR": str(base / "cydr"),
            }
        )

    def argv(self, *command: str, empty_run: bool = False) -> list[str]:
        """``command`` as ``nobody``, in a private mount namespace with what it lacks (and
        with an empty ``/run``, as on a machine where no ``/run/netns`` was ever made)."""
        lines = ["set -e", "t=$1; shift", 'mount -t tmpfs -o mode=0755 msctl-test "$t"']
        if empty_run:
            lines.append("mount -t tmpfs -o mode=0755 msctl-test /run")
        if os.stat(TUN).st_mode & 0o006 != 0o006:
            device = os.stat(TUN).st_rdev
            lines += [
                f'mknod -m 0666 "$t/tun" c {os.major(device)} {os.minor(device)}',
                f'mount --bind "$t/tun" {TUN}',
            ]
        for index, (closed, children) in enumerate(sorted(self.ways.items())):
            saved = f'"$t/closed{index}"'
            lines += [
                f"mkdir {saved}",
                f"mount --bind {shlex.quote(str(closed))} {saved}",
                f"mount -t tmpfs -o mode=0755 msctl-test {shlex.quote(str(closed))}",
            ]
            for child in sorted(children):
                inside = shlex.quote(str(closed / child))
                lines += [f"mkdir {inside}", f"mount --bind {saved}/{shlex.quote(child)} {inside}"]
        lines.append(f'exec setpriv --reuid {NOBODY} --regid {NOBODY} --clear-groups -- "$@"')
        script = "\n".join(lines)
        return [
            "unshare",
            "--mount",
            "--propagation",
            "private",
            "--",
            "sh",
            "-c",
            script,
            "as-nobody",
            str(self.stage),
            *command,
        ]

    def run(
        self,
        *command: str,
        timeout: float = 120.0,
        stdin: str | None = None,
        empty_run: bool = False,
    ) -> subprocess.CompletedProcess[str]:
        """``command`` as ``nobody``, to its end."""
        return subprocess.run(
            self.argv(*command, empty_run=empty_run),
            env=self.env,
            cwd=self.base,
            input=stdin,
            stdin=None if stdin is not None else subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def msctl(self, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
        """``msctl ARGS`` as ``nobody``."""
        return self.run(sys.executable, "-m", "msctl", *args, timeout=timeout)

    def on(self, *argv: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
        """``ARGV`` as the rehearsal's computer, through ``msctl rehearse exec``."""
        return self.msctl("rehearse", "exec", HOST, "--", *argv, timeout=timeout)

    def status(self) -> dict[str, Any]:
        """``msctl rehearse status --json``."""
        done = self.msctl("rehearse", "status", "--json")
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    def processes(self) -> set[int]:
        """Every process of user ``nobody`` running on this machine (one that has exited is
        init's to reap: a keeper whose ``rehearse up`` exited is init's child)."""
        import psutil

        return {
            p.pid
            for p in psutil.process_iter(["uids", "status"])
            if p.info["uids"].real == NOBODY and p.info["status"] != psutil.STATUS_ZOMBIE
        }


def _nobody_or_why(base: Path, stage: Path) -> Nobody | str:
    if sys.platform != "linux" or os.geteuid() != 0:
        return "runs msctl as user nobody, which takes root (as CI has)"
    missing = [c for c in ("setpriv", "unshare", "nsenter", "mount", "ip") if not shutil.which(c)]
    if missing:
        return f"not installed: {', '.join(missing)}"
    if not TUN.exists():
        return f"{TUN} is missing"
    needed = [
        Path(sys.executable).resolve(),
        Path(sys.base_prefix).resolve(),
        Path(sys.prefix).resolve(),
        Path(msctl.__file__).resolve().parents[1],
        Path(components.__file__).resolve().parents[1],
        base,
    ]
    ways = _ways_through(needed)
    if isinstance(ways, str):
        return f"the interpreter cannot be made usable by nobody: {ways}"
    nobody = Nobody(base, stage, ways)
    done = nobody.run(sys.executable, "-c", "import msctl, components, zenoh, psutil")
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["?"])[-1]
        return f"{sys.executable} is not usable by nobody: {tail}"
    check = "from msctl.rehearse.computers import privileges_problem as p; print(p() or '')"
    done = nobody.run(sys.executable, "-c", check)
    if done.returncode != 0 or done.stdout.strip():
        return f"as nobody: {done.stdout.strip() or done.stderr.strip()}"
    return nobody


@pytest.fixture(scope="module")
def nobody() -> Iterator[Nobody]:
    base = Path(tempfile.mkdtemp(prefix="msctl_userns_"))
    stage = Path(tempfile.mkdtemp(prefix="msctl_userns_mounts_"))
    try:
        os.chown(base, NOBODY, NOBODY)
        found = _nobody_or_why(base, stage)
        if isinstance(found, str):
            pytest.skip(found)
        yield found
    finally:
        if (base / "home" / "rehearse").exists():
            subprocess.run(
                Nobody(base, stage, {}).argv(sys.executable, "-m", "msctl", "rehearse", "down"),
                capture_output=True,
                timeout=120,
                check=False,
            )
        shutil.rmtree(base, ignore_errors=True)
        shutil.rmtree(stage, ignore_errors=True)


@pytest.fixture(scope="module")
def before(nobody: Nobody) -> set[int]:
    """User nobody's processes before the rehearsal (another's are not this test's)."""
    return nobody.processes()


@pytest.fixture(scope="module")
def rehearsal(nobody: Nobody, before: set[int]) -> dict[str, Any]:
    done = nobody.msctl("rehearse", "up", "minimal", "--detach", "--timeout", "360", timeout=420)
    assert done.returncode == 0, done.stderr
    return nobody.status()


def _all_ok(document: dict[str, Any]) -> bool:
    """Every item OK (a rate may WARN on a loaded machine), but the computer's own CPU and
    memory, which are this loaded machine's."""
    return all(
        item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
        for row in document["modules"]
        for item in row["items"]
        if "/host/" not in item["name"]
    )


#: A keeper and one namespace made, entered and removed, with the library's own calls.
ONE_NAMESPACE = """
import subprocess, sys
from pathlib import Path
from msctl.rehearse import computers as rc, privileges as pv
root = Path(sys.argv[1])
print(Path("/run/netns").exists())
keeper = pv.UserNamespace.start(root)
computer = rc.Computer("hl-limb-01", "robot", "msr-t-hl-limb-01", "10.77.0.11", root, "lan", keeper)
rc.make_namespace(computer, [computer])
inside = subprocess.run(rc.exec_argv(computer, ["hostname"]), capture_output=True, text=True)
print(inside.stdout.strip(), rc.namespaces(keeper))
rc.remove_namespace(computer.netns, keeper)
print(keeper.close(), keeper.alive())
"""


def test_without_run_netns_the_keeper_covers_run(nobody: Nobody) -> None:
    # Only root may make /run/netns, and a tmpfs needs a mountpoint: the keeper's is /run.
    root = nobody.base / "one-namespace"
    done = nobody.run(sys.executable, "-c", ONE_NAMESPACE, str(root), empty_run=True)
    assert done.returncode == 0, done.stderr
    had_run_netns, inside, closed = done.stdout.splitlines()
    assert had_run_netns == "False"
    assert inside == f"{HOST} ['msr-t-hl-limb-01']"  # its name, its namespace in the keeper's
    assert closed.startswith("['keeper ") and closed.endswith("'] False")  # ended, and gone


def test_up_without_root_runs_everything_as_the_user(
    nobody: Nobody, rehearsal: dict[str, Any], before: set[int]
) -> None:
    assert rehearsal["privileges"]["mode"] == "userns"
    assert rehearsal["emulator"] == "running"
    (computer,) = rehearsal["computers"]
    assert computer["name"] == HOST and computer["processes"]
    import psutil

    keeper = psutil.Process(rehearsal["privileges"]["keeper"])
    assert KEEPER_MODULE in keeper.cmdline()
    # The keeper, the link emulator and the computer's agent, router and workers: the user's.
    made = nobody.processes() - before
    assert keeper.pid in made and {p["pid"] for p in computer["processes"]} <= made
    # Its namespace is not the system's: nothing in /run/netns or /etc/netns.
    prefix = namespace_prefix(nobody.home / "rehearse")
    assert not [n for n in namespaces() if n.startswith(prefix)]
    assert not list(Path("/etc/netns").glob(prefix + "*"))


def test_a_command_runs_as_the_computer(nobody: Nobody, rehearsal: dict[str, Any]) -> None:
    done = nobody.on("sh", "-c", 'hostname; getent hosts "$(hostname)"; pwd; echo "$MSCTL_HOME"')
    assert done.returncode == 0, done.stderr
    name, hosts, where, home = done.stdout.splitlines()
    assert name == HOST
    assert hosts.split() == ["10.77.0.11", HOST]  # its /etc/hosts is the rehearsal's
    assert where == str(nobody.base)  # in the caller's directory
    assert home == str(nobody.home / "rehearse" / "computers" / HOST)


def test_health_and_ps_from_the_computer(nobody: Nobody, rehearsal: dict[str, Any]) -> None:
    def health() -> dict[str, Any] | None:
        done = nobody.on("msctl", "health", "--once", "--json", "--timeout", "15")
        assert done.returncode in (0, 1), done.stderr
        document = json.loads(done.stdout)
        return document if _all_ok(document) else None

    document = wait_until(health, timeout=120, what="limb1 healthy", interval=1.0)
    assert [row["name"] for row in document["modules"]] == ["limb1"]
    done = nobody.on("msctl", "ps", "--json", "--timeout", "30")
    assert done.returncode == 0, done.stderr
    components = json.loads(done.stdout)["components"]
    assert {c["host"] for c in components} == {HOST}
    assert all(c["state"] == "running" for c in components), components


def test_a_shell_on_the_computer(nobody: Nobody, rehearsal: dict[str, Any]) -> None:
    done = nobody.run(
        sys.executable, "-m", "msctl", "rehearse", "shell", HOST, stdin="hostname\nexit 3\n"
    )
    assert done.returncode == 3, done.stderr
    assert HOST in done.stdout.splitlines()


def test_an_outage_of_its_link(nobody: Nobody, rehearsal: dict[str, Any]) -> None:
    done = nobody.msctl("rehearse", "link", HOST, "--down", "0")
    assert done.returncode == 0, done.stderr
    link = nobody.status()["computers"][0]["link"]
    assert link["up"]["outage"]["cause"] == "scripted"
    done = nobody.msctl("rehearse", "link", HOST, "--up")
    assert done.returncode == 0, done.stderr
    assert nobody.status()["computers"][0]["link"]["up"]["outage"] is None
    done = nobody.msctl("rehearse", "link", HOST, "--down", "1")
    assert done.returncode == 0 and "down for 1 s" in done.stderr, done.stderr


def test_a_reboot_kills_everything_and_starts_the_agent(
    nobody: Nobody, rehearsal: dict[str, Any]
) -> None:
    done = nobody.msctl("rehearse", "reboot", HOST)
    assert done.returncode == 0, done.stderr
    assert "processes killed" in done.stderr

    def agent() -> bool:
        running = nobody.status()["computers"][0]["processes"]
        return any("msctl agent" in p["command"] for p in running)

    wait_until(agent, timeout=60, what="its agent started again", interval=0.5)


def test_down_leaves_no_process_keeper_or_file(
    nobody: Nobody, rehearsal: dict[str, Any], before: set[int]
) -> None:
    keeper = rehearsal["privileges"]["keeper"]
    done = nobody.msctl("rehearse", "down")
    assert done.returncode == 0, done.stderr
    assert f"keeper {keeper}" in done.stderr
    assert not nobody.processes() - before
    assert not (nobody.home / "rehearse").exists()
    # Nothing of root's was needed, nor left: no namespace or file of the system's.
    prefix = namespace_prefix(nobody.home / "rehearse")
    assert not [n for n in namespaces() if n.startswith(prefix)]
    assert not list(Path("/etc/netns").glob(prefix + "*"))


def test_down_after_up_was_killed_midway(nobody: Nobody, before: set[int]) -> None:
    up = subprocess.Popen(
        nobody.argv(sys.executable, "-m", "msctl", "rehearse", "up", "minimal", "--no-up"),
        env=nobody.env,
        cwd=nobody.base,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        # Killed once its keeper, namespace and links are made: the worst moment to crash.
        wait_until(
            lambda: (nobody.home / "rehearse" / "links.ready").exists(),
            timeout=120,
            what="links made",
        )
        # unshare, its shell and setpriv exec each other: the pid is `msctl rehearse up`'s.
        up.send_signal(signal.SIGKILL)
        up.wait(30)
        again = nobody.msctl("rehearse", "up", "minimal", "--detach")
        assert again.returncode != 0 and "a rehearsal is already in" in again.stderr
        done = nobody.msctl("rehearse", "down")
        assert done.returncode == 0, done.stderr
        assert "keeper" in done.stderr
    finally:
        if up.poll() is None:
            up.kill()
    wait_until(lambda: not nobody.processes() - before, timeout=30, what="no process left")
    assert not (nobody.home / "rehearse").exists()
