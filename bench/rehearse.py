"""Rehearsal benchmark: msctl on five emulated computers vs bare Zenoh through the same links.

Run ``sudo python bench/rehearse.py [--profiles lan,wifi,field-wifi] [--rounds N] [--json]``
(it needs what ``msctl rehearse`` needs: root, or unprivileged user namespaces; without
either it says so and exits 2). For each profile, in a temporary ``MSCTL_HOME`` of its own
(so it never meets another rehearsal):

Set-up. ``msctl rehearse up dragon --link PROFILE --no-up --detach``: five computers (robot
computers hl-limb-01/02 and hl-wheel-01/02, ground station ground1), a network namespace
each, every radio link through the userspace link emulator with that profile, secure
(mutual TLS between the routers, access control), an agent on each. ``msctl rehearse down``
at the end, also after an error or Ctrl-C. Every command below runs as a computer exactly as
``msctl rehearse exec HOST -- ...`` runs it (``exec_argv`` and the rehearsal's environment:
namespace, host name, ``MSCTL_HOME``, the operator's identity on ground1).

The baseline ("bare"), in the same namespaces, through the same emulated links, in the same
run: bare zenoh-python peers, peer to peer over plain TCP. One on each robot computer
listens at its radio address (``10.77.0.x:17447``) with a queryable and a publisher; one on
ground1 connects to the four of them. No router, no TLS, no access control, no msctl layer
(no node, CDR, liveliness or service); gossip and multicast scouting off, so only those four
sessions exist; msctl's own link settings (1 s lease, 4 keep-alives per lease, its connect
retry), so that the links, not a setting, are what the two sides share. A packet between
ground1 and a robot crosses ground1's link and the robot's, as msctl's router-to-router
traffic does.

Measured, msctl beside bare (in the order 1, 4, 3, 2, so that the estop's halts come last):

1. ``up --all -> healthy``: from starting ``msctl up --all`` on ground1 until it exits 0 (exit
   0 is its word that every host's agent reported every component running; any other exit
   is reported as failed, with its last line). Bare: a fresh ``python`` on ground1 that
   imports zenoh, opens a peer session to the four robots' bare peers and gets one reply
   from each one's queryable, start to exit ("reach every other computer from the ground",
   the floor of any command run there); twice before and twice after ``up --all``, median.
   When ``up --all`` fails, the failure is reported (with the hosts it names); when ``msctl
   ps --all`` then shows every component of every host running all the same, the rest is
   measured on that assembly; else, as its message tells an operator, ``msctl down --all``
   and ``up --all`` again (three tries at most; a later try's time is marked so).
   Beside it, msctl only: from up's exit until ``msctl health --once --json`` first shows
   every module OK (the computers' CPU and memory items aside: all five share this
   machine's cores, so the load is not theirs).
2. ``estop ack p50 / p99`` per module: ``--rounds`` rounds of ``msctl estop --json`` on
   ground1, each module's acknowledgement time as the command reports it (from its halt
   request to the joint manager's answer, through ground1's router, the radio and the
   robot's router), each round followed by ``msctl recover``. Bare, in each round: the
   ground peer queries the four robots' queryables at once, each reply's round trip (a warm
   session: the link's floor). A module that did not acknowledge (within the command's
   ``--timeout``, or at once: "no server") or a query not answered within 5 s counts as
   slower than any ("no answer", with how many answered); the estop's own messages are
   listed under the table. Beside it: the estop command's wall time, interpreter start
   included, against the bare "reach" process above.
3. ``data again after a 5 s outage``: hl-limb-01's link cut both ways (as ``msctl rehearse
   link hl-limb-01 --down 5``, through the emulator's control socket) and restored 5 s
   later; from the moment it is restored until ground1 receives ``/limb1/joint_states``
   again (a subscriber on ground1 on msctl's plane: its router, mutual TLS, the operator's
   identity), and until ``msctl health --watch --json`` on ground1 shows limb1 OK again
   (and when it left OK). Bare, in the same outage: the bare peer on hl-limb-01 publishing
   256 bytes at 100 Hz to ground1's bare peer, its first sample after the return.
4. ``bytes/s at rest`` on each computer's link, up (sent by that computer) and down (to it):
   the link emulator's counters (those of ``msctl rehearse status --json``: IPv4 bytes offered
   to the link) over 10 s of the healthy assembly with nothing asked of it, less the bare
   sessions' own bytes in the same window. Bare: those sessions' bytes (their sockets' TCP
   counters from ``ss``, payload plus 52 bytes of IPv4/TCP headers per segment).

field-wifi has random drop-outs (about one a minute, 1.5 s on average, seeded): they fall
where they fall, on both sides alike. Every wait is bounded: a figure that did not happen
is "not within N s", never a hang. ``--json`` prints exactly one JSON document on stdout
(progress on stderr). ``MSCTL_BENCH_KEEP=1`` keeps each profile's directory (the helpers'
output and the rehearsal's logs).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # runnable as `python bench/rehearse.py` from anywhere
    sys.path.insert(0, str(ROOT))

from bench._common import compiled_sources, percentile, print_table  # noqa: E402

TEMPLATE = "dragon"
DEFAULT_PROFILES = ("lan", "wifi", "field-wifi")
#: Rounds of estop + recover per profile: each is two msctl commands started on ground1
#: (seconds each on a loaded 2-core machine), so few by default; p99 of 5 is their worst.
DEFAULT_ROUNDS = 5
#: The computer the outage is on, and the topic watched from the ground for it.
OUTAGE_HOST = "hl-limb-01"
OUTAGE_TOPIC = "/limb1/joint_states"
OUTAGE_MODULE = "limb1"
OUTAGE_S = 5.0
#: Seconds of the idle window the link counters are read over.
REST_S = 10.0
#: Seconds left for the assembly to settle before the idle window.
SETTLE_S = 3.0
#: The bare peers' port on each robot's radio address (below the ephemeral range the
#: computers' own sessions take their ports from).
BARE_PORT = 17447
#: The bare peers' key space.
BARE_KEY = "bench/rehearse"
#: The bare publisher: a joint_states-sized payload at the motor interface's rate.
BARE_PAYLOAD = 256
BARE_RATE_HZ = 100.0
#: A gap longer than this between two samples of a stream starts a new "data" event.
DATA_GAP = 0.25
#: IPv4 (20) + TCP (20) + the timestamp option (12) bytes per segment, on top of its payload.
HEADER_BYTES = 52
#: Bounds (seconds).
REHEARSE_UP_WITHIN = 420.0
UP_ALL_WITHIN = 180.0
HEALTH_WITHIN = 120.0
HELPERS_WITHIN = 90.0
#: ``msctl up --all`` tries: after a failure, ``msctl down --all`` and again, as its message
#: tells an operator (the hosts it started refuse a second ``up``).
UP_ALL_TRIES = 3
ESTOP_TIMEOUT = 5.0
PING_TIMEOUT = 5.0
AGAIN_WITHIN = 60.0
COMMAND_WITHIN = 90.0
DOWN_WITHIN = 240.0


def log(message: str) -> None:
    """Progress, on stderr (stdout is the tables, or the JSON document with ``--json``)."""
    print(message, file=sys.stderr, flush=True)


# ============================================================================ pure parts
def parse_estop(stdout: str) -> dict[str, float | None]:
    """Module -> acknowledgement seconds (``None``: no acknowledgement) of one ``msctl
    estop`` run: its ``--json`` document, else its lines (``limb1  halted  20.2 ms``)."""
    try:
        document = json.loads(stdout)
    except ValueError:
        document = None
    if isinstance(document, dict) and isinstance(document.get("modules"), list):
        return {
            str(m["module"]): (
                float(m["seconds"]) if m.get("ok") and m.get("seconds") is not None else None
            )
            for m in document["modules"]
            if isinstance(m, dict) and "module" in m
        }
    found: dict[str, float | None] = {}
    for line in stdout.splitlines():
        match = re.match(r"^(\S+)\s+(?:(halted|recovered)\s+([\d.]+) ms|NO ACK)", line.strip())
        if match:
            found[match.group(1)] = None if match.group(3) is None else float(match.group(3)) / 1e3
    return found


def no_ack_messages(stdout: str) -> list[str]:
    """``module: message`` of each module an ``msctl estop --json`` run says did not
    acknowledge."""
    try:
        document = json.loads(stdout)
    except ValueError:
        return []
    if not isinstance(document, dict):
        return []
    return [
        f"{m.get('module')}: {m.get('message')}"
        for m in document.get("modules") or []
        if isinstance(m, dict) and not m.get("ok")
    ]


def tail_percentile(values: Sequence[float | None], q: float) -> float | None:
    """The q-th percentile of ``values`` by nearest rank, a missing value (``None``) counting
    as slower than any; ``None`` when that percentile is a missing one (or there are none)."""
    if not values:
        return None
    ranked = percentile([math.inf if v is None else v for v in values], q)
    return None if math.isinf(ranked) else ranked


_SS_FIELD = re.compile(r"\b(bytes_sent|bytes_received|segs_out|segs_in):(\d+)")


def socket_counters(ss_text: str) -> dict[str, tuple[int, int]]:
    """Socket (``"local peer"``) -> ``(sent, received)`` IPv4 bytes, of the TCP sockets
    ``ss -tinH`` lists: each one's payload counters plus :data:`HEADER_BYTES` per segment."""
    found: dict[str, tuple[int, int]] = {}
    socket = None
    for line in ss_text.splitlines():
        counters = {name: int(value) for name, value in _SS_FIELD.findall(line)}
        if counters and socket is not None:
            found[socket] = (
                counters.get("bytes_sent", 0) + HEADER_BYTES * counters.get("segs_out", 0),
                counters.get("bytes_received", 0) + HEADER_BYTES * counters.get("segs_in", 0),
            )
        elif line.strip() and not line[0].isspace():
            socket = " ".join(line.split()[-2:])
    return found


