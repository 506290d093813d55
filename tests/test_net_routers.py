"""This computer's router as `msctl up` and `msctl agent` start it: where it listens
(MSCTL_ROUTER_LISTEN), which routers it links to (MSCTL_ROUTER_CONNECT), what fails at once
(a port taken, an address that is not this computer's), and `msctl up --all`'s refusal of
agents behind a router that links over plain TCP.

Real routers and real `msctl` subprocesses, on free ports, multicast off. A wildcard listener
(0.0.0.0) is what MSCTL_ROUTER_LISTEN's field use is, so two of these bind it on a free port.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, wait_until

from components.comm.session import SessionSettings, open_session
from msctl.errors import InputError
from msctl.net import endpoints
from msctl.net.endpoints import EndpointError, check_listen, covers, parse, plain_links

#: What each failing command may take, start-up included: generous for a loaded machine,
#: and far below the 60 s of a supervisor's five restarts it replaces.
FAST = 10.0


def _base_env() -> dict[str, str]:
    # Nothing of the caller's msctl settings may leak into the computers played here.
    return {k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))}


def _client(endpoint: str) -> Any:
    return open_session(SessionSettings(mode="client", connect=(endpoint,), listen=()))


def _own_address() -> str | None:
    """A non-loopback IPv4 address of this computer, if it has one."""
    candidates = []
    with contextlib.suppress(OSError):
        candidates += [i[4][0] for i in socket.getaddrinfo(socket.gethostname(), None)]
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("192.0.2.254", 9))  # no packet is sent: it only picks the route's address
        candidates.append(s.getsockname()[0])
    for address in candidates:
        if "." in address and not address.startswith("127."):
            with contextlib.suppress(OSError), socket.socket() as probe:
                probe.bind((address, 0))
                return address
    return None


# --------------------------------------------------------------------------- pure rules
def test_a_wildcard_on_the_same_port_covers_loopback() -> None:
    assert covers("tcp/0.0.0.0:7447", "tcp/127.0.0.1:7447")
    assert covers("tcp/[::]:7447", "tcp/localhost:7447")
    assert not covers("tcp/0.0.0.0:7448", "tcp/127.0.0.1:7447")
    assert not covers("tls/0.0.0.0:7447", "tcp/127.0.0.1:7447")
    assert not covers("tcp/192.168.1.5:7447", "tcp/127.0.0.1:7447")
    assert parse("tcp/[::1]:7447").loopback and parse("tcp/[::]:7447").wildcard
    assert not parse("tcp/ground1:7448").loopback and parse("tls/ground1:7448").encrypted


def test_plain_tcp_beyond_this_computer_is_warned_of() -> None:
    from msctl.commands.router import plain_exposure

    assert plain_exposure(["tcp/127.0.0.1:7447"], ["tcp/localhost:7448"]) == ""
    assert plain_exposure(["tls/0.0.0.0:7448"], ["tls/ground1:7448"]) == ""
    said = plain_exposure(["tcp/127.0.0.1:7447", "tcp/0.0.0.0:7448"], ["tcp/ground1:7448"])
    assert "listens on tcp/0.0.0.0:7448; links to tcp/ground1:7448 over plain TCP" in said
    assert "MSCTL_SECURE=1" in said


def test_plain_links_are_those_leaving_the_computer_unencrypted() -> None:
    def router(zid: str, *links: tuple[str, str]) -> dict[str, Any]:
        sessions = [{"peer": "p", "whatami": "router", "links": [{"src": s, "dst": d}]}
                    for s, d in links]  # fmt: skip
        return {"zid": zid, "sessions": sessions}

    loopback = router("a", ("tcp/127.0.0.1:7447", "tcp/127.0.0.1:50000"))
    tls = router("b", ("tls/10.0.0.5:7448", "tls/10.0.0.7:41000"))
    assert plain_links([loopback, tls]) == []
    plain = router("c", ("tcp/10.0.0.5:7448", "tcp/10.0.0.7:41000"))
    other_end = router("d", ("tcp/10.0.0.7:41000", "tcp/10.0.0.5:7448"))
    found = plain_links([loopback, plain, other_end])
    assert len(found) == 1  # both routers report the one link
    assert "tcp/10.0.0.7:41000" in str(found[0])


def test_a_taken_port_names_who_holds_it_and_a_foreign_address_is_refused() -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(EndpointError) as taken:
            check_listen(f"tcp/0.0.0.0:{port}")
    said = str(taken.value)
    assert f"tcp/0.0.0.0:{port}" in said and f"pid {os.getpid()}" in said, said
    assert "no msctl router" in said and "MSCTL_ROUTER_LISTEN" in said, said
    # 198.51.100.0/24 is documentation space: no computer has it.
    with pytest.raises(EndpointError, match=r"198\.51\.100\.7 is not an address of this computer"):
        check_listen(f"tcp/198.51.100.7:{free_port()}")
    check_listen(f"tcp/127.0.0.1:{free_port()}")  # a free one passes


@pytest.mark.e2e
@pytest.mark.parametrize("command", ["up", "agent"])
def test_help_says_where_the_router_listens_and_links(command: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "msctl", command, "--help"],
        env={**_base_env(), "COLUMNS": "200"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    for variable in ("MSCTL_ROUTER_LISTEN", "MSCTL_ROUTER_CONNECT", "MSCTL_SECURE"):
        assert variable in done.stdout, done.stdout


# --------------------------------------------------------------------------- two computers
class Agent:
    """``msctl agent`` as one computer, its own home, its log in a file."""

    def __init__(self, root: Path, host: str, **env: str) -> None:
        self.host = host
        self.home = root / host
        self.home.mkdir(parents=True, exist_ok=True)
        self.log = root / f"{host}.log"
        self.local = f"tcp/127.0.0.1:{free_port()}"
        self.env = {
            **_base_env(),
            "MSCTL_HOME": str(self.home),
            "MSCTL_HOST": host,
            "MSCTL_ZENOH_CONNECT": self.local,
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            **env,
        }
        with self.log.open("w") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "msctl", "agent"],
                env=self.env,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def text(self) -> str:
        """What it said so far."""
        return self.log.read_text(errors="replace")

    def wait_serving(self) -> None:
        """Until it serves its request service (its router is up)."""
        wait_until(
            lambda: "idle until" in self.text() or self.proc.poll() is not None,
            60.0,
            f"{self.host}'s agent serving",
        )
        assert self.proc.poll() is None, self.text()

    def stop(self) -> None:
        """SIGINT, as Ctrl-C; killed if it hangs."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5)


