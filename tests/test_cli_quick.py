"""The fast path of ``msctl ps`` and ``msctl topic list`` (issue 16, CLI).

Checked without timing anything:

* what the two commands import: run as a user runs them (a real subprocess against a real
  router), neither loads typer, pydantic, numpy, rosbags, mujoco, pinocchio or the assembly
  schema, and ``--json`` / plain lines load no rich either;
* the quick path and the typer commands cannot drift: every typer option is known to the
  quick path with the same default, and every form the quick path does not own reaches typer
  (its help, its errors);
* the supervisor request written without the type registry is byte for byte the registry's,
  its response is read as the registry reads it, and its key, token and errors are those of a
  registry-made client, against a real server.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import quick_peer_settings, quick_router, wait_until

from components.comm import Node
from components.comm.services import ServiceError, ServiceTimeout
from components.comm.session import SessionSettings, open_session
from components.comm.types import registry
from components.supervision.wire import (
    AGENT_SRV_HASH,
    decode_response,
    encode_request,
)
from components.supervision.wire import SupervisorClient as AgentClient
from msctl import quick
from msctl.launcher.control import AGENT_SRV

ROOT = Path(__file__).resolve().parents[1]
#: Never needed to list components or topics (each costs 0.05-0.3 s to import; hashlib,
#: which loads OpenSSL, logging, and dataclasses with the inspect it loads, 6-10 ms each).
HEAVY = (
    "typer",
    "pydantic",
    "numpy",
    "rosbags",
    "mujoco",
    "pinocchio",
    "components.assembly",
    "hashlib",
    "logging",
    "dataclasses",
    "inspect",
)
#: Loaded only to draw a table.
RICH = ("rich",)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


def _loaded_by(argv: list[str], endpoint: str, home: Path) -> tuple[set[str], str]:
    """The top-level packages ``msctl ARGV`` has imported when it exits, and its stdout."""
    probe = (
        "import atexit, sys\n"
        "atexit.register(lambda: sys.stderr.write('\\nLOADED ' + ' '.join(sys.modules)))\n"
        f"sys.argv = ['msctl', *{argv!r}]\n"
        "from msctl.cli import main\n"
        "main()\n"
    )
    env = {
        **os.environ,
        "MSCTL_HOME": str(home),
        "MSCTL_HOST": "test-laptop",
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }
    done = subprocess.run(
        [sys.executable, "-c", probe],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    loaded = set(done.stderr.rsplit("LOADED ", 1)[1].split())
    return loaded, done.stdout


def _heavy(loaded: set[str], names: tuple[str, ...]) -> list[str]:
    return sorted(n for n in names if n in loaded or any(m.startswith(n + ".") for m in loaded))


@pytest.mark.parametrize(
    "argv",
    [
        ["ps", "--json"],
        ["ps", "--json", "--timeout", "1.5"],
        ["ps", "--all", "--json"],
        ["topic", "list", "-t"],
        ["topic", "list", "-v", "--json"],
    ],
)
def test_listing_commands_import_nothing_heavy(
    argv: list[str], router_endpoint: str, session_settings: SessionSettings, tmp_path: Path
) -> None:
    """A real listing against a real router (a publisher on it) loads no framework, no
    numerics, no codec, no rich."""
    with open_session(session_settings) as session:
        node = Node(session, "talker", "/probe")
        node.publisher("chatter", "std_msgs/msg/String")
        loaded, stdout = _loaded_by(argv, router_endpoint, tmp_path)
        node.close()
    assert _heavy(loaded, HEAVY + RICH) == []
    if "--json" in argv:
        json.loads(stdout)  # exactly one document
    if argv[0] == "topic" and "--json" not in argv:
        assert "/probe/chatter [std_msgs/msg/String]" in stdout.splitlines()
    if argv[0] == "topic" and "--json" in argv:
        assert {
            "name": "/probe/chatter",
            "types": ["std_msgs/msg/String"],
            "publishers": 1,
            "subscribers": 0,
        } in json.loads(stdout)


def test_ps_table_loads_nothing_heavy_not_even_rich(router_endpoint: str, tmp_path: Path) -> None:
    """``msctl ps`` with nothing running says so (on stderr) and loads nothing heavy: its
    table is plain aligned columns (msctl.console.print_table)."""
    loaded, stdout = _loaded_by(["ps"], router_endpoint, tmp_path)
    assert _heavy(loaded, HEAVY + RICH) == []
    assert stdout == ""


def test_ps_reads_the_plan_without_the_lock_schema(router_endpoint: str, tmp_path: Path) -> None:
    """With a resolved Dragon here and nothing running, ``msctl ps`` names the plan's hosts
    it did not ask (on stderr), exits 0, and the lock's schema (msgspec, the module specs)
    is not loaded to read them."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    write_resolution(tmp_path / "assembly", resolve("dragon", {}), mjcf=False)
    loaded, stdout = _loaded_by(["ps", "--json"], router_endpoint, tmp_path)
    assert _heavy(loaded, (*HEAVY, *RICH, "msgspec")) == []
    assert [u["host"] for u in json.loads(stdout)["unreachable"]] == [
        "hl-limb-01",
        "hl-limb-02",
        "hl-wheel-01",
        "hl-wheel-02",
        "ground1",
    ]


