"""A computer that reboots brings its part back by itself: the desired state an agent keeps on
disk (written, read, removed; refused whole when cut, edited or another computer's), what a
real :class:`~msctl.launcher.agent.Agent` does with it at its start when it must refuse, and
how the health board turns an agent's report into an item and an alarm (plain calls, fake
time). The rejoin across computers is tests/test_rehearse_rejoin_e2e.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
from conftest import wait_until

from components.data_monitor.plan import board_for, watched
from components.messages import ERROR, OK
from msctl.assembler import resolve
from msctl.launcher import desired, state
from msctl.launcher.agent import Agent, _why_back, desired_state_path

HOST = "hl-wheel-02"


@pytest.fixture(scope="module")
def dragon_document() -> dict[str, Any]:
    """The resolved dragon as ``up --all`` sends it (through JSON)."""
    return json.loads(json.dumps(resolve("dragon").document))


def wanted(document: dict[str, Any], host: str = HOST, **changes: Any) -> desired.DesiredState:
    fields = {
        "host": host,
        "template": "dragon",
        "assembly": document,
        "sim": None,
        "speed": 1.0,
        "asked_at": 1_700_000_000.0,
        **changes,
    }
    return desired.DesiredState(**fields)


# ---------------------------------------------------------------------------- the file
def test_a_desired_state_is_written_read_back_and_removed(tmp_path: Path, dragon_document):
    path = tmp_path / "agent" / desired.FILE_NAME
    assert desired.read(path, HOST) is None  # never asked: nothing to bring back
    desired.write(path, wanted(dragon_document, sim=True, speed=2.0))
    kept = desired.read(path, HOST)
    assert kept == wanted(dragon_document, sim=True, speed=2.0)
    assert [p.name for p in path.parent.iterdir()] == [desired.FILE_NAME]  # no temporary left
    document = json.loads(path.read_text())
    assert document["format"] == desired.FORMAT and document["version"] == desired.VERSION
    assert document["digest"] == desired.digest(dragon_document)
    assert desired.remove(path) is True
    assert desired.remove(path) is False  # a second down: nothing to remove, no error
    assert desired.read(path, HOST) is None


def test_a_write_that_fails_leaves_the_previous_desired_state_whole(
    tmp_path: Path, dragon_document
):
    path = tmp_path / desired.FILE_NAME
    desired.write(path, wanted(dragon_document))
    before = path.read_bytes()
    with pytest.raises(TypeError):  # fails midway through the JSON, as a full disk would
        desired.write(path, wanted({"template": "dragon", "bad": object()}))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [desired.FILE_NAME]


@pytest.mark.parametrize(
    ("content", "why"),
    [
        ('{"format": "msctl-desired-state", "version": 1, "host": "hl-wh', "not a desired state"),
        ("[1, 2]", "a JSON list, not an object"),
        ('{"format": "something-else"}', "'format' is 'something-else'"),
        ('{"format": "msctl-desired-state", "version": 9}', "'version' is 9"),
        ("\udcff", "cannot read"),
    ],
)
def test_a_file_that_is_not_a_desired_state_is_refused_naming_it(
    tmp_path: Path, content: str, why: str
):
    path = tmp_path / desired.FILE_NAME
    path.write_bytes(content.encode("utf-8", "surrogateescape"))
    with pytest.raises(desired.DesiredStateError) as caught:
        desired.read(path, HOST)
    text = str(caught.value)
    assert str(path) in text and why in text, text
    assert "msctl up --all" in text and f"remove {path}" in text, text  # what to do


def test_an_edited_assembly_or_a_bad_field_is_refused(tmp_path: Path, dragon_document):
    path = tmp_path / desired.FILE_NAME
    desired.write(path, wanted(dragon_document))
    document = json.loads(path.read_text())
    edited = json.loads(json.dumps(document))
    edited["assembly"]["template"] = "two_dragons"
    for changed, why in (
        (edited, "does not match its digest"),
        ({**document, "sim": "yes"}, "'sim' is 'yes'"),
        ({**document, "speed": True}, "'speed' is True"),
        ({**document, "assembly": []}, "'assembly' is missing or not a dict"),
    ):
        path.write_text(json.dumps(changed))
        with pytest.raises(desired.DesiredStateError, match=why):
            desired.read(path, HOST)


def test_another_computers_desired_state_is_refused(tmp_path: Path, dragon_document):
    path = tmp_path / desired.FILE_NAME
    desired.write(path, wanted(dragon_document, host="hl-limb-01"))
    with pytest.raises(desired.DesiredStateError, match=f"written for hl-limb-01, not .*{HOST}"):
        desired.read(path, HOST)


def test_a_directory_in_its_place_is_refused_not_a_crash(tmp_path: Path):
    path = tmp_path / desired.FILE_NAME
    path.mkdir()
    with pytest.raises(desired.DesiredStateError, match="cannot read"):
        desired.read(path, HOST)


# ---------------------------------------------------------------------------- the agent
@pytest.fixture
def agent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Agent]:
    """A real agent of hl-wheel-02 in its own MSCTL_HOME, not started (no network needed to
    judge a desired state it must refuse)."""
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path / "home"))
    lines: list[str] = []
    agent = Agent(HOST, log=lines.append)
    agent.lines = lines  # type: ignore[attr-defined]
    try:
        yield agent
    finally:
        agent.router.shutdown()


def test_without_a_desired_state_the_agent_stays_idle(agent: Agent):
    agent.rejoin_part()
    assert agent.rejoin is None and agent.launch is None
    assert agent.document().rejoin is msgspec.UNSET
    assert b'"rejoin"' not in msgspec.json.encode(agent.document())  # left off the wire


def test_a_desired_state_cut_short_is_reported_and_not_acted_on(agent: Agent):
    path = desired_state_path()
    path.parent.mkdir(parents=True)
    path.write_text('{"format": "msctl-desired-state", "ver')
    agent.rejoin_part()
    assert agent.launch is None
    report = agent.document().rejoin
    assert report.outcome == "refused" and str(path) in report.message, report
    assert report.agent_started <= report.at
    assert agent.document().state == "idle"
    assert any(str(path) in line for line in agent.lines)  # type: ignore[attr-defined]
    assert path.exists()  # left for the operator


def test_an_assembly_this_computer_no_longer_resolves_alike_is_refused(
    agent: Agent, dragon_document
):
    # The robot's data changed since `up --all` (another calibration, another template
    # version): what was asked is not what this computer would run now.
    changed = json.loads(json.dumps(dragon_document))
    changed["hosts"] = [*changed["hosts"], "hl-spare-01"]
    desired.write(desired_state_path(), wanted(changed))
    agent.rejoin_part()
    assert agent.launch is None
    report = agent.document().rejoin
    assert report.outcome == "refused"
    assert "did not bring back dragon" in report.message
    assert "differs from hl-wheel-02's own resolution" in report.message, report
    assert "hosts" in report.message


@pytest.fixture
def leftover(tmp_path: Path) -> Iterator[subprocess.Popen]:
    """A process of a previous run that outlived its agent (its own group, msctl's marker)."""
    process = subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.stdin.read()", "msctl"],
        stdin=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        yield process
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=10)


