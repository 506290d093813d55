"""The beginner-friendly Python API: move a running assembly in a few lines.

Connect (the running assembly is found on the data plane), then move modules with syncers::

    import asyncio
    from components.api import connect

    async def main():
        async with await connect() as robot:
            limb = robot.syncer("limb1")
            await limb.lerp({"joint2": 0.5, "joint4": -0.8})

    asyncio.run(main())

Or synchronously, for short scripts::

    from components.api import connect_sync

    with connect_sync() as robot:
        robot.syncer("limb1").lerp({"joint2": 0.5}).wait()

Public names: :func:`connect`, :func:`connect_sync`, :class:`Robot`, :class:`JointHandler`,
:class:`JointSyncer`, :class:`IkSyncer`, :class:`WheelDrive`, :class:`WheelSteering`,
:class:`SyncSettings`, :class:`IkSyncSettings`, :class:`Motion` and the errors. See
``docs/api.md``.
"""

from components.api.connect import Robot, connect
from components.api.errors import (
    ApiError,
    ClaimLostError,
    JointNotReadyError,
    ModuleClaimedError,
    RobotClosedError,
    RobotNotFoundError,
    UnknownJointError,
)
from components.api.joints import JointHandler, JointInfo, JointState
from components.api.motion import Motion
from components.api.planner import SyncPlanner, SyncSettings
from components.api.sync import SyncRobot, connect_sync
from components.api.syncer import JointSyncer

# Pinocchio is imported only when the IK syncer or the wheel helper is first used.
_LAZY = {
    "IkSyncer": "components.api.ik_syncer",
    "IkSyncSettings": "components.api.ik_syncer",
    "WheelDrive": "components.api.wheels",
    "WheelGeometry": "components.api.wheels",
    "WheelSteering": "components.api.steering",
}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'components.api' has no attribute {name!r}")


__all__ = [
    "ApiError",
    "ClaimLostError",
    "IkSyncSettings",
    "IkSyncer",
    "JointHandler",
    "JointInfo",
    "JointNotReadyError",
    "JointState",
    "JointSyncer",
    "ModuleClaimedError",
    "Motion",
    "Robot",
    "RobotClosedError",
    "RobotNotFoundError",
    "SyncPlanner",
    "SyncRobot",
    "SyncSettings",
    "UnknownJointError",
    "WheelDrive",
    "WheelGeometry",
    "WheelSteering",
    "connect",
    "connect_sync",
]
