"""Python source parsed into its syntax tree, despite a race in CPython 3.11's ``ast``.

CPython 3.11 (before 3.11.8) keeps the AST constructor's recursion counter in state shared by
every thread of the interpreter, so a parse that overlaps another thread's (``traceback``
parses a line to place its carets when a background thread logs an exception) fails with
``SystemError: AST constructor recursion depth mismatch``; seen on a full test run, where a
Zenoh callback logged while the test parsed. The same source parses again at once.
"""

from __future__ import annotations

import ast

#: Parses tried before the race is taken for a real fault.
ATTEMPTS = 5


def parse_source(source: str, filename: str = "<unknown>") -> ast.Module:
    """``ast.parse(source, filename)``, parsed again when CPython's counter race hit it.

    Raises:
        SyntaxError: If the source is not Python (as :func:`ast.parse`).
        SystemError: If every attempt failed (a real interpreter fault, not the race).
    """
    for attempt in range(ATTEMPTS):
        try:
            return ast.parse(source, filename=filename)
        except SystemError as exc:
            if "recursion depth mismatch" not in str(exc) or attempt == ATTEMPTS - 1:
                raise
    raise AssertionError("unreachable")  # the loop returns or raises
