"""``.repos`` files (vcstool's format) and the experiment overlays laid over them.

A workspace file is vcstool's, unchanged, so ``vcs import`` reads the same file::

    repositories:
      moonbot/limb_firmware:          # the path of the clone, relative to the workspace
        type: git
        url: https://git.example.org/moonbot/limb_firmware.git
        version: main                 # a branch, a tag or a commit (default: the remote's)

An experiment overlay is a file of the same format laid over it: for a repository already
named, it may change ``url`` and/or ``version`` only (``type`` may be repeated); a
repository it names for the first time is added, and needs ``type`` and ``url`` like in the
base file. An entry for an unknown repository without a ``url`` is taken for a typo and
refused, with the nearest names. A lock file (``msctl update --lock``) is a plain
``.repos`` file with commits for versions, so it can be the input of a later update.

Everything read here is checked before anything is touched: a path is a plain relative
path inside the workspace, a URL a git URL without shell metacharacters or git's
``transport::`` forms, a version a plain ref name or commit. The same checks guard what an
agent is sent from a ground station.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from msctl.errors import InputError, NotFoundError, did_you_mean

#: vcstool's repository types; msctl updates git ones only.
VCS_TYPES = ("git", "hg", "svn", "bzr", "tar", "zip")
FIELDS = ("type", "url", "version")
#: URL schemes git reaches a remote with (``ext::`` and the other ``transport::`` forms run
#: commands and are refused).
URL_SCHEMES = ("https", "http", "ssh", "git", "file", "git+ssh", "ssh+git")
_SHELL_META = set(";|&$`<>(){}*?!'\"\\") | {chr(c) for c in range(33)} | {"\x7f"}
_IPV6_AUTHORITY = re.compile(r"^[a-z+]+://(?:[^@/\[\]]*@)?\[[0-9A-Fa-f:.]+\](?::\d+)?/")
_SCP_LIKE = re.compile(r"^(?:[A-Za-z0-9._-]+@)?[A-Za-z0-9.-]+:(?!//)[^:].*$")
_VERSION = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9._/+-]*$")
_PATH_PART = re.compile(r"^[A-Za-z0-9_+][A-Za-z0-9_.+-]*$")
_HEX = re.compile(r"^[0-9a-f]{7,64}$")


@dataclass(frozen=True)
class Repository:
    """One repository of the workspace, as the files (merged) ask for it.

    Attributes:
        path: Where its clone lives, relative to the workspace (the key in the file).
        url: Its remote (``origin`` of the clone).
        version: A branch, tag or commit; ``None`` is the remote's default branch.
        type: The VCS type (always ``git`` once checked).
        defined_at: ``file:line`` of the entry that set the URL.
        version_at: ``file:line`` of the entry that set the version (an overlay, maybe).
    """

    path: str
    url: str
    version: str | None
    type: str = "git"
    defined_at: str = ""
    version_at: str = ""

    def to_dict(self) -> dict[str, str | None]:
        """The entry as the JSON outputs show it."""
        return {
            "path": self.path,
            "type": self.type,
            "url": self.url,
            "version": self.version,
            "defined_at": self.defined_at,
            "version_at": self.version_at or self.defined_at,
        }


@dataclass(frozen=True)
class Entry:
    """One repository entry as one file writes it (fields may be missing in an overlay).

    Attributes:
        path: The key (the clone's path).
        fields: The fields given (``type``, ``url``, ``version``); a null version is ``None``.
        line: The entry's line in its file (1-based).
        field_lines: Each given field's line.
    """

    path: str
    fields: dict[str, str | None]
    line: int
    field_lines: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class ReposFile:
    """One ``.repos`` file as read: its name (for messages) and its entries in order."""

    name: str
    entries: tuple[Entry, ...]

    def where(self, entry: Entry, field_name: str | None = None) -> str:
        """``file:line`` of an entry (or of one of its fields)."""
        line = entry.field_lines.get(field_name, entry.line) if field_name else entry.line
        return f"{self.name}:{line}"


# --------------------------------------------------------------------------- checks
def check_path(path: str, where: str) -> str:
    """A repository path: relative, plain parts, inside the workspace.

    Raises:
        InputError: Naming ``where`` and the path.
    """
    parts = path.split("/") if isinstance(path, str) else []
    if not parts or any(not _PATH_PART.match(p) or p in (".", "..") for p in parts):
        raise InputError(
            f"{where}: repository path {path!r} is not a plain relative path",
            hint="use letters, digits and _ . + - in parts separated by /, no '..', "
            "not starting with / or -",
        )
    if parts[0] == ".msctl":
        raise InputError(f"{where}: repository path {path!r} is msctl's own state directory")
    return path


def check_url(url: str, where: str) -> str:
    """A git URL msctl will pass to git: no shell metacharacters, no ``transport::``.

    Raises:
        InputError: Naming ``where``, the URL and what is wrong with it.
    """
    if not isinstance(url, str) or not url:
        raise InputError(f"{where}: the url is empty", hint="give the repository's git URL")
    bad = sorted({c for c in url if c in _SHELL_META})
    brackets = "[" in url or "]" in url
    if brackets and not _IPV6_AUTHORITY.match(url):
        bad = sorted({*bad, *(c for c in "[]" if c in url)})
    if bad:
        shown = " ".join(repr(c) for c in bad)
        raise InputError(
            f"{where}: url {url!r} is refused: it holds shell metacharacters ({shown})",
            hint="a git URL never needs them; check the file",
        )
    if url.startswith("-"):
        raise InputError(f"{where}: url {url!r} is refused: it starts with '-'")
    if "::" in url.split("/", 1)[0] or re.match(r"^[A-Za-z0-9+.-]+::", url):
        raise InputError(
            f"{where}: url {url!r} is refused: git's transport::address form can run commands",
            hint=f"use a {', '.join(URL_SCHEMES[:4])} or file URL",
        )
    scheme = re.match(r"^([A-Za-z][A-Za-z0-9+.-]*)://", url)
    if scheme:
        if scheme.group(1).lower() not in URL_SCHEMES:
            raise InputError(
                f"{where}: url {url!r} has scheme {scheme.group(1)!r}",
                hint=f"git URLs use {', '.join(URL_SCHEMES)}",
            )
        return url
    if url.startswith("/") or _SCP_LIKE.match(url):
        return url  # a local path, or user@host:path
    raise InputError(
        f"{where}: url {url!r} is neither a URL, user@host:path nor an absolute path",
        hint="write the remote as git clone would take it, e.g. https://host/org/repo.git "
        "or file:///srv/git/repo.git",
    )


def check_version(version: str, where: str) -> str:
    """A version: a plain branch or tag name, or a commit.

    Raises:
        InputError: Naming ``where`` and the version.
    """
    if (
        not isinstance(version, str)
        or not _VERSION.match(version)
        or ".." in version
        or "//" in version
        or version.endswith(("/", ".", ".lock"))
        or len(version) > 255
    ):
        raise InputError(
            f"{where}: version {version!r} is not a branch, tag or commit name",
            hint="use letters, digits and _ . / + - (no spaces, '..' or '@{')",
        )
    return version


def looks_like_commit(version: str | None) -> bool:
    """Whether ``version`` reads as an (abbreviated) commit id."""
    return bool(version and _HEX.match(version))


# --------------------------------------------------------------------------- reading
def read_repos(path: Path, *, overlay: bool = False) -> ReposFile:
    """Read and check one ``.repos`` file.

    Args:
        path: The file.
        overlay: An experiment overlay: entries may give only ``url`` and/or ``version``.

    Raises:
        NotFoundError: If the file does not exist.
        InputError: For a YAML error or a malformed entry, naming the file, line and
            repository.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise NotFoundError(
            f"{path}: no such .repos file",
            hint="name the workspace's .repos file (or run in the workspace that has "
            "workspace.repos)",
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read it: {exc}") from None
    return parse_repos(text, str(path), overlay=overlay)


def parse_repos(text: str, name: str, *, overlay: bool = False) -> ReposFile:
    """Parse the text of a ``.repos`` file (see :func:`read_repos`)."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        # At the end of the stream YAML's mark is past the last line: name the last line.
        last = max(1, len(text.splitlines()))
        line = f":{min(mark.line + 1, last)}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        repository = _repository_at(text, mark.line) if mark is not None else None
        inside = f" (in repository {repository!r})" if repository else ""
        raise InputError(
            f"{name}{line}: not valid YAML{inside}: {problem}",
            hint="a .repos file is a `repositories:` mapping of path: {type, url, version}",
        ) from None
    if root is None:
        raise InputError(f"{name}: the file is empty", hint="it needs a `repositories:` mapping")
    if isinstance(root, yaml.SequenceNode):
        raise InputError(
            f"{name}:{root.start_mark.line + 1}: this is the older rosinstall format",
            hint="convert it with `vcs import` + `vcs export`, or write a `repositories:` mapping",
        )
    if not isinstance(root, yaml.MappingNode):
        raise InputError(f"{name}:1: the file must hold a `repositories:` mapping")
    repositories = None
    for key, value in root.value:
        if _scalar(key) == "repositories":
            repositories = value
    if repositories is None:
        raise InputError(
            f"{name}: no `repositories:` key",
            hint="a .repos file is a `repositories:` mapping of path: {type, url, version}",
        )
    if _is_null(repositories):
        return ReposFile(name, ())
    if not isinstance(repositories, yaml.MappingNode):
        raise InputError(
            f"{name}:{repositories.start_mark.line + 1}: `repositories` must be a mapping "
            "of path: {type, url, version}"
        )
    entries: list[Entry] = []
    seen: dict[str, int] = {}
    for key, value in repositories.value:
        line = key.start_mark.line + 1
        path = _scalar(key)
        if path is None:
            raise InputError(f"{name}:{line}: a repository's key must be its path (a string)")
        where = f"{name}:{line}: repository {path!r}"
        check_path(path, f"{name}:{line}")
        if path in seen:
            raise InputError(
                f"{where} appears twice (lines {seen[path]} and {line})",
                hint="keep one entry per path (an overlay file is where a version changes)",
            )
        seen[path] = line
        entries.append(_entry(path, value, line, where, overlay))
    _refuse_nesting([e.path for e in entries], name)
    return ReposFile(name, tuple(entries))


_KEY_LINE = re.compile(r"""^(\s+)(?:'([^']*)'|"([^"]*)"|([^\s#'"{\[][^:#]*?))\s*:(?:\s|$)""")


