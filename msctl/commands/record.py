"""``msctl record``: capture the data plane into a rosbag2 (MCAP) bag, as ``ros2 bag record``.

Topics are discovered continuously (a topic that appears later is recorded from its first
message); latched topics get their cached samples. SIGINT and SIGTERM close the bag cleanly;
in a terminal, space pauses and resumes. A live line shows duration, messages and size; a
summary is printed at the end (``--json``: one JSON document on stdout).

Through a radio outage the recording goes on and resumes by itself: each interruption of a
topic is said on stderr when it starts and when it ends, listed in the summary and written
into the bag's metadata (``custom_data``: ``msctl.gaps``, ``msctl.lost``). A recording that
ended while topics it had been receiving were silent exits 3 naming them: it never passes
for a complete one.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import typer

from msctl.errors import InputError

COMMAND_SETTINGS = {"help": "Record topics into a rosbag2 (MCAP) bag directory."}

_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kKmMgGtT]i?[bB]?|[bB])?\s*$")
_UNITS = {"": 1, "b": 1, "k": 1e3, "m": 1e6, "g": 1e9, "t": 1e12}
#: Interruptions listed in the summary (all of them are in the bag's metadata).
_GAPS_SHOWN = 10


def parse_size(text: str) -> int:
    """Bytes from ``1000``, ``100M``, ``1.5G``, ``64KiB`` (powers of 1024 with ``i``).

    Raises:
        InputError: If the text is not a size.
    """
    match = _SIZE.match(text)
    if not match:
        raise InputError(f"--max-bag-size {text!r} is not a size; give bytes, or e.g. 100M, 2G")
    number, unit = float(match.group(1)), (match.group(2) or "").lower()
    factor = _UNITS[unit[:1]]
    if "i" in unit:
        factor = 1024 ** "bkmgt".index(unit[0])
    return int(number * factor)


def command(
    topics: list[str] = typer.Argument(None, help="Topics to record (with --all: as well)."),
    all_topics: bool = typer.Option(False, "--all", "-a", help="Record every topic."),
    regex: str = typer.Option("", "--regex", "-e", help="Record topics matching this regex."),
    exclude: str = typer.Option("", "--exclude", "-x", help="Leave out topics matching this."),
    output: Path = typer.Option(
        None, "--output", "-o", help="Bag directory to create (default rosbag2_<date-time>)."
    ),
    max_bag_size: str = typer.Option(
        "0", "--max-bag-size", "-b", help="Split files at this size (bytes, or 100M, 2G; 0: never)."
    ),
    max_bag_duration: float = typer.Option(
        0.0, "--max-bag-duration", "-d", help="Split files every this many seconds (0: never)."
    ),
    compression: str = typer.Option(
        "none", "--compression", help="Chunk compression inside the MCAP files: zstd or none."
    ),
    start_paused: bool = typer.Option(
        False, "--start-paused", help="Start paused (space or SIGUSR1 resumes); latched kept."
    ),
    json_output: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Record topics into a new bag until Ctrl-C (or SIGTERM)."""
    from components.data_archiver.core import TopicSelection
    from components.recording.metadata import default_bag_name
    from components.recording.recorder import Recorder
    from components.recording.thinned import radio_thinned
    from msctl.console import err
    from msctl.plane import connected

    size = parse_size(max_bag_size)
    if max_bag_duration < 0:
        raise InputError(f"--max-bag-duration cannot be negative ({max_bag_duration})")
    if compression not in ("zstd", "none"):
        raise InputError(f"--compression {compression!r}: use zstd or none")
    try:
        from components.comm.names import NameError_, qualify

        selection = TopicSelection(
            topics=tuple(qualify(t, "/") for t in topics or ()),
            all_topics=all_topics,
            regex=regex,
            exclude=exclude,
        )
    except (ValueError, NameError_) as exc:
        raise InputError(str(exc)) from None
    directory = output if output is not None else Path(default_bag_name())
    stop = threading.Event()
    with connected("record") as node, _Signals(stop) as signals:
        recorder = Recorder(
            node.session,
            directory,
            selection,
            domain=node.domain,
            node=node,
            compression=None if compression == "none" else compression,
            max_bytes=size,
            max_duration=max_bag_duration,
            start_paused=start_paused,
            on_stop=lambda _: stop.set(),
            thinned=radio_thinned(),
        )
        signals.on_toggle = lambda: recorder.resume() if recorder.paused else recorder.pause()
        recorder.start()
        err.print(f"recording into {directory}", highlight=False)
        notices = threading.Thread(
            target=_tell_gaps, args=(recorder, stop), name="record-gaps", daemon=True
        )
        notices.start()
        try:
            with _Keys(signals.on_toggle):
                _show_progress(recorder, stop)
        finally:
            status = recorder.stop()
            stop.set()
            notices.join()
    _summary(recorder, status, json_output)
    _refuse_silent_end(recorder)


class _Signals:
    """SIGINT/SIGTERM set ``stop``; SIGUSR1 toggles pause (for scripts without a terminal)."""

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self.on_toggle: Any = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _Signals:
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, lambda *_: self.stop.set())
        self._previous[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, self._toggle)
        return self

    def _toggle(self, *_: object) -> None:
        if self.on_toggle is not None:
            self.on_toggle()

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


