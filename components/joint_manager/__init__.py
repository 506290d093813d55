"""The Joint Manager (Motion-Stack lvl1): calibration, limits and watchdog for one module.

The core is :class:`~components.joint_manager.core.JointManagerCore`; its data-plane
declaration is :data:`~components.joint_manager.interface.JOINT_MANAGER`; injections
(``rezero``) live in :mod:`components.joint_manager.injections` and robot overrides
(``locked_joint``) in :mod:`components.overrides`.
"""

from components.joint_manager.core import (
    CommandFilter,
    JointManagerConfig,
    JointManagerCore,
    Refusal,
)

__all__ = ["CommandFilter", "JointManagerConfig", "JointManagerCore", "Refusal"]
