"""``msctl update``: every repository of the workspace on the version its files ask for.

For each repository, in parallel:

1. a missing clone is cloned into a temporary directory beside its place and renamed into
   place only once it is on its version, so a failed or interrupted clone leaves nothing;
2. an existing clone is checked (a git clone, with the same ``origin``), fetched (unless
   ``offline``), and the version resolved: a remote branch, a tag or a commit;
3. before anything moves, the preflight refuses the repository for: uncommitted changes,
   commits no remote holds on the branch being left, a detached HEAD with commits on no
   branch, or a branch that has diverged from its remote (never reset);
4. one git command then moves it (``checkout``/``merge --ff-only``), which git carries out
   whole or not at all.

A repository refused or failed is left exactly as it was, and says why and which git
command resolves it; the others still update, and the run's outcome is non-zero. Fetching
changes no working tree or branch, so it is done before the preflight.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from msctl.errors import InputError, nearest
from msctl.workspace import state_dir
from msctl.workspace.git import Clone, GitError, Target, remote_versions, run_git, same_remote
from msctl.workspace.repos import Repository, dump_repos, looks_like_commit

#: Results of one repository's update; the first three are successes.
RESULTS = ("cloned", "updated", "unchanged", "refused", "failed")
#: Stages reported while a repository updates (for a progress bar: this many steps).
STAGES = ("checking", "fetching", "checking out")
#: Called with (repository path, stage) as the update of that repository goes on.
Report = Callable[[str, str], None]


@dataclass(frozen=True)
class UpdateOptions:
    """How to update.

    Attributes:
        offline: Use no network: check out what the clones already hold.
        shallow: Clone missing repositories with history depth 1.
        jobs: Repositories updated at once.
        retries: Extra attempts of a clone or fetch that failed (radio links drop).
    """

    offline: bool = False
    shallow: bool = False
    jobs: int = 8
    retries: int = 0


@dataclass
class Outcome:
    """What became of one repository.

    Attributes:
        path: The repository's path in the workspace.
        url: Its remote.
        version: The version asked for.
        result: One of :data:`RESULTS`.
        before: ``branch@commit`` before (``(absent)`` when there was no clone).
        after: ``branch@commit`` after.
        commit: The full commit checked out after, if any.
        reason: Why it was refused or failed.
        fix: The git command (or step) that resolves it.
        notes: Anything else worth saying (e.g. local commits not pushed yet).
    """

    path: str
    url: str
    version: str | None
    result: str
    before: str
    after: str
    commit: str | None = None
    reason: str = ""
    fix: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Whether the repository is on its version."""
        return self.result in RESULTS[:3]

    def to_dict(self) -> dict[str, Any]:
        """The outcome as ``--json`` prints it."""
        return {**asdict(self), "ok": self.ok}


class _Stop(Exception):
    """Ends one repository's update: ``result`` is ``refused`` or ``failed``."""

    def __init__(self, result: str, reason: str, fix: str = ""):
        super().__init__(reason)
        self.result = result
        self.reason = reason
        self.fix = fix


def _q(path: Path | str) -> str:
    return shlex.quote(str(path))


