"""The ``msctl`` entry point: run the app and turn every failure into one line and an exit code.

Nothing is imported here before :func:`main` starts, so a Ctrl-C even while the commands are
being imported ends with one line and exit 130, not a traceback.
"""

from __future__ import annotations

import os
import sys

#: The exit status of a command stopped by Ctrl-C (128 + SIGINT), as shells report it.
INTERRUPTED = 130


def main() -> None:
    """Entry point: run the app and turn project errors into one red line and an exit code.

    Every error raised on purpose, the runtime's and the CLI's, is a
    :class:`~components.errors.ComponentError`; its exit code is its category's
    (:func:`msctl.errors.exit_code_of`), here and nowhere else.
    """
    from msctl.launcher.boot import enable_faulthandler

    # A crash in native code (Zenoh, MuJoCo) prints where each thread was, not just "-11".
    enable_faulthandler()
    try:
        from components.errors import ComponentError
        from msctl.errors import exit_code_of

        try:
            from msctl import quick

            # `msctl ps` and `msctl topic list` as typed all day skip typer's import.
            if not quick.run(sys.argv[1:]):
                from msctl.app import command

                # Standalone mode: typer prints its own usage errors and exits with code 2.
                command(sys.argv[1:])()
        except ComponentError as exc:
            from rich.markup import escape

            from msctl.console import err

            if os.environ.get("MSCTL_DEBUG") == "1":
                err.print_exception()
            # Escaped: an operator's text such as "[joints.joint3]" must print as written.
            err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
            sys.exit(exit_code_of(exc))
        except SystemExit as exc:
            # typer turns a Ctrl-C inside a command into a silent exit 130: say it once.
            if exc.code == INTERRUPTED and _from_ctrl_c(exc):
                _interrupted()
            raise
        except Exception as exc:
            if os.environ.get("MSCTL_DEBUG") == "1":
                raise
            from rich.markup import escape

            from msctl.console import err

            err.print(
                f"[bold red]internal error:[/] {type(exc).__name__}: {escape(str(exc))} "
                "(run again with MSCTL_DEBUG=1 for the traceback, and report it)",
                highlight=False,
            )
            sys.exit(70)
    except KeyboardInterrupt:
        _interrupted()
        sys.exit(INTERRUPTED)


def _from_ctrl_c(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is somewhere in ``exc``'s chain of causes."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def _interrupted() -> None:
    # Plain stderr: a second Ctrl-C while rich is being imported must not print a traceback.
    sys.stderr.write("interrupted\n")
    sys.stderr.flush()
