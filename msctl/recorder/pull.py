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

The pure parts (:func:`~msctl.recorder.pull_plan.decide`,
:class:`~msctl.recorder.pull_window.ChunkWindow`, :class:`~msctl.recorder.pull_window.RateBudget`)
take plain values and are tested with plain calls; :class:`Puller` does the I/O.
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
from typing import Any

from msctl.recorder.pull_plan import (
    CONFLICT,
    CUT_SHORT,
    FETCH,
    LEFT,
    SKIP,
    Action,
    PullError,
    RemoteFile,
    decide,
    remote_files,
)
from msctl.recorder.pull_window import (
    CHUNK,
    WINDOW,
    ChunkWindow,
    RateBudget,
    RateMeter,
    ShortRead,
    request_timeout,
)
from msctl.recorder.shelf import MAX_READ, sha256_of

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
    from components.supervision.protocol import AnswerError, bag_read_answer

    try:
        read = bag_read_answer(answer)
    except AnswerError:
        read = None
    if read is None or read.path != remote.path:
        raise Refused(f"the answer for {remote.path} at byte {offset:,} is not one")
    if read.offset != offset or read.file_size != remote.size:
        raise ShortRead(f"{remote.path} changed there while it was pulled")
    try:
        return base64.b64decode(read.data, validate=True)
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
