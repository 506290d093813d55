"""``msctl bag pull``: the pure bookkeeping (what to fetch, resume, verification, rate) with plain
calls; the robot side's shelf (listing, reads, refusal of any path outside it) on real files;
and a real pull between two computers played on this one: an ``msctl agent`` subprocess with
its own MSCTL_HOME holding real bags, a real loopback router, and the ``msctl bag pull``
command run as the ground station."""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import wait_until

from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import message_definition
from components.recording.writer import BagWriter, TopicSpec
from msctl.launcher.control import RequestError, encode_args, host_namespace
from msctl.recorder import shelf
from msctl.recorder.pull_plan import (
    CONFLICT,
    FETCH,
    LEFT,
    SKIP,
    PullError,
    RemoteFile,
    decide,
    remote_files,
)
from msctl.recorder.pull_window import (
    ChunkWindow,
    RateBudget,
    RateMeter,
    ShortRead,
    request_timeout,
)

# The real pulls start an agent and run the command, each a Python start-up on a machine
# shared with other runs (345 s for this module at load 40): the default 120 s is too short.
pytestmark = pytest.mark.timeout(600)

STRING = "std_msgs/msg/String"
SHA = "ab" * 32


def remote(name: str = "b_0.mcap", size: int = 100, complete: bool = True) -> RemoteFile:
    return RemoteFile("bag", name, size, SHA if complete else None, complete)


# ----------------------------------------------------------------------------- decisions
def test_a_file_still_recorded_is_left_for_later() -> None:
    action = decide(remote(complete=False), None, None)
    assert action.kind == LEFT and "still being recorded" in action.why


def test_a_file_left_unfinished_by_a_killed_recorder_is_pulled_as_it_is() -> None:
    cut = RemoteFile("bag", "b_3.mcap", 100, SHA, complete=False, abandoned=True)
    action = decide(cut, None, None)
    assert action.kind == FETCH and "msctl bag recover" in action.why
    assert decide(cut, SHA, None).kind == SKIP
    # Finished there since (its recorder was only quiet): it replaces the cut copy here...
    assert decide(remote("b_3.mcap"), "cd" * 32, None, here_cut=True).kind == FETCH
    # ... and only a copy pulled cut short.
    assert decide(remote("b_3.mcap"), "cd" * 32, None, here_cut=False).kind == CONFLICT


def test_a_file_here_with_the_same_sha256_is_skipped() -> None:
    assert decide(remote(), SHA, None).kind == SKIP


def test_a_different_finished_file_of_the_same_name_is_never_overwritten() -> None:
    action = decide(remote(), "cd" * 32, None)
    assert action.kind == CONFLICT and "different file" in action.why


def test_metadata_changed_there_is_fetched_again() -> None:
    action = decide(remote("metadata.yaml"), "cd" * 32, None)
    assert action.kind == FETCH and action.offset == 0


def test_a_part_resumes_at_its_size_and_a_part_too_long_starts_over() -> None:
    assert decide(remote(size=100), None, 40) == (
        FETCH,
        remote(size=100),
        40,
        "resuming at byte 40",
    )
    assert decide(remote(size=100), None, 100).offset == 100  # whole: only verified
    assert decide(remote(size=100), None, 101).offset == 0
    assert decide(remote(size=100), None, 0).offset == 0


# ----------------------------------------------------------------------------- the window
def test_the_window_asks_in_order_and_writes_only_what_is_contiguous() -> None:
    window = ChunkWindow(size=25, start=0, chunk=10, window=2)
    assert window.asks() == [(0, 10), (10, 10)]
    assert window.asks() == []  # the window is full
    assert window.arrived(10, b"b" * 10) == b""  # early: held until byte 0 came
    assert window.written == 0
    assert window.asks() == [(20, 5)]
    assert window.arrived(0, b"a" * 10) == b"a" * 10 + b"b" * 10
    assert window.written == 20 and not window.done
    assert window.arrived(20, b"c" * 5) == b"c" * 5
    assert window.done and window.in_flight == 0


