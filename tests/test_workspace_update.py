"""``msctl update`` against real git: local bare remotes served by file:// URLs.

Every case that would lose work (dirty, diverged, unpushed, detached with commits, another
remote) is refused for that repository alone, which is left exactly as it was, while the
others update.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from workspace_rigs import TERMINAL, Remote, branch, git, head, progress_rows, repos_text

from msctl.errors import MsctlError
from msctl.workspace import workspace_lock
from msctl.workspace.git import Clone, _state_from_files
from msctl.workspace.repos import load, merge, parse_repos
from msctl.workspace.status import status, unlisted_clones
from msctl.workspace.update import UpdateOptions, lock_text, update_workspace

pytestmark = pytest.mark.e2e  # every test runs git


def _update(tmp_path: Path, entries: dict[str, tuple[str, str | None]], **options: object):
    repos = merge(parse_repos(repos_text(entries), "ws.repos"))
    outcomes = update_workspace(repos, tmp_path / "ws", UpdateOptions(**options))  # type: ignore[arg-type]
    return {o.path: o for o in outcomes}


def _state(clone: Path) -> tuple[str, str, str]:
    """Branch, commit and status of a clone: what 'left as it was' compares."""
    return branch(clone), head(clone), git("status", "--porcelain", cwd=clone)


def test_ten_repositories_clone_in_parallel_on_branches_tags_and_commits(tmp_path: Path) -> None:
    remotes = [Remote(tmp_path, f"repo{i}") for i in range(10)]
    wanted: dict[str, tuple[str, str | None]] = {}
    expected: dict[str, tuple[str, str]] = {}
    for i, remote in enumerate(remotes):
        first = head(remote.scratch)
        remote.push({"dev.txt": "dev"}, "on dev", branch="dev")
        kind = i % 4
        if kind == 0:
            wanted[f"src/r{i}"] = (remote.url, "dev")
            expected[f"src/r{i}"] = ("dev", head(remote.scratch))
        elif kind == 1:
            remote.tag("v1", first)
            wanted[f"src/r{i}"] = (remote.url, "v1")
            expected[f"src/r{i}"] = ("", first)
        elif kind == 2:
            wanted[f"src/r{i}"] = (remote.url, first[:10])
            expected[f"src/r{i}"] = ("", first)
        else:
            wanted[f"src/r{i}"] = (remote.url, None)
            expected[f"src/r{i}"] = ("main", first)
    jobs = 4
    meeting = threading.Barrier(jobs, timeout=120)
    arrivals = itertools.count()

    def report(path: str, stage: str) -> None:
        # The first `jobs` repositories to reach the network meet here, and go on only
        # once all of them are fetching at once: an update one at a time breaks the
        # barrier (BrokenBarrierError ends the update).
        if stage == "fetching" and next(arrivals) < jobs:
            meeting.wait()

    repos = merge(parse_repos(repos_text(wanted), "ws.repos"))
    done = update_workspace(repos, tmp_path / "ws", UpdateOptions(jobs=jobs), report)
    outcomes = {o.path: o for o in done}
    assert {p: o.result for p, o in outcomes.items()} == {p: "cloned" for p in wanted}
    assert not meeting.broken
    for path, (on_branch, commit) in expected.items():
        clone = tmp_path / "ws" / path
        assert (branch(clone), head(clone)) == (on_branch, commit), path
        assert outcomes[path].commit == commit
    # Nothing half-made is left beside the clones.
    assert not list((tmp_path / "ws" / "src").glob(".*msctl-partial*"))
    again = _update(tmp_path, wanted, jobs=4)
    assert {o.result for o in again.values()} == {"unchanged"}


def test_a_branch_fast_forwards(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    _update(tmp_path, {"limb": (remote.url, "main")})
    new = remote.push({"a.txt": "new"}, "upstream work")
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "updated"
    assert head(tmp_path / "ws" / "limb") == new
    assert outcome.after == f"main@{new[:7]}"


def test_a_diverged_branch_is_refused_never_reset_and_the_others_update(tmp_path: Path) -> None:
    limb, wheel = Remote(tmp_path, "limb"), Remote(tmp_path, "wheel")
    entries = {"limb": (limb.url, "main"), "wheel": (wheel.url, "main")}
    _update(tmp_path, entries)
    clone = tmp_path / "ws" / "limb"
    (clone / "local.txt").write_text("mine")
    git("add", "local.txt", cwd=clone)
    git("-c", "user.name=a", "-c", "user.email=a@b", "commit", "-q", "-m", "local", cwd=clone)
    before = _state(clone)
    limb.push({"remote.txt": "theirs"}, "remote work")
    new_wheel = wheel.push({"b.txt": "b"}, "wheel work")
    outcomes = _update(tmp_path, entries)
    assert outcomes["limb"].result == "refused"
    assert "diverged" in outcomes["limb"].reason and "1 local, 1 remote" in outcomes["limb"].reason
    assert "rebase origin/main" in outcomes["limb"].fix
    assert _state(clone) == before
    assert outcomes["wheel"].result == "updated" and head(tmp_path / "ws" / "wheel") == new_wheel


def test_uncommitted_changes_refuse_a_move_and_are_kept(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    _update(tmp_path, {"limb": (remote.url, "main")})
    clone = tmp_path / "ws" / "limb"
    (clone / "README.md").write_text("edited on the robot\n")
    remote.push({"README.md": "upstream\n"}, "upstream edit")
    before = _state(clone)
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "refused"
    assert "uncommitted changes in 1 file(s): README.md" in outcome.reason
    assert f"git -C {clone} stash" in outcome.fix
    assert _state(clone) == before
    assert (clone / "README.md").read_text() == "edited on the robot\n"


def test_a_dirty_clone_already_on_its_version_is_left_alone(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    _update(tmp_path, {"limb": (remote.url, "main")})
    (tmp_path / "ws" / "limb" / "README.md").write_text("work in progress\n")
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "unchanged"


def test_unpushed_commits_on_the_branch_being_left_refuse_it(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    remote.push({"d": "d"}, "dev", branch="dev")
    _update(tmp_path, {"limb": (remote.url, "dev")})
    clone = tmp_path / "ws" / "limb"
    (clone / "mine.txt").write_text("x")
    git("add", "mine.txt", cwd=clone)
    git("commit", "-q", "-m", "not pushed", cwd=clone)
    before = _state(clone)
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "refused"
    assert "branch dev has 1 commit(s) no remote holds" in outcome.reason
    assert "push origin dev" in outcome.fix
    assert _state(clone) == before
    # Staying on dev keeps them, and says they are not pushed.
    stay = _update(tmp_path, {"limb": (remote.url, "dev")})["limb"]
    assert stay.result == "unchanged" and "ahead" in stay.notes[0]


def test_a_detached_head_with_local_commits_is_refused(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    tag = remote.tag("v1")
    remote.push({"n": "n"}, "after v1")
    _update(tmp_path, {"limb": (remote.url, "v1")})
    clone = tmp_path / "ws" / "limb"
    assert head(clone) == tag and branch(clone) == ""
    (clone / "hotfix.txt").write_text("x")
    git("add", "hotfix.txt", cwd=clone)
    git("commit", "-q", "-m", "hotfix on the robot", cwd=clone)
    before = _state(clone)
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "refused"
    assert "detached HEAD has 1 commit(s) on no branch" in outcome.reason
    assert "switch -c" in outcome.fix
    assert _state(clone) == before


def test_a_detached_head_without_local_commits_moves_onto_a_branch(tmp_path: Path) -> None:
    # vcstool #165: `vcs pull` fails on a detached HEAD; an update puts it on its branch.
    remote = Remote(tmp_path, "limb")
    tagged = remote.tag("v1")
    newer = remote.push({"n": "n"}, "after v1")
    _update(tmp_path, {"limb": (remote.url, "v1")})
    clone = tmp_path / "ws" / "limb"
    assert (branch(clone), head(clone)) == ("", tagged)
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "updated"
    assert (outcome.before, outcome.after) == (f"(detached)@{tagged[:7]}", f"main@{newer[:7]}")
    assert (branch(clone), head(clone)) == ("main", newer)


def test_head_read_from_the_clones_files_agrees_with_git(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    remote.push({"x": "x"}, "on a branch with a slash", branch="feature/x")
    clone = tmp_path / "clone"
    git("clone", "-q", remote.url, str(clone))

    def agrees() -> bool:
        ours = Clone(clone)
        return (ours.branch() or "", ours.head(), ours.is_clone()) == (
            branch(clone),
            head(clone),
            True,
        )

    assert _state_from_files(clone) is not None and agrees()  # main, its ref packed by clone
    git("checkout", "-q", "feature/x", cwd=clone)  # a loose ref in a subdirectory
    assert _state_from_files(clone) is not None and agrees()
    git("pack-refs", "--all", cwd=clone)
    assert agrees()
    git("checkout", "-q", "--detach", "HEAD", cwd=clone)
    assert _state_from_files(clone) is not None and agrees()
    # Layouts it does not read are asked of git: a worktree's .git file, a branch with no
    # commit yet, a config moving the working tree.
    git("worktree", "add", "-q", str(tmp_path / "other"), "main", cwd=clone)
    assert _state_from_files(tmp_path / "other") is None
    assert Clone(tmp_path / "other").branch() == "main" and Clone(tmp_path / "other").is_clone()
    git("init", "-q", str(tmp_path / "empty"))
    empty = Clone(tmp_path / "empty")
    assert _state_from_files(empty.path) is None
    assert (empty.is_clone(), empty.head(), empty.describe()) == (True, None, "(no commit)")
    git("config", "core.worktree", str(tmp_path), cwd=clone)
    assert _state_from_files(clone) is None and not Clone(clone).is_clone()


def test_a_clone_of_another_remote_is_refused(tmp_path: Path) -> None:
    limb, other = Remote(tmp_path, "limb"), Remote(tmp_path, "other")
    _update(tmp_path, {"limb": (other.url, "main")})
    outcome = _update(tmp_path, {"limb": (limb.url, "main")})["limb"]
    assert outcome.result == "refused"
    assert f"its origin is {other.url}" in outcome.reason
    assert f"remote set-url origin {limb.url}" in outcome.fix


def test_a_directory_that_is_not_a_clone_is_refused(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    (tmp_path / "ws" / "limb").mkdir(parents=True)
    (tmp_path / "ws" / "limb" / "notes.txt").write_text("mine")
    outcome = _update(tmp_path, {"limb": (remote.url, "main")})["limb"]
    assert outcome.result == "refused" and "is not a git clone" in outcome.reason
    assert (tmp_path / "ws" / "limb" / "notes.txt").read_text() == "mine"


def test_a_missing_version_names_the_versions_there_nearest_first(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    remote.push({"f": "f"}, "f", branch="feature-light")
    remote.push({"g": "g"}, "g", branch="zeta")
    remote.tag("v1.0")
    outcome = _update(tmp_path, {"limb": (remote.url, "feature-ligth")})["limb"]
    assert outcome.result == "failed"
    assert "version 'feature-ligth' (set at ws.repos:5) does not exist" in outcome.reason
    assert "it has: feature-light, main" in outcome.reason
    assert "zeta" in outcome.reason and "v1.0" in outcome.reason
    assert not (tmp_path / "ws" / "limb").exists()  # no half clone
    assert not list((tmp_path / "ws").glob(".*msctl-partial*"))
    # An existing clone, too.
    _update(tmp_path, {"limb": (remote.url, "main")})
    again = _update(tmp_path, {"limb": (remote.url, "feature-ligth")})["limb"]
    assert again.result == "failed" and "feature-light" in again.reason


def test_offline_uses_only_what_the_clones_hold(tmp_path: Path) -> None:
    limb, wheel = Remote(tmp_path, "limb"), Remote(tmp_path, "wheel")
    limb.push({"d": "d"}, "dev", branch="dev")
    entries = {"limb": (limb.url, "main"), "wheel": (wheel.url, "main")}
    _update(tmp_path, entries)
    wheel.push({"x": "x"}, "only on the server", branch="experiment")
    # The servers go away: an offline update must not need them.
    shutil.move(tmp_path / "remotes", tmp_path / "gone")
    outcomes = _update(
        tmp_path,
        {
            "limb": (limb.url, "dev"),
            "wheel": (wheel.url, "experiment"),
            "gripper": ("file:///nowhere/gripper.git", "main"),
        },
        offline=True,
    )
    assert outcomes["limb"].result == "updated" and branch(tmp_path / "ws" / "limb") == "dev"
    assert outcomes["wheel"].result == "failed"
    assert "'experiment'" in outcomes["wheel"].reason
    assert "not in the local clone (--offline)" in outcomes["wheel"].reason
    assert outcomes["gripper"].result == "failed"
    assert "not cloned yet" in outcomes["gripper"].reason


def test_a_lock_file_reproduces_the_exact_commits(tmp_path: Path) -> None:
    limb, wheel = Remote(tmp_path, "limb"), Remote(tmp_path, "wheel")
    entries = {"src/limb": (limb.url, "main"), "src/wheel": (wheel.url, "main")}
    repos = merge(parse_repos(repos_text(entries), "ws.repos"))
    update_workspace(repos, tmp_path / "ws", UpdateOptions())
    locked = {r: head(tmp_path / "ws" / r) for r in entries}
    lock = tmp_path / "exp.lock.repos"
    lock.write_text(lock_text(tmp_path / "ws", repos))
    limb.push({"later": "x"}, "later work")
    update_workspace(repos, tmp_path / "ws", UpdateOptions())
    assert head(tmp_path / "ws" / "src/limb") != locked["src/limb"]
    outcomes = update_workspace(load(lock), tmp_path / "ws", UpdateOptions())
    assert all(o.ok for o in outcomes)
    assert {r: head(tmp_path / "ws" / r) for r in entries} == locked
    # And into a fresh workspace.
    update_workspace(load(lock), tmp_path / "fresh", UpdateOptions())
    assert {r: head(tmp_path / "fresh" / r) for r in entries} == locked


def test_one_failure_among_ten_leaves_the_other_nine_updated(tmp_path: Path) -> None:
    remotes = [Remote(tmp_path, f"repo{i}") for i in range(10)]
    entries: dict[str, tuple[str, str | None]] = {
        f"r{i}": (r.url, "main") for i, r in enumerate(remotes)
    }
    entries["r7"] = (remotes[7].url, "no-such-branch")
    outcomes = _update(tmp_path, entries, jobs=5)
    assert [p for p, o in outcomes.items() if not o.ok] == ["r7"]
    assert sum(o.result == "cloned" for o in outcomes.values()) == 9
    assert sorted(p.name for p in (tmp_path / "ws").iterdir()) == sorted(
        p for p in entries if p != "r7"
    )


def test_shallow_clones_and_switches_branch(tmp_path: Path) -> None:
    remote = Remote(tmp_path, "limb")
    remote.push({"a": "1"}, "two")
    remote.push({"a": "2"}, "three")
    remote.push({"b": "1"}, "dev", branch="dev")
    outcome = _update(tmp_path, {"limb": (remote.url, "main")}, shallow=True)["limb"]
    clone = tmp_path / "ws" / "limb"
    assert outcome.result == "cloned"
    assert git("rev-parse", "--is-shallow-repository", cwd=clone) == "true"
    assert git("rev-list", "--count", "HEAD", cwd=clone) == "1"
    switched = _update(tmp_path, {"limb": (remote.url, "dev")}, shallow=True)["limb"]
    assert switched.result == "updated" and branch(clone) == "dev"
    assert head(clone) == head(remote.scratch)


def test_status_shows_branch_commit_dirty_ahead_behind_and_unlisted_clones(
    tmp_path: Path,
) -> None:
    limb, wheel = Remote(tmp_path, "limb"), Remote(tmp_path, "wheel")
    entries = {"limb": (limb.url, "main"), "wheel": (wheel.url, "main")}
    repos = merge(parse_repos(repos_text(entries), "ws.repos"))
    ws = tmp_path / "ws"
    update_workspace(repos, ws, UpdateOptions())
    clone = ws / "limb"
    (clone / "README.md").write_text("dirty\n")
    (clone / "new.txt").write_text("n")
    git("add", "new.txt", cwd=clone)
    git("commit", "-q", "-m", "ahead", cwd=clone)
    wheel.push({"w": "w"}, "upstream")
    git("fetch", "-q", "origin", cwd=ws / "wheel")
    git("clone", "-q", limb.url, str(ws / "stray"))
    rows = {r.path: r for r in status(repos, ws)}
    assert (rows["limb"].dirty, rows["limb"].ahead, rows["limb"].behind) == (1, 1, 0)
    assert rows["limb"].on_version is True
    assert (rows["wheel"].behind, rows["wheel"].on_version) == (1, False)
    assert unlisted_clones(ws, repos) == ["stray"]


def test_a_second_update_of_one_workspace_is_refused_while_one_runs(tmp_path: Path) -> None:
    with (
        workspace_lock(tmp_path, "update"),
        pytest.raises(MsctlError) as caught,
        workspace_lock(tmp_path, "update"),
    ):
        pass
    assert f"pid {os.getpid()}" in str(caught.value)


def _msctl(tmp_path: Path, *args: str, **extra: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "MSCTL_HOME": str(tmp_path / "home"), "COLUMNS": "200", **extra}
    env.pop("MSCTL_WORKSPACE", None)
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_msctl_update_end_to_end(tmp_path: Path) -> None:
    limb, wheel = Remote(tmp_path, "limb"), Remote(tmp_path, "wheel")
    wheel.push({"s": "s"}, "sand", branch="sand-field")
    (tmp_path / "ws").mkdir()
    (tmp_path / "ws" / "workspace.repos").write_text(
        repos_text({"src/limb": (limb.url, "main"), "src/wheel": (wheel.url, "main")})
    )
    overlay = tmp_path / "sand.repos"
    overlay.write_text("repositories:\n  src/wheel:\n    version: sand-field\n")
    first = _msctl(tmp_path, "update", "-w", "ws", "--overlay", str(overlay), "--json", **TERMINAL)
    assert first.returncode == 0, first.stderr
    document = json.loads(first.stdout)
    assert document["ok"] is True
    assert [r["result"] for r in document["repositories"]] == ["cloned", "cloned"]
    assert branch(tmp_path / "ws" / "src/wheel") == "sand-field"
    # A progress bar per repository on stderr, each ending in its result.
    assert progress_rows(first.stderr) == {"src/limb": "cloned", "src/wheel": "cloned"}
    # The next bare update reads the same files; the table goes to stdout.
    old_limb = head(tmp_path / "ws" / "src/limb")
    new_limb = limb.push({"n": "n"}, "upstream work")
    second = _msctl(tmp_path, "update", "-w", "ws", "--lock", "exact.repos")
    assert second.returncode == 0, second.stderr
    table = {line.split("│")[1].strip(): line for line in second.stdout.splitlines()[3:-1]}
    # repository, from -> to, result
    assert [c.strip() for c in table["src/limb"].split("│")[1:5]] == [
        "src/limb",
        f"main@{old_limb[:7]}",
        f"main@{new_limb[:7]}",
        "updated",
    ]
    assert [c.strip() for c in table["src/wheel"].split("│")[3:5]] == ["=", "unchanged"]
    assert "wrote exact.repos" in second.stderr
    exact = load(tmp_path / "exact.repos")
    assert exact[1].version == head(tmp_path / "ws" / "src/wheel")
    state = _msctl(tmp_path, "update", "-w", "ws", "--status", "--json")
    rows = json.loads(state.stdout)["repositories"]
    assert [(r["path"], r["version"], r["on_version"]) for r in rows] == [
        ("src/limb", "main", True),
        ("src/wheel", "sand-field", True),
    ]
    # A failure: exit status 1, the repository named with its reason and fix.
    (tmp_path / "ws" / "src/limb" / "README.md").write_text("dirty\n")
    limb.push({"README.md": "up\n"}, "upstream")
    third = _msctl(tmp_path, "update", "-w", "ws")
    assert third.returncode == 1
    assert "src/limb: uncommitted changes" in third.stderr
    assert "fix: git -C" in third.stderr
    assert "1 of 2 repositories not updated: src/limb" in third.stderr


def test_msctl_update_names_a_malformed_file(tmp_path: Path) -> None:
    (tmp_path / "bad.repos").write_text("repositories:\n  a:\n    type: git\n    url: x;y\n")
    result = _msctl(tmp_path, "update", "bad.repos", "-w", "ws")
    assert result.returncode == 2
    assert "bad.repos:2: repository 'a' (line 4): url 'x;y' is refused" in result.stderr
    assert not (tmp_path / "ws").exists()
