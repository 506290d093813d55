"""``msctl view --rerun``'s desktop window where there is a display, its web viewer elsewhere.

The choice is a pure function (plain calls). Then, on a real X server (Xvfb; the viewer
draws with Mesa's Vulkan, lavapipe), the real ``msctl view`` in a subprocess (the dragon's
lock, a real router, no robot running: the picture of an assembly whose modules have not
spoken): with ``DISPLAY`` set it opens rerun's own viewer window (found on the X server by
its title) and closes it on Ctrl-C; with a window that cannot open (no viewer binary; Mesa's
GL, which lacks a format the viewer needs) it says why in one line and serves the web viewer,
which answers; ``--web`` serves the web viewer with no window.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import select
import shutil
import signal
import subprocess
import sys
import threading
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, quick_router, wait_until

from msctl.view.window import WEB, WINDOW, choose_viewer

ROOT = Path(__file__).resolve().parents[1]
XVFB = shutil.which("Xvfb")
XWININFO = shutil.which("xwininfo")
VULKAN = glob.glob("/usr/share/vulkan/icd.d/*.json") + glob.glob("/etc/vulkan/icd.d/*.json")
#: How xwininfo lists rerun's viewer window: its class (the title is "Rerun").
TITLE = '("" "rerun")'


# ---------------------------------------------------------------------- the choice (Core)
def test_the_window_where_there_is_a_display_else_the_web() -> None:
    assert choose_viewer(None, {"DISPLAY": ":0"}) == (WINDOW, "display :0")
    assert choose_viewer(None, {"WAYLAND_DISPLAY": "wayland-0"}) == (WINDOW, "display wayland-0")
    assert choose_viewer(None, {"DISPLAY": ""}) == (WEB, "no DISPLAY or WAYLAND_DISPLAY")
    assert choose_viewer(False, {"DISPLAY": ":0"}) == (WEB, "--web")
    assert choose_viewer(True, {})[0] == WINDOW, "--window tries even with no display variable"


# ---------------------------------------------------------------------- on a real X server
#: What every test on the X server needs; each is an end-to-end test (subprocesses, X).
ON_X = [
    pytest.mark.e2e,
    pytest.mark.timeout(300),
    pytest.mark.skipif(XVFB is None, reason="Xvfb is not installed (apt-get install xvfb)"),
    pytest.mark.skipif(XWININFO is None, reason="xwininfo is missing (apt-get install x11-utils)"),
    pytest.mark.skipif(
        importlib.util.find_spec("rerun") is None,
        reason="the view extra is not installed: pip install '.[view]'",
    ),
]


def on_x(test: Any) -> Any:
    """Mark a test with :data:`ON_X`."""
    for mark in ON_X:
        test = mark(test)
    return test


@pytest.fixture(scope="module")
def display() -> Iterator[str]:
    """A real X server on a display number it picks (``-displayfd``: said once it is ready)."""
    assert XVFB is not None
    read, write = os.pipe()
    server = subprocess.Popen(
        [XVFB, "-displayfd", str(write), "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
        pass_fds=(write,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write)
    try:
        ready, _, _ = select.select([read], [], [], 60)
        assert ready, "Xvfb did not say its display within 60 s"
        yield f":{os.read(read, 64).decode().strip()}"
    finally:
        os.close(read)
        server.terminate()
        server.wait(timeout=30)


@pytest.fixture(scope="module")
def home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An MSCTL_HOME with the dragon resolved in it, as `msctl assemble dragon` leaves it."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path_factory.mktemp("window") / "home"
    write_resolution(home / "assembly", resolve("dragon", {}))
    return home


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    yield from quick_router()


def windows(display: str) -> str:
    """Every window of the X server, as xwininfo lists them."""
    assert XWININFO is not None
    return subprocess.run(
        [XWININFO, "-display", display, "-root", "-tree"],
        capture_output=True,
        text=True,
        timeout=30,
    ).stdout


class View:
    """``msctl view --rerun`` in a subprocess, its stdout and stderr lines collected."""

    def __init__(self, home: Path, router: str, env: dict[str, str], *options: str) -> None:
        self.process = subprocess.Popen(
            [
                *(sys.executable, "-m", "msctl", "view", "--rerun"),
                *("--port", str(free_port()), "--grpc-port", str(free_port())),
                *("--for", "240", *options),
            ],
            env={
                **{k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")},
                "MSCTL_HOME": str(home),
                "MSCTL_ZENOH_CONNECT": router,
                "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
                "MSCTL_ZENOH_MULTICAST": "0",
                **env,
            },
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.out: list[str] = []
        self.err: list[str] = []
        for stream, lines in ((self.process.stdout, self.out), (self.process.stderr, self.err)):
            threading.Thread(target=self._read, args=(stream, lines), daemon=True).start()

    @staticmethod
    def _read(stream: object, lines: list[str]) -> None:
        for line in stream:  # type: ignore[attr-defined]
            lines.append(line.rstrip())

    def said(self, text: str) -> str | None:
        """The first stderr line holding ``text``; fails at once if the view ended."""
        found = next((line for line in list(self.err) if text in line), None)
        if found is None and self.process.poll() is not None:
            pytest.fail(f"msctl view ended ({self.process.returncode}): {self.err}")
        return found

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait(timeout=30)


def web_viewer_answers(url: str) -> bool:
    with urllib.request.urlopen(url, timeout=30) as answer:
        return answer.status == 200 and b"<html" in answer.read().lower()


@on_x
@pytest.mark.skipif(not VULKAN, reason="no Vulkan driver: apt-get install mesa-vulkan-drivers")
def test_with_a_display_the_view_opens_rerun_s_window(
    home: Path, router: str, display: str
) -> None:
    view = View(home, router, {"DISPLAY": display})
    try:
        line = wait_until(lambda: view.said("in rerun's window"), 120, "the window line")
        assert f"(display {display})" in line
        wait_until(lambda: TITLE in windows(display), 60, "rerun's window on the X server")
        assert view.out and view.out[0].startswith("rerun+http://127.0.0.1:"), view.out
        assert not any("http://127.0.0.1" in o and "?url=" in o for o in view.out), "no web page"
    finally:
        code = view.stop()
    assert code == 0, view.err
    wait_until(lambda: TITLE not in windows(display), 60, "the window closed with the view")


@on_x
@pytest.mark.parametrize(
    ("why", "env", "reason"),
    [
        ("no viewer binary", {"RERUN_CLI_PATH": "/nonexistent/rerun"}, "no viewer binary at"),
        ("Mesa's GL", {"WGPU_BACKEND": "gl"}, "graphics driver"),
    ],
)
def test_a_window_that_cannot_open_falls_back_to_the_web_viewer(
    home: Path, router: str, display: str, why: str, env: dict[str, str], reason: str
) -> None:
    view = View(home, router, {"DISPLAY": display, **env})
    try:
        line = wait_until(lambda: view.said("no desktop window ("), 120, f"the fallback ({why})")
        print(f"\n{why}: {line}")
        assert line.endswith("serving the web viewer instead") and reason in line
        url = wait_until(lambda: next((o for o in view.out if "?url=" in o), None), 60, "url")
        assert url.startswith("http://127.0.0.1:")
        assert web_viewer_answers(url)
        assert TITLE not in windows(display)
    finally:
        assert view.stop() == 0, view.err


@on_x
def test_web_forces_the_web_viewer_even_with_a_display(
    home: Path, router: str, display: str
) -> None:
    view = View(home, router, {"DISPLAY": display}, "--web")
    try:
        url = wait_until(lambda: next((o for o in view.out if "?url=" in o), None), 120, "url")
        assert web_viewer_answers(url)
        assert not view.said("window") and TITLE not in windows(display)
    finally:
        assert view.stop() == 0, view.err
