"""Git, run as a program: one clone's state, and the few operations ``msctl update`` needs.

Every call is ``git`` with an argument list (never a shell), with no terminal prompt (a
credential question on a robot would hang forever), git's ``transport::`` helpers off, and
``LC_ALL=C`` so the messages parsed here read the same everywhere.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from msctl.errors import MsctlError

#: Options given to every git call: ``ext::``/``fd::`` transports stay off whatever the
#: user's configuration says.
_SAFE_CONFIG = ("-c", "protocol.ext.allow=never", "-c", "protocol.fd.allow=never")


class GitError(MsctlError):
    """A git command failed; ``stderr`` holds what git said.

    Attributes:
        args: The git arguments (after ``git``).
        stderr: git's error output, stripped.
        returncode: git's exit status.
    """

    exit_code = 3

    def __init__(self, args: Sequence[str], returncode: int, stderr: str):
        self.args_run = list(args)
        self.stderr = stderr.strip()
        self.returncode = returncode
        last = self.stderr.splitlines()[-1] if self.stderr else f"exit status {returncode}"
        super().__init__(f"`git {' '.join(args)}` failed: {last}")


def git_env() -> dict[str, str]:
    """The environment of every git call (no prompts, C locale, no pager)."""
    env = dict(os.environ)
    env.update(
        GIT_TERMINAL_PROMPT="0",
        GIT_ASKPASS="true",
        SSH_ASKPASS="true",
        LC_ALL="C",
        LANGUAGE="C",
        GIT_PAGER="cat",
    )
    # ssh must not ask whether to trust a host either: it fails instead.
    env.setdefault("GIT_SSH_COMMAND", "ssh -o BatchMode=yes")
    return env


def run_git(
    args: Sequence[str],
    cwd: Path | None = None,
    *,
    check: bool = True,
    timeout: float | None = None,
) -> subprocess.CompletedProcess[str]:
    """Run ``git <args>`` and return it (stdout and stderr as text).

    Raises:
        GitError: If ``check`` and git fails.
        MsctlError: If git is not installed.
    """
    try:
        result = subprocess.run(
            ["git", *_SAFE_CONFIG, *args],
            cwd=cwd,
            env=git_env(),
            capture_output=True,
            text=True,
            check=False,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
    except FileNotFoundError:
        raise MsctlError(
            "git is not installed on this computer", hint="install it (e.g. apt install git)"
        ) from None
    if check and result.returncode != 0:
        raise GitError(args, result.returncode, result.stderr)
    return result


@dataclass(frozen=True)
class Target:
    """What a version resolved to in one clone.

    Attributes:
        ref_type: ``branch``, ``tag`` or ``commit``.
        name: The branch or tag name (the full commit id for a commit).
        commit: The commit to end on.
    """

    ref_type: str
    name: str
    commit: str


class Clone:
    """One local clone, asked about its state (no network).

    What it reads most is kept until the next :meth:`git` or :meth:`ok` call, which may
    change it: its HEAD (read from its files, see :func:`_state_from_files`) and every
    branch and tag with its commit (one git call). A repository with nothing to do costs
    three git calls: its remote's URL, the fetch, and its refs.

    Args:
        path: The clone's working tree.
    """

    def __init__(self, path: Path):
        self.path = path
        self._state: tuple[str | None, str | None, str | None] | None = None
        self._refs: dict[str, tuple[str, str]] | None = None

    def forget(self) -> None:
        """Drop what was read: the clone may have changed."""
        self._state = None
        self._refs = None

    def forget_refs(self) -> None:
        """Drop the branches and tags read (after a fetch: HEAD did not move)."""
        self._refs = None

    def git(self, *args: str, check: bool = True) -> str:
        """``git <args>`` in this clone; its stdout, stripped."""
        self.forget()
        return run_git(args, self.path, check=check).stdout.strip()

    def ok(self, *args: str) -> bool:
        """Whether ``git <args>`` succeeds in this clone."""
        self.forget()
        return run_git(args, self.path, check=False).returncode == 0

    def _read_state(self) -> tuple[str | None, str | None, str | None]:
        """(top of the working tree, HEAD commit, branch): from the clone's own files when
        they have the plain layout, else in one git call."""
        if self._state is None:
            self._state = _state_from_files(self.path)
        if self._state is None:
            result = run_git(
                ["rev-parse", "--show-toplevel", "HEAD", "--symbolic-full-name", "HEAD"],
                self.path,
                check=False,
            )
            lines = result.stdout.splitlines()
            top = lines[0] if lines and lines[0].startswith("/") else None
            if result.returncode != 0 or len(lines) != 3:
                # No commit yet (or not a clone): ask for the top alone.
                again = run_git(["rev-parse", "--show-toplevel"], self.path, check=False)
                top = again.stdout.strip() if again.returncode == 0 else None
                self._state = (top, None, None)
            else:
                symbolic = lines[2]
                branch = (
                    symbolic[len("refs/heads/") :] if symbolic.startswith("refs/heads/") else None
                )
                self._state = (top, lines[1], branch)
        return self._state

    def refs(self) -> dict[str, tuple[str, str]]:
        """Every local branch, ``origin`` branch and tag: ``{refname: (commit, symref)}``
        (annotated tags peeled to their commit), in one call."""
        if self._refs is None:
            text = run_git(
                [
                    "for-each-ref",
                    "--format=%(refname)%09%(objectname)%09%(*objectname)%09%(symref)",
                    "refs/heads",
                    "refs/remotes/origin",
                    "refs/tags",
                ],
                self.path,
            ).stdout
            refs = {}
            for line in text.splitlines():
                name, obj, peeled, symref = [*line.split("\t"), "", "", ""][:4]
                refs[name] = (peeled or obj, symref)
            self._refs = refs
        return self._refs

    # ------------------------------------------------------------------ what it is
    def is_clone(self) -> bool:
        """Whether the path is the top of a git working tree."""
        if not (self.path / ".git").exists():
            return False
        top = self._read_state()[0]
        return top is not None and Path(top).resolve() == self.path.resolve()

    def remote_url(self) -> str | None:
        """``origin``'s URL, or ``None`` without an ``origin``."""
        result = run_git(["remote", "get-url", "origin"], self.path, check=False)
        return result.stdout.strip() if result.returncode == 0 else None

    def head(self) -> str | None:
        """The commit checked out (``None`` in a clone with no commit yet)."""
        return self._read_state()[1]

    def branch(self) -> str | None:
        """The branch checked out, or ``None`` on a detached HEAD."""
        return self._read_state()[2]

    def is_shallow(self) -> bool:
        """Whether the clone is shallow (``--shallow``)."""
        result = run_git(["rev-parse", "--is-shallow-repository"], self.path, check=False)
        return result.stdout.strip() == "true"

    def changes(self) -> list[str]:
        """Tracked files with changes, staged or not (``git status --porcelain``, untracked
        files left out: a checkout never loses them, it refuses to overwrite them)."""
        text = run_git(["status", "--porcelain", "--untracked-files=no"], self.path).stdout.rstrip(
            "\n"
        )
        return [line[3:] for line in text.splitlines() if line.strip()]

    def commit_of(self, ref: str) -> str | None:
        """The commit ``ref`` names, or ``None``."""
        if ref.startswith("refs/"):
            known = self.refs().get(ref)
            return known[0] if known else None
        result = run_git(
            ["rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"], self.path, check=False
        )
        return result.stdout.strip() or None

    def is_ancestor(self, older: str, newer: str) -> bool:
        """Whether ``older`` is an ancestor of (or the same as) ``newer``."""
        result = run_git(["merge-base", "--is-ancestor", older, newer], self.path, check=False)
        return result.returncode == 0

    def count(self, *rev_list: str) -> int:
        """``git rev-list --count <rev_list>``."""
        return int(run_git(["rev-list", "--count", *rev_list], self.path).stdout.strip() or 0)

    def ahead_behind(self, local: str, upstream: str) -> tuple[int, int]:
        """Commits only on ``local`` and only on ``upstream``."""
        text = run_git(
            ["rev-list", "--left-right", "--count", f"{local}...{upstream}"], self.path
        ).stdout
        ahead, behind = text.split()
        return int(ahead), int(behind)

    def unpushed(self, branch: str) -> int:
        """Commits on ``branch`` that no remote-tracking branch holds."""
        return self.count(f"refs/heads/{branch}", "--not", "--remotes")

    def orphaned_by_leaving(self) -> int:
        """On a detached HEAD: its commits that no branch, tag or remote branch holds."""
        return self.count("HEAD", "--not", "--branches", "--tags", "--remotes")

    def default_branch(self) -> str | None:
        """The remote's default branch as this clone last saw it (``origin/HEAD``)."""
        symref = self.refs().get("refs/remotes/origin/HEAD", ("", ""))[1]
        prefix = "refs/remotes/origin/"
        return symref[len(prefix) :] if symref.startswith(prefix) else None

    def versions(self) -> list[str]:
        """The branch and tag names this clone knows of its remote (for "did you mean")."""
        names = []
        for ref in self.refs():
            if ref.startswith("refs/remotes/origin/") and ref != "refs/remotes/origin/HEAD":
                names.append(ref[len("refs/remotes/origin/") :])
            elif ref.startswith("refs/tags/"):
                names.append(ref[len("refs/tags/") :])
        return names

    def resolve(self, version: str | None) -> Target | None:
        """What ``version`` names here: a remote branch, a tag, or a commit (in that order).

        ``None`` is the remote's default branch. Returns ``None`` when the clone does not
        hold it.
        """
        if version is None:
            version = self.default_branch()
            if version is None:
                return None
        remote = self.commit_of(f"refs/remotes/origin/{version}")
        if remote is not None:
            return Target("branch", version, remote)
        tag = self.commit_of(f"refs/tags/{version}")
        if tag is not None:
            return Target("tag", version, tag)
        from msctl.workspace.repos import looks_like_commit

        if looks_like_commit(version):
            commit = self.commit_of(version)
            if commit is not None:
                return Target("commit", commit, commit)
        return None

    def describe(self) -> str:
        """``branch@abc1234`` or ``(detached)@abc1234``, for a summary table."""
        head = self.head()
        if head is None:
            return "(no commit)"
        return f"{self.branch() or '(detached)'}@{head[:7]}"


