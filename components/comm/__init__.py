"""The data plane: ROS 2 topics and services carried natively on Zenoh, as rmw_zenoh does.

Typical use::

    from components.comm import Node, open_session

    with open_session() as session:
        node = Node(session, "probe", namespace="/limb1")
        pub = node.publisher("joint_set", "sensor_msgs/msg/JointState")
        ...
        node.close()
"""

from components.comm.node import Node
from components.comm.qos import LATCHED, SENSOR, QoS
from components.comm.services import ServiceClient, ServiceError, ServiceServer, ServiceTimeout
from components.comm.session import SessionSettings, open_session, router_settings
from components.comm.stats import drops
from components.comm.topics import Publisher, Subscription
from components.comm.types import registry

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
