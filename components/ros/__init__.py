"""msctl on real ROS 2: rclpy as a data plane (``MSCTL_TRANSPORT=rclpy``) and the DDS bridge.

Everything here imports rclpy, which comes from the ``ros`` extra (``pip install
'msctl[ros]'``: the ros-python-wheels builds of ROS 2 Jazzy with Fast DDS) or a sourced ROS 2
install. Nothing else in msctl imports this package unless asked, so msctl runs and is tested
without it.

* :mod:`components.ros.typesupport`: type support made at run time from msctl's own type
  registry, so rclpy carries any type msctl knows (``msctl_msgs`` included) as CDR bytes.
* :mod:`components.ros.plane`: an rclpy context and nodes with the interface of msctl's Zenoh
  nodes (publishers, subscriptions, servers, clients), so the executor binds cores to either.
* :mod:`components.ros.graph`: the ROS graph as rclpy sees it, as a
  :class:`~components.comm.graph.GraphView`.
"""

from __future__ import annotations

from typing import Any

from components.errors import ComponentError

#: What to do when rclpy is missing (the ``ros`` extra, or a sourced ROS 2 install).
INSTALL_HINT = (
    "install the ROS 2 wheels with `pip install 'msctl[ros]'` (or source "
    "/opt/ros/<distro>/setup.bash so that `import rclpy` works)"
)


class RclpyUnavailable(ComponentError, RuntimeError):
    """rclpy (a ROS 2 install) is not importable here."""


def require_rclpy(purpose: str = "MSCTL_TRANSPORT=rclpy") -> Any:
    """Import rclpy, or raise :class:`RclpyUnavailable` saying what to do.

    Args:
        purpose: What needs it, for the message (``msctl bridge``).
    """
    try:
        import rclpy
    except ImportError as exc:
        raise RclpyUnavailable(
            f"{purpose} needs a ROS 2 install: {INSTALL_HINT}; or unset MSCTL_TRANSPORT to use "
            "the Zenoh data plane, which needs no ROS"
        ) from exc
    return rclpy


def rclpy_available() -> bool:
    """Whether rclpy can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("rclpy") is not None