def test_a_chunk_with_no_answer_is_asked_again_before_any_new_one() -> None:
    window = ChunkWindow(size=40, start=0, chunk=10, window=2)
    window.asks()
    window.failed(0)
    assert window.asks() == [(0, 10)]
    window.arrived(10, b"x" * 10)
    window.failed(0)
    assert window.asks() == [(0, 10), (20, 10)]  # again, first
    assert window.arrived(0, b"y" * 10) == b"y" * 10 + b"x" * 10


def test_resuming_starts_at_the_part_and_asks_nothing_before_it() -> None:
    window = ChunkWindow(size=100, start=64, chunk=32, window=4)
    assert window.asks() == [(64, 32), (96, 4)]
    assert window.written == 64


def test_on_a_slow_link_the_bytes_in_flight_are_bounded_but_one_request_always_goes() -> None:
    window = ChunkWindow(size=100, start=0, chunk=10, window=8)
    assert window.asks(max_bytes=25) == [(0, 10), (10, 10)]
    assert window.bytes_in_flight == 20
    assert window.asks(max_bytes=25) == []
    window.arrived(0, b"a" * 10)
    assert window.asks(max_bytes=25) == [(20, 10)]
    window.failed(10)
    assert window.asks(max_bytes=5) == []  # one in flight already: nothing more
    window.arrived(20, b"c" * 10)
    assert window.asks(max_bytes=5) == [(10, 10)]  # none in flight: one goes, failed first


def test_a_chunk_of_another_length_is_refused() -> None:
    window = ChunkWindow(size=30, start=0, chunk=10, window=1)
    window.asks()
    with pytest.raises(ShortRead):
        window.arrived(0, b"short")
    with pytest.raises(ValueError, match="no request"):
        window.arrived(20, b"x" * 10)


def test_the_rate_budget_lets_a_burst_go_then_paces() -> None:
    budget = RateBudget(rate=1000.0, burst=500, now=0.0)
    assert budget.delay(500, now=0.0) == 0.0
    assert budget.delay(500, now=0.0) == pytest.approx(0.5)
    assert budget.delay(500, now=1.5) == pytest.approx(0.0)  # 1 s refilled 1000 (cap 500)
    assert RateBudget(rate=0, burst=1, now=0.0).delay(10**9, now=0.0) == 0.0


def test_a_request_may_wait_for_the_window_ahead_of_it_on_a_slow_link() -> None:
    # 256 kbit/s: four 64 KiB chunks in flight need 8 s; three times that, within patience.
    assert request_timeout(4 * 65536, 32_000, floor=10, ceiling=30) == pytest.approx(24.6, 0.01)
    assert request_timeout(4 * 65536, 32_000, floor=10, ceiling=20) == 20
    assert request_timeout(4 * 65536, 2_000_000, floor=10, ceiling=30) == 10  # fast: the floor
    assert request_timeout(4 * 65536, 0, floor=10, ceiling=30) == 10  # not known yet


def test_the_rate_meter_counts_from_the_first_request_and_knows_nothing_before_a_second() -> None:
    meter = RateMeter()
    meter.asked(now=100.0)  # the listing and planning before it are not the link's time
    meter.asked(now=100.2)
    meter.answered(50_000, now=100.5)
    assert meter.rate == 0.0
    meter.answered(50_000, now=102.0)
    assert meter.rate == pytest.approx(50_000)


# ----------------------------------------------------------------------------- listings
def test_a_listing_naming_a_path_is_refused_naming_the_host() -> None:
    for bad in ("../etc", "a/b", "..", ""):
        listing = {"bags": [{"name": bad, "files": []}]}
        with pytest.raises(PullError, match="hl-limb-01's bag listing is refused"):
            remote_files(listing, "hl-limb-01")
    listing = {"bags": [{"name": "b", "files": [{"name": "../x", "size": 1, "complete": False}]}]}
    with pytest.raises(PullError, match="not a plain name"):
        remote_files(listing, "hl-limb-01")
    listing = {"bags": [{"name": "b", "files": [{"name": "x", "size": 1, "complete": True}]}]}
    with pytest.raises(PullError, match="SHA-256"):
        remote_files(listing, "hl-limb-01")


