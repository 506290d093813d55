"""``msctl bag play`` onto a live module: what a recording may not say, from the roles
(issue 32, cases 2 and 3).

A real joint manager of a Dragon's limb1, built from the resolved assembly, runs in this
process on a loopback router (random port, no multicast), fed ``joint_states`` by a node
named as the module's motor interface. ``msctl bag play`` runs as a real subprocess against
it, with a bag recorded from such a limb:

- a remap whose source is not a topic of the bag (a typo) is refused, naming the remap and
  listing the bag's topics, and nothing is published (case 2);
- the module's feedback (``joint_states``) is refused onto the live module, with or without
  ``--allow-commands``, and plays once remapped away (case 3).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.assembly import ResolvedAssembly
from components.build import build_component
from components.comm.node import Node
from components.comm.qos import SENSOR
from components.comm.session import SessionSettings, open_session
from components.comm.stats import drops
from components.comm.topics import INTRUDER
from components.comm.types import registry
from components.executor.executor import Executor
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state
from components.recording.definitions import message_definition
from components.recording.writer import BagWriter, TopicSpec
from msctl.errors import InputError

pytestmark = pytest.mark.e2e

MSCTL = shutil.which("msctl") or str(Path(sys.executable).with_name("msctl"))
#: A position no live component reports: what the bag says.
RECORDED = 0.42
MESSAGES = 8


@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture(scope="module")
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    return resolved_assembly(tmp_path_factory.mktemp("play_roles"), "dragon")


class LiveLimb:
    """limb1's real joint manager, fed by its motor interface, and an observer."""

    def __init__(self, assembly: ResolvedAssembly, settings: SessionSettings) -> None:
        self.built = build_component(assembly.component("limb1/joint_manager"), assembly)
        self.joint = assembly.module("limb1").actuated_joints[0]
        #: What the bag carries: RECORDED, calibrated (joint_read) and raw (joint_states).
        self.recorded = {RECORDED, self.joint.calibration.to_raw(RECORDED)}
        self.executor = Executor(settings=settings)
        self.executor.add(self.built.core, self.built.spec, self.built.namespace, "joint_manager")
        self.runner = threading.Thread(target=self.executor.run, daemon=True)
        self.runner.start()
        self.session = open_session(settings)
        self.motors = Node(self.session, "motor_interface", "/limb1")
        self.observer = Node(self.session, "observer", "/")
        self.lock = threading.Lock()
        self.heard: dict[str, int] = {}
        for topic in ("/limb1/joint_read", "/replay/limb1_states", "/limb1/joint_states"):
            self.observer.subscription(topic, JOINT_STATE, self._hear(topic), SENSOR)
        self._states = self.motors.publisher("joint_states", JOINT_STATE, SENSOR)
        self._stop = threading.Event()
        self._feeder = threading.Thread(target=self._feed, daemon=True)
        self._feeder.start()

    def _hear(self, topic: str) -> Any:
        def heard(message: Any) -> None:
            if any(s.position in self.recorded for s in joint_samples(message)):
                with self.lock:
                    self.heard[topic] = self.heard.get(topic, 0) + 1

        return heard

    def recorded_heard(self, topic: str) -> int:
        """Samples carrying the bag's position seen on ``topic``."""
        with self.lock:
            return self.heard.get(topic, 0)

    def _feed(self) -> None:
        raw = self.joint.calibration.to_raw(0.0)
        while not self._stop.wait(0.02):
            self._states.publish(joint_state([JointSample(self.joint.spec.name, raw, 0.0, 0.0)]))

    def position(self) -> float | None:
        sample = self.built.core.latest(self.joint.spec.name)
        return None if sample is None else sample.position

    def close(self) -> None:
        self._stop.set()
        self._feeder.join(timeout=5.0)
        self.motors.close()
        self.observer.close()
        self.session.close()
        self.executor.stop()
        self.runner.join(timeout=10.0)
        self.built.close()


