"""Headless Chromium (Debian's package, SwiftShader for WebGL) driven over the DevTools
protocol: open a page, take screenshots, as a person looking at it would.

Only what the view's tests need: start, navigate, screenshot (PNG -> RGB array), close.
"""

from __future__ import annotations

import base64
import contextlib
import io
import itertools
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class Chromium:
    """One headless Chromium with one page.

    Args:
        url: The page to open (opened from the start: a navigation later swaps the page's
            process, and the DevTools session can lose it).
        width: Window width (px).
        height: Window height (px).
    """

    def __init__(self, url: str = "about:blank", width: int = 1280, height: int = 800) -> None:
        from websockets.sync.client import connect

        assert CHROMIUM, "chromium is not installed (apt-get install chromium)"
        self.profile = Path(tempfile.mkdtemp(prefix="msctl-chromium-"))
        self.process = subprocess.Popen(
            [
                CHROMIUM,
                "--headless",
                "--no-sandbox",
                "--no-first-run",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                # A headless page counts as hidden: keep its timers and frames running.
                "--disable-background-timer-throttling",
                "--disable-renderer-backgrounding",
                "--disable-backgrounding-occluded-windows",
                f"--window-size={width},{height}",
                "--remote-debugging-port=0",
                "--remote-debugging-address=127.0.0.1",
                f"--user-data-dir={self.profile}",
                url,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self._ids = itertools.count(1)
        self._stack = contextlib.ExitStack()
        try:
            port = self._port(timeout=120)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=120) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            self.socket = self._stack.enter_context(
                connect(pages[0]["webSocketDebuggerUrl"], max_size=64 << 20)
            )
        except BaseException:
            self.close()
            raise

    def _port(self, timeout: float) -> int:
        # Chromium writes the port it bound into the profile once it listens.
        marker = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if marker.exists() and marker.read_text().strip():
                return int(marker.read_text().split()[0])
            if self.process.poll() is not None:
                raise RuntimeError(f"chromium exited with {self.process.returncode}")
            time.sleep(0.05)
        raise TimeoutError("chromium did not open its DevTools port")

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command; its result."""
        ident = next(self._ids)
        self.socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            reply = json.loads(self.socket.recv(timeout=180))
            if reply.get("id") == ident:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def screenshot(self, path: Path | None = None) -> np.ndarray:
        """The page as an ``(height, width, 3)`` uint8 array (and a PNG at ``path``)."""
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            path.write_bytes(data)
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        """Stop Chromium and remove its profile (idempotent)."""
        self._stack.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
