"""The errors of the Python API: one base class, each also a builtin so ``except`` reads well."""

from __future__ import annotations

from components.errors import ComponentError


class ApiError(ComponentError):
    """Something the API cannot do; the message names the joint, module or topic at fault."""


class UnknownJointError(ApiError, KeyError):
    """A motion names joints the syncer does not drive (or that are locked)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class JointNotReadyError(ApiError, RuntimeError):
    """A joint has no measured state yet (no ``joint_read`` from its joint manager)."""


class RobotNotFoundError(ApiError, LookupError):
    """No running assembly (or not the one asked for) was found on the data plane."""


class RobotClosedError(ApiError, RuntimeError):
    """The robot connection was closed (``msctl run`` stopping): no new motion starts."""


class ModuleClaimedError(ApiError, PermissionError):
    """A module this script would command is claimed by another operator (who, since when).

    Attributes:
        holder: The claim holding the module (a :class:`components.claims.ClaimInfo`).
    """

    def __init__(self, message: str, holder: object) -> None:
        super().__init__(message)
        self.holder = holder


class ClaimLostError(ApiError, RuntimeError):
    """Another operator took over a module this script was commanding: it moves no more."""