# ----------------------------------------------------------------------- quick path vs typer
def _typer_params(words: tuple[str, ...]) -> dict[str, object]:
    from msctl.app import command

    click_command = command(list(words))
    for word in words:
        click_command = click_command.commands[word]
    return {p.name: p for p in click_command.params}


@pytest.mark.parametrize("quick_command", quick.COMMANDS, ids=lambda q: " ".join(q.words))
def test_quick_path_knows_every_typer_option_with_its_default(
    quick_command: quick.QuickCommand,
) -> None:
    """Each typer option: every spelling in the quick path, a flag as a flag, the same
    default as the function the quick path calls; no quick spelling typer lacks."""
    params = _typer_params(quick_command.words)
    defaults = quick_command.defaults()
    assert set(params) == set(defaults)
    spelled: dict[str, str] = {**quick_command.flags, **quick_command.numbers}
    for name, param in params.items():
        for opt in param.opts:
            assert spelled.get(opt) == name, f"{opt} of {' '.join(quick_command.words)}"
            assert (opt in quick_command.flags) == param.is_flag, opt
        assert param.default == defaults[name], name
    typer_spellings = {opt for p in params.values() for opt in p.opts}
    assert set(spelled) <= typer_spellings


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["ps"], {}),
        (["ps", "--json", "--timeout", "0.5"], {"json_output": True, "timeout": 0.5}),
        (["ps", "--all"], {"all_hosts": True}),
        (["topic", "list", "-t", "--verbose"], {"show_types": True, "verbose": True}),
        (["topic", "list", "-v", "--json"], {"verbose": True, "json_output": True}),
        # Everything else is typer's: help, typos, other spellings and numbers.
        (["ps", "--help"], None),
        (["ps", "--jsn"], None),
        (["ps", "--timeout=5"], None),
        (["ps", "--timeout"], None),
        (["ps", "--timeout", "-1"], None),
        (["ps", "--timeout", "1e3"], None),
        (["ps", "extra"], None),
        (["topic", "list", "-tv"], None),
        (["topic", "echo", "/x"], None),
        (["topic"], None),
        (["--help"], None),
        ([], None),
    ],
)
def test_quick_path_owns_only_the_plain_forms(argv: list[str], expected: dict | None) -> None:
    """The arguments the quick path would call with, or None where typer must parse."""
    parsed = [q.parse(argv) for q in quick.COMMANDS]
    found = [p for p in parsed if p is not None]
    assert found == ([] if expected is None else [expected])


def test_forms_the_quick_path_leaves_reach_typer(tmp_path: Path) -> None:
    """``--help`` is typer's help, a bad number typer's usage error (exit 2)."""
    env = {**os.environ, "MSCTL_HOME": str(tmp_path), "PYTHONPATH": str(ROOT)}
    run = {"env": env, "capture_output": True, "text": True, "timeout": 60, "cwd": ROOT}
    shown = subprocess.run([sys.executable, "-m", "msctl", "ps", "--help"], **run)
    assert shown.returncode == 0 and "--timeout" in shown.stdout, shown.stderr
    bad = subprocess.run([sys.executable, "-m", "msctl", "ps", "--timeout", "soon"], **run)
    assert bad.returncode == 2 and "--timeout" in bad.stderr, bad.stderr


# ------------------------------------------------------------------ supervisor request, by hand
@pytest.mark.parametrize(
    ("verb", "args"),
    [
        ("ps", "{}"),
        ("logs", '{"component":"limb1/joint_manager","lines":20}'),
        ("", ""),
        ("up", '{"a":"ü→"}'),
    ],
)
def test_request_is_the_registry_s_bytes(verb: str, args: str) -> None:
    """Each string 4-aligned with its length and NUL, as the registry's codec writes it."""
    parts = registry().service(AGENT_SRV)
    request = registry().msg_class(parts.request)(verb=verb, args=args)
    assert encode_request(verb, args) == registry().serializer(parts.request)(request)


