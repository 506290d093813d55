"""Kinematics Manager: a limb chain's forward kinematics (``tip_pose``) and IK (``ik_target``).

``model`` cuts Pinocchio models out of the composed URDF, ``ik`` solves, ``core`` is the
component's logic; the location publisher (:mod:`components.location_publisher`) reuses
``model`` and ``poses``.
"""
