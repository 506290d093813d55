"""Standing a rehearsal's computers up: namespaces, the link emulator, assemble, agents.

What :func:`msctl.rehearse.rehearsal.up` does once the rehearsal is planned and written
down: :func:`make_computers` makes every computer and starts its agent (steps 2 to 5 of
:mod:`msctl.rehearse.rehearsal`), :func:`up_all` runs ``msctl up --all`` from the ground
station (step 6).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from msctl.rehearse.computers import (
    Computer,
    RehearseError,
    describe_processes,
    make_namespace,
    make_python_environment,
)

if TYPE_CHECKING:
    from msctl.rehearse.rehearsal import Progress, Rehearsal

#: The radio subnet every rehearsal uses (each computer's namespace has its own stack, so
#: two rehearsals never meet).
SUBNET = "10.77.0.0/24"
#: Seconds a computer's agent has to answer on the fleet after it starts.
AGENTS_WITHIN = 120.0
#: Lines of a crashed step's output shown (a fault handler's traceback is about this long).
CRASH_LINES = 40


def left(deadline: float, step: str, budget: float) -> float:
    """Seconds left of the rehearsal's one budget (``rehearse up --timeout``) for ``step``.

    Every step takes from the same budget: given the whole of it each, the steps of a loaded
    machine added up to several times what the user asked (a soak's ``--timeout 840`` was
    still running after 900 s).

    Args:
        deadline: When the budget ends (``time.monotonic()``).
        step: The command about to run, named if nothing is left for it.
        budget: The whole budget, in the message.

    Raises:
        OperationTimeout: If nothing is left, naming the step that was not reached (exit 5,
            as for a step that ran out).
    """
    from msctl.errors import OperationTimeout

    remaining = deadline - time.monotonic()
    if remaining <= 0:
        raise OperationTimeout(
            f"`{step}` did not finish within {budget:g} s: --timeout is one budget for every "
            "step, and the steps before it spent it",
            hint="give `msctl rehearse up` a longer --timeout (a loaded machine is slower)",
        )
    return remaining


def make_computers(
    rehearsal: Rehearsal, progress: Progress, deadline: float, budget: float
) -> None:
    """Make every computer (namespace, home, Python environment), the link emulator, each
    computer's assembly (and, secure, its net/), and start every agent; waits until the
    ground station sees them all, all before ``deadline`` (``time.monotonic()``).

    Raises:
        RehearseError: Naming the computer and the step that failed, or the step the
            deadline came before.
    """
    computers = rehearsal.computers
    progress.step(f"{len(computers)} computers: network namespaces")
    for computer in computers:
        make_namespace(computer, computers)
        computer.home.mkdir(parents=True, exist_ok=True)
        make_python_environment(computer)
    progress.step("radio links (link emulator)")
    rehearsal.emulator_pid = _start_emulator(rehearsal)
    rehearsal.save()
    progress.step(f"msctl assemble {rehearsal.template} on every computer")
    uses = [a for slot, unit in rehearsal.uses.items() for a in ("--use", f"{slot}={unit}")]
    assemble = ["msctl", "assemble", rehearsal.template, *uses]
    _on_every(rehearsal, assemble, left(deadline, " ".join(assemble), budget))
    if rehearsal.secure:
        ground = rehearsal.ground
        progress.step(f"{ground.name}: msctl net init; its net/ copied to every computer")
        from components.claims import default_holder

        # As the README says it: on the ground station, `msctl net init` makes you (user@ground1).
        done = rehearsal.run(
            ground, ["msctl", "net", "init"], left(deadline, "msctl net init", budget)
        )
        _check(done, ground, "msctl net init")
        rehearsal.operator = default_holder().split("@")[0] + "@" + ground.name
        rehearsal.save()
        # All but the CA's key, which stays on the ground station (README, "In the field").
        keep_key = shutil.ignore_patterns("ca.key")
        for computer in computers:
            if computer is not ground:
                shutil.copytree(
                    ground.home / "net", computer.home / "net", ignore=keep_key, dirs_exist_ok=True
                )
    progress.step("msctl agent on every computer")
    for computer in computers:
        rehearsal.start_agent(computer)
    progress.step("waiting for every agent to answer from the ground station")
    _wait_for_agents(rehearsal, min(left(deadline, "the agents answering", budget), AGENTS_WITHIN))


def _on_every(rehearsal: Rehearsal, argv: list[str], timeout: float) -> None:
    """Run ``argv`` on every computer at once; the first failure raises, naming its host."""
    from msctl.launcher.fanout import at_once

    results = at_once(lambda c: (c, rehearsal.run(c, argv, timeout)), rehearsal.computers)
    for computer, done in results:
        _check(done, computer, " ".join(argv))


def _check(done: subprocess.CompletedProcess[str], computer: Computer, what: str) -> None:
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        if done.returncode < 0:
            # Killed by a signal (a crash): its last words, a fault handler's traceback too.
            said = "\n".join(lines[-CRASH_LINES:]) if lines else "no output"
            raise RehearseError(
                f"`{what}` crashed on {computer.name} "
                f"({signal.Signals(-done.returncode).name}); its last output:\n{said}"
            )
        raise RehearseError(
            f"`{what}` failed on {computer.name} ({done.returncode}): "
            f"{lines[-1] if lines else 'no output'}"
        )


def _start_emulator(rehearsal: Rehearsal) -> int:
    """The access point: one emulator process for every computer's link; waits until ready."""
    spec = {
        "control": str(rehearsal.control_socket),
        "ready": str(rehearsal.root / "links.ready"),
        "seed": rehearsal.seed,
        "profiles_file": os.environ.get("MSCTL_LINK_PROFILES") or None,
        "subnet": SUBNET,
        "hosts": [
            {
                "name": c.name,
                "netns": c.netns,
                "address": c.address,
                "profile": c.profile,
                "device": "rh0",
            }
            for c in rehearsal.computers
        ],
    }
    spec_file = rehearsal.root / "links.json"
    spec_file.write_text(json.dumps(spec, indent=2))
    ready = Path(spec["ready"])
    ready.unlink(missing_ok=True)
    rehearsal.logs.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "msctl.rehearse.emulator", str(spec_file)]
    with open(rehearsal.logs / "links.log", "ab") as log:
        # Where the namespaces are: it enters each one to make its TUN device there.
        process = subprocess.Popen(
            rehearsal.privileges.command(argv),
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    deadline = time.monotonic() + 30.0
    while not ready.exists():
        if process.poll() is not None:
            tail = (rehearsal.logs / "links.log").read_text().strip().splitlines()[-1:]
            raise RehearseError(
                f"the link emulator exited ({process.returncode}): {tail[0] if tail else ''}",
                hint=f"see {rehearsal.logs / 'links.log'}",
            )
        if time.monotonic() > deadline:
            process.kill()
            raise RehearseError("the link emulator was not ready within 30 s")
        time.sleep(0.05)
    return process.pid


def _wait_for_agents(rehearsal: Rehearsal, timeout: float) -> None:
    """Until the ground station sees every computer's agent (its request service)."""
    from msctl.errors import OperationTimeout
    from msctl.launcher.control import host_namespace

    ground = rehearsal.ground

    wanted = {f"{host_namespace(c.name)}/request" for c in rehearsal.computers}
    deadline = time.monotonic() + timeout
    missing = wanted
    while True:
        try:
            done = rehearsal.run(ground, ["msctl", "service", "list", "--json"], timeout=30.0)
        except OperationTimeout:
            # A machine this loaded (five computers starting at once) is slow to answer, not
            # broken: asked again until the deadline, which says what is missing.
            done = subprocess.CompletedProcess([], 1, "", "")
        if done.returncode == 0:
            try:
                listed = json.loads(done.stdout)
            except ValueError:
                listed = []
            names = {s["name"] if isinstance(s, dict) else s for s in listed}
            missing = wanted - names
            if not missing:
                return
        for computer in rehearsal.computers:
            if not describe_processes(computer.netns, computer.privileges):
                raise RehearseError(
                    f"the agent of {computer.name} exited",
                    hint=f"see {rehearsal.logs / (computer.name + '.log')}",
                )
        if time.monotonic() > deadline:
            raise RehearseError(
                f"{ground.name} does not see the agents of "
                f"{', '.join(sorted(m.split('/')[2] for m in missing))} after {timeout:g} s",
                hint=f"see the logs in {rehearsal.logs}",
            )
        time.sleep(0.5)


def up_all(rehearsal: Rehearsal, deadline: float, budget: float) -> None:
    """``msctl up --all`` from the ground station, with what is left before ``deadline``.

    Raises:
        RehearseError: If it fails, or no time is left for it.
    """
    ground = rehearsal.ground
    timeout = left(deadline, "msctl up --all", budget)
    argv = ["msctl", "up", "--all", "--timeout", f"{timeout:g}"]
    if not rehearsal.secure:
        argv.append("--insecure")
    done = rehearsal.run(ground, argv, timeout=timeout + 30.0)
    _check(done, ground, " ".join(argv))