# --------------------------------------------------------------------------- one repository
def update_repository(
    repo: Repository, workspace: Path, options: UpdateOptions, report: Report | None = None
) -> Outcome:
    """Put one repository on its version (see the module's description); never raises for
    what git or the repository's state refuses: that is the outcome's ``result``."""
    tell = report or (lambda _path, _stage: None)
    where = workspace / repo.path
    clone = Clone(where)
    before = "(absent)"
    try:
        tell(repo.path, "checking")
        if not where.exists() or (where.is_dir() and not any(where.iterdir())):
            commit, after = _clone(repo, where, options, tell)
            return Outcome(repo.path, repo.url, repo.version, "cloned", before, after, commit)
        if not clone.is_clone():
            raise _Stop(
                "refused",
                f"{where} exists and is not a git clone",
                f"move it away (mv {_q(where)} {_q(str(where) + '.old')}), then update again",
            )
        before = clone.describe()
        _check_remote(clone, repo)
        if not options.offline:
            tell(repo.path, "fetching")
            _fetch(clone, options)
        target = _resolve(clone, repo, options)
        tell(repo.path, "checking out")
        moved, notes = _move(clone, target)
        return Outcome(
            repo.path,
            repo.url,
            repo.version,
            "updated" if moved else "unchanged",
            before,
            clone.describe(),
            clone.head(),
            notes=notes,
        )
    except _Stop as stop:
        after = clone.describe() if before != "(absent)" else "(absent)"
        return Outcome(
            repo.path,
            repo.url,
            repo.version,
            stop.result,
            before,
            after,
            reason=stop.reason,
            fix=stop.fix,
            commit=clone.head() if after != "(absent)" else None,
        )
    except GitError as exc:
        after = clone.describe() if before != "(absent)" else "(absent)"
        return Outcome(
            repo.path,
            repo.url,
            repo.version,
            "failed",
            before,
            after,
            commit=clone.head() if after != "(absent)" else None,
            reason=_git_reason(exc),
            fix=_git_fix(exc, where),
        )


def _git_reason(exc: GitError) -> str:
    lines = [line for line in exc.stderr.splitlines() if line.strip()]
    tail = " / ".join(lines[-3:]) if lines else f"exit status {exc.returncode}"
    return f"git {exc.args_run[0]} failed: {tail}"


def _git_fix(exc: GitError, where: Path) -> str:
    text = exc.stderr
    if "would clobber existing tag" in text:
        return f"a tag moved on the remote: git -C {_q(where)} fetch --tags --force origin"
    if any(
        s in text
        for s in ("Could not resolve host", "Connection refused", "timed out", "unable to access")
    ):
        return "check the network to the remote (or use --offline to stay on local clones)"
    if "Permission denied" in text or "Authentication failed" in text:
        return "check this computer's credentials for the remote (ssh key or token)"
    return f"see `git -C {_q(where)} status`"


def _network(args: list[str], cwd: Path | None, options: UpdateOptions) -> None:
    """A git command that reaches the remote, tried ``1 + retries`` times."""
    for attempt in range(options.retries + 1):
        try:
            run_git(args, cwd)
            return
        except GitError as exc:
            permanent = any(
                s in exc.stderr
                for s in (
                    "not found in upstream",
                    "does not appear to be a git repository",
                    "would clobber",
                    "couldn't find remote ref",
                )
            )
            if attempt == options.retries or permanent:
                raise


def _clone(
    repo: Repository, where: Path, options: UpdateOptions, tell: Report
) -> tuple[str | None, str]:
    """Clone into a temporary sibling, put it on its version, then rename it into place;
    returns its commit and ``branch@commit``."""
    if options.offline:
        raise _Stop(
            "failed",
            "not cloned yet, and --offline uses no network",
            "run `msctl update` once with the network (or copy a clone of it here)",
        )
    tell(repo.path, "fetching")
    where.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(prefix=f".{where.name}.msctl-partial-", dir=where.parent))
    try:
        version = repo.version
        by_name = version is not None and not looks_like_commit(version)
        args = ["clone", "--quiet", "--origin", "origin"]
        if options.shallow:
            args += ["--depth", "1"]
        if by_name:
            args += ["--branch", version]
        try:
            for attempt in range(options.retries + 1):
                try:
                    run_git([*args, "--", repo.url, str(partial)])
                    break
                except GitError as exc:
                    if attempt == options.retries or "not found in upstream" in exc.stderr:
                        raise
                    shutil.rmtree(partial, ignore_errors=True)
                    partial.mkdir()
        except GitError as exc:
            if "not found in upstream" in exc.stderr:
                missing = _missing(repo, remote_versions(repo.url))
                raise _Stop("failed", missing, _missing_fix(repo)) from None
            raise
        clone = Clone(partial)
        tell(repo.path, "checking out")
        if version is not None and not by_name:
            if options.shallow:
                _network(["fetch", "--quiet", "--depth", "1", "origin", version], partial, options)
                clone.forget()
            target = clone.resolve(version)
            if target is None and options.shallow:
                commit = clone.commit_of("FETCH_HEAD")
                if commit and commit.startswith(version):
                    target = Target("commit", commit, commit)
            if target is None:
                raise _Stop("failed", _missing(repo, clone.versions()), _missing_fix(repo))
            _checkout(clone, target)
        commit, shown = clone.head(), clone.describe()
        if where.exists():
            where.rmdir()  # the empty directory found in its place
        os.rename(partial, where)
        return commit, shown
    finally:
        if partial.exists():
            shutil.rmtree(partial, ignore_errors=True)