def test_metadata_comes_last_in_its_bag() -> None:
    files = [
        {"name": n, "size": 1, "complete": True, "sha256": SHA}
        for n in ("metadata.yaml", "b_1.mcap", "b_0.mcap")
    ]
    listed = remote_files({"bags": [{"name": "b", "files": files}]}, "h")
    assert [f.name for f in listed] == ["b_0.mcap", "b_1.mcap", "metadata.yaml"]


# ----------------------------------------------------------------------------- the shelf
def write_bag(directory: Path, megabytes: float, files: int, finished: bool = True) -> Path:
    """A real bag of incompressible strings, split into about ``files`` files."""
    size = int(megabytes * 1e6)
    directory.parent.mkdir(parents=True, exist_ok=True)
    writer = BagWriter(directory, max_bytes=size // files + 1 if files > 1 else 0, fsync=False)
    topic = writer.add_topic(
        TopicSpec(
            "/limb1/chatter", STRING, registry().type_hash(STRING), (), message_definition(STRING)
        )
    )
    serialize = registry().serializer(STRING)
    start = time.time_ns()
    for i in range(size // 2000):
        writer.write(topic, start + i * 1000, serialize(msg(STRING, data=secrets.token_hex(1000))))
    if finished:
        writer.close()
    else:
        writer.tick()  # flushed so far, the last file left open as a recording leaves it
    return directory


def test_the_shelf_lists_complete_files_with_their_sha256(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "limb1_rec", 0.3, 3)
    (tmp_path / "not a bag.txt").write_text("x")
    listing = shelf.listing(tmp_path)
    (listed,) = listing["bags"]
    assert listed["name"] == "limb1_rec" and not listed["recording"]
    by_name = {f["name"]: f for f in listed["files"]}
    assert "metadata.yaml" in by_name and len(by_name) >= 3
    for name, entry in by_name.items():
        assert entry["complete"]
        assert entry["sha256"] == hashlib.sha256((bag / name).read_bytes()).hexdigest()


def test_an_mcap_file_being_written_is_incomplete_and_not_hashed(tmp_path: Path) -> None:
    write_bag(tmp_path / "open", 0.1, 1, finished=False)
    (listed,) = shelf.listing(tmp_path)["bags"]
    (mcap,) = [f for f in listed["files"] if f["name"].endswith(".mcap")]
    assert listed["recording"] and not mcap["complete"] and mcap["sha256"] is None
    assert not mcap["abandoned"]


def test_an_unfinished_file_left_unwritten_is_abandoned_and_hashed(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "killed", 0.1, 1, finished=False)
    (path,) = bag.glob("*.mcap")
    then = time.time() - shelf.STALE_SECONDS - 5
    os.utime(path, (then, then))  # as a recorder killed that long ago left it
    (listed,) = shelf.listing(tmp_path)["bags"]
    (mcap,) = [f for f in listed["files"] if f["name"].endswith(".mcap")]
    assert mcap["abandoned"] and not mcap["complete"] and not listed["recording"]
    assert mcap["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    (remote_mcap,) = [f for f in remote_files(shelf.listing(tmp_path), "h") if f.abandoned]
    assert remote_mcap.sha256 == mcap["sha256"]


def test_the_shelf_refuses_any_path_outside_it_naming_it(tmp_path: Path) -> None:
    root = tmp_path / "bags"
    write_bag(root / "b", 0.01, 1)
    (tmp_path / "secret").write_text("key")
    (root / "b" / "link").symlink_to(tmp_path / "secret")
    for path in ("../secret", "/etc/passwd", "b/../../secret", "b", "b/x/y", "b/link", 7, None):
        with pytest.raises(RequestError, match="not a bag file of robo") as raised:
            shelf.locate(path, "robo", root)
        assert str(root) in str(raised.value)
    with pytest.raises(RequestError, match="has no bag file b/nothing"):
        shelf.locate("b/nothing", "robo", root)
    assert shelf.locate("b/metadata.yaml", "robo", root) == (root / "b" / "metadata.yaml").resolve()


def test_a_read_returns_the_bytes_asked_within_bounds(tmp_path: Path) -> None:
    write_bag(tmp_path / "b", 0.01, 1)
    data = (tmp_path / "b" / "metadata.yaml").read_bytes()
    got = shelf.read({"path": "b/metadata.yaml", "offset": 5, "size": 10}, "robo", tmp_path)
    import base64

    assert base64.b64decode(got["data"]) == data[5:15] and got["file_size"] == len(data)
    for bad in ({"offset": -1, "size": 1}, {"offset": 0, "size": 0}, {"offset": 0, "size": 10**9}):
        with pytest.raises(RequestError, match="bag_read's"):
            shelf.read({"path": "b/metadata.yaml", **bad}, "robo", tmp_path)


# ----------------------------------------------------------------------------- a real pull
ROBOT = "robo-01"


def start_agent(env: dict[str, str], log_path: Path) -> subprocess.Popen[bytes]:
    """``msctl agent`` started, once it serves or has exited."""
    with log_path.open("w") as log:
        agent = subprocess.Popen(
            [sys.executable, "-m", "msctl", "agent"],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    wait_until(
        lambda: "serving" in log_path.read_text() or agent.poll() is not None,
        timeout=60,
        what="the agent serving",
    )
    return agent


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory, net_env: dict[str, str]) -> Iterator[Path]:
    """An agent subprocess as ROBOT, its home holding two finished bags and one still open."""
    home = tmp_path_factory.mktemp("robot")
    write_bag(home / "bags" / "limb1_data_archiver_a", 1.0, 4)
    write_bag(home / "bags" / "limb1_data_archiver_b", 0.2, 2)
    write_bag(home / "bags" / "limb1_data_archiver_open", 0.05, 1, finished=False)
    # Still being written, as far as the agent can tell, for the module's whole run.
    later = time.time() + 3600
    for path in (home / "bags" / "limb1_data_archiver_open").glob("*.mcap"):
        os.utime(path, (later, later))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))}
    env.update(net_env, MSCTL_HOME=str(home), MSCTL_HOST=ROBOT)
    # Started again if it gave up at once: an agent probes its router for 0.5 s
    # (router_reachable), which a machine at load 40 missed once; the agent then tried to
    # start a router of its own on the taken port and exited, saying so.
    log_path = home / "agent.log"
    for _attempt in range(3):
        agent = start_agent(env, log_path)
        if agent.poll() is None:
            break
    try:
        assert agent.poll() is None, log_path.read_text()
        yield home
    finally:
        agent.terminate()
        try:
            agent.wait(timeout=20)
        except subprocess.TimeoutExpired:
            agent.kill()
            agent.wait()


