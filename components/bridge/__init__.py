"""The DDS bridge: msctl's Zenoh data plane and a DDS ROS 2 graph, relayed both ways through
rclpy (``msctl bridge``, and the ``bridge`` component kind a ground station runs).

* :mod:`components.bridge.core`: what to relay and the status, pure;
* :mod:`components.bridge.relay`: the relays (Zenoh on one side, rclpy on the other);
* :mod:`components.bridge.kind`, :mod:`components.bridge.build`: the component kind.
"""