def _check_remote(clone: Clone, repo: Repository) -> None:
    remote = clone.remote_url()
    if remote is None:
        raise _Stop(
            "refused",
            "the clone has no remote 'origin'",
            f"git -C {_q(clone.path)} remote add origin {_q(repo.url)}",
        )
    if not same_remote(remote, repo.url):
        raise _Stop(
            "refused",
            f"its origin is {remote}, the files ({repo.defined_at}) say {repo.url}",
            f"if {repo.url} is meant: git -C {_q(clone.path)} remote set-url origin "
            f"{_q(repo.url)}; else fix the url in {repo.defined_at.rsplit(':', 1)[0]}",
        )


def _fetch(clone: Clone, options: UpdateOptions) -> None:
    # --prune drops remote branches that are gone; tags fetched by --tags are not pruned.
    _network(["fetch", "--quiet", "--prune", "--tags", "origin"], clone.path, options)
    clone.forget_refs()


def _resolve(clone: Clone, repo: Repository, options: UpdateOptions) -> Target:
    target = clone.resolve(repo.version)
    if target is None and not options.offline:
        _fetch_named(clone, repo.version, options)
        target = clone.resolve(repo.version)
    if target is not None:
        return target
    if options.offline:
        raise _Stop(
            "failed",
            _missing(repo, clone.versions(), offline=True),
            "run `msctl update` with the network once, so the clone holds it",
        )
    raise _Stop("failed", _missing(repo, remote_versions(repo.url)), _missing_fix(repo))


def _fetch_named(clone: Clone, version: str | None, options: UpdateOptions) -> None:
    """Fetch one version by name: a shallow or single-branch clone does not hold every
    branch after a plain fetch."""
    depth = ["--depth", "1"] if clone.is_shallow() else []
    if version is None:
        clone.ok("remote", "set-head", "origin", "--auto")
        return
    branch_refspec = f"+refs/heads/{version}:refs/remotes/origin/{version}"
    if clone.ok("fetch", "--quiet", *depth, "origin", branch_refspec):
        # A single-branch clone's fetch does not cover the new branch: add it, so later
        # fetches follow it and it can track origin/<version>.
        refspecs = clone.git("config", "--get-all", "remote.origin.fetch", check=False)
        if "refs/heads/*" not in refspecs:
            clone.git("remote", "set-branches", "--add", "origin", version)
        return
    tag_refspec = f"+refs/tags/{version}:refs/tags/{version}"
    if clone.ok("fetch", "--quiet", *depth, "origin", tag_refspec):
        return
    if looks_like_commit(version):
        clone.ok("fetch", "--quiet", *depth, "origin", version)


def _missing(repo: Repository, versions: Sequence[str], offline: bool = False) -> str:
    asked = repr(repo.version) if repo.version else "the remote's default branch"
    where = f" (set at {repo.version_at or repo.defined_at})" if repo.version else ""
    if offline:
        head = f"version {asked}{where} is not in the local clone (--offline)"
    else:
        head = f"version {asked}{where} does not exist in {repo.url}"
    if not versions:
        return head
    close = nearest(repo.version or "", versions, count=3) if repo.version else []
    rest = sorted(v for v in set(versions) if v not in close)
    shown = [*close, *rest][:12]
    more = len(close) + len(rest) - len(shown)
    return f"{head}; it has: {', '.join(shown)}" + (f" (+{more} more)" if more > 0 else "")


