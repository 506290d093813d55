"""The simulator's names on the data plane: each module's motor topics and services as the
motor interface names them, the ground-truth poses and the clock.

Pure names, shared by the core, its interface and whoever subscribes (a ground station's
guardian reads the poses).
"""

from __future__ import annotations

from collections.abc import Sequence

#: Namespace of what belongs to the simulator itself (pose ground truth, diagnostics).
SIM_NAMESPACE = "/sim"
#: The simulated time, ``rosgraph_msgs/msg/Clock`` on ``/clock`` (ROS's name), every pose.
CLOCK = "rosgraph_msgs/msg/Clock"
CLOCK_TOPIC = "/clock"


def states_topic(slot: str) -> str:
    """The absolute ``joint_states`` topic of a module."""
    return f"/{slot}/joint_states"


def commands_topic(slot: str) -> str:
    """The absolute ``joint_commands`` topic of a module."""
    return f"/{slot}/joint_commands"


def module_diagnostics_topic(slot: str) -> str:
    """The absolute ``diagnostics`` topic of a module (shared with its joint manager)."""
    return f"/{slot}/diagnostics"


def pose_topics(roots: Sequence[str]) -> list[tuple[str, str]]:
    """(root link, topic) pairs of the ground-truth poses.

    The first robot's root is ``/sim/base_pose``; with several robots every root also has
    ``/sim/<root link>/pose``, so a ground station subscribes to the one robot it needs.
    """
    pairs = [(roots[0], f"{SIM_NAMESPACE}/base_pose")] if roots else []
    if len(roots) > 1:
        pairs.extend((root, f"{SIM_NAMESPACE}/{root}/pose") for root in roots)
    return pairs


def commands_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/joint_commands``."""
    return f"on_joint_commands_{slot}"


def halt_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/motors/halt``."""
    return f"on_halt_{slot}"


def recover_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/motors/recover``."""
    return f"on_recover_{slot}"
