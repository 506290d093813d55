"""The paper's Table IV measured here: real rclpy on Fast DDS against msctl on Zenoh.

Set-up, for each N robots and each stack (``dds``, ``zenoh``):

  * N robots, each a Linux network namespace of its own with one veth pair to a bridge; the
    bridge sits in a hub namespace of its own, so nothing of the run touches this computer's
    interfaces (no address on the bridge; multicast snooping off, so the bridge floods
    multicast as a radio channel would; IPv6 off, so the counters carry only the stacks').
  * Each robot runs one module's components on the emulated motor backend: the motor
    interface (the real CANopen backend against emulated CiA 402 drives on an in-process
    python-can ``virtual`` bus), the joint manager and the health monitor, built from one
    resolved assembly (``msctl assemble`` of a template with a slot ``robotK`` per robot, each
    a copy of unit hlv1-limb-01) and run in one process through
    :func:`components.executor.runner.run_built`, as ``msctl up`` runs a module. The emulated
    bus runs SYNC at 20 Hz and drive physics at 100 Hz (``--sync-period``,
    ``--emulator-tick``; the module's own 100 Hz SYNC doubles a robot's CPU), because N
    robots share this computer's cores where real ones have a computer each; ``joint_states``
    still goes out at the motor interface's 100 Hz.
  * ``dds``: that process runs every component as a real rclpy node (``transport="rclpy"``,
    one DDS participant per process) on ``rmw_fastrtps_cpp``, UDPv4 only (Fast DDS's shared
    memory transport would carry samples between namespaces of one computer around the
    bridge), discovering by SPDP multicast over the bridge (ROS 2 Jazzy's default range,
    SUBNET), every robot on one ROS domain.
  * ``zenoh``: one ``msctl router`` per robot, listening on the robot's address, multicast
    scouting off; robot K>1's router links to robot 1's with an explicit tcp endpoint
    (msctl's topology for an assembly without a ground station: robots link to the first
    robot's router); the components are clients of their own robot's router
    (tcp/127.0.0.1:7447), as msctl's generated per-host configs make them. A robot's router
    runs from boot, before its components: the routers are started, listening and given 1 s
    to link before the clock starts (their own start-up is shown apart, "routers up").

What is measured (every time is CLOCK_MONOTONIC, one clock for every namespace):

  * startup: from starting every robot's component process at once until every robot's view
    of the graph holds every robot's three nodes and their publishers of ``joint_states``,
    ``joint_read`` and ``health``. Each robot process looks at its own graph every 0.1 s
    (rclpy's graph queries on its participant; msctl's liveliness graph on its session).
    Shown with the part after the last robot's components were bound ("after ready":
    discovery alone; the rest is interpreters importing on a shared 2-core machine).
  * bytes on the bridge: the kernel's counters of the bridge's ports (what
    ``/sys/class/net/<port>/statistics`` shows, read through ``/proc/<pid>/net/dev`` of a
    process in the hub namespace). "Mb/s" is what the robots sent into the bridge, all
    together, with its peak over any 1 s; "link" the most one robot's link carried, both
    ways (the paper measured on one robot), on average and at its peak. Startup: over the
    startup window. At rest: over ``--steady`` seconds once the graph is whole, no data
    crossing on purpose (each stack's upkeep). "+1 stream": the same once robot 1
    subscribes to robot N's ``joint_states`` (100 Hz, best effort).
  * recovery (N >= 2): robot N's bridge port is set down (``ip link set rN down``: its
    carrier goes off, as a radio out of range) until robot 1's graph loses robot N, or for
    ``--cut-max`` seconds, then up again. From up: until robot 1 receives robot N's
    ``joint_states`` again ("data again"), until every robot that lost them sees every
    publisher again, and every node again (``ros2 node list``; on Zenoh the liveliness
    tokens).
  * stable: the graph was whole within ``--bound`` and no robot saw it break while at rest.
    "Max stable robots" is the largest N that was. CPU per robot process is shown too.

Every step is bounded (``--bound``): a stack that does not converge is reported as
"> bound", never waited on. Every namespace, veth, bridge and process is removed at the end,
also after an error or Ctrl-C. Needs root and ``ip netns``; ``dds`` needs the ``ros`` extra
(without it the DDS column is skipped, saying so).

Run: ``sudo python bench/dds_vs_zenoh.py [--robots 1 4 7 10] [--stacks dds zenoh]
[--bound 90] [--steady 5] [--cut-max 30] [--json]``. ``--json`` prints exactly one JSON
document on stdout (progress on stderr). ``MSCTL_BENCH_KEEP=1`` keeps the run's directory
(each robot's log and events).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench._common import print_table  # noqa: E402

#: The paper's Table IV (one robot among 6 others).
PAPER = {
    "component_startup": ("10 s - 1 min", "1 s"),
    "startup_bandwidth": ("69 Mb/s", "1.65 Mb/s"),
    "recovery": ("20 s", "2 s"),
    "max_stable_robots": ("4", "10+"),
}
#: The robot count the paper's figures are for ("one robot among 6 others").
PAPER_ROBOTS = 7
#: A robot's components, as the launcher runs a module's (their node names).
COMPONENTS = ("motor_interface", "joint_manager", "health_monitor")
#: Each robot's publisher a whole graph must show, per component.
OUTPUTS = {
    "motor_interface": "joint_states",
    "joint_manager": "joint_read",
    "health_monitor": "health",
}
#: The unit every robot is a copy of (an H-line limb: CANopen drives, emulated here).
UNIT = "hlv1-limb-01"
SUBNET = "10.77.0"
ROUTER_PORT = 7447
#: A ROS domain of the run's own (the namespaces keep it apart from any other graph anyway).
ROS_DOMAIN = 77
#: Each robot's emulated CAN bus: SYNC every 50 ms (the module's data says 10 ms) and drive
#: physics every 10 ms (the emulator's default is 2 ms). The hardware emulation is most of a
#: robot process's CPU (a Zenoh robot on the module's own rates took 35-50% of a core here,
#: about 20% on these), and N robots share this computer's cores where real ones have their
#: own; joint_states still goes out at the motor interface's 100 Hz.
SYNC_PERIOD = 0.05
EMULATOR_TICK = 0.01
#: Seconds between two looks of a robot at its graph.
LOOK_PERIOD = 0.1
#: A gap in robot N's joint_states (100 Hz) longer than this starts a new "data" event.
DATA_GAP = 0.25
#: Seconds the graph is left whole before the steady window starts.
SETTLE = 1.0
#: What a window of the bridge's counters gives (see :meth:`CounterLog.window`).
WINDOW_KEYS = (
    "seconds",
    "bytes",
    "mbps",
    "peak_mbps",
    "busiest_link_mbps",
    "busiest_link_peak_mbps",
)
#: Namespaces of this benchmark: msb-<pid of the run>-<role>.
NS_PREFIX = "msb"
NS_RE = re.compile(rf"^{NS_PREFIX}-(\d+)-\S+")


def log(message: str) -> None:
    """Progress, on stderr (stdout is the table, or the JSON document with ``--json``)."""
    print(message, file=sys.stderr, flush=True)


# ============================================================================ the network
def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
    if check and done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip() or done.returncode}")
    return done


def _sysctl(namespace: str, key: str, value: str) -> None:
    path = "/proc/sys/" + key.replace(".", "/")
    _ip("netns", "exec", namespace, "sh", "-c", f"echo {value} > {path}")


def netns_usable() -> str | None:
    """Why this machine cannot run the benchmark (``None``: it can)."""
    if os.geteuid() != 0:
        return "needs root (network namespaces, veths and a bridge are made and removed)"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    probe = f"{NS_PREFIX}-{os.getpid()}-probe"
    done = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if done.returncode != 0:
        return f"ip netns add fails here: {done.stderr.strip()}"
    subprocess.run(["ip", "netns", "delete", probe], capture_output=True)
    return None


def remove_stale_namespaces() -> None:
    """Delete what an earlier run of this benchmark left (its own process is gone, killed
    before it could clean up): its namespaces and the robots' processes still in them."""
    for line in _ip("netns", "list").stdout.splitlines():
        name = line.split()[0] if line.strip() else ""
        match = NS_RE.match(name)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            for pid in _ip("netns", "pids", name, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
            _ip("netns", "delete", name, check=False)


class Testbed:
    """N robot namespaces on one bridge (in a hub namespace). Close it to remove everything.

    Args:
        robots: How many robots.
    """

    def __init__(self, robots: int) -> None:
        self.robots = robots
        tag = f"{NS_PREFIX}-{os.getpid()}"
        self.hub = f"{tag}-hub"
        self.namespaces = [f"{tag}-r{k}" for k in range(1, robots + 1)]
        self.holder: subprocess.Popen[bytes] | None = None
        self._made: list[str] = []
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _build(self) -> None:
        _ip("netns", "add", self.hub)
        self._made.append(self.hub)
        _sysctl(self.hub, "net.ipv6.conf.all.disable_ipv6", "1")
        _sysctl(self.hub, "net.ipv6.conf.default.disable_ipv6", "1")
        # forward_delay 0 and no STP: a port forwards as soon as it is up (after a cut too);
        # no multicast snooping: a port set down and up again would otherwise stop getting
        # the groups its robot joined before (nobody asks it again), which no radio does.
        _ip("-n", self.hub, "link", "add", "br0", "type", "bridge", "forward_delay", "0",
            "stp_state", "0", "mcast_snooping", "0")  # fmt: skip
        _ip("-n", self.hub, "link", "set", "br0", "up")
        for k, namespace in enumerate(self.namespaces, start=1):
            _ip("netns", "add", namespace)
            self._made.append(namespace)
            _sysctl(namespace, "net.ipv6.conf.all.disable_ipv6", "1")
            _sysctl(namespace, "net.ipv6.conf.default.disable_ipv6", "1")
            port = self.port(k)
            _ip("link", "add", port, "netns", self.hub, "type", "veth",
                "peer", "name", "eth0", "netns", namespace)  # fmt: skip
            _ip("-n", self.hub, "link", "set", port, "master", "br0")
            _ip("-n", self.hub, "link", "set", port, "up")
            _ip("-n", namespace, "addr", "add", f"{self.address(k)}/24", "dev", "eth0")
            _ip("-n", namespace, "link", "set", "eth0", "up")
            _ip("-n", namespace, "link", "set", "lo", "up")
            # DDS discovery sends to 239.255.0.1: the group goes out on the bridge link.
            _ip("-n", namespace, "route", "add", "224.0.0.0/4", "dev", "eth0")
        # A process in the hub namespace: its /proc/<pid>/net/dev is the hub's counters.
        self.holder = subprocess.Popen(
            ["ip", "netns", "exec", self.hub, "sleep", "infinity"], start_new_session=True
        )
        deadline = time.monotonic() + 5.0
        while "br0:" not in self._net_dev_text():
            if time.monotonic() > deadline:
                raise RuntimeError(f"cannot read the counters of namespace {self.hub}")
            time.sleep(0.01)

    @staticmethod
    def port(k: int) -> str:
        """Robot ``k``'s bridge port (the hub's end of its veth pair)."""
        return f"r{k}"

    @staticmethod
    def address(k: int) -> str:
        """Robot ``k``'s address on the bridge."""
        return f"{SUBNET}.{k}"

    def _net_dev_text(self) -> str:
        assert self.holder is not None
        try:
            return Path(f"/proc/{self.holder.pid}/net/dev").read_text()
        except OSError:
            return ""

    def counters(self) -> dict[str, tuple[int, int]]:
        """Bridge port -> (rx_bytes, tx_bytes): rx is what its robot sent into the bridge."""
        found = {}
        for line in self._net_dev_text().splitlines()[2:]:
            name, _, rest = line.partition(":")
            name = name.strip()
            if re.fullmatch(r"r\d+", name):
                values = rest.split()
                found[name] = (int(values[0]), int(values[8]))
        return found

    def set_link(self, k: int, up: bool) -> None:
        """Robot ``k``'s link up or down (its bridge port: the robot's carrier goes off)."""
        _ip("-n", self.hub, "link", "set", self.port(k), "up" if up else "down")

    def exec_argv(self, k: int, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside robot ``k``'s namespace."""
        return ["ip", "netns", "exec", self.namespaces[k - 1], *argv]

    def close(self) -> None:
        """Remove every namespace made (their veths and the bridge go with them)."""
        if self.holder is not None:
            _kill_group(self.holder, signal.SIGKILL, 2.0)
            self.holder = None
        for namespace in reversed(self._made):
            _ip("netns", "delete", namespace, check=False)
        self._made.clear()


@dataclass
class Sample:
    """The bridge's counters at one moment."""

    t: float
    ports: dict[str, tuple[int, int]]

    @property
    def sent(self) -> int:
        """Bytes every robot sent into the bridge so far."""
        return sum(rx for rx, _ in self.ports.values())


class CounterLog:
    """Samples the bridge's counters every ``period`` seconds on a thread of its own."""

    def __init__(self, testbed: Testbed, period: float = 0.25) -> None:
        self.testbed = testbed
        self.samples: list[Sample] = []
        self._period = period
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.take()
        self._thread = threading.Thread(target=self._run, name="bridge-counters", daemon=True)
        self._thread.start()

    def take(self) -> Sample:
        """Read the counters now (and keep the reading)."""
        sample = Sample(time.monotonic(), self.testbed.counters())
        with self._lock:
            self.samples.append(sample)
        return sample

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            self.take()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def window(self, start: float, end: float) -> dict[str, float]:
        """Bytes and rates between the samples nearest ``start`` and ``end``."""
        with self._lock:
            samples = sorted(self.samples, key=lambda s: s.t)
        first = min(samples, key=lambda s: abs(s.t - start))
        last = min(samples, key=lambda s: abs(s.t - end))
        seconds = max(last.t - first.t, 1e-6)
        sent = last.sent - first.sent
        links = [
            (last.ports[p][0] - first.ports.get(p, (0, 0))[0])
            + (last.ports[p][1] - first.ports.get(p, (0, 0))[1])
            for p in last.ports
        ]
        inside = [s for s in samples if first.t <= s.t <= last.t]
        link_peaks = [
            _peak_mbps([(s.t, sum(s.ports.get(port, (0, 0)))) for s in inside])
            for port in last.ports
        ]
        return {
            "seconds": seconds,
            "bytes": sent,
            "mbps": sent * 8 / 1e6 / seconds,
            "peak_mbps": _peak_mbps([(s.t, s.sent) for s in inside]),
            "busiest_link_mbps": max(links, default=0) * 8 / 1e6 / seconds,
            "busiest_link_peak_mbps": max(link_peaks, default=0.0),
        }


def _peak_mbps(series: Sequence[tuple[float, int]]) -> float:
    """The highest rate of a byte counter over any span of 1 s or more (Mb/s)."""
    peak = 0.0
    j = 0
    for i, (t, count) in enumerate(series):
        while j < i and t - series[j + 1][0] >= 1.0:
            j += 1
        if t - series[j][0] >= 1.0:
            peak = max(peak, (count - series[j][1]) * 8 / 1e6 / (t - series[j][0]))
    return peak


# ============================================================================ the fleet data
def resolve_fleet(home: Path, robots: int) -> Path:
    """``msctl assemble`` of a template with one slot per robot; the lock's path.

    Each robot is a copy of :data:`UNIT` (its own serial, its computer named ``robotK``), so
    robot K's module is ``/robotK`` on the graph.
    """
    assemblies, calibration = home / "assemblies", home / "calibration"
    assemblies.mkdir(parents=True)
    calibration.mkdir()
    (assemblies / "modules").symlink_to(ROOT / "assemblies" / "modules")
    unit = (ROOT / "calibration" / f"{UNIT}.toml").read_text()
    lines = ['description = "Robots of bench/dds_vs_zenoh.py, one limb each"', "mobile = false"]
    for k in range(1, robots + 1):
        text = re.sub(r'(?m)^host = ".*"$', f'host = "robot{k}"', unit)
        (calibration / f"bench-robot{k}.toml").write_text(text)
        lines += [
            "",
            "[[slots]]",
            f'name = "robot{k}"',
            'fits = ["hl_limb_v1"]',
            f'default = "bench-robot{k}"',
            f"place = {{ xyz = [{2.0 * k}, 0.0, 0.8], rpy = [0.0, 0.0, 0.0] }}",
        ]
    (assemblies / "bench_robots.toml").write_text("\n".join(lines) + "\n")
    env = {
        **os.environ,
        "MSCTL_HOME": str(home),
        "MSCTL_ASSEMBLIES_DIR": str(assemblies),
        "MSCTL_CALIBRATION_DIR": str(calibration),
    }
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "bench_robots"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"msctl assemble bench_robots failed:\n{done.stderr}")
    return home / "assembly"


# ============================================================================ a robot
class _Events:
    """One JSON line per event on stdout, for the benchmark's parent process."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def emit(self, event: str, t: float | None = None, **fields: Any) -> None:
        line = json.dumps({"ev": event, "t": time.monotonic() if t is None else t, **fields})
        with self._lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()


class _ZenohLook:
    """What one robot sees of msctl's graph: its session's liveliness tokens."""

    def __init__(self, executor: Any) -> None:
        self.graph = executor.graph()

    def missing(self, nodes: set[str], topics: set[str]) -> list[str]:
        names = self.graph.node_names()
        published = {t for t, info in self.graph.topics().items() if info.publishers}
        return sorted((nodes - names) | (topics - published))

    def close(self) -> None:
        self.graph.close()


class _RclpyLook:
    """What one robot sees of the DDS graph: its participant's graph cache, through rclpy."""

    def __init__(self, executor: Any) -> None:
        self.ros = executor.plane.graph_node()

    def missing(self, nodes: set[str], topics: set[str]) -> list[str]:
        names = {
            f"{namespace.rstrip('/')}/{name}"
            for name, namespace in self.ros.get_node_names_and_namespaces()
        }
        published = {t for t in topics if self.ros.count_publishers(t) > 0}
        return sorted((nodes - names) | (topics - published))

    def close(self) -> None:
        pass  # the graph node is the plane's, closed with it


class _GraphWatch:
    """Looks at the graph every :data:`LOOK_PERIOD` s; says what is missing when it changes."""

    def __init__(self, look: Any, robots: int, events: _Events) -> None:
        self.look = look
        self.nodes = {f"/robot{k}/{c}" for k in range(1, robots + 1) for c in COMPONENTS}
        self.topics = {f"/robot{k}/{t}" for k in range(1, robots + 1) for t in OUTPUTS.values()}
        self.events = events
        self.missing: list[str] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="graph-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                missing = self.look.missing(self.nodes, self.topics)
            except Exception as exc:  # the plane closing under us
                if not self._stop.is_set():
                    self.events.emit("error", what=f"graph look failed: {exc}")
                return
            if missing != self.missing:
                self.missing = missing
                self.events.emit(
                    "look",
                    nodes=sum(m in self.nodes for m in missing),
                    topics=sum(m in self.topics for m in missing),
                    missing=missing[:6],
                )
            self._stop.wait(LOOK_PERIOD)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.look.close()


def _subscribe_on_demand(executor: Any, events: _Events, source: int) -> None:
    """Robot 1 subscribes to robot ``source``'s ``joint_states`` when its parent says so.

    Not before: the steady window measures each stack at rest (discovery's upkeep only), and
    the data stream after it is what shows a cut link heal.
    """
    from components.comm.qos import SENSOR
    from components.executor.core import Core
    from components.executor.interface import InterfaceSpec, Subscribe
    from components.messages import JOINT_STATE

    class ArrivalProbe(Core):
        """Says when robot ``source``'s samples start arriving, and again after each gap."""

        def __init__(self) -> None:
            super().__init__("bench/arrival_probe")
            self.last: float | None = None

        def on_joint_states(self, _message: Any, now: float) -> None:
            if self.last is None or now - self.last > DATA_GAP:
                events.emit("data", t=now, gap=None if self.last is None else now - self.last)
            self.last = now

    topic = f"/robot{source}/joint_states"
    spec = InterfaceSpec(subscribe=(Subscribe(topic, JOINT_STATE, "on_joint_states", SENSOR),))

    def add() -> None:  # on the executor thread; the node is closed with the executor
        component = executor.add(ArrivalProbe(), spec, "/robot1", "bench_probe")
        executor.start_component(component)
        events.emit("subscribed")

    def wait_for_word() -> None:
        for line in sys.stdin:
            if line.strip() == "subscribe":
                executor.post(add)
                return

    threading.Thread(target=wait_for_word, name="bench-orders", daemon=True).start()


def role_robot(
    lock: Path, index: int, robots: int, stack: str, sync_period: float, tick: float
) -> int:
    """Run robot ``index``'s module (three components on emulated drives) until signalled.

    ``sync_period`` is the CANopen SYNC period the motor interface drives its bus at,
    ``tick`` the emulated drives' physics period (see ``--sync-period``).
    """
    from components.assembly import load_assembly
    from components.build import build_component
    from components.comm.session import SessionSettings
    from components.executor.runner import run_built
    from components.motors.emulation.cia402 import EmulatedCia402Bus

    events = _Events()
    assembly = load_assembly(lock)
    slot = f"robot{index}"
    module = assembly.module(slot)
    counts = {
        j.motor_id: int(j.motor_params.get("counts_per_rev", 4096)) for j in module.actuated_joints
    }
    channel = f"bench-{slot}"  # python-can's virtual bus: this process only
    drives = EmulatedCia402Bus(channel, counts, counts_per_rev=counts, tick=tick).start()
    names = [f"{slot}/{kind}" for kind in COMPONENTS]
    bus_options = {"interface": "virtual", "sync_period": sync_period}
    options = {"channel": channel, "bus_options": bus_options, "launched": names}
    built = []
    try:
        built = [build_component(assembly.component(name), assembly, options) for name in names]
        health = built[COMPONENTS.index("health_monitor")]

        def on_ready(executor: Any) -> None:
            events.emit("ready")  # every component bound: its publishers are declared
            look = _RclpyLook(executor) if stack == "dds" else _ZenohLook(executor)
            # Closed with the health monitor's resources, before the executor's plane.
            health.resources.append(_GraphWatch(look, robots, events))
            if index == 1 and robots > 1:
                _subscribe_on_demand(executor, events, robots)

        if stack == "dds":
            settings = SessionSettings.from_env()  # msctl's control plane only: stays local
            run_built(built, settings, on_ready=on_ready, transport="rclpy")
        else:
            settings = SessionSettings(
                mode="client", connect=(f"tcp/127.0.0.1:{ROUTER_PORT}",), listen=()
            )
            run_built(built, settings, on_ready=on_ready)
    except KeyboardInterrupt:  # stopped while still starting (a run past its bound)
        pass
    finally:
        for item in built:
            item.close()
        drives.stop()
    return 0


# ============================================================================ one run
@dataclass
class Run:
    """What one stack measured with N robots (``None``: did not happen within the bound)."""

    stack: str
    robots: int
    bound: float
    converged: bool = False
    routers_s: float | None = None
    routers: dict[str, float] = field(default_factory=dict)
    startup_s: float | None = None
    ready_s: float | None = None
    discovery_s: float | None = None
    startup: dict[str, float] = field(default_factory=dict)
    steady: dict[str, float] = field(default_factory=dict)
    steady_data: dict[str, float] = field(default_factory=dict)
    first_data_s: float | None = None
    stable: bool = False
    breaks_while_steady: int = 0
    loss_noticed_s: float | None = None
    cut_s: float | None = None
    recovery_data_s: float | None = None
    recovery_graph_s: float | None = None
    recovery_topics_s: float | None = None
    recovery_nodes_s: float | None = None
    cpu_percent: dict[str, float] = field(default_factory=dict)
    load_average: float = 0.0
    problems: list[str] = field(default_factory=list)


class _Robot:
    """One robot's processes and what they said."""

    def __init__(self, k: int, logs: Path) -> None:
        self.k = k
        self.logs = logs
        self.processes: list[subprocess.Popen[str]] = []
        self.names: list[str] = []
        self.events: list[dict[str, Any]] = []
        self.lock = threading.Lock()
        self.router_at: float | None = None
        self.readers: list[threading.Thread] = []

    def start(self, argv: list[str], env: dict[str, str], name: str) -> subprocess.Popen[str]:
        err = open(self.logs / f"robot{self.k}-{name}.log", "w")  # noqa: SIM115 (kept open)
        process = subprocess.Popen(
            argv,
            env=env,
            stdin=subprocess.DEVNULL if name == "router" else subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE if name == "router" else err,
            text=True,
            start_new_session=True,
        )
        self.processes.append(process)
        self.names.append(name)
        if name == "router":
            reader = threading.Thread(target=self._read_router, args=(process, err), daemon=True)
        else:
            reader = threading.Thread(target=self._read_events, args=(process, err), daemon=True)
        reader.start()
        self.readers.append(reader)
        return process

    def tell(self, word: str) -> None:
        """Send ``word`` to this robot's component process (its stdin)."""
        stdin = self.processes[-1].stdin
        assert stdin is not None
        stdin.write(word + "\n")
        stdin.flush()

    def _read_router(self, process: subprocess.Popen[str], err: IO[str]) -> None:
        assert process.stderr is not None
        with err:
            for line in process.stderr:
                err.write(line)
                if "listening on" in line and self.router_at is None:
                    self.router_at = time.monotonic()

    def _read_events(self, process: subprocess.Popen[str], err: IO[str]) -> None:
        assert process.stdout is not None
        with err, open(self.logs / f"robot{self.k}-events.jsonl", "w") as kept:
            for line in process.stdout:
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                kept.write(line)
                with self.lock:
                    self.events.append(event)

    def cpu(self) -> dict[str, float]:
        """CPU seconds (user + system) each of this robot's processes used so far."""
        used = {}
        for name, process in zip(self.names, self.processes, strict=True):
            try:
                fields = Path(f"/proc/{process.pid}/stat").read_text().rpartition(")")[2].split()
            except OSError:
                continue
            used[name] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        return used

    def seen(self, kind: str, after: float = 0.0) -> list[float]:
        """Times of this robot's ``kind`` events after ``after``."""
        with self.lock:
            return [e["t"] for e in self.events if e["ev"] == kind and e["t"] > after]

    def looked(self, part: str = "all", whole: bool = True, after: float = 0.0) -> list[float]:
        """Times after ``after`` this robot's graph became whole (``whole``) or not, counting
        its missing ``nodes``, ``topics`` (their publishers) or ``all``."""
        with self.lock:
            return [
                e["t"]
                for e in self.events
                if e["ev"] == "look" and e["t"] > after and (_missing(e, part) == 0) == whole
            ]

    def whole_at(self, t: float, part: str = "all") -> bool | None:
        """Whether this robot's graph was whole at ``t`` (``None``: it had not looked yet)."""
        with self.lock:
            looks = [e for e in self.events if e["ev"] == "look" and e["t"] <= t]
        return None if not looks else _missing(looks[-1], part) == 0

    def exited(self) -> str | None:
        """A process of this robot that ended, and its log's last lines."""
        for name, process in zip(self.names, self.processes, strict=True):
            if process.poll() is not None:
                log_file = self.logs / f"robot{self.k}-{name}.log"
                tail = log_file.read_text().splitlines()[-5:] if log_file.exists() else []
                return f"robot{self.k}'s {name} exited ({process.returncode}): " + " | ".join(tail)
        return None


def _missing(look: dict[str, Any], part: str) -> int:
    return look["nodes"] + look["topics"] if part == "all" else look[part]


def _kill_group(process: subprocess.Popen[Any], sig: int, wait: float) -> None:
    try:
        os.killpg(process.pid, sig)
    except ProcessLookupError:
        return
    try:
        process.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=5.0)