def _missing_fix(repo: Repository) -> str:
    file = (repo.version_at or repo.defined_at).rsplit(":", 1)[0]
    return f"fix the version in {file}, or push it to the remote" if file else ""


def _checkout(clone: Clone, target: Target) -> None:
    if target.ref_type == "branch":
        clone.git("checkout", "--quiet", "-B", target.name, f"refs/remotes/origin/{target.name}")
    else:
        clone.git("checkout", "--quiet", "--detach", target.commit)


def _move(clone: Clone, target: Target) -> tuple[bool, list[str]]:
    """Preflight, then one git command; returns (whether HEAD moved, notes)."""
    head, branch = clone.head(), clone.branch()
    notes: list[str] = []
    command: list[str] | None
    if target.ref_type == "branch":
        name, remote = target.name, target.commit
        local = clone.commit_of(f"refs/heads/{name}")
        if local is None:
            final, command = (
                remote,
                ["checkout", "--quiet", "-b", name, "--track", f"origin/{name}"],
            )
        elif local == remote or clone.is_ancestor(remote, local):
            final = local
            command = None if branch == name else ["checkout", "--quiet", name]
            if local != remote:
                ahead = clone.count(local, "--not", remote)
                notes.append(f"{name} is {ahead} commit(s) ahead of origin/{name}, not pushed")
        elif clone.is_ancestor(local, remote):
            final = remote
            command = (
                ["merge", "--quiet", "--ff-only", remote]
                if branch == name
                else ["checkout", "--quiet", "-B", name, f"refs/remotes/origin/{name}"]
            )
        else:
            ahead, behind = clone.ahead_behind(local, remote)
            raise _Stop(
                "refused",
                f"branch {name} has diverged from origin/{name} ({ahead} local, {behind} "
                "remote commits); msctl never resets a branch",
                f"git -C {_q(clone.path)} rebase origin/{name} (or merge it), then push",
            )
        if branch == name and head == final:
            return False, notes
    else:
        if branch is None and head == target.commit:
            return False, notes
        command = ["checkout", "--quiet", "--detach", target.commit]
        name = None
    _preflight(clone, branch, head, leaving=branch is not None and branch != name)
    if command is not None:
        clone.git(*command)
    if target.ref_type == "branch" and clone.head() != final:
        clone.git("merge", "--quiet", "--ff-only", final)
    return True, notes


def _preflight(clone: Clone, branch: str | None, head: str | None, leaving: bool) -> None:
    """Refuse the move if it could lose or hide work (nothing has changed yet)."""
    where = _q(clone.path)
    changes = clone.changes()
    if changes:
        shown = ", ".join(changes[:3]) + (
            f" (+{len(changes) - 3} more)" if len(changes) > 3 else ""
        )
        raise _Stop(
            "refused",
            f"uncommitted changes in {len(changes)} file(s): {shown}",
            f"git -C {where} stash (or commit them), then update again",
        )
    if leaving and branch is not None:
        unpushed = clone.unpushed(branch)
        if unpushed:
            raise _Stop(
                "refused",
                f"branch {branch} has {unpushed} commit(s) no remote holds; leaving it "
                "would hide them",
                f"git -C {where} push origin {shlex.quote(branch)}, then update again",
            )
    if branch is None and head is not None:
        orphans = clone.orphaned_by_leaving()
        if orphans:
            raise _Stop(
                "refused",
                f"the detached HEAD has {orphans} commit(s) on no branch; leaving it would "
                "lose them",
                f"git -C {where} switch -c <new-branch> (keeps them), push it, then update again",
            )


