"""The rclpy path: the same executor, with every core's node a real rclpy node.

Chosen with ``MSCTL_TRANSPORT=rclpy`` (the worker) or by constructing :class:`RclpyExecutor`.
It *is* the :class:`~components.executor.executor.Executor` — one binding code path: each
core's topics, services (injected ones included: ``extra_publish`` / ``extra_subscribe`` /
``extra_serve``), timers, urgent requests, contained handler exceptions and their counts,
heartbeats, rebuilds and clean shutdown are the executor's own; only the node each core gets
differs, made by :class:`~components.ros.plane.RclpyPlane` on whatever rmw the ROS 2 install
uses (rmw_fastrtps_cpp from the ``ros`` extra). Samples cross as CDR bytes, decoded by
msctl's codec into the same message objects the Zenoh path gives.

The graph a component follows (the health monitor's, the data monitor's) is rclpy's
(:class:`~components.ros.graph.RclpyGraph`). msctl's own control protocols stay on Zenoh:
claims and the supervisors' requests are not ROS data, and a Zenoh session for them is opened
only if a component asks for :attr:`RclpyExecutor.session` (a claim-guarded input does).

rclpy is imported only when this executor is made, and a missing rclpy fails with what to do.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from components.comm.session import SessionSettings, open_session
from components.executor.executor import Executor
from components.executor.heartbeat import Heartbeat
from components.ros import RclpyUnavailable, require_rclpy

__all__ = ["RclpyExecutor", "RclpyUnavailable"]


class RclpyExecutor(Executor):
    """Runs cores as rclpy nodes: the :class:`Executor` with rclpy as its data plane.

    Args:
        settings: Zenoh settings for msctl's control plane (claims), used only if asked for;
            ``settings.domain`` is the ROS domain id unless ``domain`` is given.
        clock: Monotonic clock giving ``now`` to handlers.
        heartbeat: The supervisor's proof-of-life pipe, beaten by the loop.
        domain: ROS domain id of the DDS graph (default: ``ROS_DOMAIN_ID``, else 0).

    Raises:
        RclpyUnavailable: If rclpy cannot be imported (the message says what to install).
    """

    transport = "rclpy"

    def __init__(
        self,
        settings: SessionSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
        heartbeat: Heartbeat | None = None,
        domain: int | None = None,
    ) -> None:
        require_rclpy()  # before anything is opened: the refusal is the first thing said
        self._domain_override = domain
        self._session_lock = threading.Lock()
        self.plane: Any = None
        super().__init__(settings, clock=clock, heartbeat=heartbeat)

    def _open_plane(self, session: Any) -> Any:
        from components.ros.plane import RclpyPlane

        domain = self._domain_override
        self.plane = RclpyPlane(self._settings.domain if domain is None else domain)
        return session  # the Zenoh session: opened when first asked for (see session)

    @property
    def session(self) -> Any:
        """A Zenoh session for msctl's control plane (claims), opened on first use."""
        with self._session_lock:
            if self._session is None:
                if self._closed:
                    raise RuntimeError("the executor is closed")
                self._session = open_session(self._settings)
            return self._session

    @property
    def domain(self) -> int:
        """The ROS domain id of the DDS graph."""
        return self.plane.domain

    def _node(self, name: str, namespace: str) -> Any:
        return self.plane.node(name, namespace)

    def graph(
        self, on_change: Callable[[Any, bool], None] | None = None, nodes_only: bool = False
    ) -> Any:
        """A live view of the ROS graph as rclpy sees it (see :class:`Executor.graph`; it
        reads the whole graph whatever ``nodes_only`` says)."""
        from components.ros.graph import RclpyGraph

        return RclpyGraph(self.plane, on_change)

    def close(self) -> None:
        """Close every node, the control-plane session if one was opened, and the rclpy
        context (idempotent)."""
        first = not self._closed
        super().close()
        if first and self.plane is not None:
            self.plane.close()
