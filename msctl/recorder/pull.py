"""``msctl bag pull HOST``: copy a computer's own bags to this one over the fleet, chunk by
chunk, resuming after a cut, verifying every file.

The other computer's agent lists its shelf and reads its files (:mod:`msctl.recorder.shelf`);
this side decides what to fetch and keeps the bookkeeping that makes a cut cheap:

- a file already here whose SHA-256 is the one the other computer computed is skipped;
- a file is written to ``<name>.part``, strictly in order (chunks that come early wait in
  memory, a window's worth at most), so after a cut the ``.part``'s size is where the next
  pull starts; nothing already here is asked for again;
- a whole ``.part`` is renamed to its name only when its SHA-256 matches; a mismatch is
  fetched again from zero once, then named as failed;
- while the link flaps, chunk requests that got no answer are asked again until no answer
  came for ``patience`` seconds; then the pull stops, naming the host, and a pull run later
  resumes.

The pure parts (:func:`decide`, :class:`ChunkWindow`, :class:`RateBudget`) take plain values
and are tested with plain calls; :class:`Puller` does the I/O.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import os
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from msctl.errors import MsctlError
from msctl.recorder.shelf import MAX_READ, is_plain, sha256_of

#: Bytes asked per request. 64 KiB keeps each answer small: a cut throws away little, and
#: halts (sent at a higher priority) pass between its fragments.
CHUNK = 64 * 1024
#: Requests in flight at most. The agent answers the requests queued at each turn of its
#: loop, so more in flight is more per turn: on the rehearsal's wifi profile (two loaded
#: cores) 64 KiB x 8 pulled 2.2-2.4 MB/s where x 4 pulled 1.0-1.3 and x 1 1.0 (16 KiB x 4:
#: 0.6; 256 KiB x 4: 1.1-2.2). On a slow link :data:`IN_FLIGHT_SECONDS` bounds it lower.
WINDOW = 8
#: Seconds of the link (at the rate seen so far) that may be in flight: at 256 kbit/s
#: (32 kB/s) 128 kB, one or two chunks, since more would only queue answers behind each
#: other, to be asked again if they outlast their bound and thrown away at a cut.
IN_FLIGHT_SECONDS = 4.0
#: Seconds one chunk request may take before it is asked again, at least (it grows with
#: the bytes in flight on a slow link: :func:`request_timeout`).
REQUEST_TIMEOUT = 10.0
#: Seconds with no answer at all from the host before a pull gives up (a pull run later
#: resumes): a short outage is ridden through, a computer gone is named.
PATIENCE = 30.0
#: Seconds between two attempts while the host does not answer.
RETRY_PAUSE = 0.25
#: What a file being fetched is called until its SHA-256 matched.
PART_SUFFIX = ".part"
#: Beside a file pulled cut short (``.<name>.cut``): a later pull may replace it.
CUT_MARK = ".{}.cut"
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

    if not isinstance(listing, dict) or not isinstance(listing.get("bags"), list):
        raise bad("it is not a listing of bags")
    files: list[RemoteFile] = []
    for bag in listing["bags"]:
        name = bag.get("name") if isinstance(bag, dict) else None
        if not isinstance(name, str) or not is_plain(name):
            raise bad(f"bag name {name!r} is not a plain name")
        entries = bag.get("files")
        if not isinstance(entries, list):
            raise bad(f"bag {name} has no list of files")
        found = []
        for entry in entries:
            try:
                remote = RemoteFile(
                    name,
                    entry["name"],
                    int(entry["size"]),
                    entry.get("sha256"),
                    bool(entry["complete"]),
                    bool(entry.get("abandoned", False)),
                )
            except (TypeError, KeyError, ValueError):
                raise bad(f"a file of bag {name} is not described as one") from None
            if not isinstance(remote.name, str) or not is_plain(remote.name):
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


class ShortRead(ValueError):
    """A chunk of another size than asked: the file changed there while it was pulled."""


class ChunkWindow:
    """The resume bookkeeping of one file: which chunks to ask, which are in flight, and which
    bytes can be appended to the ``.part`` now (strictly in order).

    Args:
        size: The file's size.
        start: Bytes already in the ``.part`` (fetching starts there).
        chunk: Bytes per request.
        window: Requests in flight at most.
    """

    def __init__(self, size: int, start: int, chunk: int = CHUNK, window: int = WINDOW) -> None:
        if not 0 <= start <= size:
            raise ValueError(f"start {start} is outside a file of {size} bytes")
        if chunk <= 0 or window <= 0:
            raise ValueError("chunk and window must be positive")
        self.size = size
        self.chunk = chunk
        self.window = window
        #: Bytes in order so far: what the ``.part`` holds, where a later pull resumes.
        self.written = start
        self._next = start
        self._waiting: set[int] = set()
        self._early: dict[int, bytes] = {}
        self._again: list[int] = []

    @property
    def done(self) -> bool:
        """Whether every byte is written."""
        return self.written >= self.size

    @property
    def in_flight(self) -> int:
        """Requests asked and not answered."""
        return len(self._waiting)

    def expected(self, offset: int) -> int:
        """The bytes a request at ``offset`` returns."""
        return min(self.chunk, self.size - offset)

    @property
    def bytes_in_flight(self) -> int:
        """Bytes asked and not answered."""
        return sum(self.expected(offset) for offset in self._waiting)

    def asks(self, max_bytes: int = 0) -> list[tuple[int, int]]:
        """``(offset, size)`` of the requests to send now: the window's free places, chunks
        that failed first.

        Args:
            max_bytes: Bytes in flight at most (0: no bound); one request always may go.
        """
        asks = []
        in_flight = self.bytes_in_flight
        while len(self._waiting) < self.window:
            if self._again:
                offset = self._again[0]
            elif self._next < self.size:
                offset = self._next
            else:
                break
            size = self.expected(offset)
            if max_bytes and self._waiting and in_flight + size > max_bytes:
                break
            if self._again:
                self._again.pop(0)
            else:
                self._next += size
            self._waiting.add(offset)
            in_flight += size
            asks.append((offset, size))
        return asks

    def arrived(self, offset: int, data: bytes) -> bytes:
        """Take the answer to the request at ``offset``; returns the bytes to append now
        (empty while an earlier chunk is missing).

        Raises:
            ShortRead: If ``data`` is not as long as asked.
            ValueError: If nothing was asked at ``offset``.
        """
        if offset not in self._waiting:
            raise ValueError(f"no request at byte {offset} is waiting")
        if len(data) != self.expected(offset):
            raise ShortRead(
                f"{len(data)} bytes came at byte {offset:,} where {self.expected(offset)} were "
                "asked"
            )
        self._waiting.discard(offset)
        self._early[offset] = data
        ready = bytearray()
        while self.written in self._early:
            piece = self._early.pop(self.written)
            ready += piece
            self.written += len(piece)
        return bytes(ready)

    def failed(self, offset: int) -> None:
        """The request at ``offset`` got no answer: ask it again (before any new one)."""
        if offset in self._waiting:
            self._waiting.discard(offset)
            self._again.append(offset)
            self._again.sort()


class RateBudget:
    """A token bucket over the bytes asked, so a pull leaves the radio room for the rest.

    Args:
        rate: Bytes per second at most (0: no limit).
        burst: Bytes that may go at once (one chunk).
        now: The time it starts (seconds, any clock).
    """

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self._tokens = float(burst)
        self._then = now

    def delay(self, size: int, now: float) -> float:
        """Seconds to wait before asking for ``size`` more bytes (the bytes are taken)."""
        if self.rate <= 0:
            return 0.0
        self._tokens = min(self.burst, self._tokens + (now - self._then) * self.rate)
        self._then = now
        self._tokens -= size
        return 0.0 if self._tokens >= 0 else -self._tokens / self.rate


def request_timeout(in_flight_bytes: int, rate: float, floor: float, ceiling: float) -> float:
    """Seconds a chunk request may take before it is asked again.

    On a slow link the answers of a window queue behind each other: at 256 kbit/s four
    64 KiB chunks take 8 s to come through, and a fixed bound would ask the last ones again
    while they are on their way, sending them twice. So the bound is three times what the
    link, at the rate seen so far, needs for every byte in flight, never below ``floor``
    (no rate known yet, or a fast link: a lost request is asked again soon) nor above
    ``ceiling``.

    Args:
        in_flight_bytes: Bytes asked and not answered, this request's included.
        rate: Bytes per second answered so far (0: not known yet).
        floor: The least bound.
        ceiling: The largest bound.
    """
    if rate <= 0:
        return floor
    return min(max(floor, 3.0 * in_flight_bytes / rate), max(ceiling, floor))


class RateMeter:
    """Bytes per second answered, from the first request on, over the whole pull (a radio's
    rate changes slowly; a short window would chase every burst of loss).

    Args:
        now: When the first request left (seconds, any clock); ``None``: not yet, see
            :meth:`asked`.
    """

    def __init__(self, now: float | None = None) -> None:
        self._started = now
        self._bytes = 0
        self._seconds = 0.0

    def asked(self, now: float) -> None:
        """A request left at ``now``: the clock starts at the first."""
        if self._started is None:
            self._started = now

    def answered(self, size: int, now: float) -> None:
        """``size`` bytes came at ``now``."""
        self.asked(now)
        assert self._started is not None
        self._bytes += size
        self._seconds = now - self._started

    @property
    def rate(self) -> float:
        """Bytes per second so far (0 until a second's worth is known)."""
        return self._bytes / self._seconds if self._seconds >= 1.0 else 0.0


# ----------------------------------------------------------------------------- the report
#: Outcomes of a file (:attr:`FileOutcome.status`).
PULLED, SKIPPED, NOT_READY, FAILED = "pulled", "skipped", "left", "failed"


@dataclass
class FileOutcome:
    """What a pull did with one file.

    Attributes:
        path: ``<bag>/<file>``.
        status: :data:`PULLED`, :data:`SKIPPED`, :data:`NOT_READY` or :data:`FAILED`.
        size: Its size there.
        fetched: Bytes fetched by this pull.
        resumed_from: Bytes that were already here in its ``.part`` (0: from the start).
        why: For a person (why it failed, was skipped or left).
    """

    path: str
    status: str
    size: int
    fetched: int = 0
    resumed_from: int = 0
    why: str = ""


@dataclass
class PullReport:
    """What a pull did.

    Attributes:
        host: The computer pulled from.
        into: The directory pulled into.
        files: Every file listed there, in order.
        seconds: How long the fetching took.
        silent: Why the host stopped answering ("" if it answered throughout).
    """

    host: str
    into: Path
    files: list[FileOutcome] = field(default_factory=list)
    seconds: float = 0.0
    silent: str = ""

    def having(self, status: str) -> list[FileOutcome]:
        """The files with that status."""
        return [f for f in self.files if f.status == status]

    @property
    def fetched(self) -> int:
        """Bytes fetched."""
        return sum(f.fetched for f in self.files)

    @property
    def rate(self) -> float:
        """Bytes per second fetched (0 if nothing was)."""
        return self.fetched / self.seconds if self.seconds > 0 else 0.0

    @property
    def ok(self) -> bool:
        """Whether the host answered and every finished file there is here, verified."""
        return not self.silent and not self.having(FAILED)

    def as_dict(self) -> dict[str, Any]:
        """The report as ``--json`` prints it."""
        return {
            "host": self.host,
            "into": str(self.into),
            "ok": self.ok,
            "silent": self.silent,
            "seconds": round(self.seconds, 3),
            "fetched_bytes": self.fetched,
            "kB_per_s": round(self.rate / 1000, 1),
            **{status: [asdict(f) for f in self.having(status)] for status in _STATUSES},
        }


_STATUSES = (PULLED, SKIPPED, NOT_READY, FAILED)


# ----------------------------------------------------------------------------- the I/O
class HostSilent(Exception):
    """The host gave no answer for the pull's patience."""


class Refused(Exception):
    """The host answered with an error (its message)."""


class Puller:
    """Pull one computer's bags into a directory here.

    Args:
        node: An open node of this computer (the caller closes it).
        host: The computer whose bags are pulled.
        into: The directory the bags go to (``<into>/<bag>/<file>``).
        chunk: Bytes per request (at most :data:`~msctl.recorder.shelf.MAX_READ`).
        window: Requests in flight at most.
        patience: Seconds with no answer before giving up on the host.
        limit: Bytes per second at most (0: as fast as the link goes).
        request_timeout: Seconds one request may take before it is asked again.
        progress: Called with ``(path, bytes just written)`` as the pull goes.
    """

    def __init__(
        self,
        node: Any,
        host: str,
        into: Path,
        *,
        chunk: int = CHUNK,
        window: int = WINDOW,
        patience: float = PATIENCE,
        limit: float = 0.0,
        request_timeout: float = REQUEST_TIMEOUT,
        progress: Callable[[str, int], None] | None = None,
    ) -> None:
        from components.supervision.wire import SupervisorClient as AgentClient
        from msctl.launcher.control import host_namespace

        if not 0 < chunk <= MAX_READ:
            raise ValueError(f"chunk must be 1 to {MAX_READ} bytes")
        self.host = host
        self.into = into
        self.chunk = chunk
        self.window = window
        self.patience = patience
        self.request_timeout = request_timeout
        self.progress = progress or (lambda path, size: None)
        self._budget = RateBudget(limit, chunk, time.monotonic())
        self._meter = RateMeter()
        self._limit = limit
        self._client = AgentClient(node, f"{host_namespace(host)}/request")

    def close(self) -> None:
        """Withdraw the client from the graph (idempotent)."""
        self._client.close()

    def __enter__(self) -> Puller:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ asking
    def _ask(self, verb: str, args: dict[str, Any], timeout: float) -> Any:
        """One request; its payload.

        Raises:
            ServiceTimeout: No answer (the caller asks again while patient).
            Refused: An error answer.
        """
        from components.comm.services import ServiceTimeout
        from msctl.launcher.control import encode_args

        try:
            response = self._client.ask(verb, encode_args(args), timeout=timeout)
        except ServiceTimeout:
            raise
        except Exception as exc:  # an error reply, or one that is not a response
            raise Refused(str(exc)) from exc
        if not response.success:
            raise Refused(response.message)
        return json.loads(response.payload) if response.payload else {}

    def _patiently(self, verb: str, args: dict[str, Any]) -> Any:
        """:meth:`_ask` again while the host does not answer, for :attr:`patience` seconds.

        Raises:
            HostSilent: If no answer came in that time.
            Refused: An error answer.
        """
        from components.comm.services import ServiceTimeout

        started = time.monotonic()
        while True:
            left = self.patience - (time.monotonic() - started)
            try:
                return self._ask(verb, args, max(min(self.request_timeout, left), 0.5))
            except ServiceTimeout as exc:
                if time.monotonic() - started + RETRY_PAUSE >= self.patience:
                    raise HostSilent(str(exc)) from None
                time.sleep(RETRY_PAUSE)  # a lapsed route answers "no server" at once

    def listing(self) -> list[RemoteFile]:
        """The host's bag files.

        Raises:
            HostSilent: If it did not answer within :attr:`patience`.
            PullError: If it refused, or its answer is not a listing.
        """
        try:
            answer = self._patiently("bags", {})
        except Refused as exc:
            raise PullError(
                f"{self.host} refused to list its bags: {exc}",
                hint=f"bring {self.host}'s msctl to this computer's version (`msctl update`)",
            ) from None
        return remote_files(answer, self.host)

    # ------------------------------------------------------------------ deciding
    def local_path(self, remote: RemoteFile) -> Path:
        """Where ``remote`` goes here."""
        return self.into / remote.bag / remote.name

    def plan(self, files: Iterable[RemoteFile]) -> list[Action]:
        """What to do with each file, from what is here (finished files are hashed)."""
        actions = []
        for remote in files:
            final = self.local_path(remote)
            part = final.with_name(final.name + PART_SUFFIX)
            served = remote.complete or remote.abandoned
            here = sha256_of(final) if served and final.is_file() else None
            part_size = part.stat().st_size if part.is_file() else None
            cut = final.with_name(CUT_MARK.format(final.name)).is_file()
            actions.append(decide(remote, here, part_size, cut))
        return actions

    # ------------------------------------------------------------------ fetching
    def pull(self, actions: list[Action]) -> PullReport:
        """Carry out ``actions``: fetch, verify, rename; everything else is reported.

        Stops fetching when the host stays silent for :attr:`patience` (the rest of the
        files are then reported failed, resumable).
        """
        report = PullReport(self.host, self.into)
        started = time.monotonic()
        with (
            _only_pull(self.into),
            ThreadPoolExecutor(self.window, thread_name_prefix="bag-pull") as pool,
        ):
            for action in actions:
                remote = action.file
                if report.silent and action.kind == FETCH:
                    report.files.append(
                        FileOutcome(
                            remote.path,
                            FAILED,
                            remote.size,
                            resumed_from=action.offset,
                            why=f"not pulled: {self.host} stopped answering",
                        )
                    )
                    continue
                if action.kind == SKIP:
                    report.files.append(
                        FileOutcome(remote.path, SKIPPED, remote.size, why=action.why)
                    )
                elif action.kind == LEFT:
                    report.files.append(
                        FileOutcome(remote.path, NOT_READY, remote.size, why=action.why)
                    )
                elif action.kind == CONFLICT:
                    report.files.append(
                        FileOutcome(
                            remote.path,
                            FAILED,
                            remote.size,
                            why=f"{action.why} ({self.local_path(remote)}), and it differs from "
                            f"{self.host}'s: move it away and pull again",
                        )
                    )
                else:
                    report.files.append(self._fetch(pool, action, report))
        report.seconds = time.monotonic() - started
        return report

    def _fetch(self, pool: ThreadPoolExecutor, action: Action, report: PullReport) -> FileOutcome:
        remote = action.file
        final = self.local_path(remote)
        part = final.with_name(final.name + PART_SUFFIX)
        outcome = FileOutcome(remote.path, PULLED, remote.size, resumed_from=action.offset)
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PullError(f"cannot make {final.parent}: {exc.strerror or exc}") from exc
        start = action.offset
        for attempt in (1, 2):  # a SHA-256 mismatch is fetched again from zero, once
            try:
                self._fetch_part(pool, remote, part, start, outcome)
            except HostSilent as exc:
                report.silent = f"{self.host} gave no answer for {self.patience:g} s ({exc})"
                have = part.stat().st_size if part.is_file() else 0
                outcome.status = FAILED
                outcome.why = (
                    f"{self.host} stopped answering: {have:,} of {remote.size:,} bytes are in "
                    f"{part}; `msctl bag pull {self.host}` again resumes there"
                )
                return outcome
            except (Refused, ShortRead) as exc:
                outcome.status, outcome.why = FAILED, f"{self.host}: {exc}"
                return outcome
            except OSError as exc:
                outcome.status = FAILED
                outcome.why = f"cannot write {part}: {exc.strerror or exc}"
                return outcome
            digest = sha256_of(part)
            if digest == remote.sha256:
                cut = final.with_name(CUT_MARK.format(final.name))
                if remote.abandoned:
                    cut.touch()
                os.replace(part, final)
                if not remote.abandoned:
                    cut.unlink(missing_ok=True)
                _sync_directory(final.parent)
                notes = [CUT_SHORT] if remote.abandoned else []
                if attempt == 2:
                    notes.append("SHA-256 matched at the second try")
                outcome.why = "; ".join(notes)
                return outcome
            part.unlink(missing_ok=True)
            outcome.why = f"SHA-256 {digest[:12]}... here, {remote.sha256[:12]}... on {self.host}"
            start = 0
        outcome.status = FAILED
        outcome.why = f"not verified twice: {outcome.why}"
        return outcome

    def _rate(self) -> float:
        """The link's rate as far as known: what came so far, or ``--limit`` if lower."""
        rate = self._meter.rate
        if self._limit > 0:
            return min(rate, self._limit) if rate else self._limit
        return rate

    def _in_flight_bound(self) -> int:
        """Bytes in flight at most: :data:`IN_FLIGHT_SECONDS` of the link at its rate, and
        two chunks until a rate is known (a first full window on a 256 kbit/s link would
        queue 16 s of answers). On a fast link the window bounds; on a 256 kbit/s one, one or
        two 64 KiB chunks (:data:`IN_FLIGHT_SECONDS`)."""
        rate = self._rate()
        return max(int(rate * IN_FLIGHT_SECONDS), self.chunk) if rate else 2 * self.chunk

    def _fetch_part(
        self,
        pool: ThreadPoolExecutor,
        remote: RemoteFile,
        part: Path,
        start: int,
        outcome: FileOutcome,
    ) -> None:
        """Fill ``part`` from byte ``start`` to the end, counting in ``outcome.fetched``.

        Raises:
            HostSilent: No answer for :attr:`patience` (what came is in ``part``).
            Refused, ShortRead: The host refused, or the file changed there.
        """
        from components.comm.services import ServiceTimeout

        window = ChunkWindow(remote.size, start, self.chunk, self.window)
        futures: dict[Future[Any], int] = {}
        # Seconds waited with a request out and no answer: the host's silence. Time the pull
        # spends pacing itself (--limit) with nothing asked is not; a request that failed at
        # once (a lapsed route) and was asked again does not end it.
        silent_for = 0.0
        tick = time.monotonic()
        mode = "r+b" if part.is_file() else "wb"
        with part.open(mode) as stream:
            stream.truncate(start)
            stream.seek(start)
            try:
                while not window.done:
                    for offset, size in window.asks(self._in_flight_bound()):
                        pause = self._budget.delay(size, time.monotonic())
                        if pause:
                            idle = not futures
                            time.sleep(pause)  # the pull's own rate limit (--limit)
                            if idle:
                                tick = time.monotonic()
                        args = {"path": remote.path, "offset": offset, "size": size}
                        bound = request_timeout(
                            window.bytes_in_flight,
                            self._rate(),
                            self.request_timeout,
                            self.patience,
                        )
                        self._meter.asked(time.monotonic())
                        futures[pool.submit(self._ask, "bag_read", args, bound)] = offset
                    done, _ = wait(futures, timeout=1.0, return_when=FIRST_COMPLETED)
                    answered = failed = False
                    for future in done:
                        offset = futures.pop(future)
                        try:
                            answer = future.result()
                        except ServiceTimeout:
                            window.failed(offset)
                            failed = True
                            continue
                        data = _chunk_data(answer, remote, offset)
                        ready = window.arrived(offset, data)
                        answered = True
                        self._meter.answered(len(data), time.monotonic())
                        if ready:
                            stream.write(ready)
                            stream.flush()
                            outcome.fetched += len(ready)
                            self.progress(remote.path, len(ready))
                    now = time.monotonic()
                    silent_for = 0.0 if answered else silent_for + (now - tick)
                    tick = now
                    if silent_for > self.patience:
                        raise HostSilent(f"no chunk of {remote.path} came for {silent_for:.0f} s")
                    if failed:
                        time.sleep(RETRY_PAUSE)  # a lapsed route answers "no server" at once
                os.fsync(stream.fileno())
            finally:
                for future in futures:
                    future.cancel()


def _chunk_data(answer: Any, remote: RemoteFile, offset: int) -> bytes:
    """The bytes of a ``bag_read`` answer.

    Raises:
        Refused: If it is not an answer for that file and offset.
    """
    if not isinstance(answer, dict) or answer.get("path") != remote.path:
        raise Refused(f"the answer for {remote.path} at byte {offset:,} is not one")
    if answer.get("offset") != offset or answer.get("file_size") != remote.size:
        raise ShortRead(f"{remote.path} changed there while it was pulled")
    try:
        return base64.b64decode(answer.get("data", ""), validate=True)
    except (binascii.Error, TypeError, ValueError):
        raise Refused(f"the answer for {remote.path} at byte {offset:,} is not base64") from None


@contextlib.contextmanager
def _only_pull(into: Path) -> Iterator[None]:
    """Hold ``<into>/.pull.lock`` while pulling: two pulls into one directory would write the
    same ``.part`` files.

    Raises:
        PullError: If another pull holds it, or the directory cannot be made.
    """
    import fcntl

    try:
        into.mkdir(parents=True, exist_ok=True)
        handle = (into / ".pull.lock").open("a+")
    except OSError as exc:
        raise PullError(f"cannot pull into {into}: {exc.strerror or exc}") from exc
    try:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise PullError(
                f"another `msctl bag pull` is writing into {into}",
                hint="let it finish (or stop it), then pull again: it resumes",
            ) from None
        yield
    finally:
        handle.close()


def _sync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable (a power cut keeps the verified name)."""
    try:
        handle = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(handle)
    except OSError:
        pass
    finally:
        os.close(handle)
