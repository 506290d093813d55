"""The msctl runtime: components that run on robots and ground stations.

Cores are pure Python; Interfaces bind them to the ROS 2-compatible Zenoh data plane
(`components.comm`); Executors run them (`components.executor`).
"""
