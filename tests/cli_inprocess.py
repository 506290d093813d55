"""Run an ``msctl`` command in this process and read its exit status as ``msctl`` gives it.

A subprocess per command costs a second or more of imports on a loaded machine; a property
test runs hundreds. The command goes through the same typer app ``msctl`` runs, and the
exception it ends with is turned into the exit status by the rules of ``msctl.cli.main``:
an ``MsctlError`` its own code, a session setting 2, anything else 70 (an internal error,
what the fault-injection tests look for).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: What ``msctl`` exits with on an exception it did not expect.
INTERNAL = 70


@dataclass(frozen=True)
class Ran:
    """One command's outcome.

    Attributes:
        code: The exit status ``msctl`` would have given.
        stdout: What it printed as data.
        stderr: What it told the operator.
        exception: The exception it ended with, if any (not a normal exit).
    """

    code: int
    stdout: str
    stderr: str
    exception: BaseException | None

    @property
    def said(self) -> str:
        """Its stderr on one line (rich wraps long lines at its width)."""
        return " ".join(self.stderr.split())


def msctl(home: Path, *args: str, env: dict[str, str] | None = None) -> Ran:
    """Run ``msctl ARGS`` here with ``MSCTL_HOME=home`` (and ``env``)."""
    from typer.testing import CliRunner

    from components.errors import ComponentError
    from msctl.app import app
    from msctl.errors import exit_code_of

    result = CliRunner().invoke(
        app,
        list(args),
        env={"MSCTL_HOME": str(home), "COLUMNS": "200", **(env or {})},
        catch_exceptions=True,
    )
    exc = result.exception
    if exc is None or isinstance(exc, SystemExit):
        code, exc = result.exit_code, None
    elif isinstance(exc, ComponentError):
        code = exit_code_of(exc)
    else:
        code = INTERNAL
    stderr = result.stderr
    if isinstance(exc, ComponentError):
        stderr += f"error: {exc}\n"  # main() prints it as this one line
    return Ran(code, result.stdout, stderr, exc)
