"""``msctl view --rerun`` as a person looks at it: a simulated dragon, the view's web viewer
opened in headless Chromium (Debian's package, SwiftShader), screenshots checked for the robot
(pixels that are not background in the 3D view) and its motion (a jog of limb1 changes the
robot's silhouette on limb1's side); then the ``--save`` file read back with rerun's own reader.

One assembly and one view for the module. Needs chromium and the view extra (rerun-sdk).
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from chromium import CHROMIUM, Chromium
from conftest import free_port, wait_until
from running import ROOT, Up

rerun = pytest.importorskip(
    "rerun", reason="the view extra is not installed: pip install '.[view]'"
)

pytestmark = [
    pytest.mark.e2e,
    # Chromium compiles rerun's viewer (WebAssembly) and draws with SwiftShader on the CPU.
    pytest.mark.timeout(600),
    pytest.mark.skipif(
        CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)"
    ),
]

JOINT_STATE = "sensor_msgs/msg/JointState"
JOG_JOINT = "limb1_joint2"


class View:
    """``msctl view`` running against an assembly, its address read from stdout."""

    def __init__(self, up: Up, save: Path) -> None:
        self.save = save
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "msctl",
                "view",
                "--rerun",
                "--web",  # Chromium looks at the web viewer, whatever the display
                "--port",
                str(free_port()),
                "--grpc-port",
                str(free_port()),
                "--save",
                str(save),
            ],
            env=up.env,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        self.stderr: list[str] = []
        threading.Thread(target=self._read_err, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.strip())

    def _read_err(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.stderr.append(line.rstrip())

    def url(self) -> str:
        wait_until(lambda: self.lines or self.process.poll() is not None, 120, "the view's address")
        assert self.lines, "\n".join(self.stderr)
        return self.lines[0]

    def stop(self) -> int:
        """Ctrl-C, as a person ends it; its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            return self.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("view") / "home", "dragon", "--sim")
    try:
        yield up
    finally:
        up.down()


@pytest.fixture(scope="module")
def view(dragon: Up, tmp_path_factory: pytest.TempPathFactory) -> Iterator[View]:
    running = View(dragon, tmp_path_factory.mktemp("rrd") / "dragon.rrd")
    try:
        yield running
    finally:
        with contextlib.suppress(subprocess.TimeoutExpired):
            running.stop()


def viewport(picture: np.ndarray) -> np.ndarray:
    """The 3D view's part of a screenshot (its left part, below the title bar)."""
    height, width, _ = picture.shape
    return picture[int(0.11 * height) : int(0.93 * height), : int(0.62 * width)].astype(int)


def robot_mask(picture: np.ndarray) -> np.ndarray:
    """Pixels of the 3D view that are not its background (white, the light grid)."""
    view = viewport(picture)
    low, high = view.min(axis=2), view.max(axis=2)
    return (low < 200) | ((high - low) > 60)


def showing_3d(picture: np.ndarray) -> bool:
    """Whether the 3D view is up: its background is pure white (rerun's welcome page, shown
    until the recording arrives, is off-white with dark text)."""
    return float((viewport(picture) == 255).all(axis=2).mean()) > 0.6


class Jogger:
    """Sends limb1's joint2 a position, 20 times a second, as teleop would; watches where
    limb1's joint_read says it is."""

    def __init__(self, up: Up) -> None:
        from components.comm import Node, open_session

        self.session = open_session(up.settings())
        self.node = Node(self.session, "view_test_jog", "/")
        self.position: float | None = None
        self.node.subscription("/limb1/joint_read", JOINT_STATE, self._on_states)
        self.publisher = self.node.publisher("/limb1/joint_set", JOINT_STATE)
        self.target: float | None = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._send, daemon=True)
        self.thread.start()

    def _on_states(self, message: Any) -> None:
        names = list(message.name)
        if JOG_JOINT in names:
            self.position = float(message.position[names.index(JOG_JOINT)])

    def _send(self) -> None:
        from components.messages import msg

        while not self.stop.wait(0.05):
            if self.target is not None:
                self.publisher.publish(
                    msg(JOINT_STATE, name=[JOG_JOINT], position=np.array([self.target]))
                )

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.node.close()
        self.session.close()


