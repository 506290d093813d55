"""How ``msctl rehearse`` gets its namespaces, with plain calls (nothing is made).

Which privilege mode a machine allows, from probes given as data: root's as root, a user
namespace's for anyone where the kernel allows one; else exactly why not and what to do.
Then what each mode runs: the same ``ip netns exec`` command, entered into the keeper's
namespaces without root, and the state file keeping the mode for ``down`` and ``exec``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from components.assembly import from_document
from msctl.assembler import resolve
from msctl.rehearse import computers as rc
from msctl.rehearse import privileges as pv
from msctl.rehearse import rehearsal as rh

#: A Linux machine with every command a rehearsal runs, and /dev/net/tun open to all.
LINUX = pv.Probes(
    platform="linux",
    euid=1000,
    commands=frozenset({"ip", "unshare", "nsenter", "mount"}),
    tun="ok",
    tun_mode=0o666,
    userns=None,
    sysctls={"user.max_user_namespaces": "63000"},
)


def _probes(**changes: object) -> pv.Probes:
    return pv.Probes(**{**LINUX.__dict__, **changes})


def test_root_makes_the_systems_namespaces() -> None:
    assert pv.choose(_probes(euid=0, userns="not tried")) == pv.Choice(pv.Root)


def test_anyone_else_gets_a_user_namespace_where_the_kernel_allows_it() -> None:
    assert pv.choose(LINUX) == pv.Choice(pv.UserNamespace)


@pytest.mark.parametrize(
    ("sysctl", "value", "fix"),
    [
        (
            "kernel.unprivileged_userns_clone",
            "0",
            "sudo sysctl -w kernel.unprivileged_userns_clone=1",
        ),
        ("user.max_user_namespaces", "0", "sudo sysctl -w user.max_user_namespaces=15000"),
        (
            "kernel.apparmor_restrict_unprivileged_userns",
            "1",
            "sudo sysctl -w kernel.apparmor_restrict_unprivileged_userns=0",
        ),
    ],
)
def test_user_namespaces_turned_off_name_the_setting_and_both_ways_out(
    sysctl: str, value: str, fix: str
) -> None:
    probes = _probes(userns="RTNETLINK answers: Operation not permitted", sysctls={sysctl: value})
    choice = pv.choose(probes)
    assert choice.mode is None and choice.problem is not None
    assert "needs root or unprivileged user namespaces" in choice.problem
    assert f"{sysctl} = {value}" in choice.problem
    assert f"`{fix}`" in choice.problem
    assert "sudo -E env PATH=$PATH msctl rehearse" in choice.problem  # or as root
    assert "/etc/sysctl.d/" in choice.problem  # how to keep it across boots


def test_a_user_namespace_failing_for_another_reason_says_what_failed() -> None:
    choice = pv.choose(_probes(userns="unshare failed: Operation not permitted"))
    assert choice.mode is None
    assert "cannot be made here (unshare failed: Operation not permitted)" in str(choice.problem)
    assert "sudo" in str(choice.problem)


def test_a_tun_device_closed_to_the_user_says_how_to_open_it() -> None:
    choice = pv.choose(_probes(tun="denied", tun_mode=0o600))
    assert choice.mode is None
    assert "/dev/net/tun is not open to you (mode 0600)" in str(choice.problem)
    assert "`sudo chmod 0666 /dev/net/tun`" in str(choice.problem)
    # Root opens it whatever its mode.
    assert pv.choose(_probes(euid=0, tun="ok", tun_mode=0o600)).mode is pv.Root


def test_util_linux_missing_says_what_to_install() -> None:
    choice = pv.choose(_probes(commands=frozenset({"ip", "mount"}), userns="not tried"))
    assert "`unshare`, `nsenter` (util-linux) not installed" in str(choice.problem)
    assert "sudo apt-get install util-linux" in str(choice.problem)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"platform": "darwin"}, "needs Linux"),
        ({"commands": frozenset({"unshare", "nsenter", "mount"})}, "sudo apt-get install iproute2"),
        ({"tun": "missing", "tun_mode": None}, "sudo modprobe tun"),
        ({"euid": 0, "tun": "missing", "tun_mode": None}, "sudo modprobe tun"),
    ],
)
def test_what_no_mode_can_do_without(changes: dict, message: str) -> None:
    choice = pv.choose(_probes(**changes))
    assert choice.mode is None and message in str(choice.problem)


def test_the_checks_the_cli_and_tests_use_read_the_probes(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(
        rc, "probe", lambda: _probes(userns="x", sysctls={"user.max_user_namespaces": "0"})
    )
    problem = rc.privileges_problem()
    assert problem is not None and "user.max_user_namespaces = 0" in problem
    with pytest.raises(rc.RehearseError, match="needs root or unprivileged user namespaces"):
        rc.need_privileges()
    monkeypatch.setattr(rc, "probe", lambda: LINUX)
    assert rc.privileges_problem() is None
    assert rc.need_privileges() is pv.UserNamespace


def test_this_machine_is_read_without_changing_it() -> None:
    probes = pv.probe()
    assert probes.euid == os.geteuid()
    assert "ip" in probes.commands
    assert probes.tun in ("ok", "missing", "denied")


# --------------------------------------------------------------------------- what each runs
@pytest.fixture
def keeper(tmp_path: Path) -> pv.UserNamespace:
    """This test's own process stands for a keeper (alive, its user namespace the same)."""
    userns = os.stat(f"/proc/{os.getpid()}/ns/user").st_ino
    return pv.UserNamespace(keeper=os.getpid(), userns=userns, root=tmp_path)


