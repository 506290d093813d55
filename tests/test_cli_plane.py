"""``msctl router/topic/node/service`` end to end: real subprocesses against a real
``msctl router`` subprocess, with publishers, subscribers and servers in this process.

Checked: data reaches both ways, every ``--json`` output is exactly one JSON document, bad
input exits 2 with one line naming the field, no router exits 3 naming the endpoint.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import free_port, quick_peer_settings, wait_until

from components.comm import LATCHED, Node
from components.comm.session import SessionSettings
from components.comm.types import registry
from components.messages import msg

pytestmark = pytest.mark.e2e

MSCTL = shutil.which("msctl") or str(Path(sys.executable).with_name("msctl"))
STRING = "std_msgs/msg/String"
ADD = "example_interfaces/srv/AddTwoInts"


def _accepts(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: a real ``msctl router`` subprocess shared by this module."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen(
        [MSCTL, "router", "--listen", endpoint, "--for", "300"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_until(lambda: proc.poll() is not None or _accepts(port), timeout=10.0)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        yield endpoint
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError("msctl router ignored SIGTERM for 5 s") from None
    assert proc.returncode == 0, err
    assert "router stopped" in err


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def node(open_sessions: Callable[[], Any]) -> Iterator[Node]:
    """This process's node, ``/cli/probe``, joined to the router."""
    probe = Node(open_sessions(), "probe", "/cli")
    yield probe
    probe.close()


@pytest.fixture
def env(zenoh_env: dict[str, str]) -> dict[str, str]:
    """Environment for msctl subprocesses: the test router only."""
    return {**os.environ, **zenoh_env}


def msctl(*args: str, env: dict[str, str], timeout: float = 20.0) -> subprocess.CompletedProcess:
    """Run one msctl command to completion."""
    return subprocess.run(
        [MSCTL, *args], capture_output=True, text=True, env=env, timeout=timeout, check=False
    )


def one_json(stdout: str) -> Any:
    """The single JSON document on stdout (fails if there is more or less)."""
    document, end = json.JSONDecoder().raw_decode(stdout.lstrip())
    assert stdout.lstrip()[end:].strip() == "", f"more than one JSON document: {stdout!r}"
    return document