def _repository_at(text: str, line: int) -> str | None:
    """The repository whose entry holds (0-based) ``line``, read from the text itself: a
    file YAML cannot parse has no tree to ask. The entries are the keys indented like the
    first one under ``repositories:``; the last of them at or before ``line`` is the one."""
    lines = text.splitlines()
    start = next(
        (i for i, t in enumerate(lines) if re.match(r"^repositories\s*:\s*(#.*)?$", t)), None
    )
    if start is None:
        return None
    indent = None
    found = None
    for number in range(start + 1, min(line, len(lines) - 1) + 1):
        match = _KEY_LINE.match(lines[number])
        if match is None or lines[number].lstrip().startswith("#"):
            continue
        width = len(match.group(1))
        if indent is None:
            indent = width
        if width == indent:
            found = next(g for g in match.groups()[1:] if g is not None)
    return found


def _entry(path: str, node: yaml.Node, line: int, where: str, overlay: bool) -> Entry:
    if not isinstance(node, yaml.MappingNode):
        raise InputError(f"{where}: its entry must be a mapping with type, url and version")
    fields: dict[str, str | None] = {}
    lines: dict[str, int] = {}
    for key, value in node.value:
        name = _scalar(key)
        field_line = key.start_mark.line + 1
        if name not in FIELDS:
            hint = did_you_mean(str(name), FIELDS)
            raise InputError(
                f"{where}: unknown field {name!r} (line {field_line})",
                hint=hint or f"an entry has {', '.join(FIELDS)}",
            )
        if not isinstance(value, yaml.ScalarNode):
            raise InputError(f"{where}: field {name!r} (line {field_line}) must be a string")
        fields[name] = None if _is_null(value) else value.value
        lines[name] = field_line
    vcs = fields.get("type")
    if vcs is not None and vcs != "git":
        if vcs in VCS_TYPES:
            raise InputError(
                f"{where}: type {vcs!r} (line {lines['type']}): msctl update handles git "
                "repositories only",
                hint="use `vcs import` for it, or move it to git",
            )
        raise InputError(
            f"{where}: unknown type {vcs!r} (line {lines['type']})",
            hint=did_you_mean(vcs, VCS_TYPES) or f"vcstool's types are {', '.join(VCS_TYPES)}",
        )
    if not overlay:
        for required in ("type", "url"):
            if fields.get(required) is None:
                raise InputError(
                    f"{where}: missing {required!r}",
                    hint="every repository needs `type: git` and its `url`",
                )
    if fields.get("url") is not None:
        check_url(fields["url"], f"{where} (line {lines['url']})")
    if fields.get("version") is not None:
        check_version(fields["version"], f"{where} (line {lines['version']})")
    return Entry(path, fields, line, lines)


