"""The live recorder: the data plane into a bag, without deserialising anything.

How it listens: every sample rmw_zenoh puts is on the key
``<domain>/<topic>/<pkg>::msg::dds_::<Name>_/RIHS01_<hash>``, so the key alone says the topic,
type and hash. The recorder declares one Zenoh *advanced* subscriber (``<domain>/**`` when
it takes topics not named in advance, ``<domain>/<topic>/*/*`` per named topic), with history
and late-publisher detection: a topic that appears later is recorded from its first sample
(no waiting for discovery), and every latched (transient-local) publisher's cached samples
are fetched, even from publishers that appear after the recording started.

The liveliness graph supplies the rest: each topic's publishers' QoS (stored as
``offered_qos_profiles``) and the recorder's own presence (a node, and a subscription
token per recorded topic, with the QoS rosbag2's rule gives it).

The sample callback (on a Zenoh thread) only stamps the receive time and appends
``(topic, time, payload, attachment)`` to a bounded queue; a writer thread drains it into a
:class:`~components.recording.writer.BagWriter`. A full queue drops the sample and counts it. Gaps
in the publishers' sequence numbers are counted as losses upstream.

The queue is a plain deque the writer thread polls (a short nap when it is empty), not a
queue that wakes the writer at every sample: at tens of thousands of samples a second, one
thread wake-up and GIL hand-over per sample cost more than the writing (bench/record.py:
the flood was recorded at half the rate a bare subscriber received it).
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from components.comm.qos import QoS
from components.data_archiver.core import (
    RecorderStatus,
    SequenceTracker,
    TopicSelection,
    subscription_qos,
)
from components.data_archiver.gaps import Gap, GapWatch
from components.recording.definitions import message_definition, qos_profiles
from components.recording.errors import BagWriteError
from components.recording.keys import TopicKey, parse_key, read_attachment
from components.recording.writer import BagWriter, TopicSpec

_log = logging.getLogger(__name__)


#: Messages the queue holds before it drops (about 2 s of 50 kHz).
DEFAULT_QUEUE_MESSAGES = 100_000
#: Bytes the queue holds before it drops.
DEFAULT_QUEUE_BYTES = 512 * 1024 * 1024
#: Seconds between the writer thread's housekeeping (flushes, QoS updates from the graph).
_HOUSEKEEPING = 0.2
#: Seconds the writer thread naps when the queue is empty: the most a sample waits before
#: it is written (at 50,000 a second, 500 queued: far below the bound), and 100 wake-ups a
#: second for an idle recorder.
_IDLE = 0.01
#: Seconds to wait for the network's answer about a new topic's publishers.
_QOS_QUERY = 0.5
_SEQ_STAMP = struct.Struct("<qq")
_CONTROL = -1
_IGNORED = -2


class Recorder:
    """Record topics of the data plane into a new bag. Start, then stop (or use ``with``).

    Args:
        session: An open Zenoh session (the caller closes it, after :meth:`stop`).
        directory: The bag directory to create (must not exist).
        selection: Which topics.
        domain: ROS domain id.
        node_name: The recorder's node name on the graph.
        namespace: Its namespace.
        compression: ``"zstd"`` or ``None``.
        max_bytes: Split files at this size (0: never).
        max_duration: Split files at this many seconds (0: never).
        start_paused: Start paused (latched samples are kept and written at resume).
        queue_messages: Queue bound in messages.
        queue_bytes: Queue bound in bytes.
        fsync: Fsync at each flush (benchmarks of raw throughput turn it off).
        node: A node of ``session`` to appear on the graph as (the caller closes it); by
            default the recorder makes its own (``node_name`` in ``namespace``).
        on_stop: Called (from the writer thread) if the recording stops by itself (an error).

    Raises:
        BagError: If the directory cannot be a new bag (exists, no parent).
    """

    def __init__(
        self,
        session: Any,
        directory: Path,
        selection: TopicSelection,
        *,
        domain: int = 0,
        node_name: str = "",
        namespace: str = "/",
        compression: str | None = None,
        max_bytes: int = 0,
        max_duration: float = 0.0,
        start_paused: bool = False,
        queue_messages: int = DEFAULT_QUEUE_MESSAGES,
        queue_bytes: int = DEFAULT_QUEUE_BYTES,
        fsync: bool = True,
        node: Any = None,
        on_stop: Callable[[str], None] | None = None,
        thinned: Mapping[str, float] | None = None,
    ) -> None:
        self.session = session
        self.directory = Path(directory)
        self.selection = selection
        self.domain = domain
        self._node_name = node_name or f"msctl_record_{os.getpid()}"
        self._namespace = namespace
        self._writer = BagWriter(
            self.directory,
            compression=compression,
            max_bytes=max_bytes,
            max_duration=max_duration,
            fsync=fsync,
            custom_data=_who(node, self._node_name, namespace),
        )
        # Appends and pops of a deque are atomic: callbacks append, the writer pops.
        self._queue: deque[tuple[int, Any, Any, Any]] = deque()
        self._queue_messages = queue_messages
        self._queue_bytes = queue_bytes
        self._queued_bytes_in = 0  # written by the callbacks
        self._queued_bytes_out = 0  # written by the writer thread
        self._keys: dict[str, int] = {}
        self._keys_lock = threading.Lock()
        self._topic_keys: list[TopicKey] = []
        self._paused = start_paused
        self._held: dict[int, tuple[int, Any, Any, Any]] = {}
        self._latched: set[int] = set()
        self._dropped = 0
        self._received = 0
        self._sequences = SequenceTracker()
        # Topics a router samples on their way here (radio_thinned): their sequence numbers
        # jump by design, and those jumps are no losses.
        self._thinned = dict(thinned or {})
        # Written by the writer thread only; the others read the snapshots below.
        self._gaps = GapWatch()
        self._silent: list[Gap] = []
        self._gaps_written = 0
        self._final_gaps: list[Gap] | None = None
        self._unknown: list[str] = []
        self._tokens: list[Any] = []
        self._subscribers: list[Any] = []
        self._node: Any = node
        self._own_node = node is None
        self._graph: Any = None
        self._thread: threading.Thread | None = None
        self._accepting = False
        self._stopped = threading.Event()
        self._error = ""
        self._on_stop = on_stop
        self._closed = False
        self._first_time = 0
        self._last_time = 0

    # ------------------------------------------------------------------------ lifecycle
    def start(self) -> Recorder:
        """Join the graph, subscribe and start the writer thread."""
        import zenoh.ext

        from components.comm.graph import Graph
        from components.comm.names import key_name
        from components.comm.node import Node

        if self._node is None:
            self._node = Node(self.session, self._node_name, self._namespace, domain=self.domain)
        self._graph = Graph(self.session, self.domain)
        self._thread = threading.Thread(target=self._write_loop, name="bag-writer", daemon=True)
        self._thread.start()
        self._accepting = True
        if self.selection.wildcard:
            keys = [f"{self.domain}/**"]
        else:
            keys = [f"{self.domain}/{key_name(t)}/*/*" for t in self.selection.topics]
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True)
        for key in keys:
            self._subscribers.append(
                zenoh.ext.declare_advanced_subscriber(
                    self.session, key, self._on_sample, history=history
                )
            )
        return self

    def pause(self) -> None:
        """Stop writing samples (latched topics keep their latest, written at resume)."""
        self._paused = True

    def resume(self) -> None:
        """Write samples again, starting with the latched ones held while paused."""
        if not self._paused:
            return
        held, self._held = self._held, {}
        # The writer thread decides which held samples are latched (it knows the topics' QoS
        # best), before any sample that arrives after the resume.
        self._queue.append((_CONTROL, self._write_held, held, None))
        self._paused = False

    @property
    def held(self) -> int:
        """Samples held while paused (the latest of each topic)."""
        return len(self._held)

    @property
    def paused(self) -> bool:
        """Whether recording is paused."""
        return self._paused

    def stop(self) -> RecorderStatus:
        """Stop listening, write what is queued, close the bag (idempotent).

        Raises:
            BagWriteError: If the bag could not be finished (what was written is kept).
        """
        if not self._closed:
            self._closed = True
            self._accepting = False
            for subscriber in self._subscribers:
                try:
                    subscriber.undeclare()
                except Exception as exc:  # the session may be closed already
                    _log.debug("recorder: subscriber not undeclared: %s", exc)
            self._subscribers.clear()
            if self._thread is not None:
                self._queue.append((_CONTROL, None, None, None))
                self._thread.join()
            else:
                self._finish()
            for token in self._tokens:
                try:
                    token.undeclare()
                except Exception as exc:  # the session may be closed already
                    _log.debug("recorder: token not undeclared: %s", exc)
            self._tokens.clear()
            if self._graph is not None:
                self._graph.close()
            if self._node is not None and self._own_node:
                self._node.close()
        if self._error:
            raise BagWriteError(self._error)
        return self.status()

    def sync(self, timeout: float = 10.0) -> bool:
        """Write out and flush everything queued so far; returns whether it was done within
        ``timeout`` (then a reader of the bag's files sees every message received before)."""
        if self._thread is None or not self._thread.is_alive():
            return False
        done = threading.Event()
        self._queue.append((_CONTROL, lambda *_: (self._writer.flush(), done.set()), None, None))
        return done.wait(timeout)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the recording stops by itself (an error) or ``timeout``; returns
        whether it stopped."""
        return self._stopped.wait(timeout)

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------------ status
    def status(self) -> RecorderStatus:
        """A snapshot of the recording (safe from any thread)."""
        writer = self._writer
        current = writer.current_file
        first, last = self._first_time, self._last_time
        return RecorderStatus(
            directory=str(self.directory),
            current_file=current.name if current else "",
            files=writer.file_count,
            topics=len(writer.topics),
            messages=writer.message_count,
            bytes=writer.bytes_written,
            dropped=self._dropped,
            lost=self._sequences.total,
            unknown_types=tuple(self._unknown),
            duration=(last - first) / 1e9 if first else 0.0,
            paused=self._paused,
            error=self._error,
            gaps=len(self._gaps.gaps),
            silent=tuple(g.topic for g in self._silent),
        )

    @property
    def topics(self) -> list[TopicSpec]:
        """The topics recorded so far."""
        return self._writer.topics

    @property
    def metadata(self) -> Any:
        """The bag's metadata as of now."""
        return self._writer.metadata()

    def silent(self) -> list[Gap]:
        """Topics that were flowing and are silent now past their limit (as of the writer
        thread's last look, at most 0.2 s ago): the recording is not receiving them."""
        return list(self._silent)

    def gaps(self) -> list[Gap]:
        """Every interruption so far; after :meth:`stop`, with the ones still open at the
        end (``end_ns`` ``None``: the topic never came back)."""
        final = self._final_gaps
        return list(final if final is not None else self._gaps.gaps)

    # ------------------------------------------------------------------------ hot path
    def _on_sample(self, sample: Any) -> None:
        now = time.time_ns()
        if not self._accepting:
            return
        key = str(sample.key_expr)
        topic_id = self._keys.get(key)
        if topic_id is None:
            topic_id = self._new_key(key)
        if topic_id < 0:
            return
        payload = sample.payload.to_bytes()
        attachment = sample.attachment
        item = (topic_id, now, payload, None if attachment is None else attachment.to_bytes())
        if self._paused:
            self._held[topic_id] = item
            return
        if (
            len(self._queue) >= self._queue_messages
            or self._queued_bytes_in - self._queued_bytes_out >= self._queue_bytes
        ):
            self._dropped += 1
            return
        self._queued_bytes_in += len(payload)
        self._queue.append(item)

    def _new_key(self, key: str) -> int:
        with self._keys_lock:
            known = self._keys.get(key)
            if known is not None:
                return known
            parsed = parse_key(key, self.domain)
            if parsed is None or not self.selection.matches(parsed.topic):
                self._keys[key] = _IGNORED
                return _IGNORED
            topic_id = len(self._topic_keys)
            self._topic_keys.append(parsed)
            # The topic is added by the writer thread, before this first sample.
            self._queue.append((_CONTROL, self._add_topic, topic_id, parsed))
            self._keys[key] = topic_id
            return topic_id

    # ------------------------------------------------------------------------ writer thread
    def _write_loop(self) -> None:
        # The hot loop: locals only (a slow stream must still be flushed every second, so
        # the clock is read for every message; it costs ~50 ns).
        pop = self._queue.popleft
        write = self._writer.write
        count = self._sequences.count
        watch = self._gaps.sample
        unpack = _SEQ_STAMP.unpack_from
        monotonic = time.monotonic
        sleep = time.sleep
        next_housekeeping = monotonic() + _HOUSEKEEPING
        try:
            while True:
                try:
                    item = pop()
                except IndexError:
                    if monotonic() >= next_housekeeping:
                        self._housekeeping()
                        next_housekeeping = monotonic() + _HOUSEKEEPING
                    sleep(_IDLE)
                    continue
                topic_id, log_time, payload, attachment = item
                if topic_id == _CONTROL:
                    if log_time is None:
                        break
                    log_time(payload, attachment)
                    continue
                self._queued_bytes_out += len(payload)
                sequence = publish_time = 0
                missing: int | None = None
                if attachment is not None:
                    if len(attachment) == 33:
                        sequence, publish_time = unpack(attachment)
                        missing = count(topic_id, attachment[17:33], sequence)
                    else:
                        sequence, publish_time, missing = read_attachment(
                            attachment, topic_id, self._sequences
                        )
                if not self._first_time:
                    self._first_time = log_time
                self._last_time = log_time
                watch(topic_id, log_time, missing)
                write(topic_id, log_time, payload, publish_time, sequence)
                if monotonic() >= next_housekeeping:
                    self._housekeeping()
                    next_housekeeping = monotonic() + _HOUSEKEEPING
            self._finish()
        except BagWriteError as exc:
            self._fail(str(exc))
        except Exception as exc:  # never leave the bag without saying why
            self._fail(f"the recorder's writer failed: {type(exc).__name__}: {exc}")

    def _write(self, item: tuple[int, Any, Any, Any]) -> None:
        topic_id, log_time, payload, attachment = item
        sequence = publish_time = 0
        missing: int | None = None
        if attachment is not None:
            if len(attachment) == 33:
                sequence, publish_time = _SEQ_STAMP.unpack_from(attachment)
                missing = self._sequences.count(topic_id, attachment[17:33], sequence)
            else:
                sequence, publish_time, missing = read_attachment(
                    attachment, topic_id, self._sequences
                )
        if not self._first_time:
            self._first_time = log_time
        self._last_time = log_time
        self._gaps.sample(topic_id, log_time, missing)
        self._writer.write(topic_id, log_time, payload, publish_time, sequence)

    def _write_held(self, held: dict[int, tuple[int, Any, Any, Any]], _: object) -> None:
        for topic_id, item in sorted(held.items()):
            if topic_id in self._latched:
                self._write(item)

    def _housekeeping(self) -> None:
        self._watch_links()
        self._writer.tick()

    def _watch_links(self) -> None:
        """Tell the gap watch which topics still have a reachable publisher (the graph's
        view: a radio link that drops takes its computer's tokens away after the lease),
        take a snapshot of the topics silent now, and put new gaps into the metadata."""
        from components.comm.liveliness import EntityKind

        gaps = self._gaps
        if self._paused:
            gaps.forget()
            self._silent = []
            return
        if self._graph is not None and self._topic_keys:
            offered = {e.topic for e in self._graph.entities() if e.kind is EntityKind.PUBLISHER}
            for topic_id, parsed in enumerate(self._topic_keys):
                gaps.publishers(topic_id, parsed.topic in offered)
        self._silent = gaps.silent(time.time_ns())
        if len(gaps.gaps) != self._gaps_written:
            self._gaps_written = len(gaps.gaps)
            self._annotate()

    def _annotate(self, end_ns: int | None = None) -> None:
        """The gaps (and the ones still open at ``end_ns``) into ``metadata.yaml``'s
        ``custom_data``, where any rosbag2 reader finds them."""
        import json

        gaps = list(self._gaps.gaps)
        if end_ns is not None:
            gaps += self._gaps.silent(end_ns)
        lost = {
            self._topic_keys[topic_id].topic: n
            for topic_id, n in sorted(self._sequences.lost.items())
            if topic_id < len(self._topic_keys)
        }
        self._writer.annotate(
            {
                "msctl.gaps": json.dumps([g.as_dict() for g in gaps], separators=(",", ":")),
                "msctl.lost": json.dumps(lost, separators=(",", ":")),
                "msctl.thinned": json.dumps(self.thinned(), separators=(",", ":")),
            }
        )

    def thinned(self) -> dict[str, float]:
        """Topic -> rate of the recorded topics a router sampled on their way here (their
        losses are not counted: their sequence numbers jump by design)."""
        return {
            self._topic_keys[topic_id].topic: self._thinned[self._topic_keys[topic_id].topic]
            for topic_id in sorted(self._sequences.thinned)
            if topic_id < len(self._topic_keys)
        }

    def _add_topic(self, topic_id: int, parsed: TopicKey) -> None:
        offered = self._offered(parsed)
        self._gaps.add_topic(topic_id, parsed.topic)
        if parsed.topic in self._thinned:
            self._sequences.thinned.add(topic_id)
        definition = message_definition(parsed.type)
        if definition is None:
            self._unknown.append(parsed.type)
        added = self._writer.add_topic(
            TopicSpec(
                parsed.topic,
                parsed.type,
                parsed.type_hash,
                tuple(qos_profiles(offered)),
                definition,
            )
        )
        if added != topic_id:
            raise AssertionError(f"topic {parsed.topic} got id {added}, expected {topic_id}")
        if offered and all(q.latched for q in offered):
            self._latched.add(topic_id)
        self._declare_token(parsed, subscription_qos(offered))

    def _offered(self, parsed: TopicKey) -> list[QoS]:
        """The QoS the topic's publishers offer, from their liveliness tokens.

        Asked of the network when the live graph has not heard of them yet (a sample can
        outrun the token's history): the QoS goes into the bag once, in the channel and in
        ``metadata.yaml`` alike, and readers (rosbags) insist that the two agree.
        """
        offered = self._matching(self._graph.entities(), parsed)
        if offered:
            return offered
        from components.comm.liveliness import PREFIX, Entity, EntityKind, TokenError, ask_tokens
        from components.comm.names import mangle

        selector = (
            f"{PREFIX}/{self.domain}/*/*/*/{EntityKind.PUBLISHER.value}/*/*/*/"
            f"{mangle(parsed.topic)}/*/*/*"
        )
        entities = []
        try:
            for key in ask_tokens(self.session, selector, _QOS_QUERY):
                try:
                    entities.append(Entity.parse(key))
                except TokenError:
                    continue
        except Exception:
            return []
        return self._matching(entities, parsed)

    @staticmethod
    def _matching(entities: list[Any], parsed: TopicKey) -> list[QoS]:
        from components.comm.liveliness import EntityKind

        offered = []
        for entity in entities:
            if (
                entity.kind is EntityKind.PUBLISHER
                and entity.topic == parsed.topic
                and entity.type_name == parsed.type
                and entity.qos is not None
            ):
                try:
                    offered.append(QoS.decode(entity.qos))
                except ValueError:
                    continue
        return offered

    def _declare_token(self, parsed: TopicKey, qos: QoS) -> None:
        from components.comm.liveliness import EntityKind

        entity = self._node.entity(
            EntityKind.SUBSCRIPTION, parsed.topic, parsed.type, parsed.type_hash, qos
        )
        try:
            self._tokens.append(self.session.liveliness().declare_token(entity.token()))
        except Exception:
            pass  # presence on the graph is a courtesy; the recording goes on

    def _finish(self) -> None:
        if self._held and not self._error:
            # Stopped while paused: the latched samples held are part of the recording.
            held, self._held = self._held, {}
            self._write_held(held, None)
        end = time.time_ns()
        self._final_gaps = list(self._gaps.gaps) + self._gaps.silent(end)
        self._annotate(end)
        self._writer.close()

    def _fail(self, message: str) -> None:
        self._accepting = False
        self._error = message
        self._writer.abandon()
        self._stopped.set()
        if self._on_stop is not None:
            try:
                self._on_stop(message)
            except Exception:  # the recording has stopped either way
                _log.warning("recorder: on_stop callback failed", exc_info=True)


def _who(node: Any, name: str, namespace: str) -> dict[str, str]:
    """``custom_data`` of a recording: which node on which computer made it."""
    import socket

    fqn = getattr(node, "fqn", None) or f"{namespace.rstrip('/')}/{name}"
    return {"recorded_by": f"msctl {fqn}", "host": socket.gethostname()}
