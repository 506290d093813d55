"""Build a bridge component from the resolved assembly, and start its relays when bound.

The core only reports; the relays are :class:`components.bridge.relay.Bridge`, started by the
``on_bound`` hook with the component's own node on the side the executor runs (so both graphs
show the relays under the component's name) and a node of the same name on the other side.
They stop with the component's other resources.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.bridge.core import BridgeConfig, BridgeCore, BridgeStatus
from components.bridge.interface import BRIDGE
from components.build import BuiltComponent, config_from_params, node_name

if TYPE_CHECKING:
    from components.executor.executor import Component, Executor


class Bridging:
    """The bridge component's ``on_bound`` hook and its relays (closed with the component).

    Args:
        config: The component's parameters.
    """

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        self._bridge: Any = None
        self._error = ""
        self._lock = threading.Lock()

    def __call__(self, executor: Executor, component: Component) -> None:
        """Start relaying (called once, before the executor runs)."""
        from components.bridge.relay import Bridge
        from components.ros import RclpyUnavailable

        on_rclpy = executor.transport == "rclpy"
        try:
            bridge = Bridge(
                executor.session,
                self.config.selection(),
                name=component.node.name,
                namespace=component.node.namespace,
                domain=executor.domain,
                zenoh_node=None if on_rclpy else component.node,
                ros_node=component.node if on_rclpy else None,
                plane=getattr(executor, "plane", None) if on_rclpy else None,
                discovery_period=self.config.discovery_period,
                call_timeout=self.config.call_timeout,
            )
        except RclpyUnavailable as exc:
            # Reported on diagnostics (ERROR), where the station's operator looks.
            self._error = str(exc)
            return
        with self._lock:
            self._bridge = bridge

    def status(self) -> BridgeStatus:
        """What the relays do (an error status if they never started)."""
        with self._lock:
            bridge = self._bridge
        if bridge is None:
            return BridgeStatus(error=self._error or "not started yet")
        return bridge.status()

    def close(self) -> None:
        """Stop every relay (idempotent)."""
        with self._lock:
            bridge, self._bridge = self._bridge, None
        if bridge is not None:
            bridge.close()


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A bridge relaying what ``plan``'s parameters select.

    Params: :class:`BridgeConfig` fields.

    Raises:
        BuildError: If a parameter is out of range or selects nothing.
    """
    del assembly, options
    config = config_from_params(plan, BridgeConfig)
    bridging = Bridging(config)
    core = BridgeCore(plan.name, bridging.status, hardware_id=plan.host)
    built = BuiltComponent(core, BRIDGE, plan.namespace, node_name(plan.name))
    built.resources.append(bridging)
    built.on_bound = bridging
    return built
