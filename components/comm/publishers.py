"""The publisher tokens of a session's topics, followed by one liveliness subscriber.

Every subscription follows its topic's publisher tokens (to name a publisher of another type,
and to know who may send where senders are checked). One liveliness subscriber per
subscription cost a module process ten declarations and, through zenoh-python, ten Python
threads, each started (and waited for) as the component was bound: on a loaded two_dragons
start, 5-20 ms each. The subscriptions of one session share one subscriber per domain here;
each is told, in order, of its own topic's tokens, starting with those already alive.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from components.comm.liveliness import (
    ENDPOINT_FIELDS,
    PREFIX,
    TOPIC_FIELD,
    EntityKind,
    follow_tokens,
)
from components.errors import swallowed

#: ``(session zid, domain)`` -> its followed tokens, while a subscription of it listens.
_FOLLOWED: dict[tuple[str, int], PublisherTokens] = {}
_FOLLOWED_LOCK = threading.Lock()

#: What a listener is told: a token's key and whether it appeared (``False``: it vanished).
Listener = Callable[[str, bool], None]


class PublisherTokens:
    """The publisher tokens of one domain seen from one session (use :func:`listen`)."""

    def __init__(self, session: Any, domain: int) -> None:
        # Reentrant: a listener may open or close a subscription of the same session.
        self._lock = threading.RLock()
        self._alive: dict[str, dict[str, None]] = {}  # mangled topic -> keys, in order
        self._listeners: dict[str, list[Listener]] = {}
        self.users = 0
        self._subscriber = follow_tokens(
            session, f"{PREFIX}/{domain}/*/*/*/{EntityKind.PUBLISHER.value}/**", self._on_token
        )

    def _on_token(self, sample: Any) -> None:
        import zenoh

        key = str(sample.key_expr)
        parts = key.split("/")
        if len(parts) != ENDPOINT_FIELDS:
            return  # not a publisher token of rmw_zenoh's form (the graph counts those)
        topic = parts[TOPIC_FIELD]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            keys = self._alive.setdefault(topic, {})
            if alive:
                keys[key] = None
            else:
                keys.pop(key, None)
                if not keys:
                    del self._alive[topic]
            for listener in list(self._listeners.get(topic, ())):
                listener(key, alive)

    def add(self, topic: str, listener: Listener) -> None:
        """Tell ``listener`` of ``topic``'s tokens (mangled name): those alive now, at once,
        then every change."""
        with self._lock:
            self._listeners.setdefault(topic, []).append(listener)
            for key in list(self._alive.get(topic, ())):
                listener(key, True)

    def remove(self, topic: str, listener: Listener) -> None:
        """Stop telling ``listener`` (idempotent)."""
        with self._lock:
            listeners = self._listeners.get(topic, [])
            if listener in listeners:
                listeners.remove(listener)
            if not listeners:
                self._listeners.pop(topic, None)

    def close(self) -> None:
        """Undeclare the liveliness subscriber (the session may be closed already)."""
        try:
            self._subscriber.undeclare()
        except Exception as exc:
            swallowed("publishers: liveliness subscriber not undeclared", exc)


class Listening:
    """One listener of a topic's publisher tokens; :meth:`undeclare` ends it (idempotent), as
    undeclaring a liveliness subscriber of its own would."""

    def __init__(self, key: tuple[str, int], topic: str, listener: Listener) -> None:
        self._key, self._topic, self._listener = key, topic, listener
        self._done = False

    def undeclare(self) -> None:
        """Stop listening; the last listener of a session's domain closes its subscriber."""
        # Never both locks at once: a listener runs under its PublisherTokens' lock and may
        # close a subscription, which comes here.
        with _FOLLOWED_LOCK:
            if self._done:
                return
            self._done = True
            followed = _FOLLOWED.get(self._key)
        if followed is None:
            return
        followed.remove(self._topic, self._listener)
        with _FOLLOWED_LOCK:
            followed.users -= 1
            last = followed.users == 0 and _FOLLOWED.get(self._key) is followed
            if last:
                del _FOLLOWED[self._key]
        if last:
            followed.close()


def listen(session: Any, domain: int, topic: str, listener: Listener) -> Listening:
    """Tell ``listener`` (on a Zenoh thread) of every publisher token of ``topic`` (mangled
    name) in ``domain`` as ``session`` sees them: those alive, then every change.

    Returns:
        The handle that ends it.
    """
    key = (str(session.zid()), domain)
    with _FOLLOWED_LOCK:
        followed = _FOLLOWED.get(key)
        if followed is None:
            followed = _FOLLOWED[key] = PublisherTokens(session, domain)
        followed.users += 1
    followed.add(topic, listener)
    return Listening(key, topic, listener)