_COMMIT_ID = re.compile(r"^(?:[0-9a-f]{40}|[0-9a-f]{64})$")


def _state_from_files(path: Path) -> tuple[str, str, str | None] | None:
    """(top, HEAD commit, branch) read from ``path/.git`` without running git, or ``None``
    whenever the layout is not the plain one this reads (then git is asked).

    Every update reads HEAD at least once per repository; on a robot's small CPU with a dozen
    repositories, a process per read is a noticeable part of an update with nothing to do.
    Only the layout ``git clone`` makes is read here: a ``.git`` directory (not a worktree's
    or submodule's ``.git`` file), files refs (not reftable), no ``core.worktree`` or
    ``core.bare`` in its config, and HEAD on a branch whose ref is a commit id, or detached.
    """
    gitdir = path / ".git"
    try:
        if not gitdir.is_dir() or (gitdir / "commondir").exists():
            return None
        if (gitdir / "reftable").exists():
            return None
        config = (gitdir / "config").read_text(encoding="utf-8", errors="replace")
        if re.search(r"^\s*(worktree|bare\s*=\s*true)", config, re.MULTILINE | re.IGNORECASE):
            return None
        head = (gitdir / "HEAD").read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError):
        return None
    if _COMMIT_ID.match(head):
        return str(path), head, None
    if not head.startswith("ref: refs/heads/"):
        return None
    ref = head[len("ref: ") :]
    commit = _ref_from_files(gitdir, ref)
    if commit is None:
        return None  # a branch with no commit yet, or a ref this does not read: ask git
    return str(path), commit, ref[len("refs/heads/") :]


