"""The one error root of the runtime, and its categories.

Every failure a component, a backend or the data plane raises on purpose is a
:class:`ComponentError`. Each category also subclasses the builtin it is a kind of (as
python-can's ``CanTimeoutError(CanError, TimeoutError)`` does), so a caller that only knows
Python still catches it: a bad parameter is a ``ValueError``, a silent peer a
``TimeoutError``, a lost link a ``ConnectionError``, a failing device or disk an ``OSError``.

The runtime never decides exit codes: ``msctl.cli.main`` maps each category to one, in one
table. ``msctl``'s own :class:`~msctl.errors.MsctlError` is a :class:`ComponentError` too.
"""

from __future__ import annotations


class ComponentError(Exception):
    """A failure the runtime raises on purpose, with a message naming what is at fault.

    Args:
        message: What failed, naming the file, field, topic, host or device.
        hint: What to do about it, appended to the message when printed.
    """

    def __init__(self, *args: object, hint: str | None = None) -> None:
        # The arguments as Exception keeps them (``args``, ``repr`` and pickling unchanged
        # for the classes re-rooted here), the first one being the message.
        super().__init__(*args)
        self.message = str(args[0]) if args else ""
        self.hint = hint

    def __str__(self) -> str:
        # Exactly what Exception would print, unless a hint was given (then "message — hint").
        text = super().__str__()
        if self.hint:
            return f"{self.message} — {self.hint}"
        return text


class ConfigError(ComponentError, ValueError):
    """Bad input: a parameter, field, file or name that is wrong."""


class NotFound(ComponentError, LookupError):
    """Something named does not exist (a module, a joint, a type, a kind)."""


class LinkError(ComponentError, ConnectionError):
    """The data plane or a peer could not be reached."""


class DeadlineError(ComponentError, TimeoutError):
    """A bounded wait ran out: no answer, no sample, no healthy component."""


class HardwareError(ComponentError, OSError):
    """A device, a port or a disk failed (what was written stays readable)."""


def swallowed(what: str, exc: BaseException, *, level: int = 10) -> None:
    """Log an error a close path goes on past (``level``: logging's, DEBUG by default).

    Closing undeclares tokens and subscribers whose session may be closed already: such an
    error changes nothing, but it is said, with what failed, for whoever reads the log.
    """
    import logging

    logging.getLogger("components.close").log(level, "%s: %s: %s", what, type(exc).__name__, exc)
