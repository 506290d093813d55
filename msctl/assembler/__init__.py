"""The Robot Assembler: templates + physical units -> one resolved assembly.

``resolve`` checks every input and builds the lock document and URDF in memory; ``store``
writes them (and the MJCF) atomically into the assembly directory that
:mod:`components.assembly` reads. See ``docs/assembler.md``.
"""

from msctl.assembler.resolve import Resolution, parse_uses, resolve

__all__ = ["Resolution", "parse_uses", "resolve"]
