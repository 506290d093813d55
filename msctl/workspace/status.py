"""``msctl update --status``: each repository's state against what the files ask (no network)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from msctl.workspace.git import Clone, same_remote
from msctl.workspace.repos import Repository


@dataclass
class RepoStatus:
    """One repository's state against what the files ask (no network).

    Attributes:
        path: Its path in the workspace.
        url: The remote the files name.
        version: The version the files ask for.
        present: Whether a clone is there.
        branch: The branch checked out (``None``: detached).
        commit: The commit checked out.
        dirty: Tracked files with uncommitted changes.
        ahead: Commits on the branch that its ``origin`` branch lacks.
        behind: Commits on its ``origin`` branch the local branch lacks (as last fetched).
        on_version: Whether it is on the version asked (``None``: not known offline).
        note: What is off, in words.
    """

    path: str
    url: str
    version: str | None
    present: bool
    branch: str | None = None
    commit: str | None = None
    dirty: int = 0
    ahead: int = 0
    behind: int = 0
    on_version: bool | None = None
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The status as ``--json`` prints it."""
        return asdict(self)


def status(repositories: Sequence[Repository], workspace: Path) -> list[RepoStatus]:
    """Each repository's branch, commit and dirty/ahead/behind state, against the files."""
    rows = []
    for repo in repositories:
        clone = Clone(workspace / repo.path)
        if not clone.path.is_dir() or not clone.is_clone():
            note = "not cloned" if not clone.path.exists() else "not a git clone"
            rows.append(RepoStatus(repo.path, repo.url, repo.version, False, note=note))
            continue
        row = RepoStatus(repo.path, repo.url, repo.version, True, clone.branch(), clone.head())
        row.dirty = len(clone.changes())
        notes = []
        remote = clone.remote_url()
        if remote is None or not same_remote(remote, repo.url):
            notes.append(f"origin is {remote or 'missing'}")
        if row.branch and clone.commit_of(f"refs/remotes/origin/{row.branch}"):
            row.ahead, row.behind = clone.ahead_behind(row.branch, f"origin/{row.branch}")
        target = clone.resolve(repo.version)
        if target is None:
            row.on_version = None
            notes.append("version not in the clone (run `msctl update`)")
        elif target.ref_type == "branch":
            row.on_version = row.branch == target.name and row.behind == 0
            if row.branch != target.name:
                notes.append(f"on {row.branch or 'a detached HEAD'}, not {target.name}")
            elif row.behind:
                notes.append(f"{row.behind} commit(s) behind origin/{target.name}")
        else:
            row.on_version = row.commit == target.commit
            if not row.on_version:
                notes.append(f"not at {target.ref_type} {target.name[:12]}")
        if row.dirty:
            notes.append(f"{row.dirty} changed file(s)")
        if row.ahead:
            notes.append(f"{row.ahead} unpushed commit(s)")
        row.note = "; ".join(notes)
        rows.append(row)
    return rows


def unlisted_clones(
    workspace: Path, repositories: Sequence[Repository], depth: int = 4
) -> list[str]:
    """Git clones in the workspace that the files do not name (never removed: named)."""
    listed = {r.path for r in repositories}
    found: list[str] = []

    def walk(directory: Path, level: int) -> None:
        try:
            children = sorted(p for p in directory.iterdir() if p.is_dir())
        except OSError:
            return
        for child in children:
            if child.name.startswith(".") or child.is_symlink():
                continue
            relative = child.relative_to(workspace).as_posix()
            if (child / ".git").exists():
                if relative not in listed:
                    found.append(relative)
                continue
            if level < depth:
                walk(child, level + 1)

    if workspace.is_dir():
        walk(workspace, 1)
    return found