def bytes_between(readings: Sequence[Mapping[str, tuple[int, int]]]) -> tuple[int, int]:
    """``(sent, received)`` bytes that sockets carried from the first of successive readings
    (:func:`socket_counters`) to the last: a socket of the first reading from its counters
    there, one that appeared later from its start, one that went away (a session closed
    and opened again) up to its last reading."""
    if not readings:
        return 0, 0
    first, latest = readings[0], {}
    for reading in readings:
        latest.update(reading)
    sent = sum(s - first.get(k, (0, 0))[0] for k, (s, _) in latest.items())
    received = sum(r - first.get(k, (0, 0))[1] for k, (_, r) in latest.items())
    return sent, received


def link_rates(before: Mapping[str, Any], after: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Host -> ``{"up": B/s, "down": B/s}`` between two link-emulator status answers
    (``{"uptime_s": ..., "hosts": {name: {"up": {"bytes": ...}, "down": {...}}}}``)."""
    seconds = float(after["uptime_s"]) - float(before["uptime_s"])
    if seconds <= 0:
        raise ValueError(f"the two readings are {seconds:g} s apart")
    rates = {}
    for host, now in after["hosts"].items():
        then = before["hosts"].get(host)
        if then is None:
            continue
        rates[host] = {
            side: (now[side]["bytes"] - then[side]["bytes"]) / seconds for side in ("up", "down")
        }
    return rates


def health_all_ok(document: Mapping[str, Any]) -> bool:
    """Every item of every module OK in a ``msctl health --once --json`` document (a topic's
    rate may WARN on a loaded machine), the computers' own CPU and memory items aside: the
    five share this machine's cores, so its load is not theirs."""
    modules = document.get("modules") or []
    return bool(modules) and all(
        item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
        for row in modules
        for item in row["items"]
        if "/host/" not in item["name"]
    )


def first_after(events: Iterable[Mapping[str, Any]], since: float, **match: Any) -> float | None:
    """The time of the first event at or after ``since`` whose fields equal ``match``."""
    times = [
        event_time(e)
        for e in events
        if event_time(e) >= since and all(e.get(k) == v for k, v in match.items())
    ]
    return min(times, default=None)


def event_time(event: Mapping[str, Any]) -> float:
    """An event's own monotonic time (``t``), else when its line arrived (``_at``)."""
    return float(event.get("t", event.get("_at", 0.0)))


def _not_ok(levels: Mapping[str, str]) -> set[str]:
    """The items of ``levels`` (item -> level) that are not OK by :func:`health_all_ok`'s rule."""
    return {
        i
        for i, level in levels.items()
        if not (level == "OK" or (level == "WARN" and "/topics/" in i))
    }


def health_changes(
    alarms: Iterable[Mapping[str, Any]], module: str, cut: float, back: float
) -> tuple[float | None, float | None, list[str]]:
    """When ``module``'s health left OK and came back, from ``msctl health --watch --json``
    lines (their arrival times in ``_at``), by :func:`health_all_ok`'s rule: its items but
    the computer's own CPU and memory (``/host/``) and its aggregate line, a topic's rate
    allowed to WARN. An item is OK until a line says otherwise (the watch prints changes).

    Returns:
        Seconds from ``cut`` until an item went not OK that was OK before the cut (``None``:
        none did); seconds from ``back`` until every such item was OK again (``None``: not
        seen); and the items that were not OK already before the cut.
    """
    mine = sorted(
        (
            a
            for a in alarms
            if a.get("module") == module and a.get("item") != module and "/host/" not in a["item"]
        ),
        key=lambda a: a["_at"],
    )
    levels: dict[str, str] = {}
    for alarm in mine:
        if alarm["_at"] >= cut:
            break
        levels[alarm["item"]] = alarm["to"]
    before = _not_ok(levels)
    left = again = None
    for alarm in mine:
        if alarm["_at"] < cut:
            continue
        levels[alarm["item"]] = alarm["to"]
        worse = _not_ok(levels) - before
        if left is None and worse:
            left = alarm["_at"]
        elif left is not None and not worse and alarm["_at"] >= back:
            again = alarm["_at"]
            break
    return (
        None if left is None else left - cut,
        None if again is None else again - back,
        sorted(before),
    )


def unreachable_rows(stderr: str) -> list[str]:
    """The rows of ``msctl up --all``'s closing table that name a host it could not start
    (``hl-limb-02 | - | - | unreachable: ...``), as ``host: why``."""
    rows = []
    for line in stderr.splitlines():
        cells = [c.strip() for c in re.split(r"[│|]", line) if c.strip()]
        if len(cells) >= 4 and cells[1] == "-" and cells[2] == "-":
            rows.append(f"{cells[0]}: {' '.join(cells[3:])}")
    return rows


def every_host_running(document: Mapping[str, Any], hosts: Iterable[str]) -> bool:
    """Whether a ``msctl ps --all --json`` document lists components on every one of ``hosts``
    and every component it lists runs."""
    components = document.get("components") or []
    return {c.get("host") for c in components} >= set(hosts) and all(
        c.get("state") == "running" for c in components
    )


def up_all_text(run: ProfileRun) -> str:
    """``msctl up --all``'s cell: its time, or how each try failed."""
    tries = "; ".join(
        f"try {i}: {failure.split(':')[0]}" for i, failure in enumerate(run.up_all_failures, 1)
    )
    if run.up_all_healthy:
        text = fmt_s(run.up_all_s, UP_ALL_WITHIN)
        return f"{text} (try {run.up_all_tries}; {tries}; down --all after each)" if tries else text
    if run.assembly_up:
        return f"failed ({tries}), yet ps --all: all running"
    return f"failed ({tries})" if tries else "not tried"


def fmt_s(value: float | None, bound: float) -> str:
    """Seconds, or "not within" the bound."""
    return f"not within {bound:g} s" if value is None else f"{value:.2f} s"


def fmt_ms(value: float | None, bound: float) -> str:
    """Milliseconds, or "not within" the bound."""
    return f"not within {bound:g} s" if value is None else f"{value * 1e3:.1f} ms"


def ack_cell(values: Sequence[float | None]) -> str:
    """p50 / p99 of round trips, a missing answer slower than any ("no answer"); with how
    many answered when some did not."""
    cell = " / ".join(
        "no answer" if (v := tail_percentile(values, q)) is None else f"{v * 1e3:.1f} ms"
        for q in (50, 99)
    )
    answered = sum(v is not None for v in values)
    return cell if answered == len(values) else f"{cell} ({answered} of {len(values)} answered)"


def fmt_rate(value: float | None) -> str:
    """Bytes per second, short."""
    if value is None:
        return "-"
    return f"{value / 1e3:.1f} kB/s" if abs(value) >= 1e3 else f"{value:.0f} B/s"


def ratio(ours: float | None, bare: float | None) -> str:
    """``ours / bare`` as ``2.1x``, ``-`` when either is missing or bare is 0."""
    if ours is None or bare is None or bare <= 0:
        return "-"
    return f"{ours / bare:.2f}x"


# ============================================================================ helper roles
class _Emitter:
    """JSON lines on stdout, one per event, for the benchmark's own process."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def __call__(self, event: str, **fields: Any) -> None:
        line = json.dumps({"ev": event, "t": time.monotonic(), **fields})
        with self._lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()


class GapWatch:
    """Says when a stream's samples start arriving, and again after each gap longer than
    :data:`DATA_GAP` (a ``data`` event with the source and the gap)."""

    def __init__(self, emit: Callable[..., None]) -> None:
        self.emit = emit
        self.last: dict[str, float] = {}
        self._lock = threading.Lock()

    def arrived(self, source: str) -> None:
        """A sample of ``source`` arrived now."""
        now = time.monotonic()
        with self._lock:
            last = self.last.get(source)
            self.last[source] = now
        if last is None or now - last > DATA_GAP:
            self.emit("data", source=source, gap=None if last is None else now - last)


def bare_config(listen: Sequence[str], connect: Sequence[str]) -> Any:
    """A bare peer's Zenoh config: msctl's link settings (lease, keep-alives, connect
    retry) and nothing of msctl's plane; no scouting at all, so no other session forms."""
    from components.comm.session import SessionSettings

    settings = SessionSettings(
        mode="peer",
        connect=tuple(connect),
        listen=tuple(listen),
        multicast=False,
        extra={"scouting/gossip/enabled": False},
    )
    return settings.to_config()


def role_responder(host: str, listen: str) -> int:
    """A robot computer's bare peer: a queryable answering at once, and a publisher of
    :data:`BARE_PAYLOAD` bytes at :data:`BARE_RATE_HZ` while told ``publish`` (stdin)."""
    import zenoh

    emit = _Emitter()
    session = zenoh.open(bare_config([listen], []))
    key = f"{BARE_KEY}/ping/{host}"
    # Answered under its own key: the asker learns from it which computer answered.
    queryable = session.declare_queryable(key, lambda query: query.reply(key, b"ok"), complete=True)
    publisher = session.declare_publisher(f"{BARE_KEY}/data/{host}")
    publishing, stop = threading.Event(), threading.Event()

    def publish() -> None:
        payload, period = bytes(BARE_PAYLOAD), 1.0 / BARE_RATE_HZ
        due = time.monotonic()
        while not stop.is_set():
            if publishing.is_set():
                publisher.put(payload)
            due = max(due + period, time.monotonic() - period)
            stop.wait(max(0.0, due - time.monotonic()))

    thread = threading.Thread(target=publish, name="bare-publisher", daemon=True)
    thread.start()
    emit("ready", host=host)
    try:
        for line in sys.stdin:
            word = line.strip()
            if word == "publish":
                publishing.set()
            elif word == "quiet":
                publishing.clear()
            elif word == "quit":
                break
    finally:
        stop.set()
        thread.join(timeout=2.0)
        publisher.undeclare()
        queryable.undeclare()
        session.close()
    return 0


def _ping(session: Any, hosts: Sequence[str], timeout: float) -> dict[str, float | None]:
    """One query to every robot's queryable at once: each reply's round trip (s)."""
    import zenoh

    rtt: dict[str, float | None] = dict.fromkeys(hosts)
    sent = time.monotonic()
    replies = session.get(
        f"{BARE_KEY}/ping/*",
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )
    for reply in replies:
        if reply.ok is not None:
            host = str(reply.ok.key_expr).rsplit("/", 1)[1]
            if host in rtt and rtt[host] is None:
                rtt[host] = time.monotonic() - sent
    return rtt


def _reach(session: Any, hosts: Sequence[str], within: float) -> list[str]:
    """Query until every robot's queryable answered (its declaration has to arrive first);
    the hosts that did not within ``within`` s."""
    deadline = time.monotonic() + within
    missing = list(hosts)
    while missing and time.monotonic() < deadline:
        answered = _ping(session, missing, min(2.0, max(0.1, deadline - time.monotonic())))
        missing = [h for h in missing if answered[h] is None]
        if missing:
            time.sleep(0.01)
    return missing


def role_probe(hosts: Sequence[str], connect: Sequence[str]) -> int:
    """ground1's bare peer: connected to every robot's, subscribed to their data; ``ping``
    (stdin) queries them all at once and prints each round trip."""
    import zenoh

    emit = _Emitter()
    watch = GapWatch(emit)
    session = zenoh.open(bare_config(["tcp/127.0.0.1:0"], connect))
    subscriber = session.declare_subscriber(
        f"{BARE_KEY}/data/*", lambda sample: watch.arrived(str(sample.key_expr).rsplit("/", 1)[1])
    )
    try:
        emit("ready", missing=_reach(session, hosts, HELPERS_WITHIN))
        for line in sys.stdin:
            word = line.strip()
            if word.startswith("ping"):
                emit("ping", seq=word.partition(" ")[2], rtt=_ping(session, hosts, PING_TIMEOUT))
            elif word == "quit":
                break
    finally:
        subscriber.undeclare()
        session.close()
    return 0


def role_reach(hosts: Sequence[str], connect: Sequence[str]) -> int:
    """The floor of a command on ground1: import zenoh, open a peer session to every
    robot's bare peer, have one reply from each; exit 0 when every one answered."""
    import zenoh

    emit = _Emitter()
    session = zenoh.open(bare_config(["tcp/127.0.0.1:0"], connect))
    try:
        missing = _reach(session, hosts, 30.0)
    finally:
        session.close()
    emit("reached", missing=missing)
    return 1 if missing else 0


def role_watch(topic: str) -> int:
    """A subscriber on msctl's plane (this computer's router; with ``MSCTL_IDENTITY``, over
    mutual TLS as that operator): a ``data`` event when ``topic`` starts, and after gaps."""
    from components.comm.node import Node
    from components.comm.session import open_session
    from components.messages import JOINT_STATE

    emit = _Emitter()
    watch = GapWatch(emit)
    session = open_session()
    node = Node(session, "bench_rehearse_watch", "/bench")
    try:
        node.subscription(topic, JOINT_STATE, lambda _payload: watch.arrived(topic), raw=True)
        emit("ready")
        for line in sys.stdin:
            if line.strip() == "quit":
                break
    finally:
        node.close()
        session.close()
    return 0


# ============================================================================ the stage
class Helper:
    """A process run as one computer of the rehearsal: JSON lines out (each stamped with its
    arrival in ``_at``), words in."""

    def __init__(self, argv: list[str], env: Mapping[str, str], log_file: Path) -> None:
        self.events: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        log_file.parent.mkdir(parents=True, exist_ok=True)
        self.log_file = log_file
        self.out_file = log_file.with_suffix(".out")
        with open(log_file, "ab") as err:
            self.process = subprocess.Popen(
                argv,
                env=dict(env),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                start_new_session=True,
            )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            arrived = time.monotonic()
            try:
                event = json.loads(line)
            except ValueError:
                event = None
            with contextlib.suppress(OSError), open(self.out_file, "a") as kept:
                kept.write(line)
            with self._cond:
                if isinstance(event, dict):
                    event["_at"] = arrived
                    self.events.append(event)
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def tell(self, word: str) -> None:
        """One line on its stdin (ignored when it has exited)."""
        with contextlib.suppress(OSError, ValueError):
            assert self.process.stdin is not None
            self.process.stdin.write(word + "\n")
            self.process.stdin.flush()

    def wait_for(
        self, predicate: Callable[[dict[str, Any]], bool], timeout: float
    ) -> dict[str, Any] | None:
        """The first event so far or within ``timeout`` s that ``predicate`` accepts."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for event in self.events:
                    if predicate(event):
                        return event
                left = deadline - time.monotonic()
                if left <= 0 or (self.process.poll() is not None and not self._reader.is_alive()):
                    return None
                self._cond.wait(min(left, 0.5))

    def snapshot(self) -> list[dict[str, Any]]:
        """Its events so far."""
        with self._cond:
            return list(self.events)

    def tail(self, lines: int = 3) -> str:
        """The last lines of its stderr, for a problem's message."""
        try:
            text = self.log_file.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])

    def stop(self, sig: int = signal.SIGINT) -> None:
        """``quit`` and EOF, then ``sig``, then SIGKILL; bounded."""
        self.tell("quit")
        with contextlib.suppress(OSError, ValueError):
            assert self.process.stdin is not None
            self.process.stdin.close()
        for signum, wait in ((None, 3.0), (sig, 5.0), (signal.SIGKILL, 5.0)):
            if signum is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.process.pid, signum)
            try:
                self.process.wait(timeout=wait)
                break
            except subprocess.TimeoutExpired:
                continue
        self._reader.join(timeout=2.0)


