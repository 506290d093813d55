"""An Interface declares, as data, how a Core meets the data plane.

Names are relative to the component's namespace (``joint_set`` in namespace ``/limb1`` is
``/limb1/joint_set``); a name starting with ``/`` is absolute. Handlers are named by method
so that the declaration stays data and the Core stays free of any transport.

Handler signatures:
    Subscribe: ``handler(message, now) -> None``
    Serve: ``handler(request, now) -> response``
    Every: ``handler(now) -> None``
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from components.comm.qos import QoS
from components.roles import Role

if TYPE_CHECKING:
    from components.claim_guard import ClaimRule


@dataclass(frozen=True)
class Subscribe:
    """The core reads ``topic`` of ``msg_type``; samples go to ``handler``.

    ``senders``, when given, are the only nodes whose samples are taken (fully qualified, or
    relative to the component's namespace); the transport refuses and counts the others.
    ``claim``, when given (by the builder, which knows the module), makes it a command
    input: while the module is claimed, only the claim's holder (and the rule's relays) are
    taken (:mod:`components.claims`).
    ``role`` says what the input is (:class:`~components.roles.Role`); every input of a
    registered kind declares one, and a module's builder derives ``senders`` and ``claim``
    from it (:func:`components.roles.bind`).
    """

    topic: str
    msg_type: str
    handler: str
    qos: QoS = field(default_factory=QoS)
    senders: tuple[str, ...] | None = None
    claim: ClaimRule | None = None
    role: Role | None = None


@dataclass(frozen=True)
class Publish:
    """The core writes ``topic`` of ``msg_type``."""

    topic: str
    msg_type: str
    qos: QoS = field(default_factory=QoS)


@dataclass(frozen=True)
class Serve:
    """The core answers service ``service`` of ``srv_type`` with ``handler``.

    ``urgent`` requests are handled before anything queued (samples, timers, other
    requests), as soon as the handler running finishes, and answered at Zenoh's real-time
    priority: a halt never waits behind data. ``role`` says what the request is
    (:class:`~components.roles.Role`: a halt, a control request, a question...).
    """

    service: str
    srv_type: str
    handler: str
    urgent: bool = False
    role: Role | None = None


@dataclass(frozen=True)
class Every:
    """The executor calls ``handler`` every ``period`` seconds."""

    period: float
    handler: str


@dataclass(frozen=True)
class InterfaceSpec:
    """Everything a core reads, writes, serves and ticks on."""

    subscribe: tuple[Subscribe, ...] = ()
    publish: tuple[Publish, ...] = ()
    serve: tuple[Serve, ...] = ()
    every: tuple[Every, ...] = ()

    def claimed(self, topics: tuple[str, ...], rule: ClaimRule) -> InterfaceSpec:
        """This interface with the subscriptions to ``topics`` guarded by ``rule``.

        Raises:
            KeyError: If a topic is not one this interface subscribes to.
        """
        import dataclasses

        missing = set(topics) - {s.topic for s in self.subscribe}
        if missing:
            raise KeyError(f"no subscription to {sorted(missing)} in this interface")
        return dataclasses.replace(
            self,
            subscribe=tuple(
                dataclasses.replace(s, claim=rule) if s.topic in topics else s
                for s in self.subscribe
            ),
        )

    def output(self, topic: str) -> Publish:
        """The declared output for ``topic``.

        Raises:
            KeyError: If the core never declared that output.
        """
        for declared in self.publish:
            if declared.topic == topic:
                return declared
        raise KeyError(
            f"output {topic!r} is not declared by this interface; "
            f"declared: {[p.topic for p in self.publish]}"
        )