@pytest.mark.parametrize(
    ("success", "message", "payload"),
    [(True, "", "{}"), (False, "no such component", ""), (True, "ok", '{"host":"ü","n":[1,2]}')],
)
def test_response_reads_as_the_registry_reads_it(success: bool, message: str, payload: str) -> None:
    parts = registry().service(AGENT_SRV)
    response = registry().msg_class(parts.response)(
        success=success, message=message, payload=payload
    )
    data = registry().serializer(parts.response)(response)
    read = decode_response(data)
    assert (read.success, read.message, read.payload) == (success, message, payload)


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\x00\x01\x00\x00",
        b"\x00\x07\x00\x00\x01",
        b"\x00\x01\x00\x00\x01\x00\x00\x00\x09\x00\x00\x00ab",
    ],
)
def test_a_malformed_response_is_refused(data: bytes) -> None:
    with pytest.raises(ValueError):
        decode_response(data)


def test_hash_is_the_registry_s() -> None:
    assert registry().type_hash(AGENT_SRV) == AGENT_SRV_HASH


def test_client_against_a_real_server(open_sessions) -> None:
    """Same key and token kind as a registry-made client; the answer, a server's error and
    no server say what a registry-made client says."""
    server_node = Node(open_sessions(), "supervisor", "/msctl/test_laptop")
    client_node = Node(open_sessions(), "msctl_ps_1", "/")
    answers = {"ps": (True, "", '{"host":"test-laptop"}'), "stop": (False, "no such component", "")}

    def serve(request: object) -> object:
        parts = registry().service(AGENT_SRV)
        success, message, payload = answers[request.verb]  # type: ignore[attr-defined]
        return registry().msg_class(parts.response)(
            success=success, message=message, payload=payload
        )

    server_node.service("request", AGENT_SRV, serve)
    service = "/msctl/test_laptop/request"
    light = AgentClient(client_node, service)
    full = client_node.client(service, AGENT_SRV)
    try:
        assert light.key == full.key
        assert light.entity.kind == full.entity.kind and light.entity.type_hash == AGENT_SRV_HASH
        wait_until(lambda: _answers(light), timeout=10.0)
        answer = light.ask("ps", "{}", timeout=5.0)
        assert (answer.success, json.loads(answer.payload)) == (True, {"host": "test-laptop"})
        refused = light.ask("stop", "{}", timeout=5.0)
        assert (refused.success, refused.message) == (False, "no such component")
    finally:
        light.close()
        full.close()
    nobody = AgentClient(client_node, "/msctl/elsewhere/request")
    other = client_node.client("/msctl/elsewhere/request", AGENT_SRV)
    try:
        with pytest.raises(ServiceTimeout) as light_error:
            nobody.ask("ps", "{}", timeout=2.0)
        request = registry().msg_class(other.parts.request)(verb="ps", args="{}")
        with pytest.raises(ServiceError) as full_error:
            other.call(request, timeout=2.0)
        assert str(light_error.value).split(":")[0] == str(full_error.value).split(":")[0]
    finally:
        nobody.close()
        other.close()
        client_node.close()
        server_node.close()


def _answers(client: AgentClient) -> bool:
    try:
        return client.ask("ps", "{}", timeout=2.0).success
    except ServiceError:
        return False


