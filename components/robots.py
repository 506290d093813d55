"""The robots of an assembly: which modules move together, and what drives each one.

An assembly may hold several robots (``two_dragons``): modules joined by connections
(``limb1.tip`` carries ``wheel1.mount``) form one robot, named by its root module as the
assembler placed it. Each mobile robot with wheels has a ``cmd_vel``: ``/cmd_vel`` when the
assembly is one robot, ``/<root module>/cmd_vel`` when it has several. Teleop's drive mode,
the human operator's relay and the steering operator all name it from here, so they agree.

Static knowledge only (the resolved assembly); no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from components.roles import Role

#: The drive topic of a robot, relative to its namespace (``/cmd_vel`` for a lone robot).
CMD_VEL = "cmd_vel"
#: The inputs a whole robot has (relative to its namespace), with their roles: the drive is a
#: command (operators, the claim holder of the modules it moves). See :mod:`components.roles`.
ROBOT_INPUTS: dict[str, Role] = {CMD_VEL: Role.COMMAND}


def robots_of(assembly: Any) -> dict[str, str]:
    """Each module's robot, named by the robot's root module."""
    parent: dict[str, str] = {m.slot: m.slot for m in assembly.modules}

    def find(slot: str) -> str:
        while parent[slot] != slot:
            parent[slot] = parent[parent[slot]]
            slot = parent[slot]
        return slot

    for connection in assembly.connections:
        a = find(connection.parent.split(".", 1)[0])
        b = find(connection.child.split(".", 1)[0])
        if a != b:
            parent[b] = a
    # Each group is named by its robot's root as the assembler placed it.
    names = {find(robot.root): robot.root for robot in assembly.lock.robots if robot.root in parent}
    return {slot: names.get(find(slot), find(slot)) for slot in parent}


def robot_names(assembly: Any) -> list[str]:
    """Every robot's name (its root module), in module order."""
    return list(dict.fromkeys(robots_of(assembly).values()))


def modules_of(assembly: Any, robot: str) -> list[str]:
    """The modules of robot ``robot``, in assembly order.

    Raises:
        KeyError: If no robot has that name (the message names the robots).
    """
    robots = robots_of(assembly)
    found = [slot for slot, name in robots.items() if name == robot]
    if not found:
        raise KeyError(
            f"{assembly.template} has no robot {robot!r}; its robots (by root module): "
            f"{', '.join(robot_names(assembly))}"
        )
    return found


def root_link(assembly: Any, robot: str) -> str:
    """The root link of the robot named by its root module (a stamped Twist's frame)."""
    for placement in assembly.lock.robots:
        if placement.root == robot:
            return placement.root_link
    return assembly.module(robot).root_link


def drives(assembly: Any) -> bool:
    """Whether the assembly moves on wheels: mobile, with velocity-controlled joints."""
    rolling = any(j.control == "velocity" for m in assembly.modules for j in m.joints)
    return bool(assembly.mobile and rolling)


def robot_cmd_vel(assembly: Any, robot: str) -> str:
    """The ``cmd_vel`` of one robot (whether or not it drives)."""
    if len(robot_names(assembly)) == 1:
        return f"/{CMD_VEL}"
    return f"/{robot}/{CMD_VEL}"


def cmd_vel_topic(assembly: Any, modules: Sequence[str]) -> str | None:
    """The ``cmd_vel`` of the robot the modules belong to; None when the assembly does not
    drive or the modules span several robots."""
    if not drives(assembly):
        return None
    if len(robot_names(assembly)) == 1:
        return f"/{CMD_VEL}"
    robots = robots_of(assembly)
    mine = {robots[m] for m in modules}
    if len(mine) != 1:
        return None
    return robot_cmd_vel(assembly, mine.pop())


def cmd_vel_topics(assembly: Any) -> dict[str, str]:
    """Robot -> its ``cmd_vel``, for every robot with wheels (empty if none drives)."""
    if not drives(assembly):
        return {}
    robots = robots_of(assembly)
    out = {}
    for robot in robot_names(assembly):
        wheeled = any(
            j.control == "velocity"
            for slot, name in robots.items()
            if name == robot
            for j in assembly.module(slot).joints
        )
        if wheeled:
            out[robot] = robot_cmd_vel(assembly, robot)
    return out


def robot_inputs_of(assembly: Any) -> dict[str, tuple[Role, str]]:
    """Every robot's own inputs (:data:`ROBOT_INPUTS`) fully qualified, with their role and
    the robot's root module: the ``cmd_vel`` of each robot that drives."""
    return {
        topic: (ROBOT_INPUTS[CMD_VEL], robot) for robot, topic in cmd_vel_topics(assembly).items()
    }
