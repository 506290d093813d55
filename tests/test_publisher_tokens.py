"""The publisher tokens a session's subscriptions follow through one shared liveliness
subscriber (components.comm.publishers), on real Zenoh sessions."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from conftest import wait_until

from components.comm import Node, publishers
from components.comm.names import mangle

STRING = "std_msgs/msg/String"
JOINT_STATE = "sensor_msgs/msg/JointState"


class Heard:
    """What one listener was told, in order."""

    def __init__(self) -> None:
        self.events: list[tuple[str, bool]] = []
        self._lock = threading.Lock()

    def __call__(self, key: str, alive: bool) -> None:
        with self._lock:
            self.events.append((key, alive))

    def alive(self) -> set[str]:
        with self._lock:
            now: dict[str, bool] = {}
            for key, alive in self.events:
                now[key] = alive
        return {key for key, alive in now.items() if alive}


def test_one_subscriber_per_session_each_listener_told_its_topic_in_order(
    open_sessions: Callable[[], Any],
) -> None:
    session = open_sessions()
    talker = Node(open_sessions(), "talker", domain=5)
    talker.publisher("/chatter", STRING)
    talker.publisher("/other", STRING)
    chatter, other, late = Heard(), Heard(), Heard()
    first = publishers.listen(session, 5, mangle("/chatter"), chatter)
    second = publishers.listen(session, 5, mangle("/other"), other)
    try:
        followed = publishers._FOLLOWED[(str(session.zid()), 5)]
        assert followed.users == 2  # one liveliness subscriber for both
        wait_until(lambda: len(chatter.alive()) == 1 and len(other.alive()) == 1, 30.0)
        assert all("/%chatter/" in key for key, _ in chatter.events)
        assert all("/%other/" in key for key, _ in other.events)
        # A listener that comes later is told at once of the tokens alive (the history).
        third = publishers.listen(session, 5, mangle("/chatter"), late)
        assert late.alive() == chatter.alive()
        third.undeclare()
        # A publisher closing: its token vanishes, after it appeared.
        token = next(iter(chatter.alive()))
        talker.close()
        wait_until(lambda: (token, False) in chatter.events, 30.0, "the token vanished")
        assert chatter.events.index((token, True)) < chatter.events.index((token, False))
    finally:
        first.undeclare()
        second.undeclare()
        second.undeclare()  # idempotent
    assert (str(session.zid()), 5) not in publishers._FOLLOWED  # the last one closed it


def test_a_listener_may_close_another_subscription_from_its_call(
    open_sessions: Callable[[], Any],
) -> None:
    """Listeners run under the shared subscriber's lock: closing a subscription from one (an
    owner reacting to a publisher of another type) must not deadlock."""
    session = open_sessions()
    node = Node(session, "listener", domain=6)
    victim = node.subscription("/typed", STRING, lambda _m: None)
    closed = threading.Event()

    def on_other_type(_entity: Any) -> None:
        victim.close()
        closed.set()

    keeper = node.subscription("/typed", STRING, lambda _m: None, on_other_type=on_other_type)
    wrong = Node(open_sessions(), "wrong", domain=6)
    wrong.publisher("/typed", JOINT_STATE)
    try:
        assert closed.wait(30.0)
    finally:
        keeper.close()
        wrong.close()
        node.close()
    assert (str(session.zid()), 6) not in publishers._FOLLOWED