def _scalar(node: yaml.Node) -> str | None:
    return node.value if isinstance(node, yaml.ScalarNode) and not _is_null(node) else None


def _is_null(node: yaml.Node) -> bool:
    return isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null"


def _refuse_nesting(paths: Iterable[str], name: str) -> None:
    ordered = sorted(paths)
    for outer, inner in itertools.pairwise(ordered):
        if inner.startswith(outer + "/"):
            raise InputError(
                f"{name}: repository {inner!r} lies inside repository {outer!r}",
                hint="give each repository its own directory, side by side",
            )


# --------------------------------------------------------------------------- merging
def merge(base: ReposFile, overlays: Sequence[ReposFile] = ()) -> list[Repository]:
    """The repositories of ``base`` with each overlay laid over it, in order.

    Raises:
        InputError: For an overlay entry naming an unknown repository without a ``url``,
            or repositories nested in one another once merged.
    """
    merged: dict[str, Repository] = {}
    for entry in base.entries:
        merged[entry.path] = Repository(
            path=entry.path,
            url=entry.fields["url"] or "",
            version=entry.fields.get("version"),
            defined_at=base.where(entry),
            version_at=base.where(entry, "version") if "version" in entry.fields else "",
        )
    for overlay in overlays:
        for entry in overlay.entries:
            known = merged.get(entry.path)
            if known is None:
                if entry.fields.get("url") is None:
                    hint = did_you_mean(entry.path, merged)
                    raise InputError(
                        f"{overlay.where(entry)}: repository {entry.path!r} is not in "
                        f"{base.name}" + (f"; {hint}" if hint else ""),
                        hint="to add a repository, give its type and url as well",
                    )
                merged[entry.path] = Repository(
                    path=entry.path,
                    url=entry.fields["url"] or "",
                    version=entry.fields.get("version"),
                    defined_at=overlay.where(entry),
                    version_at=overlay.where(entry, "version") if "version" in entry.fields else "",
                )
                continue
            changes: dict[str, object] = {}
            if entry.fields.get("url") is not None:
                changes.update(url=entry.fields["url"], defined_at=overlay.where(entry, "url"))
            if "version" in entry.fields:
                changes.update(
                    version=entry.fields["version"], version_at=overlay.where(entry, "version")
                )
            merged[entry.path] = _replace(known, changes)
    _refuse_nesting(merged, " + ".join([base.name, *(o.name for o in overlays)]))
    return list(merged.values())