def test_processes_of_the_previous_run_still_alive_are_not_started_twice(
    agent: Agent, dragon_document, leftover: subprocess.Popen
):
    wait_until(lambda: state.group_alive(leftover.pid), timeout=30, what="the leftover running")
    state.write_state(
        {
            "host": HOST,
            "state": "running",
            "processes": [{"name": "wheel2", "pgid": leftover.pid}],
        }
    )
    desired.write(desired_state_path(), wanted(dragon_document))
    agent.rejoin_part()
    assert agent.launch is None
    message = agent.document().rejoin.message
    assert "still run with no supervisor (wheel2)" in message, message
    assert f"`msctl down` on {HOST}" in message


def test_a_down_forgets_the_desired_state_and_the_report(agent: Agent, dragon_document):
    path = desired_state_path()
    path.parent.mkdir(parents=True)
    path.write_text("not json")
    agent.rejoin_part()
    assert agent.rejoin is not None
    _payload, message = agent.handle("down", {})
    assert message == f"nothing was running on {HOST}"
    assert not path.exists() and agent.rejoin is None
    agent.rejoin_part()  # as at the next boot: nothing comes back
    assert agent.rejoin is None and agent.launch is None


def test_what_brought_the_agent_back_is_named_as_far_as_the_computer_can_tell():
    assert _why_back({"state": "running"}, this_boot=False) == "rebooted"
    assert _why_back({"state": "stopped"}, this_boot=False) == "rebooted"
    assert _why_back({"state": "running"}, this_boot=True) == "rebooted or lost power"
    assert _why_back({"state": "stopped"}, this_boot=True) == "restarted its agent"
    assert _why_back(None, this_boot=False) == "restarted"


