"""``msctl health`` against a live simulated Dragon (``msctl up dragon --detach``): ``--once
--json``, ``--watch`` and ``--alarms`` as subprocesses, and the real screen in tmux.

The Dragon runs in its own MSCTL_HOME behind its own router; ``msctl down`` at the end.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from running import ROOT, Up

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("health_dragon"), "dragon")
    try:
        yield up
    finally:
        up.down()


def ps(up: Up) -> dict[str, dict[str, Any]]:
    result = up.msctl("ps", "--json")
    assert result.returncode == 0, result.stderr
    return {c["name"]: c for c in json.loads(result.stdout)["components"]}


def once(up: Up) -> tuple[int, dict[str, Any]]:
    result = up.msctl("health", "--once", "--json", "--timeout", "10")
    assert result.returncode in (0, 1), result.stderr
    return result.returncode, json.loads(result.stdout)


def components_ok(document: dict[str, Any], module: str) -> bool:
    row = next(m for m in document["modules"] if m["name"] == module)
    return all(i["level"] == "OK" for i in row["items"] if "/components/" in i["name"])


def test_once_json_is_one_snapshot_of_every_module_and_station(dragon: Up) -> None:
    code, document = once(dragon)
    assert set(document) == {"assembly", "level", "modules", "stations"}
    assert document["assembly"] == "dragon"
    assert sorted(m["name"] for m in document["modules"]) == ["limb1", "limb2", "wheel1", "wheel2"]
    assert [s["name"] for s in document["stations"]] == ["gc1"]
    for row in document["modules"]:
        assert set(row) == {"name", "host", "level", "message", "items"}
        names = {i["name"] for i in row["items"]}
        # The board's own items, then what the module's monitor reported.
        assert {f"{row['name']}/health", f"{row['name']}/components/joint_manager"} <= names
        assert f"{row['name']}/topics/joint_states" in names
        assert components_ok(document, row["name"]), row
    # The exit status follows the worst level (a busy test machine may make host/cpu ERROR).
    assert code == (0 if document["level"] in ("OK", "WARN") else 1)


def test_watch_prints_a_killed_component_as_error_and_alarms_reads_it_back(dragon: Up) -> None:
    wait_until(lambda: components_ok(once(dragon)[1], "wheel2"), timeout=60.0, what="wheel2 up")
    watcher = subprocess.Popen(
        [sys.executable, "-m", "msctl", "health", "--watch", "--json"],
        env=dragon.env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # Its first lines may be modules already WARN/ERROR (a busy machine's CPU); wait for
        # it to be listening, then kill wheel2's process.
        assert watcher.stderr is not None and watcher.stdout is not None
        assert "watching dragon" in watcher.stderr.readline()
        pid = ps(dragon)["wheel2/joint_manager"]["pid"]
        wait_until(lambda: _sees_wheel2(dragon), timeout=20.0, what="the watcher on the graph")
        os.kill(pid, signal.SIGKILL)
        seen: list[dict[str, Any]] = []
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            line = watcher.stdout.readline()
            if not line:
                break
            seen.append(json.loads(line))
            if any(a["module"] == "wheel2" and a["to"] == "ERROR" for a in seen):
                break
        error = next(a for a in seen if a["module"] == "wheel2" and a["to"] == "ERROR")
        assert set(error) == {"at", "module", "item", "from", "to", "message"}
        assert "wheel2" in error["item"]
    finally:
        watcher.send_signal(signal.SIGINT)
        watcher.wait(timeout=30.0)
    assert watcher.returncode == 130
    result = dragon.msctl("health", "--alarms", "--json")
    assert result.returncode == 0, result.stderr
    session = json.loads(result.stdout)
    assert session["source"] == "msctl health --watch" and session["assembly"] == "dragon"
    assert any(a["module"] == "wheel2" and a["to"] == "ERROR" for a in session["alarms"])
    # The supervisor restarts it; the next tests start from a healthy Dragon.
    wait_until(lambda: components_ok(once(dragon)[1], "wheel2"), timeout=60.0, what="wheel2 back")


def _sees_wheel2(up: Up) -> bool:
    """Whether a ``msctl health`` on the graph (the watcher) is there to see wheel2 go."""
    result = up.msctl("node", "list")
    return "msctl_health_" in result.stdout


# ---------------------------------------------------------------------------- tmux
def _tmux(*args: str) -> str:
    result = subprocess.run(
        ["tmux", *args], capture_output=True, text=True, timeout=30.0, check=True
    )
    return result.stdout


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_the_real_screen_in_tmux_shows_the_dragon_and_drills_down(dragon: Up) -> None:
    session = f"msctl-health-{os.getpid()}"
    env = " ".join(
        f"{k}={v}"
        for k, v in dragon.env.items()
        if k.startswith("MSCTL_") or k in ("PYTHONPATH", "CYDR_CACHE_DIR")
    )
    command = f"env {env} {sys.executable} -m msctl health"
    _tmux("new-session", "-d", "-s", session, "-x", "160", "-y", "48", command)
    try:

        def screen() -> str:
            return _tmux("capture-pane", "-p", "-t", session)

        text = wait_until(
            lambda: (s := screen()) and "wheel2" in s and "dragon" in s and s,
            timeout=60.0,
            what="the overview in tmux",
        )
        for module in ("limb1", "limb2", "wheel1", "wheel2", "gc1"):
            assert module in text
        _tmux("send-keys", "-t", session, "/", "")  # nothing bound: ignored
        # Drill down into the first row, then back, then quit.
        _tmux("send-keys", "-t", session, "Enter")
        wait_until(lambda: "Motors" in screen(), timeout=30.0, what="the drill-down")
        _tmux("send-keys", "-t", session, "Escape")
        wait_until(lambda: "Motors" not in screen(), timeout=30.0, what="back to the overview")
        _tmux("send-keys", "-t", session, "q")
        wait_until(
            lambda: (
                subprocess.run(
                    ["tmux", "has-session", "-t", session], capture_output=True, check=False
                ).returncode
                != 0
            ),
            timeout=30.0,
            what="msctl health to quit",
        )
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True, check=False)
    home = Path(dragon.home)
    assert (home / "health" / "alarms.jsonl").exists()
