"""The MuJoCo simulator: one world per assembly, serving every module's motor interface.

Import the parts from their modules (``components.simulator.world`` loads MuJoCo):
:class:`~components.simulator.world.SimWorld` (the physics),
:class:`~components.simulator.core.SimulatorCore` (the component logic),
:func:`~components.simulator.interface.simulator_interface` and
:func:`~components.simulator.build.build`.
"""
