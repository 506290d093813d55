"""Where ``msctl view --rerun`` shows the picture: rerun's desktop window where there is a
display, its web viewer otherwise.

With ``DISPLAY`` or ``WAYLAND_DISPLAY`` set, the view starts the wheel's own viewer binary
(``rerun_cli/rerun``, or ``RERUN_CLI_PATH`` as rerun's own launcher honours it) connected to
the recording's gRPC port: the same data path as the web viewer, with no browser, and the web
page is then not served (rerun serves it on every interface; a window needs no port at all).
``--web`` forces the web viewer, ``--window`` asks for the window even with no display
variable (say, a display the viewer finds by itself). A window that cannot open (no viewer
binary, no display, a graphics driver that lacks what the viewer needs) is found out by the
viewer process ending: the view then serves the web viewer, saying why in one line, also when
the window dies later. Closing the window ends the view, as Ctrl-C does.
"""

from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

WINDOW, WEB = "window", "web"
#: Seconds the viewer has to fail before the window counts as open (a failure later still
#: falls back, from the view's loop).
STARTUP_GRACE = 5.0
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def display_of(environ: Mapping[str, str]) -> str:
    """The display the environment names (``DISPLAY``, else ``WAYLAND_DISPLAY``), or ``""``."""
    return environ.get("DISPLAY", "") or environ.get("WAYLAND_DISPLAY", "")


def choose_viewer(window: bool | None, environ: Mapping[str, str]) -> tuple[str, str]:
    """Which viewer to show, and why.

    Args:
        window: ``True`` (``--window``), ``False`` (``--web``) or ``None`` (by the display).
        environ: The environment.

    Returns:
        ``(WINDOW or WEB, a few words why)``.
    """
    if window is False:
        return WEB, "--web"
    display = display_of(environ)
    if display:
        return WINDOW, f"display {display}"
    if window:
        return WINDOW, "--window (no DISPLAY or WAYLAND_DISPLAY set)"
    return WEB, "no DISPLAY or WAYLAND_DISPLAY"


def viewer_binary(environ: Mapping[str, str]) -> Path:
    """The viewer binary of the installed rerun-sdk wheel (``RERUN_CLI_PATH`` overrides)."""
    if environ.get("RERUN_CLI_PATH"):
        return Path(environ["RERUN_CLI_PATH"])
    import rerun_cli

    return Path(rerun_cli.__file__).parent / "rerun"


class NativeViewer:
    """rerun's desktop viewer in its own process, reading the recording from ``url``.

    Args:
        url: The recording's gRPC address (:attr:`~msctl.view.rerun_sink.RerunSink.grpc_url`).
        environ: The environment it runs in.
    """

    def __init__(self, url: str, environ: Mapping[str, str] | None = None) -> None:
        self.url = url
        self.environ = dict(os.environ if environ is None else environ)
        self.process: subprocess.Popen[str] | None = None
        self._said: collections.deque[str] = collections.deque(maxlen=40)

    def open(self, grace: float = STARTUP_GRACE) -> str:
        """Start the viewer; wait ``grace`` seconds for it to fail.

        Returns:
            ``""`` when it is running, else why it is not (one line).
        """
        binary = viewer_binary(self.environ)
        if not binary.is_file():
            return f"no viewer binary at {binary} (is rerun-sdk installed whole?)"
        try:
            self.process = subprocess.Popen(
                [str(binary), self.url],
                env=self.environ,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                errors="replace",
                start_new_session=True,  # Ctrl-C is the view's to handle, not the window's
            )
        except OSError as exc:
            return f"cannot start {binary}: {exc.strerror}"
        threading.Thread(target=self._read, daemon=True).start()
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return self.failure()
            time.sleep(0.1)
        return ""

    def _read(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        for line in self.process.stdout:
            self._said.append(_ANSI.sub("", line).strip())

    def ended(self) -> int | None:
        """Its exit code once it ended (0: the window was closed), else ``None``."""
        return None if self.process is None else self.process.poll()

    def failure(self) -> str:
        """Why it ended: its last error line, else its exit code."""
        code = self.ended()
        said = list(self._said)
        # Its last word ("Error: ..."), else its last ERROR log line (not a warning's words).
        for found in (
            [line.removeprefix("Error: ") for line in said if line.startswith("Error: ")],
            [line.split(" ERROR ", 1)[1].split(": ", 1)[-1] for line in said if " ERROR " in line],
        ):
            if found:
                return found[-1][:300]
        return f"the viewer ended with exit code {code}"

    def close(self) -> None:
        """Close the window (idempotent)."""
        if self.process is None or self.process.poll() is not None:
            return
        try:
            os.killpg(self.process.pid, signal.SIGTERM)
            self.process.wait(timeout=10)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            self.process.kill()
            self.process.wait(timeout=10)


class Showing:
    """The recording shown: in the window (:func:`choose_viewer`), else on the web.

    Args:
        sink: The :class:`~msctl.view.rerun_sink.RerunSink` serving the recording.
        window: ``--window`` / ``--web`` / ``None``.
        port: The web viewer's port (0: any free one), if it is served.
        what: What is viewed (the assembly or the bag), for the lines said.
        environ: The environment (the display).
    """

    def __init__(
        self,
        sink: Any,
        window: bool | None,
        port: int,
        what: str,
        environ: Mapping[str, str] | None = None,
    ) -> None:
        self.sink, self.port, self.what = sink, port, what
        self.environ = dict(os.environ if environ is None else environ)
        self.native: NativeViewer | None = None
        self.url = ""
        self.mode, self.why = choose_viewer(window, self.environ)

    def open(self) -> Showing:
        """Open the window, or serve the web viewer (also when the window cannot open)."""
        from msctl.console import err, out

        if self.mode == WINDOW:
            native = NativeViewer(self.sink.grpc_url, self.environ)
            reason = native.open()
            if not reason:
                self.native, self.url = native, self.sink.grpc_url
                out.print(self.url, highlight=False, soft_wrap=True)
                err.print(
                    f"viewing {self.what} in rerun's window ({self.why}): close it or Ctrl-C "
                    "to stop"
                )
                return self
            native.close()
            err.print(
                f"[yellow]no desktop window ({reason}): serving the web viewer instead[/]",
                highlight=False,
            )
        self._serve_web()
        return self

    def _serve_web(self) -> None:
        from msctl.commands.view import free_port
        from msctl.console import err, out

        self.mode = WEB
        self.url = self.sink.serve_web_viewer(self.port or free_port())
        out.print(self.url, highlight=False, soft_wrap=True)
        err.print(f"viewing {self.what}: open {self.url} (Ctrl-C to stop)")

    def closed(self) -> bool:
        """Whether the window was closed (the view ends then); a window that died serves
        the web viewer instead, saying so."""
        from msctl.console import err

        if self.native is None or self.native.ended() is None:
            return False
        if self.native.ended() == 0:
            err.print("the window was closed")
            return True
        reason, self.native = self.native.failure(), None
        err.print(
            f"[yellow]the desktop window ended ({reason}): serving the web viewer instead[/]",
            highlight=False,
        )
        self._serve_web()
        return False

    def close(self) -> None:
        """Close the window, if any (idempotent)."""
        if self.native is not None:
            self.native.close()