# --------------------------------------------------------------------------- the workspace
def update_workspace(
    repositories: Sequence[Repository],
    workspace: Path,
    options: UpdateOptions,
    report: Report | None = None,
    finished: Callable[[Outcome], None] | None = None,
) -> list[Outcome]:
    """Update every repository, ``options.jobs`` at a time; outcomes in the files' order.

    Args:
        repositories: What the files ask for.
        workspace: The workspace directory (created if missing).
        options: How to update.
        report: Called with (path, stage) as each repository goes on.
        finished: Called with each repository's outcome as soon as it has one.
    """
    workspace.mkdir(parents=True, exist_ok=True)
    jobs = max(1, min(options.jobs, len(repositories) or 1))

    def one(repo: Repository) -> Outcome:
        outcome = update_repository(repo, workspace, options, report)
        if finished is not None:
            finished(outcome)
        return outcome

    with ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="msctl-update") as pool:
        return list(pool.map(one, repositories))


def lock_text(workspace: Path, repositories: Sequence[Repository], note: str = "") -> str:
    """The exact commits of the workspace's clones, as a ``.repos`` file (``vcs export
    --exact``): the input of a later update that reproduces this one.

    Repositories without a clone are left out.
    """
    exact = []
    for repo in repositories:
        clone = Clone(workspace / repo.path)
        if clone.path.is_dir() and clone.is_clone() and clone.head():
            exact.append(
                Repository(repo.path, clone.remote_url() or repo.url, clone.head(), repo.type)
            )
    header = f"msctl update --lock of {workspace}, {time.strftime('%Y-%m-%d %H:%M:%S %z')}"
    return dump_repos(exact, header + (f"\n{note}" if note else ""))


def refuse_unwritable(path: Path, flag: str) -> None:
    """Refuse, before any work, a file :func:`write_atomically` could not write.

    Probes the directory it would be written in (or, not there yet, the nearest one that
    is) with a temporary file, removed at once: permissions, a read-only mount, a full disk
    and a path through a file all show, whoever runs (root passes ``os.access``).

    Raises:
        InputError: Naming the flag, the path and why.
    """
    path = path.expanduser()
    if path.is_dir():
        raise InputError(f"{flag} {path} is a directory", hint="give a file name, e.g. exact.repos")
    folder = path.absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(
            f"{flag} {path} cannot be written: {folder} is not a directory",
            hint="choose another path",
        )
    try:
        handle, probe = tempfile.mkstemp(prefix=f".{path.name}.", dir=folder)
    except OSError as exc:
        raise InputError(
            f"{flag} {path} cannot be written: {exc.strerror or exc} ({folder})",
            hint="choose a path you can write, or fix the directory's permissions",
        ) from None
    os.close(handle)
    os.unlink(probe)


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary sibling, so a reader never sees half."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


# --------------------------------------------------------------------------- the files in use
_RECORD = "update.json"


def remember_files(workspace: Path, repos_file: Path, overlays: Sequence[Path]) -> None:
    """Record which files the last update used, for ``--status`` and a bare ``update``."""
    record = {
        "repos": str(repos_file.absolute()),
        "overlays": [str(p.absolute()) for p in overlays],
        "at": time.time(),
    }
    write_atomically(state_dir(workspace) / _RECORD, json.dumps(record, indent=2) + "\n")


def remembered_files(workspace: Path) -> tuple[Path, list[Path]] | None:
    """The files of the last update of ``workspace``, if it recorded them."""
    try:
        record = json.loads((state_dir(workspace) / _RECORD).read_text(encoding="utf-8"))
        return Path(record["repos"]), [Path(p) for p in record.get("overlays", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return None


#: The workspace file used when none is named and no update recorded one.
DEFAULT_REPOS = "workspace.repos"


def files_in_use(
    workspace: Path, repos_file: Path | None, overlays: Sequence[Path]
) -> tuple[Path, list[Path]]:
    """Which files an update (or ``--status``) reads.

    The file named, else the one the last update of the workspace used (with its overlays,
    unless overlays are named now), else ``<workspace>/workspace.repos``.
    """
    if repos_file is not None:
        return repos_file, list(overlays)
    remembered = remembered_files(workspace)
    if remembered is not None:
        base, previous = remembered
        return base, list(overlays) if overlays else previous
    return workspace / DEFAULT_REPOS, list(overlays)
