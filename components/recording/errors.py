"""The recorder's errors: each names the bag, file or topic at fault and what to do."""

from __future__ import annotations

from msctl.errors import InputError, MsctlError


class BagError(InputError):
    """A directory or file that is not a readable bag (what is missing or wrong is named)."""


class BagWriteError(MsctlError, OSError):
    """Writing a bag failed (full disk, lost permissions); what was written stays readable.

    Exit code 6.
    """

    exit_code = 6
