"""The teleop operator's thread with the real clock: the deadman runs without the screen (a
frozen screen still stops), close() puts the one stop on the wire before it returns, and an
output that fails does not end the thread. Outputs here only record what they are handed;
the wire itself is tested in test_teleop_tui.py."""

from __future__ import annotations

import threading
from typing import Any

from conftest import wait_until

from msctl.teleop.core import Move, Stop, TeleopCore, TeleopSettings
from msctl.teleop.keys import DRIVE, JOINT
from msctl.teleop.operator import Operator, Sent

MODULES = {"limb1": ("limb1_joint1",)}


class Recorder:
    """An output that notes every command (optionally failing on moves)."""

    def __init__(self, fail_moves: bool = False) -> None:
        self.lock = threading.Lock()
        self.commands: list[Any] = []
        self.fail_moves = fail_moves

    def move(self, move: Move) -> None:
        if self.fail_moves:
            raise RuntimeError("no joint_read for limb1_joint1 yet")
        with self.lock:
            self.commands.append(move)

    def stop(self, stop: Stop) -> None:
        with self.lock:
            self.commands.append(stop)

    def close(self) -> None:
        pass

    def stops(self) -> list[Stop]:
        with self.lock:
            return [c for c in self.commands if isinstance(c, Stop)]


def operator(output: Recorder, **settings: float) -> tuple[Operator, list[Sent]]:
    core = TeleopCore(TeleopSettings(**settings), MODULES, drive_target="/cmd_vel")
    sent: list[Sent] = []
    return Operator(core, {JOINT: output, DRIVE: output}, on_sent=sent.append).start(), sent


def test_the_deadman_stops_on_its_own_thread_when_no_key_comes() -> None:
    # One key, then nothing from the screen (as when it freezes): the stop still goes out.
    output = Recorder()
    op, sent = operator(output)
    try:
        assert op.press("w") == "move"
        wait_until(output.stops, timeout=30.0, what="the deadman's stop")
        wait_until(lambda: op.idle, timeout=30.0, what="the operator idle")
        (stop,) = output.stops()
        assert stop.reason == "deadman"
        assert isinstance(output.commands[0], Move) and output.commands[0].first
        assert output.commands[-1] is stop
        assert [s.ok for s in sent] == [True] * len(sent)
    finally:
        op.close()
    assert len(output.stops()) == 1  # closing with nothing moving sends nothing


def test_close_puts_the_one_stop_on_the_wire_before_it_returns() -> None:
    output = Recorder()
    op, _ = operator(output, first_timeout=600.0, repeat_timeout=600.0)
    op.press("w")
    wait_until(lambda: output.commands, timeout=30.0, what="the first move")
    op.close("quit")
    (stop,) = output.stops()
    assert stop.reason == "quit" and output.commands[-1] is stop
    assert op.press("w") == "refused"  # closed: keys do nothing any more
    op.close()  # idempotent
    assert len(output.stops()) == 1


def test_a_failing_output_is_reported_and_the_thread_goes_on() -> None:
    output = Recorder(fail_moves=True)
    op, sent = operator(output)
    try:
        op.press("w")
        wait_until(output.stops, timeout=30.0, what="the stop after failed moves")
        assert op.failures >= 1 and "no joint_read" in op.last_error
        assert "joint move of limb1 limb1_joint1" in op.last_error
        assert not sent[0].ok
        op.set_mode(DRIVE)
        output.fail_moves = False
        op.press("i")
        wait_until(
            lambda: any(isinstance(c, Move) and c.mode == DRIVE for c in output.commands),
            timeout=30.0,
            what="a drive command after the failures",
        )
    finally:
        op.close()