def _wait(condition: Callable[[], bool], until: float, fail: Callable[[], str | None]) -> bool:
    """Poll ``condition`` until it holds (True) or ``until`` passes or ``fail`` says why."""
    while time.monotonic() < until:
        if condition():
            return True
        if fail() is not None:
            return False
        time.sleep(0.05)
    return condition()


def _env(stack: str, home: Path) -> dict[str, str]:
    env = {
        **os.environ,
        "MSCTL_HOME": str(home),
        "PYTHONPATH": str(ROOT),
        "PYTHONUNBUFFERED": "1",
        "ROS_DOMAIN_ID": str(ROS_DOMAIN),
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    if stack == "dds":
        env.update(
            {
                "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
                # Shared memory would carry the samples between namespaces of one computer.
                "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
                "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                # msctl's control plane (claims) on rclpy, if opened: loopback, nobody there.
                "MSCTL_ZENOH_MODE": "peer",
                "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{ROUTER_PORT}",
                "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            }
        )
        for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE"):
            env.pop(key, None)
    return env


def measure(stack: str, robots: int, lock: Path, home: Path, args: argparse.Namespace) -> Run:
    """Start N robots on ``stack`` in a fresh testbed, measure, tear everything down."""
    run = Run(stack, robots, args.bound)
    logs = home / f"logs-{stack}-{robots}"
    logs.mkdir(parents=True, exist_ok=True)
    testbed = Testbed(robots)
    fleet = [_Robot(k, logs) for k in range(1, robots + 1)]
    counters: CounterLog | None = None
    env = _env(stack, home)
    worker = [sys.executable, str(Path(__file__).resolve()), "--role", "robot", "--lock", str(lock)]
    try:
        counters = CounterLog(testbed)

        def failure() -> str | None:
            return next((why for r in fleet if (why := r.exited()) is not None), None)

        if stack == "zenoh":
            # A robot's router runs from boot, before any component (msctl up starts its
            # components once the router listens): up and linked before the clock starts.
            routers_from = time.monotonic()
            for robot in fleet:
                router = [sys.executable, "-m", "msctl", "router", "--listen",
                          f"tcp/0.0.0.0:{ROUTER_PORT}"]  # fmt: skip
                if robot.k > 1:
                    router += ["--connect", f"tcp/{testbed.address(1)}:{ROUTER_PORT}"]
                robot.start(testbed.exec_argv(robot.k, router), env, "router")
            if not _wait(
                lambda: all(r.router_at is not None for r in fleet),
                routers_from + args.bound,
                failure,
            ):
                run.problems.append(failure() or "the routers did not listen within the bound")
                return run
            time.sleep(SETTLE)  # robots' routers link to robot 1's (retried every <= 1 s)
            run.routers_s = max(r.router_at for r in fleet) - routers_from  # type: ignore[misc]
            run.routers = counters.window(routers_from, counters.take().t)
        t0 = time.monotonic()
        bound = t0 + args.bound
        for robot in fleet:
            argv = [*worker, "--index", str(robot.k), "--robots-in-run", str(robots)]
            argv += ["--sync-period", str(args.sync_period)]
            argv += ["--emulator-tick", str(args.emulator_tick)]
            robot.start(testbed.exec_argv(robot.k, [*argv, "--stack", stack]), env, "robot")

        def all_whole() -> bool:
            return all(r.looked() for r in fleet)

        run.converged = _wait(all_whole, bound, failure)
        end = time.monotonic()
        if (why := failure()) is not None:
            run.problems.append(why)
        readies = [min(r.seen("ready"), default=None) for r in fleet]
        if all(t is not None for t in readies):
            run.ready_s = max(readies) - t0  # type: ignore[type-var,operator]
        if run.converged:
            whole = max(min(r.looked()) for r in fleet)
            run.startup_s = whole - t0
            if run.ready_s is not None:
                run.discovery_s = whole - (t0 + run.ready_s)
            end = whole
        counters.take()
        run.startup = counters.window(t0, end)
        log(f"  {stack} N={robots}: startup " + _fmt_s(run.startup_s, args.bound))
        if not run.converged:
            return run

        # ---- steady state
        time.sleep(SETTLE)
        cpu_from = [r.cpu() for r in fleet]
        steady_from = counters.take().t
        time.sleep(args.steady)
        steady_to = counters.take().t
        cpu_to = [r.cpu() for r in fleet]
        run.steady = counters.window(steady_from, steady_to)
        for name in ("robot", "router"):
            used = [b[name] - a[name] for a, b in zip(cpu_from, cpu_to, strict=True) if name in a]
            if used:
                run.cpu_percent[name] = 100 * sum(used) / len(used) / (steady_to - steady_from)
        run.breaks_while_steady = sum(len(r.looked(whole=False, after=steady_from)) for r in fleet)
        run.stable = run.breaks_while_steady == 0 and failure() is None
        log(f"  {stack} N={robots}: steady {run.steady['mbps']:.3f} Mb/s, stable {run.stable}")
        if robots < 2:
            return run

        # ---- one data stream across the bridge: robot 1 reads robot N's joint_states
        observer = fleet[0]
        asked = time.monotonic()
        observer.tell("subscribe")
        if not _wait(lambda: bool(observer.seen("data")), asked + args.bound, failure):
            run.problems.append(f"robot1 got no /robot{robots}/joint_states within the bound")
            return run
        run.first_data_s = min(observer.seen("data")) - asked
        time.sleep(SETTLE)
        data_from = counters.take().t
        time.sleep(args.steady)
        run.steady_data = counters.window(data_from, counters.take().t)

        # ---- a robot's link cut and restored
        _recovery(run, testbed, fleet, args, failure)
    finally:
        run.load_average = os.getloadavg()[0]
        if counters is not None:
            counters.close()
        for robot in fleet:  # components first, then the routers they are clients of
            for process in reversed(robot.processes):
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGINT)
        for robot in fleet:
            for process in reversed(robot.processes):
                _kill_group(process, signal.SIGINT, 10.0)
        testbed.close()
    return run


def _recovery(
    run: Run,
    testbed: Testbed,
    fleet: list[_Robot],
    args: argparse.Namespace,
    failure: Callable[[], str | None],
) -> None:
    """Cut robot N's link until robot 1 notices (or ``--cut-max``), restore it, time both."""
    observer, cut_robot = fleet[0], fleet[-1]
    cut_at = time.monotonic()
    testbed.set_link(cut_robot.k, up=False)
    noticed = _wait(
        lambda: bool(observer.looked(whole=False, after=cut_at)), cut_at + args.cut_max, failure
    )
    if noticed:
        run.loss_noticed_s = min(observer.looked(whole=False, after=cut_at)) - cut_at
    up_at = time.monotonic()
    testbed.set_link(cut_robot.k, up=True)
    run.cut_s = up_at - cut_at
    until = up_at + args.bound

    def data_again() -> bool:
        return bool(observer.seen("data", after=up_at))

    def again(part: str) -> float | None:
        """Seconds from up until every robot that missed ``part`` had it whole again."""
        times = []
        for robot in fleet:
            if robot.whole_at(up_at, part) is not False:
                continue
            healed = robot.looked(part, after=up_at)
            if not healed:
                return None
            times.append(min(healed) - up_at)
        return max(times, default=0.0)

    _wait(lambda: data_again() and again("all") is not None, until, failure)
    if data_again():
        run.recovery_data_s = min(observer.seen("data", after=up_at)) - up_at
    run.recovery_graph_s = again("all")
    run.recovery_topics_s = again("topics")
    run.recovery_nodes_s = again("nodes")
    log(
        f"  {run.stack} N={run.robots}: loss noticed "
        f"{_fmt_s(run.loss_noticed_s, args.cut_max)}, data again "
        f"{_fmt_s(run.recovery_data_s, args.bound)}, publishers again "
        f"{_fmt_s(run.recovery_topics_s, args.bound)}, node list again "
        f"{_fmt_s(run.recovery_nodes_s, args.bound)}"
    )


# ============================================================================ the tables
def _fmt_s(value: float | None, bound: float) -> str:
    return f"> {bound:.3g} s" if value is None else f"{value:.2f} s"


def max_stable(runs: Sequence[Run], stack: str) -> tuple[int, bool]:
    """The largest N at which ``stack`` was stable, and whether it was the largest tried."""
    ours = [r for r in runs if r.stack == stack]
    stable = [r.robots for r in ours if r.converged and r.stable]
    best = max(stable, default=0)
    return best, bool(ours) and best == max(r.robots for r in ours)


def summary_table(runs: Sequence[Run]) -> dict[str, dict[str, Any]]:
    """Table IV's four rows: the paper's figures beside ours (at N = 7 when measured)."""
    table: dict[str, dict[str, Any]] = {}
    stacks = sorted({r.stack for r in runs})
    counts = sorted({r.robots for r in runs})
    at = PAPER_ROBOTS if PAPER_ROBOTS in counts else max(counts)
    for measure, (paper_dds, paper_zenoh) in PAPER.items():
        table[measure] = {"paper_dds": paper_dds, "paper_zenoh": paper_zenoh, "robots": at}
    for stack in stacks:
        run = next((r for r in runs if r.stack == stack and r.robots == at), None)
        if run is None:
            continue
        table["component_startup"][stack] = {
            "s": run.startup_s,
            "discovery_s": run.discovery_s,
            "text": _fmt_s(run.startup_s, run.bound)
            + ("" if run.discovery_s is None else f" ({run.discovery_s:.2f} s after ready)"),
        }
        startup = {key: run.startup.get(key, float("nan")) for key in WINDOW_KEYS}
        table["startup_bandwidth"][stack] = {
            **startup,
            "text": f"{startup['mbps']:.2f} Mb/s, peak {startup['peak_mbps']:.2f} "
            f"(one robot's link: peak {startup['busiest_link_peak_mbps']:.2f})",
        }
        if run.robots < 2:
            recovery = "n/a (one robot)"
        elif run.cut_s is None:
            recovery = "not measured (" + ("no start" if not run.converged else "no data") + ")"
        else:
            recovery = (
                f"{_fmt_s(run.recovery_data_s, run.bound)} data, "
                f"{_fmt_s(run.recovery_topics_s, run.bound)} publishers, "
                f"{_fmt_s(run.recovery_nodes_s, run.bound)} node list"
            )
        table["recovery"][stack] = {
            "data_s": run.recovery_data_s,
            "publishers_s": run.recovery_topics_s,
            "nodes_s": run.recovery_nodes_s,
            "graph_s": run.recovery_graph_s,
            "text": recovery,
        }
        best, at_largest = max_stable(runs, stack)
        table["max_stable_robots"][stack] = {
            "robots": best,
            "largest_tried": at_largest,
            "text": f"{best}{'+' if at_largest else ''} (of {', '.join(map(str, counts))} tried)",
        }
    return table


def print_report(runs: Sequence[Run], table: dict[str, dict[str, Any]]) -> None:
    """Every run's figures, then Table IV beside the paper's."""
    rows = []
    for r in runs:
        rows.append(
            [
                r.stack,
                r.robots,
                "-" if r.routers_s is None else f"{r.routers_s:.2f}",
                _fmt_s(r.startup_s, r.bound),
                "-" if r.discovery_s is None else f"{r.discovery_s:.2f}",
                f"{r.startup.get('bytes', 0) / 1e6:.2f}",
                f"{r.startup.get('mbps', float('nan')):.2f}",
                f"{r.startup.get('peak_mbps', float('nan')):.2f}",
                f"{r.startup.get('busiest_link_peak_mbps', float('nan')):.2f}",
                "-" if not r.steady else f"{r.steady['mbps']:.3f}",
                "-" if not r.steady else f"{r.steady['busiest_link_mbps']:.3f}",
                "-" if not r.steady_data else f"{r.steady_data['mbps']:.3f}",
                "-" if r.robots < 2 or r.cut_s is None else _fmt_s(r.loss_noticed_s, r.cut_s),
                "-" if r.robots < 2 or r.cut_s is None else _fmt_s(r.recovery_data_s, r.bound),
                "-" if r.robots < 2 or r.cut_s is None else _fmt_s(r.recovery_topics_s, r.bound),
                "-" if r.robots < 2 or r.cut_s is None else _fmt_s(r.recovery_nodes_s, r.bound),
                "yes" if r.stable else "no",
                "-" if "robot" not in r.cpu_percent else f"{r.cpu_percent['robot']:.0f}",
                f"{r.load_average:.1f}",
            ]
        )
    print_table(
        "Per run (startup = processes started -> every robot sees every robot's nodes and "
        "publishers; Mb/s on the bridge)",
        [
            "stack",
            "N",
            "routers up (s)",
            "startup",
            "after ready (s)",
            "startup MB",
            "startup Mb/s",
            "peak 1 s",
            "link peak",
            "at rest Mb/s",
            "at rest busiest",
            "+1 stream Mb/s",
            "cut noticed",
            "data again",
            "publishers again",
            "nodes again",
            "stable",
            "CPU/robot %",
            "load",
        ],
        rows,
    )
    for r in runs:
        for problem in r.problems:
            print(f"  {r.stack} N={r.robots}: {problem}")
    stacks = [s for s in ("dds", "zenoh") if any(r.stack == s for r in runs)]
    at = next(iter(table.values()))["robots"]
    print_table(
        f"Table IV: the paper's figures (one robot among 6 others) beside this machine's (N={at})",
        ["measure", "paper DDS", "paper Zenoh", *(f"here {s}" for s in stacks)],
        [
            [measure, row["paper_dds"], row["paper_zenoh"], *(row[s]["text"] for s in stacks)]
            for measure, row in table.items()
        ],
    )
    if {"dds", "zenoh"} <= set(stacks):
        print("\nratios DDS / Zenoh (same N):")
        for n in sorted({r.robots for r in runs}):
            dds = next((r for r in runs if r.stack == "dds" and r.robots == n), None)
            zen = next((r for r in runs if r.stack == "zenoh" and r.robots == n), None)
            if dds is None or zen is None:
                continue
            parts = []
            if dds.startup_s and zen.startup_s:
                parts.append(f"startup {dds.startup_s / zen.startup_s:.1f}x")
            if dds.startup.get("bytes") and zen.startup.get("bytes"):
                parts.append(f"startup bytes {dds.startup['bytes'] / zen.startup['bytes']:.1f}x")
            if dds.steady and zen.steady and zen.steady["mbps"] > 0:
                parts.append(f"steady {dds.steady['mbps'] / zen.steady['mbps']:.1f}x")
            if dds.recovery_data_s and zen.recovery_data_s:
                parts.append(f"recovery {dds.recovery_data_s / zen.recovery_data_s:.1f}x")
            print(f"  N={n}: " + (", ".join(parts) if parts else "-"))


# ============================================================================ main
def _interrupted(*_: object) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark (or, with ``--role robot``, one robot of it)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--robots", type=int, nargs="+", default=[1, 4, 7, 10])
    parser.add_argument("--stacks", nargs="+", choices=["dds", "zenoh"], default=["dds", "zenoh"])
    parser.add_argument("--bound", type=float, default=90.0, help="seconds per step at most")
    parser.add_argument("--steady", type=float, default=5.0, help="steady-state window (s)")
    parser.add_argument("--cut-max", type=float, default=30.0, help="longest link cut (s)")
    parser.add_argument(
        "--sync-period",
        type=float,
        default=SYNC_PERIOD,
        help="CANopen SYNC period of each robot's emulated bus (s; the module's own: 0.01)",
    )
    parser.add_argument(
        "--emulator-tick",
        type=float,
        default=EMULATOR_TICK,
        help="physics period of the emulated drives (s; the emulator's default: 0.002)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--role", choices=["robot"], help=argparse.SUPPRESS)
    parser.add_argument("--lock", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--index", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--robots-in-run", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--stack", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "robot":
        return role_robot(
            args.lock,
            args.index,
            args.robots_in_run,
            args.stack,
            args.sync_period,
            args.emulator_tick,
        )

    if any(n < 1 for n in args.robots) or max(args.robots) > 200:
        parser.error("--robots: between 1 and 200 robots per run")
    why = netns_usable()
    if why is not None:
        print(f"error: bench/dds_vs_zenoh.py {why}", file=sys.stderr)
        return 2
    stacks = list(dict.fromkeys(args.stacks))
    if "dds" in stacks and importlib.util.find_spec("rclpy") is None:
        log("dds: rclpy is not installed (pip install '.[ros]'): the DDS column is skipped")
        stacks.remove("dds")
    if not stacks:
        print("error: no stack to measure", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, _interrupted)  # cleaned up as after Ctrl-C
    remove_stale_namespaces()
    home = Path(tempfile.mkdtemp(prefix="msctl_bench_dds_vs_zenoh_"))
    runs: list[Run] = []
    try:
        log(f"DDS vs Zenoh on {os.cpu_count()} cores (load {os.getloadavg()[0]:.1f}), {home}")
        lock = resolve_fleet(home, max(args.robots))
        for robots in sorted(set(args.robots)):
            for stack in stacks:
                log(f"{stack}, {robots} robot(s) ...")
                runs.append(measure(stack, robots, lock, home, args))
    except KeyboardInterrupt:
        log("interrupted: everything made was removed")
        return 130
    finally:
        if not os.environ.get("MSCTL_BENCH_KEEP"):
            shutil.rmtree(home, ignore_errors=True)
    table = summary_table(runs)
    if args.json:
        document = {
            "cores": os.cpu_count(),
            "paper_robots": PAPER_ROBOTS,
            "table": table,
            "runs": [asdict(r) for r in runs],
        }
        print(json.dumps(document, indent=2))
    else:
        print_report(runs, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