class Stage:
    """One profile's rehearsal of ``dragon``, in its own ``MSCTL_HOME``.

    Args:
        home: The temporary ``MSCTL_HOME``.
        profile: The link profile of every computer's radio link.
    """

    def __init__(self, home: Path, profile: str) -> None:
        self.home = home
        self.profile = profile
        self.logs = home / "bench"
        # msctl as installed runs it: compiled modules read (see bench._common).
        self.base_env = {
            k: v
            for k, v in os.environ.items()
            if not k.startswith(("MSCTL_", "COLUMNS", "LINES")) and k != "PYTHONDONTWRITEBYTECODE"
        }
        # Wide enough that msctl's closing tables do not wrap a host's reason.
        self.base_env["COLUMNS"] = "400"
        self.env = {**self.base_env, "MSCTL_HOME": str(home)}
        self.rehearsal: Any = None
        self.helpers: list[Helper] = []

    # ------------------------------------------------------------------ the rehearsal
    def msctl(self, *args: str, timeout: float) -> subprocess.CompletedProcess[str] | None:
        """``msctl ARGS`` on this (the rehearsing) machine; ``None`` past ``timeout``."""
        try:
            return subprocess.run(
                [sys.executable, "-m", "msctl", *args],
                env=self.env,
                capture_output=True,
                text=True,
                timeout=timeout,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                check=False,
            )
        except subprocess.TimeoutExpired:
            return None

    def up(self) -> None:
        """``msctl rehearse up dragon --link PROFILE --no-up --detach``; then loaded.

        Raises:
            RuntimeError: If it did not come up (its last line said why).
        """
        from msctl.rehearse.rehearsal import Rehearsal

        done = self.msctl(
            "rehearse", "up", TEMPLATE, "--link", self.profile, "--no-up", "--detach",
            "--timeout", f"{REHEARSE_UP_WITHIN - 60:g}",
            timeout=REHEARSE_UP_WITHIN,
        )  # fmt: skip
        if done is None:
            raise RuntimeError(f"msctl rehearse up: not within {REHEARSE_UP_WITHIN:g} s")
        if done.returncode != 0:
            raise RuntimeError(f"msctl rehearse up failed ({done.returncode}): {_last(done)}")
        self.rehearsal = Rehearsal.load(self.home / "rehearse")

    def down(self) -> str | None:
        """Stop the helpers, then ``msctl rehearse down``; what went wrong, if anything."""
        for helper in self.helpers:
            helper.stop()
        self.helpers.clear()
        if os.environ.get("MSCTL_BENCH_KEEP") and (self.home / "rehearse" / "logs").is_dir():
            shutil.copytree(
                self.home / "rehearse" / "logs", self.logs / "rehearsal", dirs_exist_ok=True
            )
        done = self.msctl("rehearse", "down", timeout=DOWN_WITHIN)
        if done is None:
            return f"msctl rehearse down: not within {DOWN_WITHIN:g} s"
        if done.returncode != 0:
            return f"msctl rehearse down failed ({done.returncode}): {_last(done)}"
        return None

    @property
    def ground(self) -> Any:
        """The ground station the operator works from."""
        return self.rehearsal.ground

    @property
    def robots(self) -> list[Any]:
        """The robot computers."""
        return [c for c in self.rehearsal.computers if c.role == "robot"]

    # ------------------------------------------------------------------ as a computer
    def argv_on(self, computer: Any, argv: Sequence[str]) -> list[str]:
        """``argv`` as ``msctl rehearse exec`` runs it on ``computer``."""
        from msctl.rehearse.computers import exec_argv

        return exec_argv(computer, list(argv))

    def env_on(self, computer: Any) -> dict[str, str]:
        """The environment ``msctl rehearse exec`` gives a command on ``computer``."""
        return self.rehearsal.env(computer, base=self.base_env)

    def run_on(
        self, computer: Any, argv: Sequence[str], timeout: float
    ) -> tuple[subprocess.CompletedProcess[str] | None, float]:
        """Run ``argv`` on ``computer`` to its end: its result (``None`` past ``timeout``,
        then killed) and its wall time."""
        started = time.monotonic()
        try:
            done = subprocess.run(
                self.argv_on(computer, argv),
                env=self.env_on(computer),
                capture_output=True,
                text=True,
                timeout=timeout,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                check=False,
            )
        except subprocess.TimeoutExpired:
            done = None
        return done, time.monotonic() - started

    def msctl_on(
        self, computer: Any, *args: str, timeout: float = COMMAND_WITHIN
    ) -> tuple[subprocess.CompletedProcess[str] | None, float]:
        """``msctl ARGS`` on ``computer``."""
        return self.run_on(computer, [sys.executable, "-m", "msctl", *args], timeout)

    def helper(self, computer: Any, name: str, argv: Sequence[str]) -> Helper:
        """Start a helper on ``computer`` (stopped by :meth:`down`)."""
        helper = Helper(
            self.argv_on(computer, argv), self.env_on(computer), self.logs / f"{name}.log"
        )
        self.helpers.append(helper)
        return helper

    def role(self, computer: Any, name: str, *args: str) -> Helper:
        """This file run as a helper role on ``computer``."""
        return self.helper(computer, name, [sys.executable, str(Path(__file__)), *args])

    def link(self, request: dict[str, Any]) -> dict[str, Any]:
        """Ask the link emulator (what ``msctl rehearse link`` and ``status`` do)."""
        from msctl.rehearse.running import link_request

        return link_request(self.rehearsal, request)

    def bare_sockets(self) -> dict[str, dict[str, tuple[int, int]]]:
        """Computer -> its bare sessions' sockets and their bytes so far
        (:func:`socket_counters`)."""
        found = {}
        for computer in self.rehearsal.computers:
            ss = ["ss", "-tinH", "state", "established"]
            ss.append(f"( sport = :{BARE_PORT} or dport = :{BARE_PORT} )")
            done = subprocess.run(
                self.argv_on(computer, ss),
                env=self.env_on(computer),
                capture_output=True,
                text=True,
                timeout=20,
                check=False,
            )
            found[computer.name] = socket_counters(done.stdout)
        return found


