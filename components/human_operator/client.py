"""How a screen (``msctl teleop``) attaches to its station's human operator.

::

    from components.human_operator.client import attach, detach, station_operator

    operator = station_operator(assembly, this_host())   # "/gc1/human_operator", or None
    attached = attach(node, operator, "ana@ground1", ["limb1", "wheel1"])
    attached.relays["/limb1/joint_set"]   # where to publish limb1's joint_set now
    detach(node, operator)                # or just close the node: the desk notices

:func:`attach` raises :class:`AttachRefused` when the operator holds a module already
(naming them and since when) and :class:`~components.comm.services.ServiceError` when no
human operator answers (none runs: the screen then runs on its own).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from components.build import node_name
from components.claims import ClaimInfo, parse_claim
from components.errors import ComponentError
from components.human_operator.desk import ATTACH, DETACH, REQUEST_SRV

#: The kind whose components a screen attaches to.
KIND = "human_operator"
#: Seconds a screen waits for the desk's answer (a claim asks the network, up to seconds).
ATTACH_TIMEOUT = 10.0


class AttachRefused(ComponentError, RuntimeError):
    """The human operator refused (a module is held by another operator).

    Attributes:
        holder: The claim that holds the module, when a claim refused it.
    """

    def __init__(self, message: str, holder: ClaimInfo | None = None) -> None:
        super().__init__(message)
        self.holder = holder


@dataclass(frozen=True)
class Attachment:
    """A screen attached to a human operator.

    Attributes:
        operator: The human operator's node (``/gc1/human_operator``).
        claimed: The modules it holds for the screen.
        relays: Command target (``/limb1/joint_set``) -> the relay topic to publish on.
        deadman_timeout: The relay's own deadman (seconds).
        claims: Slot -> the claim it holds for the screen.
    """

    operator: str
    claimed: tuple[str, ...]
    relays: dict[str, str]
    deadman_timeout: float
    claims: dict[str, ClaimInfo | None] = field(default_factory=dict)


def station_operator(assembly: Any, host: str) -> str | None:
    """The node of the human operator the assembly plans on ``host`` (the first, if it
    plans several), or None when ``host`` runs none."""
    for plan in assembly.components:
        if plan.kind == KIND and plan.host == host:
            return f"{plan.namespace.rstrip('/')}/{node_name(plan.name)}"
    return None


def _call(node: Any, operator: str, verb: str, args: dict[str, Any], timeout: float) -> Any:
    client = node.client(f"{operator}/request", REQUEST_SRV)
    try:
        request = client.request_type()(verb=verb, args=json.dumps(args))
        return client.call(request, timeout=timeout)
    finally:
        client.close()


def attach(
    node: Any,
    operator: str,
    holder: str,
    modules: list[str],
    take: bool = False,
    timeout: float = ATTACH_TIMEOUT,
) -> Attachment:
    """Have ``operator`` claim ``modules`` for ``holder`` and relay ``node``'s commands.

    Raises:
        AttachRefused: If it refused, saying why (who holds a module, and since when).
        ServiceError: If it does not answer (it does not run).
    """
    args = {"holder": holder, "node": node.fqn, "zid": node.zid, "modules": modules, "take": take}
    answer = _call(node, operator, ATTACH, args, timeout)
    payload = json.loads(answer.payload) if answer.payload else {}
    if not answer.success:
        found = payload.get("holder")
        raise AttachRefused(str(answer.message), parse_claim(found["key"]) if found else None)
    claims = {slot: parse_claim(c["key"]) for slot, c in payload.get("claims", {}).items()}
    return Attachment(
        operator=payload["operator"],
        claimed=tuple(payload["claimed"]),
        relays=dict(payload["relays"]),
        deadman_timeout=float(payload["deadman_timeout"]),
        claims=claims,
    )


def detach(node: Any, operator: str, timeout: float = 2.0) -> None:
    """Let go of everything ``operator`` holds for ``node``'s screen.

    Raises:
        ServiceError: If it does not answer (it lets go anyway once ``node`` leaves).
    """
    _call(node, operator, DETACH, {"node": node.fqn, "zid": node.zid}, timeout)