@pytest.fixture(scope="module")
def linked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The README's plain field deployment on one machine: a ground station's agent whose
    router listens for the robots on every interface, and a robot computer's agent whose
    router listens on every interface on its loopback port and links to the station's."""
    root = tmp_path_factory.mktemp("linked")
    link_port = free_port()
    ground = Agent(root, "ground1", MSCTL_ROUTER_LISTEN=f"tcp/0.0.0.0:{link_port}")
    robot_port = free_port()
    robot = Agent(
        root,
        "hl-limb-01",
        MSCTL_ZENOH_CONNECT=f"tcp/localhost:{robot_port}",
        MSCTL_ROUTER_LISTEN=f"tcp/0.0.0.0:{robot_port}",
        MSCTL_ROUTER_CONNECT=f"tcp/127.0.0.1:{link_port}",
    )
    try:
        ground.wait_serving()
        robot.wait_serving()
        yield {"root": root, "ground": ground, "robot": robot, "link_port": link_port,
               "robot_port": robot_port}  # fmt: skip
    finally:
        robot.stop()
        ground.stop()


@pytest.mark.e2e
def test_a_wildcard_listener_on_the_loopback_port_replaces_it_loudly(
    linked: dict[str, Any],
) -> None:
    robot, port = linked["robot"], linked["robot_port"]
    said = robot.text()
    assert f"started a router listening on tcp/0.0.0.0:{port}, linked to" in said, said
    assert f"tcp/127.0.0.1:{port}" not in said  # the loopback listener was replaced
    # Loud: it listens beyond loopback in plain TCP (its link goes to loopback here).
    assert f"listens on tcp/0.0.0.0:{port} over plain TCP" in said, said
    assert "restart" not in (robot.home / "agent" / "logs" / "router.log").read_text()
    session = _client(f"tcp/127.0.0.1:{port}")  # loopback still reaches it
    try:
        assert list(session.info.routers_zid())
    finally:
        session.close()


@pytest.mark.e2e
def test_router_connect_links_the_computers_routers(linked: dict[str, Any]) -> None:
    """A client of each computer's router: data crosses the link both ways."""
    ground = _client(linked["ground"].local)
    robot = _client(f"tcp/127.0.0.1:{linked['robot_port']}")
    heard: dict[str, threading.Event] = {"ground": threading.Event(), "robot": threading.Event()}
    subscribers = [
        ground.declare_subscriber("0/limb1/joint_read/**", lambda _s: heard["ground"].set()),
        robot.declare_subscriber("0/limb1/joint_set/**", lambda _s: heard["robot"].set()),
    ]
    try:
        wait_until(
            lambda: robot.put("0/limb1/joint_read/t/h", b"x") or heard["ground"].is_set(),
            15.0,
            "the robot's sample at the ground station",
        )
        wait_until(
            lambda: ground.put("0/limb1/joint_set/t/h", b"x") or heard["robot"].is_set(),
            15.0,
            "the station's sample at the robot",
        )
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        robot.close()
        ground.close()