def pull(
    tmp: Path, net_env: dict[str, str], *args: str, host: str = ROBOT
) -> tuple[int, dict, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))}
    env.update(net_env, MSCTL_HOME=str(tmp / "ground"), MSCTL_HOST="ground1")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "msctl",
            "bag",
            "pull",
            host,
            "--into",
            str(tmp / "in"),
            "--json",
            *args,
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        stdin=subprocess.DEVNULL,
        check=False,
    )
    return done.returncode, json.loads(done.stdout) if done.stdout.strip() else {}, done.stderr


def finished_files(home: Path) -> dict[str, bytes]:
    """Every file a pull copies: all but the MCAP file still being written (its bag's
    metadata.yaml is whole, and comes as it is now)."""
    root = home / "bags"
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in root.rglob("*")
        if p.is_file() and not ("open" in p.parent.name and p.suffix == ".mcap")
    }


@pytest.mark.e2e
def test_a_pull_copies_every_finished_file_verified_and_a_second_skips_them(
    robot: Path, net_env: dict[str, str], tmp_path: Path
) -> None:
    code, report, stderr = pull(tmp_path, net_env)
    assert code == 0, stderr
    expected = finished_files(robot)
    assert {f["path"] for f in report["pulled"]} == set(expected)
    for path, data in expected.items():
        assert (tmp_path / "in" / path).read_bytes() == data
    assert not list((tmp_path / "in").rglob("*.part"))
    # The bag still recorded: its open MCAP file is left there, named, not a failure.
    (left,) = report["left"]
    assert left["path"].startswith("limb1_data_archiver_open/") and left["path"].endswith(".mcap")
    assert report["fetched_bytes"] >= 1.2e6
    code, again, stderr = pull(tmp_path, net_env)
    assert code == 0, stderr
    assert again["fetched_bytes"] == 0 and not again["pulled"]
    assert {f["path"] for f in again["skipped"]} == set(expected)