def _last(done: subprocess.CompletedProcess[str]) -> str:
    lines = (done.stderr or done.stdout or "").strip().splitlines()
    return lines[-1].strip() if lines else "no output"


# ============================================================================ one profile
@dataclass
class ModuleAcks:
    """One module's estop acknowledgements (s; ``None``: none) and the bare round trips to its
    computer in the same rounds (``None``: no answer within :data:`PING_TIMEOUT`)."""

    module: str
    host: str
    acks_s: list[float | None] = field(default_factory=list)
    bare_s: list[float | None] = field(default_factory=list)


@dataclass
class ProfileRun:
    """What one profile's run measured (``None``: did not happen within its bound)."""

    profile: str
    rounds: int
    wall_s: float | None = None
    rehearse_up_s: float | None = None
    up_all_s: float | None = None
    up_all_healthy: bool = False
    assembly_up: bool = False
    up_all_tries: int = 0
    up_all_failures: list[str] = field(default_factory=list)
    health_ok_after_up_s: float | None = None
    reach_s: list[float] = field(default_factory=list)
    estop: list[ModuleAcks] = field(default_factory=list)
    estop_wall_s: list[float] = field(default_factory=list)
    estop_failures: list[str] = field(default_factory=list)
    recover_failures: int = 0
    outage_s: float = OUTAGE_S
    data_again_s: float | None = None
    bare_data_again_s: float | None = None
    health_before: list[str] = field(default_factory=list)
    health_left_ok_s: float | None = None
    health_ok_again_s: float | None = None
    rest_s: float | None = None
    rest: dict[str, dict[str, float]] = field(default_factory=dict)
    link_drops: dict[str, int] = field(default_factory=dict)
    link_packets: int = 0
    load: list[float] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    measured: list[str] = field(default_factory=list)

    @property
    def reach_median_s(self) -> float | None:
        """The median of the bare reach process's runs."""
        return statistics.median(self.reach_s) if self.reach_s else None


