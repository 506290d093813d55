"""Autonomous operators: supervised Python-API scripts, ``main(robot, **params)``.

A station's data names each one, its script and its parameters (see
:mod:`~components.autonomous_operator.script`); the launcher runs each in a process of its
own, and its supervisor restarts it when the script raises, as any crashed component.

* :mod:`~components.autonomous_operator.script`: locating a script and checking its ``main``
  against the data, without running it;
* :mod:`~components.autonomous_operator.core`: the operator's status (pure);
* :mod:`~components.autonomous_operator.robot`: the robot ``main`` gets;
* :mod:`~components.autonomous_operator.runner`: running the script in the component;
* :mod:`~components.autonomous_operator.operators`: the shipped operators (``steering``,
  ``posture``, ``guardian``).
"""
