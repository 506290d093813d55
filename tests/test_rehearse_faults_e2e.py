"""``msctl rehearse`` when things go wrong: bad options fail at once with nothing made, a
second rehearsal in the same home is refused, and ``down`` removes everything even after the
rehearsal itself was killed midway. Needs root; skipped, saying so, without it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import wait_until
from rehearse_rigs import ROOT_REHEARSAL

from msctl.rehearse.computers import namespaces
from msctl.rehearse.rehearsal import namespace_prefix

pytestmark = [
    pytest.mark.e2e,
    ROOT_REHEARSAL,
]


def _env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MSCTL_")}
    return {**env, "MSCTL_HOME": str(home)}


def _msctl(home: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=_env(home),
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
        check=False,
    )


def _left(home: Path) -> list[str]:
    prefix = namespace_prefix(home / "rehearse")
    return [n for n in namespaces() if n.startswith(prefix)]


def test_an_unknown_profile_fails_at_once_naming_the_known_ones(tmp_path: Path) -> None:
    done = _msctl(tmp_path, "rehearse", "up", "dragon", "--link", "fild-wifi", "--detach")
    assert done.returncode != 0
    assert "unknown link profile 'fild-wifi'" in done.stderr
    assert "field-wifi" in done.stderr  # known, and the nearest
    assert not _left(tmp_path) and not (tmp_path / "rehearse").exists()


def test_a_link_for_another_computer_is_refused(tmp_path: Path) -> None:
    done = _msctl(tmp_path, "rehearse", "up", "dragon", "--link", "ground9=wifi", "--detach")
    assert done.returncode != 0 and "--link names ground9" in done.stderr
    assert not _left(tmp_path)


def test_commands_without_a_rehearsal_say_how_to_start_one(tmp_path: Path) -> None:
    for args in (("status",), ("exec", "ground1", "--", "true"), ("link", "ground1", "--up")):
        done = _msctl(tmp_path, "rehearse", *args)
        assert done.returncode != 0
        assert "no rehearsal in" in done.stderr and "msctl rehearse up" in done.stderr


def test_down_after_the_rehearsal_was_killed_midway_leaves_nothing(tmp_path: Path) -> None:
    up = subprocess.Popen(
        [sys.executable, "-m", "msctl", "rehearse", "up", "dragon", "--no-up", "--detach"],
        env=_env(tmp_path),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # Killed once it has made computers and started links: the worst moment to crash.
        wait_until(
            lambda: len(_left(tmp_path)) == 5 and (tmp_path / "rehearse" / "links.ready").exists(),
            timeout=120,
            what="namespaces and links made",
        )
        up.send_signal(signal.SIGKILL)
        up.wait(30)
        again = _msctl(tmp_path, "rehearse", "up", "dragon", "--detach")
        assert again.returncode != 0 and "a rehearsal is already in" in again.stderr
        done = _msctl(tmp_path, "rehearse", "down")
        assert done.returncode == 0, done.stderr
    finally:
        if up.poll() is None:
            up.kill()
        _msctl(tmp_path, "rehearse", "down")
    assert not _left(tmp_path)
    assert not (tmp_path / "rehearse").exists()
    prefix = namespace_prefix(tmp_path / "rehearse")
    assert not list(Path("/etc/netns").glob(prefix + "*"))
    spec = str(tmp_path / "rehearse" / "links.json")
    emulators = subprocess.run(["pgrep", "-f", spec], capture_output=True, text=True).stdout
    assert not emulators.strip(), emulators


def test_a_step_that_outlasts_its_bound_is_named_and_nothing_is_left(tmp_path: Path) -> None:
    # A bound too short for the links (or the machine): the step that ran out is named (the
    # command; the computer too when it was running), exit 5 (a bounded wait ran out), and
    # nothing is left. --timeout is one budget: making the namespaces may spend it first.
    done = _msctl(tmp_path, "rehearse", "up", "dragon", "--no-up", "--detach", "--timeout", "0.1")
    assert done.returncode == 5, done.stderr
    assert "did not finish within" in done.stderr, done.stderr
    assert "msctl assemble dragon" in done.stderr and "internal error" not in done.stderr
    assert not _left(tmp_path)
    assert not (tmp_path / "rehearse").exists()