@pytest.mark.e2e
def test_a_pull_resumes_a_part_and_fetches_a_damaged_one_again(
    robot: Path, net_env: dict[str, str], tmp_path: Path
) -> None:
    bag = robot / "bags" / "limb1_data_archiver_a"
    first, second = sorted(bag.glob("*.mcap"))[:2]
    into = tmp_path / "in" / bag.name
    into.mkdir(parents=True)
    # A cut after 100 kB of the first file; the second's part holds wrong bytes.
    (into / (first.name + ".part")).write_bytes(first.read_bytes()[:100_000])
    (into / (second.name + ".part")).write_bytes(b"\x00" * 50_000)
    code, report, stderr = pull(tmp_path, net_env)
    assert code == 0, stderr
    pulled = {f["path"]: f for f in report["pulled"]}
    resumed = pulled[f"{bag.name}/{first.name}"]
    assert resumed["resumed_from"] == 100_000
    assert resumed["fetched"] == first.stat().st_size - 100_000  # nothing asked twice
    damaged = pulled[f"{bag.name}/{second.name}"]
    assert "second try" in damaged["why"]
    assert (into / first.name).read_bytes() == first.read_bytes()
    assert (into / second.name).read_bytes() == second.read_bytes()


@pytest.mark.e2e
def test_the_agent_refuses_a_path_outside_its_bags_naming_it(
    robot: Path, net_env: dict[str, str]
) -> None:
    from components.comm.node import Node
    from components.comm.session import SessionSettings, open_session
    from components.supervision.wire import SupervisorClient as AgentClient

    settings = SessionSettings(
        mode="client", connect=(net_env["MSCTL_ZENOH_CONNECT"],), listen=(), multicast=False
    )
    session = open_session(settings)
    try:
        with Node(session, "prober", "/") as node:
            client = AgentClient(node, f"{host_namespace(ROBOT)}/request")
            try:
                for path in ("../agent/assembly/assembly.lock.json", "/etc/passwd"):
                    args = encode_args({"path": path, "offset": 0, "size": 10})
                    answer = client.ask("bag_read", args, timeout=20)
                    assert not answer.success
                    assert f"is not a bag file of {ROBOT}" in answer.message
                    assert str(robot / "bags") in answer.message
            finally:
                client.close()
    finally:
        session.close()


@pytest.mark.e2e
def test_a_host_that_does_not_answer_is_named_and_the_pull_fails(
    robot: Path, net_env: dict[str, str], tmp_path: Path
) -> None:
    del robot
    code, report, stderr = pull(tmp_path, net_env, "--patience", "1", host="nobody-01")
    assert code == 3
    assert "nobody-01 did not answer within 1 s" in stderr
    assert report["ok"] is False and "nobody-01 gave no answer" in report["silent"]


@pytest.mark.e2e
def test_a_second_pull_into_the_same_directory_is_refused(
    robot: Path, net_env: dict[str, str], tmp_path: Path
) -> None:
    import fcntl

    del robot
    (tmp_path / "in").mkdir()
    with (tmp_path / "in" / ".pull.lock").open("a+") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)  # as a pull running would
        code, _report, stderr = pull(tmp_path, net_env)
    assert code == 3 and "another `msctl bag pull` is writing into" in stderr
    assert str(tmp_path / "in") in stderr


def test_the_command_refuses_a_host_that_is_not_a_name(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MSCTL_")}
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "bag", "pull", "../etc"],
        env={**env, "MSCTL_HOME": str(tmp_path)},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2 and "'../etc' is not a computer's name" in done.stderr
