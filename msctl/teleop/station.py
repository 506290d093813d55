"""The teleop screen attached to its station's human operator.

When the assembly plans a ``human_operator`` on this computer (``MSCTL_HOST`` or the
hostname) and it answers, ``msctl teleop`` attaches to it
(:mod:`components.human_operator.client`): the human operator claims the modules in this
operator's name and relays the screen's commands with its own deadman, so motion also stops
when this screen freezes. The screen then publishes on the relay topics the human operator
named instead of the modules' own ``joint_set`` and the robot's ``cmd_vel``. When none runs
here (or it does not answer), the screen runs on its own, claiming for itself.

A claim the human operator holds for this screen is followed like one of its own
(:class:`RelayedClaim`): taken over by another operator, the screen says so at once.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from typing import Any

from components.api.joints import JointHandler, JointInfo
from components.claims import ClaimInfo
from components.messages import JOINT_STATE

log = logging.getLogger(__name__)


class RelayedJointHandler(JointHandler):
    """A module's joints whose commands go to the human operator's relay, not ``joint_set``.

    Args:
        node: The screen's node.
        slot: The module.
        joints: Its joints.
        relay: The relay topic of the module's ``joint_set``.
    """

    def __init__(self, node: Any, slot: str, joints: Iterable[JointInfo], relay: str) -> None:
        super().__init__(node, slot, joints)
        # The handler declares its joint_set publisher itself: replaced by the relay's.
        self._publisher.close()
        self._publisher = node.publisher(relay, JOINT_STATE)
        self.relay = relay


class RelayedClaim:
    """A claim the human operator holds for this screen, as the screen's own claims look.

    Attributes:
        info: The claim as its token tells it.
        lost: Set once another operator took the module over.
        lost_to: Who took it, once :attr:`lost` is set.
    """

    def __init__(self, info: ClaimInfo) -> None:
        self.info = info
        self.lost = threading.Event()
        self.lost_to: ClaimInfo | None = None
        self._callbacks: list[Callable[[ClaimInfo], None]] = []
        self._lock = threading.Lock()

    @property
    def module(self) -> str:
        """The claimed module."""
        return self.info.module

    @property
    def held(self) -> bool:
        """Not taken over (yet)."""
        return not self.lost.is_set()

    def on_lost(self, callback: Callable[[ClaimInfo], None]) -> None:
        """Call ``callback(new_holder)`` when taken over (at once if it was)."""
        with self._lock:
            if self.lost_to is None:
                self._callbacks.append(callback)
                return
            taker = self.lost_to
        callback(taker)

    def changed(self, holder: ClaimInfo | None) -> None:
        """The module's holder is now ``holder`` (a claims watcher's news)."""
        if holder is None or holder.key == self.info.key:
            return  # released (the screen detaching), or still ours
        with self._lock:
            if self.lost_to is not None:
                return
            self.lost_to = holder
            callbacks = list(self._callbacks)
        self.lost.set()
        for callback in callbacks:
            try:
                callback(holder)
            except Exception:
                log.exception("claim-lost callback failed")

    def release(self) -> None:
        """Nothing to do here: detaching releases the screen's claims at the desk."""


def attach_to_station(
    node: Any, assembly: Any, slots: list[str], take: bool, host: str
) -> tuple[str, Any, Any] | None:
    """Attach to the human operator planned on ``host``.

    Returns:
        ``(operator node, attachment, claims watcher)``, or None when the assembly plans no
        human operator there or it does not answer (the screen runs on its own).

    Raises:
        AttachRefused: If it refused (a module held by another operator).
    """
    from components.claims import Claims, default_holder
    from components.comm.services import ServiceError
    from components.human_operator.client import attach, station_operator

    operator = station_operator(assembly, host)
    if operator is None:
        return None
    claims = Claims(node.session, node.domain, [m.slot for m in assembly.modules])
    try:
        # Absent, it is known at once (no server on the network); present, its claims take
        # a moment.
        attached = attach(node, operator, default_holder(), slots, take)
    except ServiceError as exc:
        log.info("no answer from the station's human operator %s: %s", operator, exc)
        claims.close()
        return None
    except BaseException:
        claims.close()
        raise
    return operator, attached, claims
