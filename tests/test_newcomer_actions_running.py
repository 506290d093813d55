"""Issue 18, what an action does to a running assembly, said exactly (point 9): a real
detached ``msctl up minimal``, acted on by real ``msctl`` subprocesses.

``tests/test_cli_running.py`` has the component-named restart and ``restart --only``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
from conftest import wait_until
from running import Up

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def minimal(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("newcomer_running"), "minimal")
    try:
        yield up
    finally:
        up.down()


def _rows(up: Up) -> dict[str, dict]:
    result = up.msctl("ps", "--json")
    assert result.returncode == 0, result.stderr
    return {row["name"]: row for row in json.loads(result.stdout)["components"]}


def _all_running(up: Up) -> dict[str, dict] | None:
    rows = _rows(up)
    return rows if all(r["state"] == "running" for r in rows.values()) else None


def _said(result) -> str:
    assert result.returncode == 0, result.stderr
    return " ".join(result.stderr.split())


def test_stop_names_the_components_it_takes_with_the_process(minimal: Up) -> None:
    before = wait_until(lambda: _all_running(minimal), 90.0, "all running", interval=0.5)
    others = sorted(n for n, r in before.items() if r["process"] == "limb1")
    others.remove("limb1/health_monitor")
    said = _said(minimal.msctl("stop", "limb1/health_monitor"))
    assert "process limb1 is stopped" in said, said
    assert all(name in said for name in others) and "share the process" in said, said
    rows = _rows(minimal)
    assert {rows[n]["state"] for n in [*others, "limb1/health_monitor"]} == {"stopped"}
    # A process named: its components are the process's own, no "--only limb1" (refused).
    said = _said(minimal.msctl("restart", "limb1"))
    assert "process limb1 is starting, and with it every component it runs" in said, said
    assert all(name in said for name in [*others, "limb1/health_monitor"]), said
    assert "--only limb1" not in said and "share the process" not in said, said
    assert "`msctl restart --only COMPONENT` restarts one of them alone" in said, said
    wait_until(lambda: _all_running(minimal), 90.0, "all running again", interval=0.5)
