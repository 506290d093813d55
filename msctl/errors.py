"""The one error path of msctl.

Every failure an operator can cause or fix is raised as an :class:`MsctlError` that carries
an exit code and a message naming what is at fault (file, field, topic, host) and what to do.
``msctl.cli.main`` turns it into one red line on stderr; a traceback is shown only when
``MSCTL_DEBUG=1``.
"""

from __future__ import annotations

from collections.abc import Iterable


class MsctlError(Exception):
    """An error the operator can act on.

    Attributes:
        exit_code: Process exit code for this error (2 usage/input, 3 runtime/network, ...).
        hint: What to do about it, appended to the message when printed.
    """

    exit_code: int = 1

    def __init__(self, message: str, *, hint: str | None = None, exit_code: int | None = None):
        super().__init__(message)
        self.message = message
        self.hint = hint
        if exit_code is not None:
            self.exit_code = exit_code

    def __str__(self) -> str:
        if self.hint:
            return f"{self.message} — {self.hint}"
        return self.message


class InputError(MsctlError, ValueError):
    """Bad input: a file, field, argument or value that is wrong. Exit code 2."""

    exit_code = 2


class NotFoundError(MsctlError, LookupError):
    """Something named does not exist (template, unit, topic, type, component). Exit code 4."""

    exit_code = 4


class NetworkError(MsctlError, ConnectionError):
    """The data plane could not be reached or did not answer. Exit code 3."""

    exit_code = 3


class OperationTimeout(MsctlError, TimeoutError):
    """A bounded wait ran out (no sample, no reply, no healthy component). Exit code 5."""

    exit_code = 5


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