def run_profile(profile: str, rounds: int) -> ProfileRun:
    """Stand a rehearsal up with ``profile`` on every link, measure, take it down."""
    run = ProfileRun(profile, rounds)
    run.load.append(os.getloadavg()[0])
    begun = time.monotonic()
    home = Path(tempfile.mkdtemp(prefix=f"msctl_bench_rehearse_{profile}_"))
    stage = Stage(home, profile)
    try:
        log(f"{profile}: msctl rehearse up {TEMPLATE} --link {profile} --no-up ({home})")
        started = time.monotonic()
        stage.up()
        run.rehearse_up_s = time.monotonic() - started
        log(f"{profile}: five computers and their agents up in {run.rehearse_up_s:.1f} s")
        probe, responders = _start_bare(stage)
        _measure_up(stage, run)
        if not run.assembly_up:
            run.problems.append("the assembly never came up whole: nothing else measured")
            return run
        for name, step in (
            ("rest", lambda: _measure_rest(stage, run)),
            ("outage", lambda: _measure_outage(stage, run, probe, responders)),
            ("estop", lambda: _measure_estop(stage, run, probe)),
        ):
            try:
                step()
                run.measured.append(name)
            except Exception as exc:  # the other steps' figures still stand
                run.problems.append(f"{name}: {type(exc).__name__}: {exc}")
                log(f"{profile}: {name} not measured: {exc}")
    except Exception as exc:
        run.problems.append(f"{type(exc).__name__}: {exc}")
        log(f"{profile}: {exc}")
    finally:
        if stage.rehearsal is not None:
            with contextlib.suppress(Exception):  # the emulator may be what failed
                drops(run, stage.link({"op": "status"}))
        previous = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            log(f"{profile}: msctl rehearse down")
            problem = stage.down()
            if problem:
                run.problems.append(problem)
            if not os.environ.get("MSCTL_BENCH_KEEP"):
                shutil.rmtree(home, ignore_errors=True)
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
        run.load.append(os.getloadavg()[0])
        run.wall_s = time.monotonic() - begun
        log(f"{profile}: done in {run.wall_s:.0f} s")
    return run