# ---------------------------------------------------------------------------- the board
def _report(outcome: str, at: float, message: str) -> dict[str, Any]:
    return {"outcome": outcome, "at": at, "agent_started": at - 2.0, "message": message}


def test_an_agents_rejoin_is_an_item_and_an_alarm_of_every_row_on_its_computer():
    from components.assembly import from_document

    assembly = from_document(resolve("dragon").document)
    board = board_for(assembly)
    board.watch_graph(0.0)
    rows = [s.name for s in watched(assembly) if s.host == HOST]
    assert rows  # wheel2
    message = f"{HOST} rebooted or lost power and rejoined: its agent brought back ..."
    document = {
        "host": HOST,
        "components": [],
        "rejoin": _report("rejoined", 1_700_000_100.5, message),
    }
    board.on_supervisors([document], 1.0)
    alarms = board.take_alarms()
    assert [(a.module, a.item, a.before, a.after, a.message, a.at) for a in alarms] == [
        (row, f"{row}/agent", None, OK, message, 1_700_000_100.5) for row in rows
    ]
    snapshot = board.evaluate(1.1)
    for row in rows:
        item = next(i for i in snapshot.row(row).items if i.name == f"{row}/agent")
        assert item.level is OK and item.message == message
    others = [s.name for s in watched(assembly) if s.host != HOST]
    assert all(not any(i.name.endswith("/agent") for i in snapshot.row(r).items) for r in others)
    # The same report again, every second: no new alarm.
    board.on_supervisors([document], 2.0)
    board.evaluate(2.1)
    assert not [a for a in board.take_alarms() if a.item.endswith("/agent")]

    # A second board (an `msctl health` opened later) records the same alarm, merged as one.
    later = board_for(assembly)
    later.on_supervisors([document], 5.0)
    assert board.merge_history(later.alarms) == 0

    # The next up or down clears the report: the item goes, with no alarm.
    board.on_supervisors([{"host": HOST, "components": []}], 3.0)
    snapshot = board.evaluate(3.1)
    assert not any(i.name == f"{rows[0]}/agent" for i in snapshot.row(rows[0]).items)


def test_a_refused_rejoin_is_an_error_of_its_rows_and_malformed_reports_are_ignored():
    from components.assembly import from_document

    assembly = from_document(resolve("dragon").document)
    board = board_for(assembly)
    row = next(s.name for s in watched(assembly) if s.host == HOST)
    refused = _report("refused", 1_700_000_200.0, f"{HOST} rebooted but did not bring back")
    board.on_supervisors([{"host": HOST, "components": [], "rejoin": refused}], 1.0)
    snapshot = board.evaluate(1.1)
    item = next(i for i in snapshot.row(row).items if i.name == f"{row}/agent")
    assert item.level is ERROR and snapshot.row(row).level is ERROR
    alarm = next(a for a in board.take_alarms() if a.item == f"{row}/agent")
    assert alarm.after is ERROR and "did not bring back" in alarm.message
    for bad in ("yes", {"outcome": "rejoined", "at": "soon"}, {"at": float("nan")}):
        fresh = board_for(assembly)
        fresh.on_supervisors([{"host": HOST, "components": [], "rejoin": bad}], 1.0)
        snapshot = fresh.evaluate(1.1)
        assert not any(i.name.endswith("/agent") for i in snapshot.row(row).items)
        assert not [a for a in fresh.take_alarms() if a.item.endswith("/agent")]
    long = _report("rejoined", 1.0, "x" * 5000)
    board.on_supervisors([{"host": HOST, "components": [], "rejoin": long}], 2.0)
    assert len(board.take_alarms()[-1].message) <= 200  # bounded like every input
