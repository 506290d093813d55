"""``msctl update --all`` / ``build --all``: what an agent accepts (data only, checked), and a
real agent on loopback updating and building its own workspace."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from typer.testing import CliRunner
from workspace_rigs import TERMINAL, Remote, branch, head, progress_rows, repos_text

from components.comm.node import Node
from components.comm.session import open_session
from msctl.app import app
from msctl.errors import InputError, NotFoundError
from msctl.launcher.control import host_namespace
from msctl.workspace.remote import LEFT, SILENT, Unanswered, workspace_services
from msctl.workspace.service import Refused, WorkspaceAgent, check_request

GOOD = "repositories:\n  src/limb:\n    type: git\n    url: file:///srv/limb.git\n"


def _update_args(text: str = GOOD, **extra: object) -> str:
    return json.dumps({"repos": {"name": "ws.repos", "text": text}, **extra})


@pytest.mark.parametrize(
    ("verb", "args", "expected"),
    [
        ("rm", "{}", "unknown verb 'rm'"),
        ("update", "[1]", "must be a JSON object"),
        ("update", "{not json", "not JSON"),
        ("update", json.dumps({"repos": {"name": "ws.repos", "text": GOOD}, "cmd": "ls"}), "cmd"),
        ("update", _update_args(offline="yes"), "offline must be true or false"),
        ("update", json.dumps({"repos": {"name": "../../etc/x", "text": GOOD}}), "plain file"),
        ("update", json.dumps({"repos": "ws.repos"}), "file's name and text"),
        (
            "update",
            _update_args(GOOD.replace("file:///srv/limb.git", "ext::reboot")),
            "transport::address",
        ),
        (
            "update",
            _update_args(GOOD.replace("file:///srv/limb.git", "file:///srv/$(reboot).git")),
            "shell metacharacters",
        ),
        ("update", _update_args(GOOD.replace("src/limb", "../outside")), "plain relative path"),
        (
            "update",
            _update_args(GOOD + "    version: '--upload-pack=reboot'\n"),
            "not a branch, tag or commit",
        ),
        (
            "update",
            _update_args(
                overlays=[
                    {"name": "exp.repos", "text": "repositories:\n  src/lmb:\n    version: x"}
                ]
            ),
            "did you mean 'src/limb'",
        ),
        ("update", "x" * (600 * 1024), "over"),
        ("build", json.dumps({"packages_up_to": ["ok", "rm -rf /"]}), "plain package names"),
        ("build", json.dumps({"workspace": "/"}), "build takes no argument workspace"),
    ],
)
def test_an_agent_accepts_data_only(verb: str, args: str, expected: str) -> None:
    with pytest.raises(Refused) as caught:
        check_request(verb, args)
    assert expected in str(caught.value)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["update", "--all", "--lock", "x.repos"], "--lock does not apply with --all"),
        (["update", "--all", "--status"], "--status does not apply with --all"),
        (["update", "--all", "-w", "ws"], "--workspace does not apply with --all"),
        (["update", "--all", "--jobs", "2"], "--jobs does not apply with --all"),
        (["build", "--all", "--wheelhouse", "wh"], "MSCTL_WHEELHOUSE where the agent runs"),
        (["build", "--all", "--workspace", "ws"], "MSCTL_WORKSPACE where the agent runs"),
        (["build", "--all", "--force"], "--force does not apply with --all"),
        (["build", "--all", "--platform", "manylinux2014_aarch64"], "--platform does not"),
    ],
)
def test_options_all_does_not_send_are_refused_not_ignored(
    args: list[str], expected: str, tmp_path: Path
) -> None:
    result = CliRunner().invoke(app, args, env={"MSCTL_HOME": str(tmp_path)})
    assert isinstance(result.exception, InputError), result.output
    assert expected in f"{result.exception} {result.exception.hint}"


def test_a_workspace_set_in_the_environment_does_not_refuse_all(tmp_path: Path) -> None:
    # The ground station's own MSCTL_WORKSPACE is not an option given to --all: the command
    # goes on (and here stops at the missing file, before any network).
    result = CliRunner().invoke(
        app,
        ["update", "--all", str(tmp_path / "nope.repos")],
        env={"MSCTL_HOME": str(tmp_path), "MSCTL_WORKSPACE": str(tmp_path)},
    )
    assert isinstance(result.exception, NotFoundError)
    assert "nope.repos: no such .repos file" in str(result.exception)


def test_a_valid_update_request_carries_the_merged_files() -> None:
    overlay = {"name": "exp.repos", "text": "repositories:\n  src/limb:\n    version: sand\n"}
    args = check_request("update", _update_args(overlays=[overlay], shallow=True))
    (repo,) = args["repositories"]
    assert (repo.path, repo.url, repo.version) == ("src/limb", "file:///srv/limb.git", "sand")
    assert repo.version_at == "exp.repos:3"


# --------------------------------------------------------------------------- a real agent


def _env(tmp_path: Path, endpoint: str, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_", "PIP_"))}
    env.update(
        MSCTL_ZENOH_CONNECT=endpoint,
        MSCTL_ZENOH_LISTEN="tcp/127.0.0.1:0",
        MSCTL_ZENOH_MULTICAST="0",
        COLUMNS="200",
        PIP_CONFIG_FILE=os.devnull,
        PIP_NO_INDEX="1",
    )
    env.update(extra)
    return env


@pytest.fixture
def router() -> Iterator[str]:
    """A loopback router for the agent and the ground station."""
    yield from quick_router()


@contextmanager
def _agent(tmp_path: Path, router: str, host: str, **env: str) -> Iterator[subprocess.Popen]:
    """``msctl agent`` as ``host`` (its own home and workspace under ``tmp_path``), serving
    its workspace service; its whole process group is stopped after."""
    log = (tmp_path / f"{host}.log").open("w")
    agent = subprocess.Popen(
        [sys.executable, "-m", "msctl", "agent"],
        env=_env(
            tmp_path,
            router,
            MSCTL_HOST=host,
            MSCTL_HOME=str(tmp_path / f"{host}-home"),
            MSCTL_WORKSPACE=str(tmp_path / f"{host}-ws"),
            **env,
        ),
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        session = open_session(quick_peer_settings(router))
        try:
            with Node(session, "watcher", "/") as node:
                wait_until(
                    lambda: host_namespace(host) in workspace_services(node),
                    timeout=60,
                    what=f"{host}'s workspace service",
                )
        finally:
            session.close()
        yield agent
    finally:
        if agent.poll() is None:
            os.killpg(agent.pid, signal.SIGTERM)
            try:
                agent.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(agent.pid, signal.SIGKILL)
                agent.wait()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(agent.pid, signal.SIGKILL)  # whatever it left running (git, ssh)
        log.close()


def _ground(
    tmp_path: Path, router: str, files: Path, home: str = "ground-home", **extra: str
) -> Callable[..., subprocess.CompletedProcess[str]]:
    """``msctl`` run from the ground station (in ``files``, with its own MSCTL_HOME)."""
    env = _env(tmp_path, router, MSCTL_HOST="ground", MSCTL_HOME=str(tmp_path / home), **extra)

    def msctl(*args: str, **more: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env={**env, **more},
            cwd=files,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )

    return msctl


@pytest.mark.e2e
@pytest.mark.timeout(600)
def test_an_agent_on_loopback_updates_and_builds_its_own_workspace(
    tmp_path: Path, router: str
) -> None:
    limb = Remote(tmp_path, "limb")
    script = "import pathlib; pathlib.Path('firmware.bin').write_text('flashed')"
    limb.push(
        {
            "msctl-build.toml": 'name = "limb_firmware"\n'
            f'commands = [[{json.dumps(sys.executable)}, "-c", {json.dumps(script)}]]\n'
        },
        "firmware for the sand field",
        branch="sand-field",
    )
    wheel = Remote(tmp_path, "wheel")
    files = tmp_path / "ground"
    files.mkdir()
    (files / "workspace.repos").write_text(
        repos_text({"src/limb": (limb.url, "main"), "src/wheel": (wheel.url, "main")})
    )
    (files / "sand.repos").write_text("repositories:\n  src/limb:\n    version: sand-field\n")
    robot_ws = tmp_path / "limb1-pc-ws"
    msctl = _ground(tmp_path, router, files)
    with _agent(tmp_path, router, "limb1-pc"):
        update = msctl(
            "update", "--all", "workspace.repos", "--overlay", "sand.repos", "--json", **TERMINAL
        )
        assert update.returncode == 0, update.stderr
        (host,) = json.loads(update.stdout)["hosts"]
        assert host["host"] == "limb1-pc" and host["ok"] is True
        assert host["workspace"] == str(robot_ws)
        assert sorted(host["done"]) == ["src/limb", "src/wheel"]
        assert branch(robot_ws / "src/limb") == "sand-field"
        assert head(robot_ws / "src/limb") == head(limb.scratch)
        # One combined progress view: a row per agent, its repositories done of all.
        assert progress_rows(update.stderr) == {"limb1-pc": "2/2 done"}
        # The robot keeps the files it was sent: its own `--status` reads them.
        status = msctl("update", "--status", "--json", "-w", str(robot_ws))
        rows = json.loads(status.stdout)["repositories"]
        assert [(r["path"], r["on_version"]) for r in rows] == [
            ("src/limb", True),
            ("src/wheel", True),
        ]
        build = msctl("build", "--all", "--json")
        assert build.returncode == 0, build.stderr
        (host,) = json.loads(build.stdout)["hosts"]
        assert host["ok"] and host["done"] == ["limb_firmware"]
        assert (robot_ws / "src/limb" / "firmware.bin").read_text() == "flashed"
        # A failure on the robot is named with its repository and reason; exit status 1.
        (robot_ws / "src/wheel" / "README.md").write_text("edited on the robot\n")
        wheel.push({"README.md": "upstream\n"}, "upstream edit")
        failed = msctl("update", "--all", "workspace.repos")
        assert failed.returncode == 1
        assert "limb1-pc" in failed.stdout and "uncommitted changes" in failed.stdout
        assert "update did not succeed on limb1-pc" in failed.stderr


#: An ssh that reaches no server: it says it started, then waits for ever (a radio link that
#: went silent), so the update using it is still running when its agent is killed.
#: An ssh that connects and then says nothing: its stdout (git's pipe) stays open, so git
#: waits (``cat > /dev/null`` closed it, and git failed at once: the job ended before the
#: ground station could see it under way, on a loaded machine).
_SILENT_SSH = """#!/bin/sh
: > "$SILENT_SSH_MARK"
exec sleep 600
"""


@pytest.mark.e2e
@pytest.mark.timeout(600)
def test_unreachable_agents_are_named_before_and_during_a_job(tmp_path: Path, router: str) -> None:
    limb = Remote(tmp_path, "limb")
    files = tmp_path / "ground"
    files.mkdir()
    (files / "workspace.repos").write_text(repos_text({"src/limb": (limb.url, "main")}))
    (files / "far.repos").write_text(
        "repositories:\n  src/far:\n    type: git\n    url: ssh://far.example.org/far.git\n"
    )
    # A ground station whose resolved assembly (a Dragon) names four computers.
    station = _ground(tmp_path, router, files, home="station-home")
    assembled = station(
        "assemble", "dragon", "--use", "limb1=gl-limb-01", "--use", "limb2=gl-limb-02"
    )
    assert assembled.returncode == 0, assembled.stderr
    ssh = tmp_path / "silent-ssh"
    ssh.write_text(_SILENT_SSH)
    ssh.chmod(0o755)
    mark = tmp_path / "ssh-started"
    with _agent(
        tmp_path, router, "gl-pi-01", GIT_SSH_COMMAND=str(ssh), SILENT_SSH_MARK=str(mark)
    ) as agent:
        # Only gl-pi-01 has an agent: it updates, the three others are named.
        update = station("update", "--all", "workspace.repos", "--json")
        assert update.returncode == 1, update.stderr
        hosts = {h["host"]: h for h in json.loads(update.stdout)["hosts"]}
        assert hosts["gl-pi-01"]["ok"] and hosts["gl-pi-01"]["done"] == ["src/limb"]
        for other in ("hl-wheel-01", "hl-wheel-02", "ground1"):
            assert hosts[other]["ok"] is False
            assert hosts[other]["note"] == (
                f"unreachable: no agent serves {host_namespace(other)}/workspace"
            )
        assert "update did not succeed on ground1, hl-wheel-01, hl-wheel-02" in " ".join(
            update.stderr.split()
        )
        # An agent that dies while its job runs is named as soon as it has left the network
        # (not after --timeout), with how far it had got. Another ground home: no assembly,
        # so no other computer is expected.
        running = subprocess.Popen(
            [sys.executable, "-m", "msctl", "update", "--all", "far.repos", "--json"],
            env=_env(
                tmp_path, router, MSCTL_HOST="ground", MSCTL_HOME=str(tmp_path / "lone"), **TERMINAL
            ),
            cwd=files,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        shown: list[bytes] = []
        reader = threading.Thread(
            target=lambda: shown.extend(iter(lambda: os.read(running.stderr.fileno(), 4096), b""))
        )
        reader.start()
        try:
            # The ground station has seen src/far under way, and the clone is in its ssh.
            try:
                wait_until(
                    lambda: (
                        progress_rows(b"".join(shown).decode(errors="replace")).get("gl-pi-01")
                        == "0/1 src/far"
                    ),
                    timeout=120,
                    what="the ground station showing src/far under way",
                )
            except AssertionError as exc:
                screen = b"".join(shown).decode(errors="replace")
                raise AssertionError(
                    f"{exc}; rows {progress_rows(screen)}, exit {running.poll()}, "
                    f"screen ends {screen[-1500:]!r}"
                ) from None
            wait_until(mark.exists, timeout=120, what="the agent's clone reaching its ssh")
            os.killpg(agent.pid, signal.SIGKILL)
            out = running.stdout.read()
            running.wait(timeout=240)
        finally:
            if running.poll() is None:
                running.kill()
                running.wait()
            reader.join(30)
        assert running.returncode == 1, b"".join(shown).decode(errors="replace")
        (host,) = json.loads(out)["hosts"]
        assert host["host"] == "gl-pi-01" and host["ok"] is False
        assert host["note"] == (
            "unreachable during the update: its agent left the network "
            "(last seen: 0/1 done, src/far)"
        )
        assert progress_rows(b"".join(shown).decode(errors="replace")) == {
            "gl-pi-01": "0/1 unreachable"
        }


def test_an_agent_a_moment_off_the_graph_is_not_named_unreachable() -> None:
    # Fake time. A busy computer misses its lease: its agent leaves the graph for 3 s and
    # answers again, job running; one that stays out 5 s left; one in the graph but silent
    # for 15 s is unreachable all the same.
    watch = Unanswered(["/msctl/a", "/msctl/b", "/msctl/c"], now=0.0)
    for now in (1.0, 2.0, 3.0, 4.0):
        assert watch.failed("/msctl/a", now, in_graph=False) is None
    watch.answered("/msctl/a", 4.5)
    assert watch.failed("/msctl/a", 8.0, in_graph=False) is None  # out again: a new count
    assert watch.failed("/msctl/a", 12.9, in_graph=False) is None
    assert watch.failed("/msctl/a", 13.0, in_graph=False) == LEFT
    assert watch.failed("/msctl/b", 1.0, in_graph=False) is None
    assert watch.failed("/msctl/b", 3.0, in_graph=True) is None  # back in the graph
    assert watch.failed("/msctl/b", 7.0, in_graph=False) is None  # out since 7, not since 1
    assert watch.failed("/msctl/c", 14.0, in_graph=True) is None
    assert watch.failed("/msctl/c", 15.0, in_graph=True) == SILENT


def test_an_agent_runs_one_job_at_a_time_and_reports_its_progress(tmp_path: Path) -> None:
    agent = WorkspaceAgent("limb1-pc", tmp_path / "ws")
    release = threading.Event()

    def slow_update(job: dict, args: dict) -> tuple[list, bool]:
        agent._set(job, "src/limb", "fetching")
        release.wait(30)
        agent._set(job, "src/limb", "updated")
        return [{"path": "src/limb", "ok": True}], True

    agent._update = slow_update  # type: ignore[method-assign]
    _payload, message = agent.handle("update", _update_args())
    assert message == "update started"
    wait_until(lambda: agent.progress()["job"]["items"] == {"src/limb": "fetching"})
    with pytest.raises(Refused) as caught:
        agent.handle("build", "{}")
    assert "limb1-pc is already running update (job 1" in str(caught.value)
    release.set()
    wait_until(lambda: agent.progress()["job"]["state"] == "done")
    job = agent.progress()["job"]
    assert job["ok"] is True and job["items"] == {"src/limb": "updated"}
    # A build now: the workspace does not exist, said as the job's error.
    agent.handle("build", "{}")
    wait_until(lambda: agent.progress()["job"]["state"] == "done")
    job = agent.progress()["job"]
    assert job["id"] == 2 and job["ok"] is False and "does not exist yet" in job["error"]


@pytest.mark.e2e
def test_msctl_update_all_with_no_agent_says_so(tmp_path: Path, router: str) -> None:
    (tmp_path / "workspace.repos").write_text(GOOD)
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "update", "--all"],
        env=_env(tmp_path, router, MSCTL_HOME=str(tmp_path / "home")),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 3, result.stderr
    assert "no agent serves /msctl/<host>/workspace" in result.stderr
