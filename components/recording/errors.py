"""The recorder's errors: each names the bag, file or topic at fault and what to do."""

from __future__ import annotations

from components.errors import ConfigError, HardwareError


class BagError(ConfigError):
    """A directory or file that is not a readable bag (what is missing or wrong is named).

    Exit code 2 (the operator's input).
    """


class BagWriteError(HardwareError):
    """Writing a bag failed (full disk, lost permissions); what was written stays readable.

    Exit code 6.
    """
