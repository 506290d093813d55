"""Agents on several computers, played on this one: one ``msctl agent`` subprocess per host of a
Dragon (each with its own ``MSCTL_HOST`` and ``MSCTL_HOME``), a real router on loopback, and a
ground station that brings the Dragon up and down with ``msctl up --all`` / ``down --all``.

The Dragon uses the two G-line limbs, which share one computer (``gl-pi-01``); its wheels have a
computer each and the ground-control station is ``ground1``: four agents, three of them with
components to run (the station's kinds are not built yet).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, wait_until

from components.assembly import load_assembly
from components.comm.node import Node
from components.comm.services import ServiceTimeout
from components.comm.session import open_session
from components.comm.types import registry
from msctl.launcher.agent import check_assembly, plan_part
from msctl.launcher.control import AGENT_SRV, RequestError, host_namespace
from msctl.launcher.plan import plan_host
from msctl.launcher.state import process_group_alive

# A whole fleet on one loaded machine: each msctl command takes seconds to start there.
pytestmark = [pytest.mark.e2e, pytest.mark.timeout(600)]

USES = ["--use", "limb1=gl-limb-01", "--use", "limb2=gl-limb-02"]
GROUND = "ground1"


def _base_env() -> dict[str, str]:
    # Nothing of the caller's msctl settings may leak into the simulated computers.
    return {k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))}


@pytest.fixture(scope="module")
def ground_home(tmp_path_factory: pytest.TempPathFactory, net_env: dict[str, str]) -> Path:
    """The ground station's MSCTL_HOME with the Dragon resolved (G-line limbs)."""
    home = tmp_path_factory.mktemp("ground")
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "dragon", *USES],
        env={**_base_env(), **net_env, "MSCTL_HOME": str(home), "MSCTL_HOST": GROUND},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return home


@pytest.fixture(scope="module")
def hosts(ground_home: Path) -> list[str]:
    """Every computer of the resolved Dragon."""
    return list(load_assembly(ground_home / "assembly").hosts)


