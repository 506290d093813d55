"""``msctl update --all`` / ``build --all``: what an agent accepts (data only, checked), and a
real agent on loopback updating and building its own workspace."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port, wait_until
from workspace_rigs import Remote, branch, head, repos_text

from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from msctl.workspace.remote import Refused, WorkspaceAgent, check_request, workspace_services

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
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    try:
        yield endpoint
    finally:
        session.close()


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
    robot_ws = tmp_path / "robot-ws"
    agent = subprocess.Popen(
        [sys.executable, "-m", "msctl", "agent"],
        env=_env(
            tmp_path,
            router,
            MSCTL_HOST="limb1-pc",
            MSCTL_HOME=str(tmp_path / "robot-home"),
            MSCTL_WORKSPACE=str(robot_ws),
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    session = open_session(
        SessionSettings(
            mode="peer", connect=(router,), listen=("tcp/127.0.0.1:0",), multicast=False
        )
    )
    try:
        with Node(session, "watcher", "/") as node:
            wait_until(
                lambda: "/msctl/limb1_pc" in workspace_services(node),
                timeout=60,
                what="the agent's workspace service",
            )
        ground = _env(tmp_path, router, MSCTL_HOST="ground", MSCTL_HOME=str(tmp_path / "gh"))

        def msctl(*args: str) -> subprocess.CompletedProcess[str]:
            return subprocess.run(
                [sys.executable, "-m", "msctl", *args],
                env=ground,
                cwd=files,
                capture_output=True,
                text=True,
                timeout=300,
                check=False,
            )

        update = msctl("update", "--all", "workspace.repos", "--overlay", "sand.repos", "--json")
        assert update.returncode == 0, update.stderr
        (host,) = json.loads(update.stdout)["hosts"]
        assert host["host"] == "limb1-pc" and host["ok"] is True
        assert host["workspace"] == str(robot_ws)
        assert sorted(host["done"]) == ["src/limb", "src/wheel"]
        assert branch(robot_ws / "src/limb") == "sand-field"
        assert head(robot_ws / "src/limb") == head(limb.scratch)
        # The robot keeps the files it was sent: its own `--status` reads them.
        status = subprocess.run(
            [sys.executable, "-m", "msctl", "update", "--status", "--json", "-w", str(robot_ws)],
            env=ground,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
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
    finally:
        session.close()
        agent.send_signal(signal.SIGTERM)
        try:
            agent.wait(timeout=30)
        except subprocess.TimeoutExpired:
            agent.kill()
            agent.wait()


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