@pytest.mark.e2e
def test_routers_linked_on_loopback_do_not_trip_the_guard(
    linked: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.launcher.remote import refuse_plain_links

    monkeypatch.setenv("MSCTL_ZENOH_CONNECT", linked["ground"].local)
    monkeypatch.setenv("MSCTL_ZENOH_MULTICAST", "0")
    monkeypatch.delenv("MSCTL_IDENTITY", raising=False)
    refuse_plain_links()  # both routers answered, and their link stays on this computer
    session = _client(linked["ground"].local)
    try:
        documents = endpoints.router_documents(session)
    finally:
        session.close()
    assert documents is not None and len(documents) == 2, documents  # both routers answered


@pytest.mark.e2e
def test_a_port_held_by_another_agents_router_fails_at_once(linked: dict[str, Any]) -> None:
    port = linked["link_port"]
    home = linked["root"] / "third"
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "agent"],
        env={
            **_base_env(),
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": "hl-limb-02",
            "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
            "MSCTL_ZENOH_MULTICAST": "0",
            "MSCTL_ROUTER_LISTEN": f"tcp/0.0.0.0:{port}",
        },
        capture_output=True,
        text=True,
        timeout=60,
    )
    elapsed = time.monotonic() - started
    assert done.returncode == 2, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    assert f"cannot listen on tcp/0.0.0.0:{port}" in error, error
    assert f"the router of `msctl agent` (pid {linked['ground'].proc.pid})" in error, error
    assert "restart" not in done.stderr and elapsed < FAST, (elapsed, done.stderr)
    assert not (home / "agent" / "logs" / "router.log").exists()  # never started, never retried


@pytest.mark.e2e
def test_an_address_that_is_not_this_computers_fails_at_once(tmp_path: Path) -> None:
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "agent"],
        env={
            **_base_env(),
            "MSCTL_HOME": str(tmp_path),
            "MSCTL_HOST": "hl-limb-02",
            "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
            "MSCTL_ZENOH_MULTICAST": "0",
            "MSCTL_ROUTER_LISTEN": "tcp/198.51.100.7:7448",
        },
        capture_output=True,
        text=True,
        timeout=60,
    )
    elapsed = time.monotonic() - started
    assert done.returncode == 2, done.stderr
    error = done.stderr.strip().splitlines()[-1]
    assert "tcp/198.51.100.7:7448" in error and "not an address of this computer" in error
    assert "MSCTL_ROUTER_LISTEN" in error, error
    assert elapsed < FAST, (elapsed, done.stderr)


# --------------------------------------------------------------------------- the guard
@pytest.fixture(scope="module")
def plain_field(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """A station's router and a robot's router linked over plain TCP on this computer's
    network address (the link a field's radio would carry), each started as `msctl router`."""
    address = _own_address()
    if address is None:
        pytest.skip("this computer has no address beyond loopback to link two routers over")
    station = f"tcp/127.0.0.1:{free_port()}"
    link = f"tcp/{address}:{free_port()}"
    argvs = [
        ["router", "--listen", station, "--listen", link],
        ["router", "--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", link],
    ]
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "msctl", *argv, "--for", "300"],
            env=_base_env(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for argv in argvs
    ]
    try:
        for proc in procs:
            assert proc.stderr is not None
            line = proc.stderr.readline()
            while "listening on" not in line:
                assert line, "msctl router ended before it listened"
                line = proc.stderr.readline()
        session = _client(station)
        try:

            def linked() -> bool:
                found = plain_links(endpoints.router_documents(session) or [])
                return bool(found)

            wait_until(linked, 15.0, "the two routers' link")
        finally:
            session.close()
        yield {"station": station, "link": link, "address": address,
               "home": str(tmp_path_factory.mktemp("station"))}  # fmt: skip
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(timeout=20)


@pytest.mark.e2e
def test_up_all_refuses_agents_behind_a_router_linked_over_plain_tcp(
    plain_field: dict[str, str],
) -> None:
    """The command itself is on loopback; the station's router links to the robot over plain
    TCP: the requests would cross that network unencrypted all the same."""
    env = {
        **_base_env(),
        "MSCTL_HOME": plain_field["home"],
        "MSCTL_HOST": "ground1",
        "MSCTL_ZENOH_CONNECT": plain_field["station"],
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    started = time.monotonic()
    refused = subprocess.run(
        [sys.executable, "-m", "msctl", "up", "dragon", "--all", "--sim"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused.returncode == InputError.exit_code, refused.stderr
    said = " ".join(refused.stderr.split())
    assert "router link that is not TLS" in said and plain_field["link"] in said, said
    assert "--insecure" in said and "msctl net init" in said, said
    assert time.monotonic() - started < FAST
    # --insecure lets it through to the agents (there are none here: it says so).
    through = subprocess.run(
        [sys.executable, "-m", "msctl", "up", "dragon", "--all", "--insecure", "--timeout", "5"],
        env=env,
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert "not TLS" not in through.stderr
    assert "no agent answered" in through.stderr, through.stderr


@pytest.mark.e2e
def test_admin_space_answers_are_read_as_json(tmp_path: Path) -> None:
    """A plain `msctl router` describes itself; what it says is a JSON object with sessions."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "msctl", "router", "--listen", endpoint, "--for", "60"],
        env=_base_env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None and "listening on" in proc.stderr.readline()
        session = _client(endpoint)
        try:
            documents = endpoints.router_documents(session)
        finally:
            session.close()
        assert documents and isinstance(documents[0].get("sessions"), list), documents
        assert json.dumps(documents)  # plain data
    finally:
        proc.terminate()
        proc.wait(timeout=20)