class _Keys:
    """In a terminal, space calls ``toggle``; the terminal is restored on exit."""

    def __init__(self, toggle: Any) -> None:
        self._toggle = toggle
        self._saved: Any = None
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> _Keys:
        if not (sys.stdin.isatty() and sys.stderr.isatty()):
            return self
        import termios
        import tty

        fd = sys.stdin.fileno()
        try:
            self._saved = termios.tcgetattr(fd)
            tty.setcbreak(fd)
        except termios.error:
            return self
        self._thread = threading.Thread(target=self._read, args=(fd,), daemon=True)
        self._thread.start()
        return self

    def _read(self, fd: int) -> None:
        import select

        while not self._done.is_set():
            ready, _, _ = select.select([fd], [], [], 0.2)
            if ready and os.read(fd, 1) == b" ":
                self._toggle()

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()
        if self._saved is not None:
            import termios

            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self._saved)


def _show_progress(recorder: Any, stop: threading.Event) -> None:
    """A live status line on stderr until ``stop`` (only when stderr is a terminal)."""
    from rich.live import Live

    from msctl.console import err

    if not err.is_terminal:
        stop.wait()
        return
    started = time.monotonic()
    with Live(_line(recorder, started), console=err, refresh_per_second=4, transient=True) as live:
        while not stop.wait(0.25):
            live.update(_line(recorder, started))


def _line(recorder: Any, started: float) -> Any:
    from rich.text import Text

    status = recorder.status()
    state = "[paused]" if status.paused else "recording"
    elapsed = time.monotonic() - started
    text = (
        f"{state} {_clock(elapsed)}  {status.messages:,} msgs  {_megabytes(status.bytes)}  "
        f"{status.topics} topic(s)  {status.current_file}"
    )
    if status.dropped:
        text += f"  {status.dropped:,} dropped"
    hint = "  (space: resume)" if status.paused else "  (space: pause, Ctrl-C: stop)"
    return Text(text + hint, style="yellow" if status.paused else "green")


def _tell_gaps(recorder: Any, stop: threading.Event) -> None:
    """Say on stderr, as it happens, when a recorded topic stops arriving and when it comes
    back (with how long and how many samples it missed): in a terminal and in a log alike,
    since a recorder on a ground station is most often left running in one."""
    from msctl.console import err

    told = 0
    silent: set[str] = set()
    while not stop.wait(0.25):
        for gap in recorder.gaps()[told:]:
            err.print(f"[green]back:[/] {gap.describe()}", highlight=False)
            silent.discard(gap.topic)
        told = len(recorder.gaps())
        now = time.time_ns()
        for gap in recorder.silent():
            if gap.topic not in silent:
                silent.add(gap.topic)
                err.print(f"[yellow]not receiving:[/] {gap.describe(now)}", highlight=False)


def _refuse_silent_end(recorder: Any) -> None:
    """Exit non-zero when topics that were recorded had stopped arriving before the end:
    a recording that silently stopped receiving is not a normal one.

    Raises:
        NetworkError: Naming every such topic, since when, and where the bag says so.
    """
    from msctl.errors import NetworkError

    open_gaps = [g for g in recorder.gaps() if g.end_ns is None]
    if not open_gaps:
        return
    names = "; ".join(g.describe(time.time_ns()) for g in open_gaps)
    raise NetworkError(
        f"the recording stopped receiving {len(open_gaps)} topic(s) before it ended: {names}",
        hint=f"the bag holds everything up to then; its gaps are in "
        f"{recorder.directory}/metadata.yaml (custom_data msctl.gaps); if a link was down, "
        "check it (`msctl ps --all`, `msctl health`)",
    )


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}"


def _megabytes(size: int) -> str:
    return f"{size / 1e6:.1f} MB"


def _summary(recorder: Any, status: Any, json_output: bool) -> None:
    from msctl.console import err, print_json

    metadata = recorder.metadata
    document = {
        "directory": str(recorder.directory),
        "files": [f.path for f in metadata.files],
        "duration_s": metadata.duration / 1e9,
        "messages": metadata.message_count,
        "bytes": status.bytes,
        "topics": {t.name: t.message_count for t in metadata.topics},
        "dropped": status.dropped,
        "lost_upstream": status.lost,
        "unknown_types": list(status.unknown_types),
        "gaps": [g.as_dict() for g in recorder.gaps()],
        "thinned": recorder.thinned(),
    }
    if json_output:
        print_json(document)
        return
    err.print(
        f"bag {recorder.directory}: {metadata.message_count:,} messages on "
        f"{len(metadata.topics)} topic(s), {metadata.duration / 1e9:.1f} s, "
        f"{_megabytes(status.bytes)} in {len(metadata.files)} file(s)",
        highlight=False,
    )
    if status.dropped:
        err.print(
            f"[yellow]{status.dropped:,} message(s) dropped by the recorder[/] "
            "(its queue was full: the disk was too slow)"
        )
    if status.lost:
        err.print(f"[yellow]{status.lost:,} message(s) lost before reaching the recorder[/]")
    thinned = recorder.thinned()
    if thinned:
        # Their sequence numbers jump by design: no loss is counted for them.
        rates = sorted({f"{rate:g} Hz" for rate in thinned.values()})
        err.print(
            f"sampled on the radio to {', '.join(rates)} (the template's [network]): "
            f"{', '.join(thinned)}; their losses are not counted",
            highlight=False,
        )
    gaps = recorder.gaps()
    if gaps:
        err.print(f"[yellow]{len(gaps)} interruption(s)[/] (in metadata.yaml, msctl.gaps):")
        for gap in gaps[:_GAPS_SHOWN]:
            err.print(f"  {gap.describe(time.time_ns())}", highlight=False)
        if len(gaps) > _GAPS_SHOWN:
            err.print(f"  ... and {len(gaps) - _GAPS_SHOWN} more", highlight=False)
    if status.unknown_types:
        err.print(
            "[yellow]recorded without a definition (msctl does not know the type):[/] "
            + ", ".join(sorted(set(status.unknown_types))),
            highlight=False,
        )
