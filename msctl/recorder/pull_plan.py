"""What ``msctl bag pull`` does with each file another computer lists: the listing read
back into :class:`RemoteFile` values, and :func:`decide` (fetch, resume, skip, leave, or a
conflict), pure and tested with plain calls; :mod:`msctl.recorder.pull` does the I/O."""

from __future__ import annotations

from typing import Any, NamedTuple

from msctl.errors import MsctlError
from msctl.recorder.shelf import is_plain

#: The bag file rewritten while a bag is recorded; every other file is final once complete.
METADATA = "metadata.yaml"


class PullError(MsctlError):
    """A pull that cannot go on: a listing that cannot be read, a directory not writable."""

    exit_code = 3


class RemoteFile(NamedTuple):
    """One file of a bag on the other computer, as its agent listed it.

    Attributes:
        bag: The bag's directory name.
        name: The file's name in it.
        size: Bytes.
        sha256: Its SHA-256 (hex) when complete, else ``None``.
        complete: Whether it is finished (an MCAP file ends with its magic).
        abandoned: Unfinished and no longer written (its recorder was killed): served as it
            is, with its SHA-256; ``msctl bag recover`` completes the copy.
    """

    bag: str
    name: str
    size: int
    sha256: str | None
    complete: bool
    abandoned: bool = False

    @property
    def path(self) -> str:
        """``<bag>/<file>``, as the agent's ``bag_read`` takes it."""
        return f"{self.bag}/{self.name}"


def remote_files(listing: Any, host: str) -> list[RemoteFile]:
    """The files of an agent's ``bags`` answer, each bag's ``metadata.yaml`` last.

    Raises:
        PullError: If the answer is not a listing, or names a bag or file that is not a plain
            name (it would make a path outside the directory pulled into).
    """

    def bad(why: str) -> PullError:
        return PullError(
            f"{host}'s bag listing is refused: {why}",
            hint=f"bring {host}'s msctl to the version of this computer's",
        )

    from components.supervision.protocol import AnswerError, bags_answer

    if not isinstance(listing, (dict, bytes, str)):
        raise bad("it is not a listing of bags")
    try:
        shelf = bags_answer(listing, host)
    except AnswerError as exc:
        raise bad(f"it is not a listing of bags ({exc.detail})") from None
    files: list[RemoteFile] = []
    for bag in shelf.bags:
        name = bag.name
        if not is_plain(name):
            raise bad(f"bag name {name!r} is not a plain name")
        found = []
        for entry in bag.files:
            remote = RemoteFile(
                name, entry.name, entry.size, entry.sha256, entry.complete, entry.abandoned
            )
            if not is_plain(remote.name):
                raise bad(f"file name {remote.name!r} in bag {name} is not a plain name")
            served = remote.complete or remote.abandoned
            if remote.size < 0 or (served and not _is_sha256(remote.sha256)):
                raise bad(f"{remote.path} has no valid size or SHA-256")
            found.append(remote)
        files += sorted(found, key=lambda f: (f.name == METADATA, f.name))
    return files


def _is_sha256(value: Any) -> bool:
    return (
        isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)
    )


# ----------------------------------------------------------------------------- decisions
#: What to do with a remote file (:attr:`Action.kind`).
FETCH, SKIP, LEFT, CONFLICT = "fetch", "skip", "left", "conflict"


class Action(NamedTuple):
    """What a pull does with one remote file.

    Attributes:
        kind: :data:`FETCH` (from ``offset``), :data:`SKIP` (here and verified),
            :data:`LEFT` (not finished there) or :data:`CONFLICT` (a different file of that
            name is here).
        file: The remote file.
        offset: Where fetching starts (the ``.part``'s size when resuming).
        why: For a person.
    """

    kind: str
    file: RemoteFile
    offset: int = 0
    why: str = ""


#: Why a file pulled as it was left unfinished (:attr:`RemoteFile.abandoned`) is pulled.
CUT_SHORT = (
    "cut short there (its recorder was stopped before finishing it): `msctl bag recover` the "
    "bag here completes it"
)


def decide(
    remote: RemoteFile, here_sha256: str | None, part_size: int | None, here_cut: bool = False
) -> Action:
    """What to do with ``remote``, given what this computer has of it.

    Args:
        remote: The file as listed.
        here_sha256: The SHA-256 of the file of that name here (``None``: none).
        part_size: The size of its ``.part`` here (``None``: none).
        here_cut: The file here was pulled cut short (:data:`CUT_MARK` beside it): one
            finished since may replace it.
    """
    if not (remote.complete or remote.abandoned):
        return Action(LEFT, remote, why="still being recorded there")
    why = CUT_SHORT if remote.abandoned else ""
    if here_sha256 is not None:
        if here_sha256 == remote.sha256:
            return Action(SKIP, remote, why="already here, verified")
        if remote.name != METADATA and not here_cut:
            # A finished MCAP file never changes: two different ones of one name is a mix-up
            # (another computer's bag, a damaged copy), never overwritten unasked.
            return Action(CONFLICT, remote, why="a different file of that name is already here")
        return Action(FETCH, remote, why=why or "changed there since it was pulled")
    if part_size is not None and 0 < part_size <= remote.size:
        resuming = f"resuming at byte {part_size:,}"
        return Action(FETCH, remote, part_size, why=f"{resuming}; {why}" if why else resuming)
    return Action(FETCH, remote, why=why)
