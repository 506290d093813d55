"""The plain forms of ``msctl ps`` and ``msctl topic list``, answered before typer is imported.

These two are typed all day in the field, and each should cost little more than opening a
Zenoh session. Importing typer costs about 0.07 s, and parsing a float option through it
0.2 s more (typer coerces values through pydantic). So when the command line is exactly one
of these commands with only its own flags (and plain decimal numbers for its number options),
:func:`run` calls the same function the typer command calls. Anything else -- ``--help``, a
typo, ``--timeout=5``, combined short flags, an unusual number -- goes to typer, which
parses, explains and refuses as always. A test checks every option of the typer commands is
here with the same default, so the two cannot drift apart.
"""

from __future__ import annotations

import errno
import importlib
import os
import re
import sys
from collections.abc import Callable
from typing import Any, NamedTuple

#: A number the quick path converts itself; typer handles every other spelling.
_PLAIN_NUMBER = re.compile(r"[0-9]{1,9}(\.[0-9]{1,9})?")


class QuickCommand(NamedTuple):
    """One command the quick path answers.

    A named tuple, not a dataclass: this path imports no dataclasses (see the note in
    :mod:`components.comm.graph`).

    Attributes:
        words: The command's words (``("topic", "list")``).
        target: ``module:function`` that does the work, with keyword parameters named as the
            typer command's.
        flags: Each switch (long and short spellings) -> the parameter it sets true.
        numbers: Each option taking a number -> its parameter.
    """

    words: tuple[str, ...]
    target: str
    flags: dict[str, str]
    numbers: dict[str, str]

    def parse(self, argv: list[str]) -> dict[str, Any] | None:
        """The keyword arguments for ``argv``, or ``None`` if it is not this command's plain
        form (typer then handles it)."""
        if tuple(argv[: len(self.words)]) != self.words:
            return None
        kwargs: dict[str, Any] = {}
        rest = argv[len(self.words) :]
        while rest:
            word, rest = rest[0], rest[1:]
            if word in self.flags:
                kwargs[self.flags[word]] = True
            elif word in self.numbers and rest and _PLAIN_NUMBER.fullmatch(rest[0]):
                kwargs[self.numbers[word]] = float(rest[0])
                rest = rest[1:]
            else:
                return None
        return kwargs

    def function(self) -> Callable[..., None]:
        """The function that does the work."""
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)

    def defaults(self) -> dict[str, Any]:
        """The function's parameters and their defaults."""
        import inspect  # 4 ms: only the tests ask, never a command

        return {
            name: p.default for name, p in inspect.signature(self.function()).parameters.items()
        }


COMMANDS: tuple[QuickCommand, ...] = (
    QuickCommand(
        ("ps",),
        "msctl.listings:show_ps",
        flags={"--json": "json_output", "--all": "all_hosts"},
        numbers={"--timeout": "timeout"},
    ),
    QuickCommand(
        ("topic", "list"),
        "msctl.listings:show_topics",
        flags={
            "--show-types": "show_types",
            "-t": "show_types",
            "--verbose": "verbose",
            "-v": "verbose",
            "--json": "json_output",
        },
        numbers={},
    ),
)


def run(argv: list[str]) -> bool:
    """Run ``argv`` if it is the plain form of a quick command; whether it did.

    A closed stdout (``msctl ps | head -1``) ends it with status 1 and no message, as typer
    does.
    """
    for quick in COMMANDS:
        kwargs = quick.parse(argv)
        if kwargs is None:
            continue
        try:
            quick.function()(**kwargs)
            sys.stdout.flush()
        except OSError as exc:
            if exc.errno != errno.EPIPE:
                raise
            # Nothing more can be written; keep Python's exit flush from complaining too.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            sys.exit(1)
        return True
    return False