def _replace(repository: Repository, changes: dict[str, object]) -> Repository:
    from dataclasses import replace

    return replace(repository, **changes)  # type: ignore[arg-type]


def load(repos_file: Path, overlays: Sequence[Path] = ()) -> list[Repository]:
    """Read a workspace file and its overlays, and merge them (see :func:`merge`)."""
    return merge(read_repos(repos_file), [read_repos(p, overlay=True) for p in overlays])


def load_texts(base: tuple[str, str], overlays: Sequence[tuple[str, str]]) -> list[Repository]:
    """Like :func:`load`, from ``(name, text)`` pairs (what a ground station sends an agent)."""
    return merge(
        parse_repos(base[1], base[0]),
        [parse_repos(text, name, overlay=True) for name, text in overlays],
    )


# --------------------------------------------------------------------------- writing
def dump_repos(repositories: Iterable[Repository], header: str = "") -> str:
    """The repositories as a ``.repos`` file (``vcs export``'s layout).

    Args:
        repositories: What to write (in this order).
        header: Comment lines put first (each prefixed with ``# ``).
    """
    document = {
        "repositories": {
            r.path: {"type": r.type, "url": r.url, **({"version": r.version} if r.version else {})}
            for r in repositories
        }
    }
    comments = "".join(f"# {line}\n" for line in header.splitlines())
    return comments + yaml.safe_dump(document, sort_keys=False, default_flow_style=False)
