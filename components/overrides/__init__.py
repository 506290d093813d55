"""Overrides: alterations of a core for one robot, named in module or unit calibration data.

Each override is registered with :func:`components.executor.registry.override` in a module
of this package, imported here so the registry finds them all by importing the package.
Overrides change a core only through the hook points that core documents (for the Joint
Manager: command filters, pins, calibration), never by editing the core.
"""

from components.overrides import locked_joint

__all__ = ["locked_joint"]