@pytest.fixture(scope="module")
def limb(dragon: ResolvedAssembly, session_settings: SessionSettings) -> Iterator[LiveLimb]:
    live = LiveLimb(dragon, session_settings)
    try:
        wait_until(lambda: live.position() is not None, 60.0, "limb1's joint manager fed")
        yield live
    finally:
        live.close()


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory, limb: LiveLimb) -> Path:
    """A recording of limb1: its joint_states and joint_read, RECORDED everywhere."""
    path = tmp_path_factory.mktemp("bags") / "limb1"
    serialize = registry().serializer(JOINT_STATE)
    raw = limb.joint.calibration.to_raw(RECORDED)
    with BagWriter(path) as writer:
        topics = {
            name: writer.add_topic(
                TopicSpec(
                    name,
                    JOINT_STATE,
                    registry().type_hash(JOINT_STATE),
                    (),
                    message_definition(JOINT_STATE),
                )
            )
            for name in ("/limb1/joint_states", "/limb1/joint_read")
        }
        start = time.time_ns()
        for i in range(MESSAGES):
            for name, topic in topics.items():
                position = raw if name.endswith("states") else RECORDED
                row = [JointSample(limb.joint.spec.name, position, 0.0, 0.0)]
                writer.write(topic, start + i * 20_000_000, serialize(joint_state(row)))
    return path


@pytest.fixture(scope="module")
def env(router_endpoint: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    return {
        **os.environ,
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "MSCTL_HOME": str(tmp_path_factory.mktemp("home")),
    }


def play(env: dict[str, str], bag: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [MSCTL, "bag", "play", str(bag), *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_remap_of_a_topic_the_bag_lacks_is_refused_and_nothing_is_played(
    limb: LiveLimb, bag: Path, env: dict[str, str]
) -> None:
    done = play(env, bag, "--remap", "/limb1/joint_reed:=/replay")
    assert done.returncode == InputError.exit_code, done.stderr
    said = " ".join(done.stderr.split())  # rich wraps at its width
    assert "--remap /limb1/joint_reed:=/replay" in said, said
    assert "/limb1/joint_read, /limb1/joint_states" in said, said  # the bag's topics
    assert "Traceback" not in done.stderr
    assert limb.recorded_heard("/limb1/joint_read") == 0
    assert limb.position() != pytest.approx(RECORDED)


def test_feedback_is_refused_onto_a_live_module_even_with_allow_commands(
    limb: LiveLimb, bag: Path, env: dict[str, str]
) -> None:
    refused_before = drops.count("/limb1/joint_states", INTRUDER)
    for extra in ((), ("--allow-commands",)):
        done = play(env, bag, "--topics", "/limb1/joint_states", *extra)
        assert done.returncode == InputError.exit_code, done.stderr
        said = " ".join(done.stderr.split())
        assert "refusing to play /limb1/joint_states (feedback: only the module's own motor" in said
        assert "remap" in said, said
    # Nothing went out: not on the wire, not even refused by the joint manager.
    assert limb.recorded_heard("/limb1/joint_states") == 0
    assert drops.count("/limb1/joint_states", INTRUDER) == refused_before
    assert limb.position() == pytest.approx(0.0, abs=1e-9)


def test_feedback_remapped_away_plays(limb: LiveLimb, bag: Path, env: dict[str, str]) -> None:
    done = play(
        env,
        bag,
        "--topics",
        "/limb1/joint_states",
        "--remap",
        "/limb1/joint_states:=/replay/limb1_states",
        "--json",
    )
    assert done.returncode == 0, done.stderr
    assert f'"/replay/limb1_states": {MESSAGES}' in done.stdout, done.stdout
    wait_until(lambda: limb.recorded_heard("/replay/limb1_states") > 0, 30.0, "the replay heard")
    assert limb.position() == pytest.approx(0.0, abs=1e-9)
