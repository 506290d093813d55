"""The MuJoCo simulator: one world per assembly, serving every module's motor interface.

Import the parts from their modules (``components.simulator.world`` loads MuJoCo):
:class:`~components.simulator.world.SimWorld` (the physics),
:class:`~components.simulator.core.SimulatorCore` (the component logic),
:func:`~components.simulator.interface.simulator_interface` and
:func:`~components.simulator.build.build`.

MuJoCo picks an OpenGL backend for offscreen rendering as it is imported, and with its
default (GLFW) the ``glfw`` package starts a Python subprocess to probe its library's
version: it slowed every simulator's start, and, being in the worker's process group, it got
the supervisor's SIGINT when a run was stopped meanwhile and printed a ``KeyboardInterrupt``
traceback of its own into ``sim.log``. The simulator renders nothing offscreen (its viewer
imports GLFW itself), so none is picked here, unless ``MUJOCO_GL`` asks for one.
"""

import os

os.environ.setdefault("MUJOCO_GL", "disable")