@pytest.fixture
def computer(tmp_path: Path) -> rc.Computer:
    minimal = from_document(resolve("minimal", {}).document)
    return rh.plan_computers(minimal, tmp_path, "lan", {})[0]


def test_as_root_a_command_enters_the_systems_namespace(computer: rc.Computer) -> None:
    assert pv.ROOT.command(["ip", "netns", "list"]) == ["ip", "netns", "list"]
    argv = rc.exec_argv(computer, ["msctl", "ps"])
    assert argv[:6] == ["ip", "netns", "exec", computer.netns, "unshare", "--uts"]
    assert argv[-3:] == [computer.name, "msctl", "ps"]
    assert pv.ROOT.etc == Path("/etc/netns")


def test_without_root_a_command_enters_the_keepers_namespaces_first(
    computer: rc.Computer, keeper: pv.UserNamespace, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    inside = rc.Computer(**{**computer.__dict__, "privileges": keeper})
    argv = rc.exec_argv(inside, ["msctl", "ps"])
    assert argv[:7] == [
        "nsenter",
        f"--target={os.getpid()}",
        "--user",
        "--mount",
        "--net",
        "--preserve-credentials",
        f"--wd={tmp_path}",  # the caller's directory, as `ip netns exec` keeps it
    ]
    assert argv[8:14] == ["ip", "netns", "exec", computer.netns, "unshare", "--uts"]
    # Its /etc files are the rehearsal's own, bound by the shell (no /etc/netns needed).
    assert argv[-4:] == [computer.name, str(tmp_path / "etc" / computer.netns), "msctl", "ps"]
    assert 'mount --bind "$f" "$t"' in argv[-5]
    # `ip` itself, for the namespaces: no working directory of the caller's to keep.
    assert keeper.command(["ip", "netns", "list"])[-4:] == ["--", "ip", "netns", "list"]


def test_a_keeper_gone_or_replaced_is_never_entered(keeper: pv.UserNamespace) -> None:
    other = pv.UserNamespace(keeper=keeper.keeper, userns=keeper.userns + 1, root=keeper.root)
    assert keeper.alive() and not other.alive()  # a pid reused by another process
    with pytest.raises(rc.RehearseError, match=r"keeper \(pid \d+\) is gone") as gone:
        other.command(["ip", "netns", "list"])
    assert "msctl rehearse down" in str(gone.value.hint)


def test_inside_the_user_is_named_as_outside(keeper: pv.UserNamespace) -> None:
    # Root in there: `msctl net init` would name the operator root@HOST, not as this process.
    named = keeper.environment({"PATH": "/usr/bin"})
    assert named["LOGNAME"] == named["USER"] != ""
    assert keeper.environment({"USER": "alice"}) == {}
    assert pv.ROOT.environment({}) == {}


def test_the_mode_is_kept_in_the_state_file_and_given_to_every_computer(
    keeper: pv.UserNamespace, tmp_path: Path
) -> None:
    dragon = from_document(resolve("dragon", {}).document)
    rehearsal = rh.Rehearsal(
        root=tmp_path,
        template="dragon",
        uses={},
        secure=True,
        computers=rh.plan_computers(dragon, tmp_path, "lan", {}),
    )
    rehearsal.use(keeper)
    rehearsal.save()
    again = rh.Rehearsal.load(tmp_path)
    assert again.privileges == keeper
    assert all(c.privileges == keeper for c in again.computers)
    assert again.computers == rehearsal.computers
    assert rc.exec_argv(again.ground, ["true"])[0] == "nsenter"


def test_a_state_file_without_a_mode_is_roots_and_an_unknown_one_is_named() -> None:
    assert pv.from_json(None) is pv.ROOT
    assert pv.from_json({"mode": "root"}) is pv.ROOT
    kept = pv.UserNamespace(keeper=12, userns=4026531837, root=Path("/tmp/r"))
    assert pv.from_json(kept.to_json()) == kept
    with pytest.raises(rc.RehearseError, match="unknown privilege mode 'setuid'"):
        pv.from_json({"mode": "setuid"})


def test_root_alone_changes_what_root_made(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pv.os, "geteuid", lambda: 1000)
    with pytest.raises(rc.RehearseError, match="made by root") as refused:
        pv.ROOT.need()
    assert "sudo" in str(refused.value.hint)


def test_the_keeper_runs_only_as_rehearse_up_starts_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Run by hand, its tmpfs would hide everyone's /run/netns: it refuses, mounting nothing.
    monkeypatch.delenv(pv.KEEPER_ENV, raising=False)
    assert pv.keep(tmp_path) == 2
    if pv.own_user_namespace() is not False:
        pytest.skip("this test runs in a user namespace: the second check would pass")
    monkeypatch.setenv(pv.KEEPER_ENV, str(tmp_path))  # as start_keeper sets it
    assert pv.keep(tmp_path) == 2  # but in the system's user namespace