def drops(run: ProfileRun, status: Mapping[str, Any]) -> None:
    """Every link's packets and drops by reason over the whole run, both directions summed,
    from a link-emulator status answer."""
    run.link_packets = 0
    run.link_drops = {}
    for host in status["hosts"].values():
        for side in ("up", "down"):
            run.link_packets += host[side]["packets"]
            for reason, count in host[side]["dropped"].items():
                run.link_drops[reason] = run.link_drops.get(reason, 0) + count


def _start_bare(stage: Stage) -> tuple[Helper, dict[str, Helper]]:
    """The bare peers: one on each robot computer, then ground1's, connected to them."""
    responders = {}
    for robot in stage.robots:
        argv = ["--role", "responder", "--host", robot.name]
        argv += ["--listen", f"tcp/{robot.address}:{BARE_PORT}"]
        responders[robot.name] = stage.role(robot, f"bare-{robot.name}", *argv)
    for name, responder in responders.items():
        if responder.wait_for(lambda e: e["ev"] == "ready", HELPERS_WITHIN) is None:
            raise RuntimeError(f"the bare peer on {name} did not start: {responder.tail()}")
    probe = stage.role(stage.ground, "bare-ground", "--role", "probe", *_bare_targets(stage))
    ready = probe.wait_for(lambda e: e["ev"] == "ready", HELPERS_WITHIN + 30)
    if ready is None or ready["missing"]:
        missing = ready["missing"] if ready else "all"
        raise RuntimeError(f"the ground's bare peer did not reach {missing}: {probe.tail()}")
    return probe, responders


def _bare_targets(stage: Stage) -> list[str]:
    return [
        "--hosts", ",".join(r.name for r in stage.robots),
        "--connect", ",".join(f"tcp/{r.address}:{BARE_PORT}" for r in stage.robots),
    ]  # fmt: skip


def _reach_once(stage: Stage, run: ProfileRun) -> None:
    done, seconds = stage.run_on(
        stage.ground,
        [sys.executable, str(Path(__file__)), "--role", "reach", *_bare_targets(stage)],
        timeout=60.0,
    )
    if done is not None and done.returncode == 0:
        run.reach_s.append(seconds)
    else:
        run.problems.append(
            "bare reach: " + ("not within 60 s" if done is None else f"failed: {_last(done)}")
        )


def _measure_up(stage: Stage, run: ProfileRun) -> None:
    """``msctl up --all`` on ground1, timed, between two pairs of bare reach runs; then
    until health shows every module OK."""
    from components.assembly import load_assembly

    hosts = set(load_assembly(stage.ground.home / "assembly").hosts)
    for _ in range(2):
        _reach_once(stage, run)
    ended = time.monotonic()
    for attempt in range(1, UP_ALL_TRIES + 1):
        log(f"{run.profile}: msctl up --all on {stage.ground.name}")
        done, seconds = stage.msctl_on(
            stage.ground, "up", "--all", "--timeout", f"{UP_ALL_WITHIN:g}",
            timeout=UP_ALL_WITHIN + 60,
        )  # fmt: skip
        ended = time.monotonic()
        run.up_all_tries = attempt
        if done is not None and done.returncode == 0:
            run.up_all_s, run.up_all_healthy, run.assembly_up = seconds, True, True
            log(f"{run.profile}: up --all healthy in {seconds:.2f} s")
            break
        failure = (
            f"not within {UP_ALL_WITHIN + 60:g} s"
            if done is None
            else f"exit {done.returncode} after {seconds:.1f} s: {_last(done)}"
            + "".join(f"; {row}" for row in unreachable_rows(done.stderr))
        )
        run.up_all_failures.append(failure)
        run.problems.append(f"msctl up --all, try {attempt}: {failure}")
        log(f"{run.profile}: up --all failed: {failure}")
        if _every_host_running(stage, hosts):
            run.assembly_up = True
            run.problems.append(
                f"  yet `msctl ps --all` then showed every component of {', '.join(sorted(hosts))} "
                "running: the rest was measured on it"
            )
            log(f"{run.profile}: ps --all shows every component running all the same")
            break
        if attempt < UP_ALL_TRIES:
            # What its message tells the operator: the hosts it started refuse a second `up`.
            log(f"{run.profile}: msctl down --all, then up --all again")
            stage.msctl_on(stage.ground, "down", "--all", timeout=COMMAND_WITHIN + 60)
    if not run.assembly_up:
        return
    while time.monotonic() - ended < HEALTH_WITHIN:
        done, _ = stage.msctl_on(stage.ground, "health", "--once", "--json", "--timeout", "10")
        try:
            healthy = done is not None and health_all_ok(json.loads(done.stdout))
        except (ValueError, KeyError, TypeError):
            healthy = False
        if healthy:
            run.health_ok_after_up_s = time.monotonic() - ended
            break
        time.sleep(1.0)
    log(f"{run.profile}: health all OK {fmt_s(run.health_ok_after_up_s, HEALTH_WITHIN)} after")
    for _ in range(2):
        _reach_once(stage, run)


def _every_host_running(stage: Stage, hosts: set[str]) -> bool:
    """``msctl ps --all --json`` on ground1 (up to three times: a host may be out of reach for
    a moment) shows every component of every host running."""
    for _ in range(3):
        done, _ = stage.msctl_on(stage.ground, "ps", "--all", "--json", "--timeout", "10")
        try:
            if done is not None and every_host_running(json.loads(done.stdout), hosts):
                return True
        except (ValueError, AttributeError):
            pass
        time.sleep(2.0)
    return False


