"""What a human operator relays, from the resolved assembly (static knowledge only).

One route per command input of the assembly: each module's ``joint_set`` and each driving
robot's ``cmd_vel``. A screen publishes on the route's relay topic, private to the human
operator's node (``/gc1/human_operator/relay/limb1/joint_set``); the human operator forwards
to the target (``/limb1/joint_set``) as its own node, the holder of the module's claim.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from components.messages import JOINT_STATE, TWIST
from components.robots import cmd_vel_topics, modules_of

#: What a route carries.
JOINT_SET = "joint_set"
DRIVE = "cmd_vel"


@dataclass(frozen=True)
class Route:
    """One relayed command input.

    Attributes:
        target: Where commands go (``/limb1/joint_set``, ``/cmd_vel``).
        relay: Where a screen puts them (absolute, under the human operator's node).
        kind: :data:`JOINT_SET` or :data:`DRIVE`.
        msg_type: The message type of both topics.
        modules: The modules whose claims decide who may use it: the one module of a
            ``joint_set``, every module of the robot a ``cmd_vel`` drives.
    """

    target: str
    relay: str
    kind: str
    msg_type: str
    modules: tuple[str, ...]


def relay_topic(node_fqn: str, target: str) -> str:
    """The relay topic of ``target`` for the human operator whose node is ``node_fqn``."""
    return f"{node_fqn.rstrip('/')}/relay/{target.strip('/')}"


def routes_of(assembly: Any, node_fqn: str) -> list[Route]:
    """Every route of ``assembly`` for the human operator ``node_fqn``: each module's
    ``joint_set`` (in assembly order), then each driving robot's ``cmd_vel``."""
    routes = []
    for module in assembly.modules:
        if not module.actuated_joints:
            continue
        target = f"{module.namespace.rstrip('/')}/joint_set"
        routes.append(
            Route(target, relay_topic(node_fqn, target), JOINT_SET, JOINT_STATE, (module.slot,))
        )
    for robot, target in cmd_vel_topics(assembly).items():
        routes.append(
            Route(
                target,
                relay_topic(node_fqn, target),
                DRIVE,
                TWIST,
                tuple(modules_of(assembly, robot)),
            )
        )
    return routes