# ------------------------------------------------------------------------ supervisor loop
def test_agent_loop_answers_a_request_without_waiting_out_its_pause(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A request wakes the agent's loop: with a 60 s pause it is still taken at once (the
    loop used to sleep its pause out first, a mean 25 ms on every `msctl ps`)."""
    import threading

    from msctl.launcher import agent as agent_module

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    monkeypatch.setattr(agent_module, "LOOP_PAUSE", 60.0)
    agent = agent_module.Agent(host="test_laptop", settings=SessionSettings(connect=()))
    taken: list[object] = []
    turns = threading.Event()

    def step() -> None:  # the loop's turn, without processes: take what is queued
        while not agent._requests.empty():
            taken.append(agent._requests.get())
        turns.set()

    monkeypatch.setattr(agent, "step", step)
    loop = threading.Thread(target=agent.run, daemon=True)
    loop.start()
    try:
        assert turns.wait(10.0), "the loop never turned"
        agent._on_request("ps request")
        wait_until(lambda: taken == ["ps request"], timeout=10.0, what="the request taken")
    finally:
        agent.request_stop()
        agent._on_request("wake to stop")
        loop.join(10.0)
    assert not loop.is_alive()


def test_supervisors_are_found_by_their_service_type_alone(open_sessions) -> None:
    """The narrowed graph query finds every AgentRequest server under /msctl/ and nothing
    else: not another type on a /msctl/ request service, not other services or topics."""
    from msctl.launcher.fleet import supervisors

    session = open_sessions()
    first = Node(session, "supervisor", "/msctl/lap")
    second = Node(open_sessions(), "supervisor", "/msctl/robot_1")
    other = Node(session, "imposter", "/msctl/other")
    for node in (first, second):
        node.service("request", AGENT_SRV, lambda request: None)
    other.service("request", "std_srvs/srv/Trigger", lambda request: None)
    other.service("elsewhere", AGENT_SRV, lambda request: None)
    other.publisher("request", "std_msgs/msg/String")
    asking = Node(open_sessions(), "msctl_ps_1", "/")
    expected = {"/msctl/lap": "/msctl/lap/request", "/msctl/robot_1": "/msctl/robot_1/request"}
    try:
        wait_until(lambda: supervisors(asking) == expected, timeout=10.0, what="both supervisors")
    finally:
        for node in (asking, other, second, first):
            node.close()


def test_ps_table_shows_this_computers_run_in_aligned_columns(
    router_endpoint: str, tmp_path: Path
) -> None:
    """A run whose supervisor is gone (its state file left): every component a row under
    the header, columns aligned, the last error whole, no colour codes into a pipe."""
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    (tmp_path / "run").mkdir()
    long_error = "unresponsive (no heartbeat for 6.1 s) " + "x" * 150
    components = [
        {
            "name": "limb1/joint_manager",
            "kind": "joint_manager",
            "state": "running",
            "pid": None,
            "uptime": 12.4,
            "restarts": 0,
            "last_error": "",
            "process": "limb1",
        },
        {
            "name": "sim/simulator",
            "kind": "simulator",
            "state": "running",
            "pid": None,
            "uptime": 3.0,
            "restarts": 2,
            "last_error": long_error,
            "process": "sim",
        },
    ]
    (tmp_path / "run" / "state.json").write_text(
        json.dumps(
            {
                "host": "test-laptop",
                "template": "dragon",
                "state": "running",
                "supervisor_pid": int(dead.stdout),
                "processes": [],
                "components": components,
            }
        )
    )
    loaded, stdout = _loaded_by(["ps"], router_endpoint, tmp_path)
    assert _heavy(loaded, HEAVY + RICH) == []
    header, *rows = stdout.splitlines()
    assert header.split() == [
        "component",
        "kind",
        "host",
        "state",
        "pid",
        "uptime",
        "restarts",
        "last",
        "error",
    ]
    assert len(rows) == 2 and "\x1b" not in stdout
    assert rows[0].split() == [
        "limb1/joint_manager",
        "joint_manager",
        "test-laptop",
        "stopped",
        "-",
        "0s",
        "0",
    ]
    assert rows[1].endswith(long_error)
    # Aligned: each column starts where its header does.
    for column in ("kind", "host", "state", "restarts", "last error"):
        at = header.index(column)
        assert rows[1][at - 2 : at] == "  " and rows[1][at] != " ", column


def test_print_table_colours_only_a_terminal_without_no_color(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from msctl.console import print_table

    rows = [[("limb1", ""), ("failed", "red")], [("limb2/joint_manager", ""), ("running", "green")]]
    print_table(("component", "state"), rows)
    plain = capsys.readouterr().out
    assert plain.splitlines() == [
        "component            state",
        "limb1                failed",
        "limb2/joint_manager  running",
    ]
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    monkeypatch.delenv("NO_COLOR", raising=False)
    print_table(("component", "state"), rows)
    coloured = capsys.readouterr().out
    assert "\x1b[31mfailed\x1b[0m" in coloured and "\x1b[32mrunning\x1b[0m" in coloured
    # Colour codes take no room: stripped, the lines are the plain ones.
    import re

    assert re.sub(r"\x1b\[[0-9;]*m", "", coloured) == plain
    monkeypatch.setenv("NO_COLOR", "1")
    print_table(("component", "state"), rows)
    assert capsys.readouterr().out == plain


def test_print_table_cuts_a_long_last_cell_to_the_terminal_and_keeps_cells_on_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A killed component's error quotes its last log line: on a terminal it must not wrap
    into the next rows; piped, it stays whole."""
    from msctl.console import print_table

    error = "killed by SIGKILL: 2026-11-23 18:20:31,220 INFO msctl.worker: built " + "x" * 80
    rows = [
        [("wheel2/joint_manager", ""), ("starting", "yellow"), (error, "")],
        [("gc1/data_monitor", ""), ("running", "green"), ("line one\nline two", "")],
    ]
    print_table(("component", "state", "last error"), rows)
    piped = capsys.readouterr().out.splitlines()
    assert piped[1].endswith(error) and piped[2].endswith("line one line two")
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    monkeypatch.setenv("NO_COLOR", "1")
    monkeypatch.setattr("shutil.get_terminal_size", lambda *a, **k: os.terminal_size((60, 24)))
    print_table(("component", "state", "last error"), rows)
    shown = capsys.readouterr().out.splitlines()
    assert len(shown) == 3 and all(len(line) <= 60 for line in shown), shown
    assert shown[1].endswith("…") and shown[1].split("  ")[-1].startswith("killed by SIGKILL")
    print_table(("component", "state", "last error"), [])  # nothing to show: a header alone
    assert capsys.readouterr().out.split() == ["component", "state", "last", "error"]