def _measure_rest(stage: Stage, run: ProfileRun) -> None:
    """Every link's bytes over :data:`REST_S` of the idle assembly, the bare sessions' apart."""
    time.sleep(SETTLE_S)
    # The bare sockets are read every second: a session that closes and opens again (a lease
    # ended by a burst of losses) starts new counters, and the old ones go with it.
    readings = [stage.bare_sockets()]
    links_from = stage.link({"op": "status"})
    deadline = time.monotonic() + REST_S
    while (left := deadline - time.monotonic()) > 0:
        time.sleep(min(1.0, left))
        readings.append(stage.bare_sockets())
    links_to = stage.link({"op": "status"})
    readings.append(stage.bare_sockets())
    run.rest_s = float(links_to["uptime_s"]) - float(links_from["uptime_s"])
    for host, rates in link_rates(links_from, links_to).items():
        sent, received = bytes_between([r.get(host, {}) for r in readings])
        bare_up, bare_down = sent / run.rest_s, received / run.rest_s
        run.rest[host] = {
            "up": rates["up"] - bare_up,
            "down": rates["down"] - bare_down,
            "bare_up": bare_up,
            "bare_down": bare_down,
        }
    total = sum(r["up"] for r in run.rest.values())
    log(f"{run.profile}: at rest, every computer sent {fmt_rate(total)} in all")


def _measure_estop(stage: Stage, run: ProfileRun, probe: Helper) -> None:
    """``msctl estop --json`` and ``msctl recover`` on ground1, and a bare ping, per round."""
    from components.assembly import load_assembly

    assembly = load_assembly(stage.ground.home / "assembly")
    hosts = {m.slot: m.host for m in assembly.modules}
    run.estop = [ModuleAcks(module, host) for module, host in hosts.items()]
    by_module = {m.module: m for m in run.estop}
    for index in range(run.rounds):
        done, seconds = stage.msctl_on(
            stage.ground, "estop", "--json", "--timeout", f"{ESTOP_TIMEOUT:g}"
        )
        acks = parse_estop(done.stdout) if done is not None else {}
        if done is None:
            run.estop_failures.append(f"round {index + 1}: not within {COMMAND_WITHIN:g} s")
        else:
            run.estop_failures += [
                f"round {index + 1}: {message}" for message in no_ack_messages(done.stdout)
            ]
        if done is not None and acks:
            run.estop_wall_s.append(seconds)
        for module in run.estop:
            module.acks_s.append(acks.get(module.module))
        done, _ = stage.msctl_on(
            stage.ground, "recover", "--json", "--timeout", f"{ESTOP_TIMEOUT:g}"
        )
        if done is None or done.returncode != 0:
            run.recover_failures += 1
        probe.tell(f"ping {index}")
        pinged = probe.wait_for(
            lambda e, i=index: e["ev"] == "ping" and e["seq"] == str(i), PING_TIMEOUT + 10
        )
        rtt = pinged["rtt"] if pinged else {}
        for module in by_module.values():
            module.bare_s.append(rtt.get(module.host))
    for module in run.estop:
        log(
            f"{run.profile}: estop {module.module} p50 "
            f"{fmt_ms(tail_percentile(module.acks_s, 50), ESTOP_TIMEOUT)}, bare "
            f"{fmt_ms(tail_percentile(module.bare_s, 50), PING_TIMEOUT)}"
        )


def _measure_outage(
    stage: Stage, run: ProfileRun, probe: Helper, responders: dict[str, Helper]
) -> None:
    """hl-limb-01's link out for :data:`OUTAGE_S`; data and health again on ground1."""
    ground = stage.ground
    watcher = stage.role(ground, "watch", "--role", "watch", "--topic", OUTAGE_TOPIC)
    health = stage.helper(
        ground, "health-watch", [sys.executable, "-m", "msctl", "health", "--watch", "--json"]
    )
    responders[OUTAGE_HOST].tell("publish")
    try:
        flowing = time.monotonic()
        if watcher.wait_for(lambda e: e["ev"] == "data", HELPERS_WITHIN) is None:
            raise RuntimeError(f"no {OUTAGE_TOPIC} on {ground.name}: {watcher.tail()}")
        if probe.wait_for(lambda e: e["ev"] == "data" and e["_at"] >= flowing, 30) is None:
            raise RuntimeError(f"no bare data from {OUTAGE_HOST} on {ground.name}")
        # The watch prints level changes only (none when every item is OK): it is running
        # once it says what it watches, and connected a moment later.
        if not _wait(lambda: "watching" in health.tail(20), HELPERS_WITHIN):
            raise RuntimeError(f"msctl health --watch did not start: {health.tail()}")
        time.sleep(3.0)
        time.sleep(1.0)
        cut = time.monotonic()
        stage.link({"op": "down", "host": OUTAGE_HOST, "seconds": None})
        try:
            time.sleep(OUTAGE_S)
        finally:
            back = time.monotonic()
            stage.link({"op": "up", "host": OUTAGE_HOST})
        log(f"{run.profile}: {OUTAGE_HOST}'s link out {back - cut:.2f} s, back")

        def settled() -> bool:
            ours = first_after(watcher.snapshot(), back, ev="data")
            bare = first_after(probe.snapshot(), back, ev="data", source=OUTAGE_HOST)
            left, again, _ = health_changes(health.snapshot(), OUTAGE_MODULE, cut, back)
            return ours is not None and bare is not None and (left is None or again is not None)

        until = back + AGAIN_WITHIN
        while not settled() and time.monotonic() < until:
            time.sleep(0.1)
        if not any(e.get("to") for e in health.snapshot() if e["_at"] >= cut):
            time.sleep(2.0)  # a level change on its way (the watch evaluates every 0.2 s)
        ours = first_after(watcher.snapshot(), back, ev="data")
        bare = first_after(probe.snapshot(), back, ev="data", source=OUTAGE_HOST)
        run.data_again_s = None if ours is None else ours - back
        run.bare_data_again_s = None if bare is None else bare - back
        run.health_left_ok_s, run.health_ok_again_s, run.health_before = health_changes(
            health.snapshot(), OUTAGE_MODULE, cut, back
        )
        log(
            f"{run.profile}: data again {fmt_s(run.data_again_s, AGAIN_WITHIN)} "
            f"(bare {fmt_s(run.bare_data_again_s, AGAIN_WITHIN)}); {OUTAGE_MODULE} health "
            + _health_text(run)
        )
    finally:
        responders[OUTAGE_HOST].tell("quiet")
        for helper in (watcher, health):
            helper.stop()
            stage.helpers.remove(helper)


def _health_text(run: ProfileRun) -> str:
    before = run.health_before
    already = (
        f" (not OK before the cut already: {before[0]}"
        + (f" and {len(before) - 1} more" if len(before) > 1 else "")
        + ")"
        if before
        else ""
    )
    if run.health_left_ok_s is None:
        return "no item went not OK" + already
    return (
        f"not OK {run.health_left_ok_s:.2f} s after the cut, OK again "
        + fmt_s(run.health_ok_again_s, AGAIN_WITHIN)
        + " after the return"
        + already
    )