def test_the_robot_shows_and_moves_with_a_jog(view: View, dragon: Up, tmp_path: Path) -> None:
    url = view.url()
    assert url.startswith("http://127.0.0.1:") and "rerun%2Bhttp" in url
    jogger = Jogger(dragon)
    try:
        with Chromium(url, width=960, height=640) as browser:
            masks: list[np.ndarray] = []

            def robot_seen_and_still() -> bool:
                try:
                    picture = browser.screenshot(tmp_path / "before.png")
                except RuntimeError:  # the page still loading
                    return False
                if not showing_3d(picture) or robot_mask(picture).sum() < 1000:
                    return False
                # Still: the viewer has caught up with what was drawn so far.
                masks.append(robot_mask(picture))
                return len(masks) >= 2 and int((masks[-1] ^ masks[-2]).sum()) < 150

            wait_until(robot_seen_and_still, 300, "the robot, still, in the viewer's 3D view")
            before = masks[-1]
            wait_until(lambda: jogger.position is not None, 60, "limb1's joint_read")
            start = jogger.position
            assert start is not None
            jogger.target = 0.8
            wait_until(
                lambda: jogger.position is not None and abs(jogger.position - start) > 0.3,
                60,
                f"{JOG_JOINT} moving",
            )
            width = before.shape[1]

            def limb_moved() -> bool:
                picture = browser.screenshot(tmp_path / "after.png")
                assert showing_3d(picture)
                after = robot_mask(picture)
                changed = before ^ after
                if changed.sum() < 200:
                    return False
                # limb1 reaches out along +x, to the right of the view (the camera looks
                # from -y): that is where the silhouette changed, not on limb2's side.
                xs = np.nonzero(changed)[1]
                return float(np.mean(xs)) > width * 0.5

            wait_until(limb_moved, 60, "limb1 moving in the picture")
    finally:
        jogger.close()


def test_the_saved_rrd_reads_back_with_rerun(view: View) -> None:
    """After the jog above (the tests of this module run in order, on one view)."""
    from rerun.chunk import RrdReader

    view.url()
    wait_until(lambda: view.save.exists() and view.save.stat().st_size > 0, 60, "the .rrd file")
    assert view.stop() == 0, "\n".join(view.stderr)
    assert any(f"saved {view.save}" in line for line in view.stderr), view.stderr
    reader = RrdReader(view.save)
    (recording,) = reader.recordings()
    assert recording.application_id == "msctl_view"
    rows: dict[str, list[Any]] = {}
    for chunk in reader.stream():
        rows.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    for module, link in [
        ("limb1", "limb1_link3"),
        ("limb2", "limb2_base_link"),
        ("wheel1", "wheel1_wheel_left_link"),
    ]:
        assert f"/robot/{module}/{link}" in rows, sorted(rows)
        assert f"/robot/{module}/{link}/visual_0" in rows
    assert "/status" in rows and "/alarms" in rows
    # limb1's palm was where joint2 put it: its transform changed over the recording.
    xs = [
        tuple(value)
        for batch in rows["/robot/limb1/limb1_palm_link"]
        for cell in batch.column("Transform3D:translation").to_pylist()
        if cell
        for value in cell
    ]
    assert len(xs) >= 2
    spread = np.ptp(np.array(xs), axis=0)
    assert float(np.max(spread)) > 0.05, xs
    text = " ".join(
        str(cell)
        for batch in rows["/status"]
        for cell in batch.column("TextDocument:text").to_pylist()
    )
    for module in ("limb1", "limb2", "wheel1", "wheel2"):
        assert module in text