def one_error_line(stderr: str) -> str:
    """The one line an operator sees for a failure."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error:"), stderr
    return lines[0]


class Repeater:
    """Publishes a message every ``period`` seconds on a thread until closed."""

    def __init__(self, publish: Callable[[], None], period: float = 0.05) -> None:
        self._stop = threading.Event()
        self.error: Exception | None = None
        self._thread = threading.Thread(target=self._run, args=(publish, period), daemon=True)
        self._thread.start()

    def _run(self, publish: Callable[[], None], period: float) -> None:
        try:
            while not self._stop.wait(period):
                publish()
        except Exception as exc:  # surfaced by close(), not lost on the thread
            self.error = exc

    def close(self) -> None:
        """Stop publishing; re-raise what made the publisher fail, if anything did."""
        self._stop.set()
        self._thread.join(2.0)
        if self.error is not None:
            raise self.error


@pytest.fixture
def repeat() -> Iterator[Callable[..., Repeater]]:
    """Start background publishers; all are stopped at teardown."""
    started: list[Repeater] = []

    def start(publish: Callable[[], None], period: float = 0.05) -> Repeater:
        started.append(Repeater(publish, period))
        return started[-1]

    yield start
    for repeater in started:
        repeater.close()


# --------------------------------------------------------------------------- router
def test_router_for_a_duration(env: dict[str, str]) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    result = msctl("router", "--listen", endpoint, "--for", "0.5", env=env)
    assert result.returncode == 0, result.stderr
    assert f"listening on {endpoint}" in result.stderr
    assert "router stopped" in result.stderr
    assert time.monotonic() - started < 10.0


# --------------------------------------------------------------------------- topics
def test_topic_pub_reaches_our_subscription(node: Node, env: dict[str, str]) -> None:
    got: list[str] = []
    node.subscription("/cli/pub_in", STRING, lambda m: got.append(m.data))
    result = msctl(
        "topic", "pub", "/cli/pub_in", STRING, "{data: hi from cli}", "-t", "3", "-r", "20",
        env=env,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "publishing #3 on /cli/pub_in" in result.stderr
    assert "published 3 messages on /cli/pub_in: all 3 delivered to a matching subscriber" in (
        result.stderr
    )
    assert result.stdout == ""
    wait_until(lambda: len(got) >= 1)
    assert set(got) == {"hi from cli"}


def test_topic_pub_to_nobody_says_none_was_delivered_and_fails(env: dict[str, str]) -> None:
    args = ("topic", "pub", "/cli/nobody", STRING, "{data: x}", "-t", "3", "-r", "50")
    result = msctl(*args, "--wait-matching", "0.2", env=env)
    assert result.returncode == 1, result.stderr
    (line,) = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert "published 3 messages on /cli/nobody, no subscriber matched: none delivered" in line
    assert "--fire-and-forget" in line and result.stdout == ""
    # Publishing to nobody, on purpose: said all the same, and fine.
    forgot = msctl(*args, "--fire-and-forget", env=env)
    assert forgot.returncode == 0, forgot.stderr
    assert "no subscriber matched: none delivered (--fire-and-forget)" in forgot.stderr


def test_topic_pub_counts_what_a_subscriber_that_left_did_not_get(
    node: Node, env: dict[str, str]
) -> None:
    got: list[str] = []
    enough = threading.Event()

    def take(message: Any) -> None:
        got.append(message.data)
        if len(got) >= 3:
            enough.set()

    subscription = node.subscription("/cli/leaving", STRING, take)
    closer = threading.Thread(target=lambda: enough.wait(30.0) and subscription.close())
    closer.start()  # the subscription goes away after 3 messages, mid-run
    result = msctl(
        "topic", "pub", "/cli/leaving", STRING, "{data: x}", "-t", "40", "-r", "20", env=env
    )  # fmt: skip
    closer.join(30.0)
    assert result.returncode == 1, result.stderr
    said = re.search(
        r"published 40 messages on /cli/leaving: (\d+) delivered to a matching subscriber, "
        r"(\d+) published with none matching",
        result.stderr,
    )
    assert said, result.stderr
    delivered, missed = int(said[1]), int(said[2])
    assert delivered + missed == 40 and missed > 0
    # Never more claimed than the subscriber could have had: what it got was counted.
    assert 3 <= len(got) <= delivered, (got, delivered)


def test_topic_echo_once_json_finds_the_type(
    node: Node, env: dict[str, str], repeat: Callable[..., Repeater]
) -> None:
    pub = node.publisher("/cli/echo_out", "sensor_msgs/msg/JointState")
    state = msg("sensor_msgs/msg/JointState", name=["j1"], position=np.array([0.5]))
    repeat(lambda: pub.publish(state))
    result = msctl("topic", "echo", "/cli/echo_out", "--once", "--json", "--timeout", "5", env=env)
    assert result.returncode == 0, result.stderr
    document = one_json(result.stdout)
    assert document["name"] == ["j1"]
    assert document["position"] == [0.5]
    assert document["header"]["frame_id"] == ""


def test_topic_echo_yaml_n_times(
    node: Node, env: dict[str, str], repeat: Callable[..., Repeater]
) -> None:
    pub = node.publisher("/cli/echo_yaml", STRING)
    repeat(lambda: pub.publish(msg(STRING, data="tick")))
    result = msctl("topic", "echo", "/cli/echo_yaml", STRING, "-n", "2", env=env)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("---")[:2] == ["data: tick\n", "\ndata: tick\n"]


def test_topic_echo_latched_gets_the_last_sample(node: Node, env: dict[str, str]) -> None:
    pub = node.publisher("/cli/robot_plan", STRING, LATCHED)
    pub.publish(msg(STRING, data="old plan"))
    pub.publish(msg(STRING, data="current plan"))
    result = msctl(
        "topic", "echo", "/cli/robot_plan", "--latched", "--once", "--json", "--timeout", "5",
        env=env,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert one_json(result.stdout) == {"data": "current plan"}


def test_topic_hz_json(node: Node, env: dict[str, str], repeat: Callable[..., Repeater]) -> None:
    pub = node.publisher("/cli/hz", STRING)
    repeat(lambda: pub.publish(msg(STRING, data="x")), period=0.05)
    result = msctl("topic", "hz", "/cli/hz", "--for", "1.5", "--json", env=env)
    assert result.returncode == 0, result.stderr
    report = one_json(result.stdout)
    assert report["topic"] == "/cli/hz"
    assert 8.0 < report["rate"] < 30.0
    assert report["window"] >= 5
    assert 0.0 < report["min"] <= report["max"]


def test_topic_list_and_node_list_json(node: Node, env: dict[str, str]) -> None:
    node.publisher("/cli/listed", "sensor_msgs/msg/JointState")
    node.subscription("/cli/listed", "sensor_msgs/msg/JointState", lambda m: None)
    topics = one_json(msctl("topic", "list", "--json", env=env).stdout)
    entry = next(t for t in topics if t["name"] == "/cli/listed")
    assert entry == {
        "name": "/cli/listed",
        "types": ["sensor_msgs/msg/JointState"],
        "publishers": 1,
        "subscribers": 1,
    }
    text = msctl("topic", "list", "-v", env=env).stdout
    assert "/cli/listed [sensor_msgs/msg/JointState] 1 publisher(s), 1 subscriber(s)" in text
    result = msctl("node", "list", "--json", env=env)
    assert result.returncode == 0, result.stderr
    nodes = one_json(result.stdout)
    probe = next(n for n in nodes if n["name"] == "/cli/probe")
    assert probe == {"name": "/cli/probe", "namespace": "/cli", "zid": node.zid}
    assert not any(n["name"].startswith("/msctl_node_list_") for n in nodes)


# --------------------------------------------------------------------------- services
def test_service_list_and_call(node: Node, env: dict[str, str]) -> None:
    parts = registry().service(ADD)
    node.service("add_two_ints", ADD, lambda r: msg(parts.response, sum=r.a + r.b))
    listed = msctl("service", "list", "--json", env=env)
    assert listed.returncode == 0, listed.stderr
    entry = next(s for s in one_json(listed.stdout) if s["name"] == "/cli/add_two_ints")
    assert entry == {"name": "/cli/add_two_ints", "types": [ADD], "servers": 1}
    called = msctl("service", "call", "/cli/add_two_ints", ADD, "{a: 2, b: 40}", "--json", env=env)
    assert called.returncode == 0, called.stderr
    assert one_json(called.stdout) == {"sum": 42}
    # Without a type: found on the graph; YAML output.
    found = msctl("service", "call", "/cli/add_two_ints", env=env)
    assert found.returncode == 0, found.stderr
    assert found.stdout.strip() == "sum: 0"


def test_service_call_errors(node: Node, env: dict[str, str]) -> None:
    def refuse(request: Any) -> Any:
        raise RuntimeError("motor not homed")

    node.service("refuser", "std_srvs/srv/Trigger", refuse)
    refused = msctl("service", "call", "/cli/refuser", "std_srvs/srv/Trigger", env=env)
    assert refused.returncode == 3
    assert "motor not homed" in one_error_line(refused.stderr)
    missing = msctl(
        "service", "call", "/cli/nobody", "std_srvs/srv/Trigger", "--timeout", "0.5", env=env
    )
    assert missing.returncode == 5
    assert "/cli/nobody" in one_error_line(missing.stderr)
    bad_field = msctl("service", "call", "/cli/x", ADD, "{a: 1, c: 2}", env=env)
    assert bad_field.returncode == 2
    assert "'c'" in one_error_line(bad_field.stderr)
    # The wrong type for a served service: named at once, not a timeout.
    wrong = msctl("service", "call", "/cli/refuser", ADD, "{a: 1, b: 2}", env=env)
    assert wrong.returncode == 2
    line = one_error_line(wrong.stderr)
    assert "std_srvs/srv/Trigger" in line and ADD in line


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("args", "code", "named"),
    [
        (("topic", "pub", "/x", STRING, "{nope: 1}"), 2, "nope"),
        (("topic", "pub", "/x", STRING, "{data: [1, 2"), 2, "VALUES"),
        (("topic", "pub", "/x", STRING, "[1, 2]"), 2, "mapping"),
        (("topic", "pub", "/x", "sensor_msgs/msg/JointState", "{position: 3}"), 2, "position"),
        (("topic", "pub", "/x", "geometry_msgs/msg/Pose", "{position: {x: abc}}"), 2, "position.x"),
        (("topic", "pub", "/x", STRING, "{data: a}", "--rate", "0"), 2, "--rate"),
        (
            ("topic", "pub", "/x", STRING, "{data: a}", "--wait-matching", "-1"),
            2,
            "--wait-matching",
        ),
        # Out of the field's range: an internal error from the serializer, exit 70.
        (("topic", "pub", "/x", "std_msgs/msg/Int8", "{data: 300}"), 2, "'data' is a int8"),
        (("topic", "pub", "/x", "std_msgs/msg/UInt8", "{data: -1}"), 2, "'data' is a uint8"),
        (
            (
                "topic",
                "pub",
                "/x",
                "sensor_msgs/msg/JointState",
                "{header: {stamp: {sec: 99999999999}}}",
            ),
            2,
            "header.stamp.sec",
        ),
        # bool("false") is True: a quoted 'false' was published as true.
        (("topic", "pub", "/x", "std_msgs/msg/Bool", "{data: 'false'}"), 2, "'data' is a bool"),
        (("topic", "pub", "/x", "std_msgs/msg/Int32", "{data: 1.5}"), 2, "whole number"),
        (("topic", "pub", "/x", "nope_msgs/msg/Nothing", "{}"), 4, "nope_msgs/msg/Nothing"),
        (("topic", "pub", "/x", "NotAType", "{}"), 2, "NotAType"),
        (("topic", "echo", "/cli/silent", STRING, "--timeout", "0.3"), 5, "/cli/silent"),
        (("topic", "echo", "/cli/never_seen"), 4, "/cli/never_seen"),
        (("topic", "hz", "/x", STRING, "--window", "1"), 2, "--window"),
    ],
)
def test_bad_input_exits_with_one_line(
    env: dict[str, str], args: tuple[str, ...], code: int, named: str
) -> None:
    result = msctl(*args, env=env)
    assert result.returncode == code, result.stderr
    assert named in one_error_line(result.stderr)
    assert result.stdout == ""


@pytest.mark.parametrize(
    "args",
    [
        ("topic", "list"),
        ("node", "list", "--json"),
        ("service", "list", "--json"),
        ("topic", "pub", "/x", STRING, "{data: a}", "--once"),
    ],
)
def test_no_router_exits_3_naming_the_endpoint(args: tuple[str, ...]) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {
        **os.environ,
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    env.pop("MSCTL_ZENOH_MODE", None)
    result = msctl(*args, env=env)
    assert result.returncode == 3, result.stderr
    assert endpoint in one_error_line(result.stderr)
    assert result.stdout == ""


def test_bad_environment_exits_2_naming_the_variable(env: dict[str, str]) -> None:
    result = msctl("topic", "list", env={**env, "MSCTL_ZENOH_LEASE_MS": "soon"})
    assert result.returncode == 2
    assert "MSCTL_ZENOH_LEASE_MS" in one_error_line(result.stderr)


# --------------------------------------------------------------------------- wrong types
JOINTS = "sensor_msgs/msg/JointState"


def test_echo_of_a_mistyped_type_names_the_nearest_and_what_the_topic_carries(
    node: Node, env: dict[str, str]
) -> None:
    node.publisher("/cli/typed", JOINTS)
    result = msctl("topic", "echo", "/cli/typed", "std_msgs/msg/Strin", "--once", env=env)
    assert result.returncode == 4, result.stderr
    line = one_error_line(result.stderr)
    assert "did you mean 'std_msgs/msg/String'?" in line
    assert f"carries {JOINTS} (/cli/probe)" in line
    assert "a type msctl does not know" not in line


def test_echo_of_another_known_type_says_which_type_is_published(
    node: Node, env: dict[str, str]
) -> None:
    node.publisher("/cli/typed2", JOINTS)
    result = msctl("topic", "echo", "/cli/typed2", STRING, "--once", env=env)
    assert result.returncode == 2, result.stderr
    line = one_error_line(result.stderr)  # no dropped-sample noise before it
    assert f"carries {JOINTS} (/cli/probe), not {STRING}" in line


def test_pub_onto_a_topic_of_another_type_is_refused_unless_forced(
    node: Node, env: dict[str, str]
) -> None:
    node.subscription("/cli/guarded", JOINTS, lambda m: None)
    refused = msctl("topic", "pub", "/cli/guarded", STRING, "{data: x}", "--once", env=env)
    assert refused.returncode == 2, refused.stderr
    line = one_error_line(refused.stderr)
    assert JOINTS in line and "--force" in line and "publishing" not in refused.stderr
    forced = msctl(
        "topic", "pub", "/cli/guarded", STRING, "{data: x}", "--once", "--force", env=env
    )
    # Published, and honest about it: no subscriber takes a String there.
    assert forced.returncode == 1, forced.stderr
    assert "publishing #1 on /cli/guarded" in forced.stderr
    assert "no subscriber matched: none delivered" in forced.stderr


def test_service_call_reads_its_input_before_the_network() -> None:
    # No router at all: a parse error must still come first, as exit 2, not 3.
    env = {**os.environ, "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}"}
    env.update(MSCTL_ZENOH_LISTEN="tcp/127.0.0.1:0", MSCTL_ZENOH_MULTICAST="0")
    result = msctl("service", "call", "/x", "std_srvs/srv/Trigger", "{x", env=env)
    assert result.returncode == 2, result.stderr
    assert "VALUES is not valid YAML" in one_error_line(result.stderr)
    typo = msctl("service", "call", "/x", "std_srvs/srv/Trigge", env=env)
    assert typo.returncode == 4, typo.stderr
    assert "did you mean 'std_srvs/srv/Trigger'?" in one_error_line(typo.stderr)


def test_service_call_with_no_server_says_what_really_happened(env: dict[str, str]) -> None:
    started = time.monotonic()
    result = msctl("service", "call", "/cli/nope", "std_srvs/srv/Trigger", env=env)
    elapsed = time.monotonic() - started
    assert result.returncode == 5, result.stderr
    line = one_error_line(result.stderr)
    assert "/cli/nope" in line
    # Whatever it says must be true: it claims a 3 s wait only if it waited that long.
    if "within 3 s" in line:
        assert elapsed >= 3.0, line
    else:
        assert "ended after" in line and "no server of /cli/nope" in line


def test_unusable_session_settings_are_one_input_error(tmp_path: Path) -> None:
    """A runtime ConfigError from the session settings reaches the operator as msctl's own
    would (exit 2, its message as the one line), through the one mapping in msctl.cli.main;
    ``down --all`` still looks after this computer's run before it says so."""
    missing = tmp_path / "zenoh.json5"
    env = {
        **os.environ,
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_ZENOH_CONFIG": str(missing),
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    said = (
        f"error: MSCTL_ZENOH_CONFIG names {missing}, which is not a file; fix the path or unset it"
    )
    listing = msctl("topic", "list", env=env)
    assert listing.returncode == 2, listing.stderr
    assert one_error_line(listing.stderr) == said
    down = msctl("down", "--all", env=env)
    assert down.returncode == 2, down.stderr
    assert said in down.stderr.splitlines() and "internal error" not in down.stderr