class Agents:
    """The agent subprocesses, by host; their logs and homes under one directory."""

    def __init__(self, root: Path, env: dict[str, str]):
        self.root = root
        self.env = env
        self.procs: dict[str, subprocess.Popen] = {}

    def home(self, host: str) -> Path:
        """The host's MSCTL_HOME."""
        return self.root / host

    def start(self, host: str) -> subprocess.Popen:
        """Start ``msctl agent`` as ``host``."""
        self.home(host).mkdir(parents=True, exist_ok=True)
        with (self.root / f"{host}.log").open("a") as log:
            self.procs[host] = subprocess.Popen(
                [sys.executable, "-m", "msctl", "agent"],
                env={**self.env, "MSCTL_HOST": host, "MSCTL_HOME": str(self.home(host))},
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        return self.procs[host]

    def logs(self) -> str:
        """Every agent's log, for assertion messages."""
        return "\n".join(
            f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}"
            for p in sorted(self.root.glob("*.log"))
        )

    def stop(self, host: str, signum: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        """Signal one agent and wait for it; SIGKILL (and a failing return) if it hangs."""
        proc = self.procs[host]
        if proc.poll() is None:
            proc.send_signal(signum)
            try:
                return proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
                return -999
        return proc.returncode

    def close(self) -> None:
        """Stop every agent, then kill any process group an agent may have left behind."""
        for host in list(self.procs):
            self.stop(host)
        for state in self.root.glob("*/run/state.json"):
            try:
                document = json.loads(state.read_text())
            except (OSError, ValueError):
                continue
            for process in document.get("processes", []):
                if process.get("pgid") and process_group_alive(process["pgid"]):
                    os.killpg(process["pgid"], signal.SIGKILL)


@pytest.fixture(scope="module")
def agents(
    tmp_path_factory: pytest.TempPathFactory, net_env: dict[str, str], hosts: list[str]
) -> Iterator[Agents]:
    """One running agent per computer of the Dragon."""
    fleet = Agents(tmp_path_factory.mktemp("agents"), {**_base_env(), **net_env})
    try:
        for host in hosts:
            fleet.start(host)
        yield fleet
    finally:
        fleet.close()


@pytest.fixture(scope="module")
def node(endpoint: str) -> Iterator[Node]:
    """A node of this test process on the router (for requests msctl itself would not send)."""
    session = open_session(quick_peer_settings(endpoint))
    test_node = Node(session, "agent_test", "/")
    try:
        yield test_node
    finally:
        test_node.close()
        session.close()


def msctl(
    ground_home: Path, net_env: dict[str, str], *args: str, timeout: float = 60
) -> subprocess.CompletedProcess:
    """Run ``msctl`` on the ground station."""
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env={**_base_env(), **net_env, "MSCTL_HOME": str(ground_home), "MSCTL_HOST": GROUND},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def raw_call(node: Node, host: str, verb: str, args_text: str) -> Any:
    """Send a request with arguments exactly as given (not necessarily JSON); wait for routes."""
    client = node.client(f"{host_namespace(host)}/request", AGENT_SRV)
    request = registry().msg_class(client.parts.request)(verb=verb, args=args_text)
    try:

        def answered() -> Any:
            try:
                return client.call(request, timeout=1.0)
            except ServiceTimeout:
                return None

        return wait_until(answered, timeout=15.0)
    finally:
        client.close()


def ps(ground_home: Path, net_env: dict[str, str]) -> dict[str, Any]:
    """``msctl ps --json`` from the ground station."""
    result = msctl(ground_home, net_env, "ps", "--json")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def wait_for_agents(ground_home: Path, net_env: dict[str, str], hosts: list[str]) -> None:
    """Until every agent answers ``ps`` (idle: no components)."""
    wait_until(lambda: set(hosts) <= set(ps(ground_home, net_env)["hosts"]), timeout=60.0)


def by_host(document: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    """``ps --json`` components as ``{host: {component: row}}``."""
    rows: dict[str, dict[str, dict[str, Any]]] = {}
    for row in document["components"]:
        rows.setdefault(row["host"], {})[row["name"]] = row
    return rows


# --------------------------------------------------------------------------- plans
def test_one_simulator_for_the_assembly_and_stations_run_their_own_part(ground_home: Path):
    assembly = load_assembly(ground_home / "assembly")
    assert assembly.modules[0].host == "gl-pi-01"
    simulators = {
        host: [c.name for c in plan_part(assembly, host, True).components if c.kind == "simulator"]
        for host in assembly.hosts
    }
    assert simulators == {
        "gl-pi-01": ["sim/simulator"],
        "hl-wheel-01": [],
        "hl-wheel-02": [],
        GROUND: [],
    }
    wheel = plan_host(assembly, "hl-wheel-01", sim=True)
    assert wheel.simulated and not wheel.off_robot
    kinds = {c.kind for c in wheel.components}
    assert "joint_manager" in kinds and not kinds & {"motor_interface", "simulator"}
    station = plan_part(assembly, GROUND, True)
    assert [p.name for p in station.processes] == ["gc1_human_operator", "gc1_data_monitor"]
    assert not station.not_built
    # Off-robot, alone (`msctl up` on a laptop), nothing changes: the whole Dragon, one world.
    laptop = plan_host(assembly, "some-laptop", sim=None)
    assert laptop.off_robot and laptop.simulated
    assert sum(c.kind == "simulator" for c in laptop.components) == 1
    assert {c.name for c in laptop.components} >= {"limb1/joint_manager", "wheel2/joint_manager"}


def test_check_assembly_refuses_names_that_are_not_plain(ground_home: Path):
    document = json.loads((ground_home / "assembly" / "assembly.lock.json").read_text())
    assert check_assembly(document, "gl-pi-01").template == "dragon"
    for bad in ("limb1/joint_manager;rm -rf ~", "limb1/../../etc/passwd", "-rf", "$(reboot)"):
        tampered = json.loads(json.dumps(document))
        tampered["components"][1]["name"] = bad
        with pytest.raises(RequestError, match="not a plain name"):
            check_assembly(tampered, "gl-pi-01")
    with pytest.raises(RequestError, match="no part in dragon"):
        check_assembly(document, "hl-limb-01")


# --------------------------------------------------------------------------- agents
def test_agents_announce_themselves_idle(
    agents: Agents, ground_home: Path, net_env: dict[str, str], hosts: list[str]
):
    wait_for_agents(ground_home, net_env, hosts)
    assert ps(ground_home, net_env)["components"] == []
    nodes = json.loads(msctl(ground_home, net_env, "node", "list", "--json").stdout)
    names = {n["name"] for n in nodes}
    assert {f"{host_namespace(h)}/supervisor" for h in hosts} <= names
    assert "serving /msctl/gl_pi_01/request" in (agents.root / "gl-pi-01.log").read_text()
    # A second computer claiming the same name is refused, not a second answer to every request.
    twin = subprocess.run(
        [sys.executable, "-m", "msctl", "agent"],
        env={**agents.env, "MSCTL_HOST": "hl-wheel-01", "MSCTL_HOME": str(agents.root / "twin")},
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert twin.returncode == 1, twin.stderr
    assert "/msctl/hl_wheel_01/request is already served" in twin.stderr


def test_malformed_requests_are_refused_and_start_nothing(
    agents: Agents, ground_home: Path, net_env: dict[str, str], hosts: list[str], node: Node
):
    wait_for_agents(ground_home, net_env, hosts)
    host = "gl-pi-01"
    document = json.loads((ground_home / "assembly" / "assembly.lock.json").read_text())

    def refused(verb: str, args_text: str) -> str:
        response = raw_call(node, host, verb, args_text)
        assert not response.success, (verb, args_text)
        return response.message

    assert "unknown verb 'reboot'" in refused("reboot", "{}")
    assert "must be a JSON object" in refused("ps", "[1, 2]")
    assert "not JSON" in refused("up", "{'assembly': ")
    assert "takes no argument command" in refused(
        "up", json.dumps({"assembly": document, "sim": True, "command": "rm -rf /"})
    )
    assert "takes no argument argv" in refused(
        "restart", json.dumps({"component": "wheel1/joint_manager", "argv": ["sh"]})
    )
    for bad in ("limb1/joint_manager;rm -rf /", "limb1/../../../bin/sh"):
        tampered = json.loads(json.dumps(document))
        tampered["components"][1]["name"] = bad
        message = refused("up", json.dumps({"assembly": tampered, "sim": True}))
        assert "not a plain name" in message and repr(bad) in message
    tampered = json.loads(json.dumps(document))
    tampered["template"] = "../../etc/dragon"
    assert "not a plain name" in refused("up", json.dumps({"assembly": tampered}))
    # Plain names, but a path in the data: this computer's own resolution does not agree.
    tampered = json.loads(json.dumps(document))
    tampered["components"][0]["params"]["channel"] = "/etc/shadow"
    assert "differs from gl-pi-01's own resolution" in refused(
        "up", json.dumps({"assembly": tampered, "sim": False})
    )
    assert "not a resolved assembly" in refused("up", json.dumps({"assembly": {"schema": 1}}))
    assert "needs the resolved assembly" in refused("up", "{}")
    assert "nothing runs on gl-pi-01" in refused(
        "restart", json.dumps({"component": "limb1/joint_manager"})
    )
    # Nothing was started or written, and every agent is still there.
    assert ps(ground_home, net_env)["components"] == []
    assert not (agents.home(host) / "agent" / "assembly").exists()
    assert all(p.poll() is None for p in agents.procs.values()), agents.logs()


def test_up_all_ps_restart_down(
    agents: Agents, ground_home: Path, net_env: dict[str, str], hosts: list[str], node: Node
):
    wait_for_agents(ground_home, net_env, hosts)
    up = msctl(ground_home, net_env, "up", "--all", "--sim", "--timeout", "45", timeout=150)
    assert up.returncode == 0, up.stderr + agents.logs()

    # What each computer runs, as its own agent plans it (kinds get built as the project grows).
    assembly = load_assembly(ground_home / "assembly")
    plans = {h: plan_part(assembly, h, True) for h in hosts}
    expected = {h: {c.name for c in p.components} for h, p in plans.items() if p.processes}
    # The ground station runs the data monitor the health screen reads.
    assert set(expected) == {"gl-pi-01", "hl-wheel-01", "hl-wheel-02", GROUND}
    assert any(name.endswith("data_monitor") for name in expected[GROUND]), expected[GROUND]
    assert {"sim/simulator", "limb1/joint_manager", "limb2/joint_manager"} <= expected["gl-pi-01"]
    assert "wheel1/joint_manager" in expected["hl-wheel-01"]
    rows = by_host(ps(ground_home, net_env))
    assert {h: set(r) for h, r in rows.items()} == expected
    assert all(r["state"] == "running" for h in rows.values() for r in h.values()), rows
    pgids = {r["pid"] for h in rows.values() for r in h.values()}
    assert len(pgids) == sum(len(p.processes) for p in plans.values())
    assert all(process_group_alive(p) for p in pgids)
    # Each agent ran what the assembly says, from its own resolution.
    assert (agents.home("gl-pi-01") / "agent" / "assembly" / "assembly.mjcf.xml").is_file()

    # The same up again (as after a partial failure, or an answer lost on the radio): every
    # agent says it already runs what was asked, and nothing restarts.
    again = msctl(ground_home, net_env, "up", "--all", "--sim", "--timeout", "60")
    assert again.returncode == 0, again.stderr + agents.logs()
    pids = {h: {c: r["pid"] for c, r in comps.items()} for h, comps in rows.items()}
    again_rows = by_host(ps(ground_home, net_env))
    assert {h: {c: r["pid"] for c, r in comps.items()} for h, comps in again_rows.items()} == pids
    # Something else (the robots on hardware, not simulated) is refused by what runs.
    other = msctl(ground_home, net_env, "up", "--all", "--timeout", "10")
    assert other.returncode != 0
    assert "already runs dragon" in other.stderr

    old_pid = rows["hl-wheel-01"]["wheel1/joint_manager"]["pid"]
    restart = msctl(ground_home, net_env, "restart", "wheel1/joint_manager")
    assert restart.returncode == 0, restart.stderr + agents.logs()
    assert "on hl-wheel-01" in restart.stderr
    pgids.add(
        wait_until(
            lambda: next(
                (
                    r["pid"]
                    for r in by_host(ps(ground_home, net_env)).get("hl-wheel-01", {}).values()
                    if r["name"] == "wheel1/joint_manager"
                    and r["state"] == "running"
                    and r["pid"] not in (None, old_pid)
                ),
                None,
            ),
            timeout=60.0,
        )
    )
    # `logs` reaches the agent too, directly and through `msctl logs` from the ground station.
    logs = raw_call(node, "gl-pi-01", "logs", json.dumps({"component": "limb2/joint_manager"}))
    assert logs.success, logs.message
    remote_log = msctl(ground_home, net_env, "logs", "limb2/joint_manager", "-n", "20")
    assert remote_log.returncode == 0, remote_log.stderr
    assert "limb2/joint_manager" in remote_log.stdout

    # A second supervisor for a host its agent serves is refused.
    clash = msctl(ground_home, net_env, "up", "--host", "gl-pi-01", "--sim", "--for", "1")
    assert clash.returncode != 0 and "already serves gl-pi-01" in clash.stderr, clash.stderr
    # `msctl down` on the agent's own computer stops its run through the agent, which stays.
    wheel_groups = {r["pid"] for r in by_host(ps(ground_home, net_env))["hl-wheel-01"].values()}
    local_down = msctl(agents.home("hl-wheel-01"), net_env, "down")
    assert local_down.returncode == 0, local_down.stderr
    assert "stays up" in local_down.stderr
    assert [p for p in wheel_groups if process_group_alive(p)] == []
    assert agents.procs["hl-wheel-01"].poll() is None, agents.logs()
    assert any("limb2" in line for line in json.loads(logs.payload)["limb2"])

    down = msctl(ground_home, net_env, "down", "--all")
    assert down.returncode == 0, down.stderr
    # The agents answer `down` once their processes are gone: nothing to wait for.
    assert [p for p in pgids if process_group_alive(p)] == []
    assert ps(ground_home, net_env)["components"] == []
    assert all(p.poll() is None for p in agents.procs.values()), agents.logs()


def test_unreachable_agent_is_named_and_the_others_start(
    agents: Agents, ground_home: Path, net_env: dict[str, str], hosts: list[str]
):
    wait_for_agents(ground_home, net_env, hosts)
    assert agents.stop("hl-wheel-02") == 0, agents.logs()

    up = msctl(ground_home, net_env, "up", "--all", "--sim", "--timeout", "45", timeout=150)
    assert up.returncode == 3, up.stderr + agents.logs()
    assert "no agent answered for hl-wheel-02" in up.stderr
    assert "started: gl-pi-01, hl-wheel-01, ground1" in " ".join(up.stderr.split())
    rows = by_host(ps(ground_home, net_env))
    assert set(rows) == {"gl-pi-01", "hl-wheel-01", GROUND}
    assert all(r["state"] == "running" for h in rows.values() for r in h.values()), rows

    # SIGTERM to an agent stops its run (every process group gone) and it exits cleanly.
    limb_groups = {r["pid"] for r in rows["gl-pi-01"].values()}
    assert agents.stop("gl-pi-01") == 0, agents.logs()
    assert [p for p in limb_groups if process_group_alive(p)] == []
    # A component planned on a computer that does not answer is that computer's silence,
    # named, not "nothing ran on this computer" (exit 4: a loaded agent once read so).
    log = msctl(ground_home, net_env, "logs", "limb2/joint_manager", "-n", "5")
    assert log.returncode == 3, log.stderr
    assert "cannot get the log of limb2/joint_manager from gl-pi-01" in " ".join(
        log.stderr.split()
    ), log.stderr

    # `down --all` stops what it reaches, and names every host of the plan it could not ask
    # (their agents are gone: nothing says their processes are), exit status 1.
    wheel_groups = {r["pid"] for r in rows["hl-wheel-01"].values()}
    down = msctl(ground_home, net_env, "down", "--all")
    assert down.returncode == 1, down.stderr
    said = " ".join(down.stderr.split())
    assert "2 host(s) did not stop: gl-pi-01, hl-wheel-02 (no supervisor on the graph)" in said
    assert "stopped: hl-wheel-01, ground1" in said or "stopped: ground1, hl-wheel-01" in said
    assert [p for p in wheel_groups if process_group_alive(p)] == []


# --------------------------------------------------------------------------- install
def test_install_writes_a_unit_and_says_what_to_run(tmp_path: Path, net_env: dict[str, str]):
    env = {**_base_env(), **net_env, "MSCTL_HOST": "gl-pi-01", "XDG_CONFIG_HOME": str(tmp_path)}
    out = tmp_path / "msctl-agent.service"
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "agent", "install", "--output", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    unit = out.read_text().splitlines()
    exec_start = next(line for line in unit if line.startswith("ExecStart="))
    program = exec_start.removeprefix("ExecStart=").split()[0].strip('"')
    assert Path(program).is_absolute() and exec_start.endswith(" agent")
    assert "Environment=MSCTL_HOST=gl-pi-01" in unit
    assert f"Environment=MSCTL_ZENOH_CONNECT={net_env['MSCTL_ZENOH_CONNECT']}" in unit
    for line in ("Restart=always", "KillMode=control-group", "WantedBy=multi-user.target"):
        assert line in unit
    assert any(line.startswith("TimeoutStopSec=") for line in unit)
    assert "systemctl daemon-reload && sudo systemctl enable --now msctl-agent" in result.stderr

    user = subprocess.run(
        [sys.executable, "-m", "msctl", "agent", "install", "--user", "--host", "hl-wheel-01"],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert user.returncode == 0, user.stderr
    user_unit = (tmp_path / "systemd" / "user" / "msctl-agent.service").read_text()
    assert "Environment=MSCTL_HOST=hl-wheel-01" in user_unit
    assert "WantedBy=default.target" in user_unit and "User=" not in user_unit
    assert "systemctl --user daemon-reload" in user.stderr

    refused = subprocess.run(
        [sys.executable, "-m", "msctl", "agent", "install", "-o", str(out), "--enable"],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert refused.returncode == 2 and "--enable" in refused.stderr
