"""The one error path of msctl.

Every failure an operator can cause or fix is raised as an :class:`MsctlError` that carries
an exit code and a message naming what is at fault (file, field, topic, host) and what to do.
``msctl.cli.main`` turns it into one red line on stderr; a traceback is shown only when
``MSCTL_DEBUG=1``.
"""

from __future__ import annotations

from collections.abc import Iterable

from components.errors import (
    ComponentError,
    ConfigError,
    DeadlineError,
    HardwareError,
    LinkError,
    NotFound,
)

#: The exit code of each category of error, the first that matches winning: the one place
#: a failure becomes a number (``msctl.cli.main``; an :class:`MsctlError` may carry its own).
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (ConfigError, 2),  # usage or input: a file, field, argument or value
    (LinkError, 3),  # the data plane or a peer could not be reached
    (NotFound, 4),  # a template, unit, topic, type or component that does not exist
    (DeadlineError, 5),  # a bounded wait ran out
    (HardwareError, 6),  # a device or a disk failed
)
#: The exit code of a project error in no category.
GENERAL = 1


def exit_code_of(exc: BaseException) -> int:
    """The exit code ``msctl`` ends with for ``exc``: its own, else its category's."""
    own = vars(exc).get("exit_code")
    if own is None:
        own = next((vars(k)["exit_code"] for k in type(exc).__mro__ if _owns_code(k)), None)
    if own is not None:
        return int(own)
    return next((code for category, code in EXIT_CODES if isinstance(exc, category)), GENERAL)


class _ExitCode:
    """``exit_code`` of an error (:func:`exit_code_of`), and of its class: ``InputError.exit_code``
    is 2 as ``InputError("...").exit_code`` is (tests compare a process's exit with it)."""

    def __get__(self, error: BaseException | None, kind: type) -> int:
        if error is not None:
            return exit_code_of(error)
        own = next((vars(k)["exit_code"] for k in kind.__mro__ if _owns_code(k)), None)
        if own is not None:
            return int(own)
        return next((code for category, code in EXIT_CODES if issubclass(kind, category)), GENERAL)


def _owns_code(cls: type) -> bool:
    # A class statement saying ``exit_code = N`` (not MsctlError's own property).
    return isinstance(vars(cls).get("exit_code"), int)


class MsctlError(ComponentError):
    """An error the operator can act on.

    It is a :class:`~components.errors.ComponentError`: the runtime's and the CLI's errors
    share one root, and ``msctl.cli.main`` turns each into one line and the exit code of its
    category (:data:`EXIT_CODES`).

    Attributes:
        exit_code: Process exit code for this error (2 usage/input, 3 runtime/network, ...):
            an ``exit_code = N`` of its class or ``exit_code=`` given, else its category's.
        hint: What to do about it, appended to the message when printed.
    """

    def __init__(self, message: str, *, hint: str | None = None, exit_code: int | None = None):
        super().__init__(message, hint=hint)
        if exit_code is not None:
            self.__dict__["exit_code"] = exit_code

    exit_code = _ExitCode()


class InputError(MsctlError, ConfigError):
    """Bad input: a file, field, argument or value that is wrong. Exit code 2."""


class NotFoundError(MsctlError, NotFound):
    """Something named does not exist (template, unit, topic, type, component). Exit code 4."""


class NetworkError(MsctlError, LinkError):
    """The data plane could not be reached or did not answer. Exit code 3."""


class OperationTimeout(MsctlError, DeadlineError):
    """A bounded wait ran out (no sample, no reply, no healthy component). Exit code 5."""


def nearest(name: str, known: Iterable[str], count: int = 3) -> list[str]:
    """The names in ``known`` closest to a mistyped ``name``, best first (maybe none).

    Only names about as close as the best one are kept: ``std_msgs/msg/Strin`` suggests
    ``std_msgs/msg/String``, not every ``std_msgs`` type that shares the long prefix.
    """
    from difflib import SequenceMatcher

    matcher = SequenceMatcher(b=name)
    scored = []
    for candidate in dict.fromkeys(known):
        matcher.set_seq1(candidate)
        if matcher.real_quick_ratio() >= 0.6 and matcher.quick_ratio() >= 0.6:
            scored.append((matcher.ratio(), candidate))
    scored.sort(key=lambda pair: (-pair[0], pair[1]))
    if scored and scored[0][0] >= 0.6:
        best = scored[0][0]
        return [c for score, c in scored[:count] if score >= best - 0.05]
    # A prefix of the last path part ("limb1/joint_m" for "limb1/joint_manager").
    tail = name.rsplit("/", 1)[-1]
    return [c for c in dict.fromkeys(known) if tail and c.rsplit("/", 1)[-1].startswith(tail)][
        :count
    ]


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """``"did you mean 'x'?"`` (or ``'x' or 'y'``) for a mistyped name; ``""`` if none is near."""
    close = nearest(name, known)
    if not close:
        return ""
    return "did you mean " + " or ".join(repr(c) for c in close) + "?"