def _wait(condition: Callable[[], bool], within: float) -> bool:
    """Poll ``condition`` every 0.1 s until it holds (True) or ``within`` s pass."""
    deadline = time.monotonic() + within
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


# ============================================================================ the report
def profile_rows(run: ProfileRun) -> list[list[str]]:
    """The table of one profile: measure, msctl, bare, ratio."""
    rows: list[list[str]] = []
    reach = run.reach_median_s
    rows.append(
        [
            "up --all -> healthy",
            up_all_text(run),
            "-" if reach is None else f"{reach:.2f} s (reach every robot)",
            ratio(run.up_all_s, reach),
        ]
    )
    if run.assembly_up:
        rows.append(
            [
                "  then health --once all OK",
                fmt_s(run.health_ok_after_up_s, HEALTH_WITHIN),
                "-",
                "-",
            ]
        )
    for module in run.estop:
        ours = [tail_percentile(module.acks_s, q) for q in (50, 99)]
        bare = [tail_percentile(module.bare_s, q) for q in (50, 99)]
        rows.append(
            [
                f"estop ack {module.module} ({module.host}) p50 / p99",
                ack_cell(module.acks_s),
                ack_cell(module.bare_s),
                " / ".join(ratio(a, b) for a, b in zip(ours, bare, strict=True)),
            ]
        )
    if run.estop_wall_s:
        wall = statistics.median(run.estop_wall_s)
        rows.append(
            [
                "  estop command, start to exit (median)",
                f"{wall:.2f} s",
                "-" if reach is None else f"{reach:.2f} s (reach every robot)",
                ratio(wall, reach),
            ]
        )
    if "outage" in run.measured:
        rows.append(
            [
                f"data again after {run.outage_s:g} s out ({OUTAGE_HOST})",
                fmt_s(run.data_again_s, AGAIN_WITHIN),
                fmt_s(run.bare_data_again_s, AGAIN_WITHIN),
                ratio(run.data_again_s, run.bare_data_again_s),
            ]
        )
        rows.append([f"  {OUTAGE_MODULE} health", _health_text(run), "-", "-"])
    for host, rate in run.rest.items():
        ours, bare = rate["up"] + rate["down"], rate["bare_up"] + rate["bare_down"]
        rows.append(
            [
                f"at rest {host} up / down",
                f"{fmt_rate(rate['up'])} / {fmt_rate(rate['down'])}",
                f"{fmt_rate(rate['bare_up'])} / {fmt_rate(rate['bare_down'])}",
                ratio(ours, bare),
            ]
        )
    return rows


def print_report(runs: Sequence[ProfileRun]) -> None:
    """One table per profile, then what went wrong."""
    for run in runs:
        print_table(
            f"{run.profile}: msctl on a secure five-computer {TEMPLATE} rehearsal vs bare "
            f"zenoh-python peers through the same emulated links (stood up in "
            f"{fmt_s(run.rehearse_up_s, REHEARSE_UP_WITHIN)}; {run.rounds} estop rounds; "
            f"load {' -> '.join(f'{x:.1f}' for x in run.load)})",
            ["measure", "msctl", "bare zenoh", "ratio"],
            profile_rows(run),
        )
        if run.link_packets:
            print(
                f"  the links over the whole run: {run.link_packets} packets offered, dropped "
                + ", ".join(f"{n} by {reason}" for reason, n in sorted(run.link_drops.items()))
            )
        for problem in run.problems:
            print(f"  {run.profile}: {problem}")
        if run.estop_failures:
            asked = len(run.estop) * run.rounds
            print(
                f"  {run.profile}: estop: {len(run.estop_failures)} of {asked} halts not "
                f"acknowledged (all in --json), the first: {run.estop_failures[0]}"
            )


def document(runs: Sequence[ProfileRun]) -> dict[str, Any]:
    """The ``--json`` document."""
    profiles = []
    for run in runs:
        entry = asdict(run)
        entry["reach_median_s"] = run.reach_median_s
        entry["estop_summary"] = {
            m.module: {
                "host": m.host,
                "p50_s": tail_percentile(m.acks_s, 50),
                "p99_s": tail_percentile(m.acks_s, 99),
                "bare_p50_s": tail_percentile(m.bare_s, 50),
                "bare_p99_s": tail_percentile(m.bare_s, 99),
            }
            for m in run.estop
        }
        profiles.append(entry)
    return {
        "template": TEMPLATE,
        "cores": os.cpu_count(),
        "bounds_s": {
            "up_all": UP_ALL_WITHIN,
            "health": HEALTH_WITHIN,
            "estop_timeout": ESTOP_TIMEOUT,
            "ping_timeout": PING_TIMEOUT,
            "again": AGAIN_WITHIN,
        },
        "profiles": profiles,
    }


# ============================================================================ main
def _interrupted(*_: object) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark (or, with ``--role``, one of its helpers on a computer)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--profiles",
        default=",".join(DEFAULT_PROFILES),
        help="comma-separated link profiles (default: %(default)s)",
    )
    parser.add_argument(
        "--rounds",
        type=int,
        default=DEFAULT_ROUNDS,
        help="estop + recover rounds per profile (default: %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument(
        "--role", choices=["responder", "probe", "reach", "watch"], help=argparse.SUPPRESS
    )
    parser.add_argument("--host", help=argparse.SUPPRESS)
    parser.add_argument("--hosts", help=argparse.SUPPRESS)
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    parser.add_argument("--topic", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "responder":
        return role_responder(args.host, args.listen)
    if args.role in ("probe", "reach"):
        hosts, connect = args.hosts.split(","), args.connect.split(",")
        return (role_probe if args.role == "probe" else role_reach)(hosts, connect)
    if args.role == "watch":
        return role_watch(args.topic)

    profiles = [p.strip() for p in args.profiles.split(",") if p.strip()]
    if not profiles:
        parser.error("--profiles names no profile")
    if args.rounds < 1:
        parser.error("--rounds must be 1 or more")
    from msctl.rehearse.computers import privileges_problem
    from msctl.rehearse.profiles import load_profiles

    problem = privileges_problem()
    if problem is not None:
        print(
            f"error: bench/rehearse.py needs what msctl rehearse needs: {problem}", file=sys.stderr
        )
        return 2
    unknown = sorted(set(profiles) - set(load_profiles()))
    if unknown:
        parser.error(f"unknown profile {', '.join(unknown)} (known: {', '.join(load_profiles())})")
    signal.signal(signal.SIGTERM, _interrupted)  # cleaned up as after Ctrl-C
    log(f"rehearse benchmark on {os.cpu_count()} cores (load {os.getloadavg()[0]:.1f})")
    compiled_sources()
    runs: list[ProfileRun] = []
    try:
        for profile in profiles:
            runs.append(run_profile(profile, args.rounds))
    except KeyboardInterrupt:
        log("interrupted: every rehearsal made was taken down")
        return 130
    if args.json:
        print(json.dumps(document(runs), indent=2))
    else:
        print_report(runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
