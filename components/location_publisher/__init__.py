"""Location Publisher: per-module, per-link poses from forward kinematics of ``joint_read``."""