def _ref_from_files(gitdir: Path, ref: str) -> str | None:
    """The commit of ``ref`` from its loose file, else from ``packed-refs``."""
    try:
        loose = (gitdir / ref).read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        loose = None
    except (OSError, UnicodeDecodeError):
        return None
    if loose is not None:
        return loose if _COMMIT_ID.match(loose) else None
    try:
        packed = (gitdir / "packed-refs").read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError):
        return None
    for line in packed.splitlines():
        commit, _, name = line.partition(" ")
        if name == ref and _COMMIT_ID.match(commit):
            return commit
    return None


def remote_versions(url: str) -> list[str]:
    """Branch and tag names on a remote (``git ls-remote``), for naming what it has.

    Returns an empty list when the remote cannot be listed.
    """
    result = run_git(["ls-remote", "--heads", "--tags", "--", url], check=False)
    names = []
    for line in result.stdout.splitlines():
        ref = line.partition("\t")[2]
        if ref.endswith("^{}"):
            continue
        for prefix in ("refs/heads/", "refs/tags/"):
            if ref.startswith(prefix):
                names.append(ref[len(prefix) :])
    return names


def same_remote(a: str, b: str) -> bool:
    """Whether two remote URLs name the same repository (``.git`` and ``/`` aside)."""

    def norm(url: str) -> str:
        url = url.strip().rstrip("/")
        if url.startswith("file://"):
            url = url[len("file://") :]
        if url.endswith(".git"):
            url = url[: -len(".git")]
        return url.rstrip("/")

    return norm(a) == norm(b)
