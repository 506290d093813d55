"""The data plane: ROS 2 topics and services carried natively on Zenoh, as rmw_zenoh does.

Typical use::

    from components.comm import Node, open_session

    with open_session() as session:
        node = Node(session, "probe", namespace="/limb1")
        pub = node.publisher("joint_set", "sensor_msgs/msg/JointState")
        ...
        node.close()
"""

from __future__ import annotations

import importlib
from typing import Any

# Each name is imported from its module when first asked for: importing one light module
# of the package (names, liveliness, graph) must not pull in every endpoint and codec.
_EXPORTS: dict[str, str] = {
    "Node": "components.comm.node",
    "LATCHED": "components.comm.qos",
    "SENSOR": "components.comm.qos",
    "QoS": "components.comm.qos",
    "ServiceClient": "components.comm.services",
    "ServiceError": "components.comm.services",
    "ServiceServer": "components.comm.services",
    "ServiceTimeout": "components.comm.services",
    "SessionSettings": "components.comm.session",
    "open_session": "components.comm.session",
    "router_settings": "components.comm.session",
    "drops": "components.comm.stats",
    "Publisher": "components.comm.topics",
    "Subscription": "components.comm.topics",
    "registry": "components.comm.types",
}


def __getattr__(name: str) -> Any:
    """The package's public names, imported on first use."""
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    return getattr(importlib.import_module(module), name)


__all__ = [
    "LATCHED",
    "SENSOR",
    "Node",
    "Publisher",
    "QoS",
    "ServiceClient",
    "ServiceError",
    "ServiceServer",
    "ServiceTimeout",
    "SessionSettings",
    "Subscription",
    "drops",
    "open_session",
    "registry",
    "router_settings",
]


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
