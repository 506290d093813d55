"""The optional rclpy path: absent here (no ROS 2 install), it must refuse clearly, and the
worker must say what to do instead of failing obscurely. Everything else runs without it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from components.executor.rclpy_executor import RclpyExecutor, RclpyUnavailable

pytestmark = pytest.mark.skipif(
    __import__("importlib").util.find_spec("rclpy") is not None,
    reason="these check the refusal when rclpy is absent",
)


def test_rclpy_executor_refuses_with_what_to_do() -> None:
    with pytest.raises(RclpyUnavailable) as caught:
        RclpyExecutor()
    text = str(caught.value)
    assert "ROS 2 install" in text and "unset MSCTL_TRANSPORT" in text


def test_worker_on_rclpy_transport_exits_3_with_one_clear_line(tmp_path: Path) -> None:
    home = tmp_path / "home"
    env = {**os.environ, "MSCTL_HOME": str(home)}
    resolved = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "minimal"], env=env, capture_output=True
    )
    assert resolved.returncode == 0, resolved.stderr
    lock = home / "assembly" / "assembly.lock.json"
    worker = subprocess.run(
        [
            sys.executable,
            "-m",
            "components.executor.worker",
            "--lock",
            str(lock),
            "--component",
            "limb1/joint_manager",
        ],
        env={**env, "MSCTL_TRANSPORT": "rclpy"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert worker.returncode == 3
    assert worker.stderr.strip().splitlines()[-1].startswith("error: MSCTL_TRANSPORT=rclpy needs")


def test_unknown_transport_is_refused(tmp_path: Path) -> None:
    home = tmp_path / "home"
    env = {**os.environ, "MSCTL_HOME": str(home)}
    subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "minimal"],
        env=env,
        check=True,
        capture_output=True,
    )
    worker = subprocess.run(
        [
            sys.executable,
            "-m",
            "components.executor.worker",
            "--lock",
            str(home / "assembly" / "assembly.lock.json"),
            "--component",
            "limb1/joint_manager",
        ],
        env={**env, "MSCTL_TRANSPORT": "dds"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert worker.returncode == 2
    assert "MSCTL_TRANSPORT='dds'" in worker.stderr
