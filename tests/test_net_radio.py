"""A budget per radio link: the template's ``[network]`` link classes, checked with errors that
name the file and the field; the router configs generated from them; and two real routers
linked over mutual TLS with those configs, where a robot's own components still get every
sample while the ground gets the downsampled rate and no large publication.

Real routers and clients on 127.0.0.1 with free ports and certificates from a fleet CA made in
a tmp dir; counts, never timings, are asserted (a sample count bounded by the rate times the
time it was measured over).
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port, resolved_assembly, wait_until

from components.comm.session import SessionSettings
from msctl.assembler import data
from msctl.commands.router import _lease_of
from msctl.errors import InputError
from msctl.net import config as netconfig
from msctl.net import pki, radio

REPO = Path(__file__).resolve().parents[1]
ROBOT = "hl-limb-01"  # limb1's computer in dragon
GROUND = "ground1"
JOINT_STATE_TYPE = (
    "sensor_msgs::msg::dds_::JointState_/"
    "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
)


def key(topic: str) -> str:
    """The data key of a JointState topic, as rmw_zenoh writes it (domain 0)."""
    return f"0/{topic.strip('/')}/{JOINT_STATE_TYPE}"


# --------------------------------------------------------------------------- the template
def test_no_network_table_is_the_field_wifi_defaults() -> None:
    network = radio.parse({}, Path("t.toml"))
    link = network.link_class(ROBOT)
    assert link.name == "radio" and link.protocol == "tls"
    assert link.max_message_bytes == 65536
    assert link.downsample_hz["joint_states"] == 10.0
    assert "halt" not in link.downsample_hz and "health" not in link.downsample_hz
    assert radio.Network.from_dict(network.as_dict()) == network
    assert radio.Network.from_dict({}) == radio.Network()  # a lock from before link classes


def test_a_template_sets_each_class_and_each_computers_link() -> None:
    table = {
        "secure": True,
        "radio": {
            "lease_s": 12,
            "protocol": "quic",
            "max_message_bytes": 0,
            "downsample_hz": {"joint_states": 5, "/limb1/tip_pose": 2.5},
        },
        "links": {"hl-wheel-01": "wired", "hl-limb-01": "radio"},
    }
    network = radio.parse(table, Path("t.toml"))
    link = network.link_class(ROBOT)
    assert (link.lease_s, link.protocol, link.max_message_bytes) == (12.0, "quic", 0)
    assert dict(link.downsample_hz) == {"joint_states": 5.0, "/limb1/tip_pose": 2.5}
    assert network.link_class("hl-wheel-01") == radio.DEFAULTS["wired"]
    assert network.links == {"hl-wheel-01": "wired"}


def test_the_topics_a_computer_gets_sampled_are_the_other_computers_thinned_ones() -> None:
    network = radio.parse(
        {
            "radio": {"downsample_hz": {"joint_states": 10, "/limb1/tip_pose": 5}},
            "links": {"hl-wheel-01": "wired"},
        },
        Path("t.toml"),
    )
    hosts = {"limb1": "hl-limb-01", "wheel1": "hl-wheel-01", "limb2": "hl-limb-02"}
    assert radio.thinned_topics(network, hosts, "ground1") == {
        "/limb1/joint_states": 10.0,
        "/limb1/tip_pose": 5.0,
        "/limb2/joint_states": 10.0,  # wheel1's link is a cable: nothing thinned
    }
    # A module's own computer gets its topics whole.
    assert "/limb1/joint_states" not in radio.thinned_topics(network, hosts, "hl-limb-01")


def test_a_link_as_slow_as_the_moons_gets_a_lease_that_outlasts_tcps_retransmissions() -> None:
    network = radio.parse({"links": {"ground1": "deep-space"}}, Path("t.toml"))
    moon = network.link_class("ground1")
    assert moon.name == "deep-space" and moon.lease_s == 30.0
    settings = radio.router_settings(moon, ["limb1"])
    tx = settings["transport"]["link"]["tx"]
    assert tx["lease"] == 30_000 and tx["keep_alive"] == radio.KEEP_ALIVES_PER_LEASE
    # The handshake and a blocked sample get a few leases, not Zenoh's 5-10 s.
    assert settings["transport"]["unicast"]["open_timeout"] == 120_000
    # The rest of the radio's budget is kept.
    assert moon.downsample_hz == radio.DEFAULTS["radio"].downsample_hz


@pytest.mark.parametrize(
    ("table", "field", "said"),
    [
        ({"radio": {"lease": 5}}, "network.radio.lease", "not a link setting"),
        ({"radio": {"lease_s": 0.1}}, "network.radio.lease_s", "at least 0.5"),
        ({"radio": {"lease_s": "5s"}}, "network.radio.lease_s", "seconds of silence"),
        ({"radio": {"protocol": "udp"}}, "network.radio.protocol", "'tls', 'quic'"),
        ({"radio": {"max_message_bytes": -1}}, "network.radio.max_message_bytes", "bytes"),
        ({"radio": {"max_message_bytes": 1.5}}, "network.radio.max_message_bytes", "bytes"),
        ({"radio": {"downsample_hz": {"joint_states": 0}}}, "joint_states", "above 0"),
        ({"radio": {"downsample_hz": {"joint_states": True}}}, "joint_states", "above 0"),
        ({"radio": {"downsample_hz": {"/*/joint_states": 5}}}, "/*/joint_states", "wildcards"),
        ({"radio": {"downsample_hz": 10}}, "network.radio.downsample_hz", "a table"),
        ({"radio": 5}, "network.radio", "must be a table"),
        (
            {"links": {"hl-limb-01": "satellite"}},
            "network.links.hl-limb-01",
            "'radio', 'wired', 'deep-space'",
        ),
        ({"links": ["hl-limb-01"]}, "network.links", "computer = class"),
    ],
)
def test_bad_settings_name_the_file_the_field_and_what_it_may_be(
    table: dict[str, Any], field: str, said: str
) -> None:
    with pytest.raises(InputError) as caught:
        radio.parse(table, Path("/t/dragon.toml"))
    text = f"{caught.value} {caught.value.hint}"
    assert "/t/dragon.toml: field" in text and field in text and said in text, text


def _world(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, network: str) -> Path:
    assemblies = tmp_path / "assemblies"
    shutil.copytree(
        REPO / "assemblies", assemblies, ignore=shutil.ignore_patterns("__pycache__", "*.pyc")
    )
    template = assemblies / "dragon.toml"
    template.write_text(template.read_text() + "\n" + network)
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(assemblies))
    return template


def test_the_template_file_is_checked_when_it_is_loaded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = _world(tmp_path, monkeypatch, '[network.radio]\nprotocol = "sctp"\n')
    with pytest.raises(InputError) as caught:
        data.load_template("dragon")
    assert f"{path}: field network.radio.protocol is 'sctp'" in str(caught.value)

    _world(tmp_path / "2", monkeypatch, "[network.radio.downsample_hz]\njoint_states = 4\n")
    template = data.load_template("dragon")
    network = radio.Network.from_dict(template.network)
    assert dict(network.link_class(ROBOT).downsample_hz) == {"joint_states": 4.0}


def test_a_link_class_for_a_computer_of_no_module_is_refused_at_resolve(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.assembler import resolve

    path = _world(tmp_path, monkeypatch, '[network.links]\nhl-limb-09 = "wired"\n')
    with pytest.raises(InputError) as caught:
        resolve("dragon")
    text = f"{caught.value} {caught.value.hint}"
    assert f"{path}: field network.links.hl-limb-09" in text and "ground1" in text, text


# --------------------------------------------------------------------------- the configs
@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    home = tmp_path_factory.mktemp("fleet")
    assembly = resolved_assembly(tmp_path_factory.mktemp("asm"), "dragon")
    pki.init_fleet(list(assembly.hosts), ["alice"], home=home)
    return {"home": home, "assembly": assembly}


def _config(fleet: dict[str, Any], host: str, **kwargs: Any) -> dict[str, Any]:
    return netconfig.router_config(fleet["assembly"], host, home=fleet["home"], **kwargs)


def test_a_robots_router_downsamples_its_own_modules_telemetry_on_its_radio_links_only(
    fleet: dict[str, Any],
) -> None:
    config = _config(fleet, ROBOT)
    (downsampling,) = config["downsampling"]
    assert downsampling["flows"] == ["egress"] and downsampling["messages"] == ["put"]
    # Never the loopback TCP of the computer's own components.
    assert "tcp" not in downsampling["link_protocols"]
    assert set(downsampling["link_protocols"]) == {"tls", "quic"}
    rules = {r["key_expr"]: r["freq"] for r in downsampling["rules"]}
    assert rules["0/limb1/joint_states/*/*"] == 10.0
    assert not [k for k in rules if "/limb2/" in k]  # limb2 runs on another computer
    (size,) = config["low_pass_filter"]
    assert size["size_limit"] == 65536 and size["messages"] == ["put"]  # services cross
    assert "tcp" not in size["link_protocols"]
    tx = config["transport"]["link"]["tx"]
    assert (tx["lease"], tx["keep_alive"]) == (5000, 4)
    # A slow link is not closed for being slow: as long as the handshake may take (µs).
    assert tx["queue"]["congestion_control"]["block"]["wait_before_close"] == 20_000_000
    assert config["transport"]["unicast"]["open_timeout"] == 20000
    assert config["connect"]["endpoints"] == ["tls/ground1:7448"]
    zenoh.Config.from_json5(json.dumps(config))  # Zenoh rejects a key it does not know


def test_the_ground_stations_router_keeps_large_publications_off_the_radio(
    fleet: dict[str, Any],
) -> None:
    config = _config(fleet, GROUND)
    assert config["downsampling"] == []  # no module runs there
    assert config["low_pass_filter"][0]["size_limit"] == 65536
    assert config["transport"]["link"]["tx"]["lease"] == 5000
    zenoh.Config.from_json5(json.dumps(config))


def test_quic_robots_link_to_a_station_that_also_listens_on_quic(fleet: dict[str, Any]) -> None:
    network = radio.parse(
        {"radio": {"protocol": "quic", "lease_s": 8}, "links": {"hl-wheel-01": "wired"}},
        Path("t.toml"),
    )
    robot = _config(fleet, ROBOT, network=network)
    assert robot["connect"]["endpoints"] == ["quic/ground1:7448"]
    wired = _config(fleet, "hl-wheel-01", network=network)
    assert wired["connect"]["endpoints"] == ["tls/ground1:7448"]
    assert wired["downsampling"] == [] and wired["low_pass_filter"] == []
    assert wired["transport"]["link"]["tx"]["lease"] == 2000
    station = _config(fleet, GROUND, network=network)
    assert station["listen"]["endpoints"][1:] == ["tls/0.0.0.0:7448", "quic/0.0.0.0:7448"]
    # The station's lease outlasts its slowest link's silences.
    assert station["transport"]["link"]["tx"]["lease"] == 8000
    zenoh.Config.from_json5(json.dumps(station))


def test_off_robot_nothing_leaves_the_computer_so_no_budget(fleet: dict[str, Any]) -> None:
    config = _config(fleet, GROUND, off_robot=True)
    assert "downsampling" not in config and "low_pass_filter" not in config


def test_a_plain_endpoint_is_still_refused_and_quic_is_taken(fleet: dict[str, Any]) -> None:
    with pytest.raises(netconfig.NetConfigError, match="MSCTL_ROUTER_CONNECT"):
        _config(fleet, ROBOT, connect=["tcp/ground1:7448"])
    config = _config(fleet, ROBOT, connect=["quic/10.0.0.1:7448"])
    assert config["connect"]["endpoints"] == ["quic/10.0.0.1:7448"]


def test_the_router_runs_with_the_configs_lease_not_the_sessions(tmp_path: Path) -> None:
    generated = tmp_path / "router.json5"
    generated.write_text(json.dumps({"transport": {"link": {"tx": {"lease": 5000}}}}))
    assert _lease_of(generated) == 5000
    hand_written = tmp_path / "hand.json5"
    hand_written.write_text("{ mode: 'router' }  // json5, no lease")
    assert _lease_of(hand_written) is None  # msctl's own lease stands
    settings = SessionSettings(mode="router", connect=(), listen=())._replace(lease_ms=5000)
    assert json.loads(settings.to_config().get_json("transport/link/tx/lease")) == 5000


# --------------------------------------------------------------------------- real routers
@pytest.fixture(scope="module")
def linked(fleet: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """limb1's robot router linked to ground1's over mutual TLS, both from generated
    configs; a client on each computer's loopback."""
    assembly = fleet["assembly"]
    ports = netconfig.Ports(
        addresses={h: "127.0.0.1" for h in assembly.hosts},
        tls_ports={ROBOT: free_port(), GROUND: free_port()},
        local_ports={ROBOT: free_port(), GROUND: free_port()},
    )
    sessions: list[Any] = []

    def open_(config: dict[str, Any]) -> Any:
        session = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
        sessions.append(session)
        return session

    try:
        open_(_config(fleet, GROUND, ports=ports))
        open_(_config(fleet, ROBOT, ports=ports))
        robot = open_(netconfig.component_config(ROBOT, ports))
        ground = open_(netconfig.component_config(GROUND, ports))
        yield {"robot": robot, "ground": ground}
    finally:
        for session in reversed(sessions):
            session.close()


class Tally:
    """Samples per key, and their sizes, from a subscriber's callback thread."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.sizes: dict[str, list[int]] = {}
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        with self.lock:
            name = str(sample.key_expr)
            self.counts[name] += 1
            self.sizes.setdefault(name, []).append(len(sample.payload.to_bytes()))

    def count(self, key_expr: str) -> int:
        with self.lock:
            return self.counts[key_expr]


def test_the_robot_keeps_every_sample_while_the_ground_gets_the_downsampled_rate(
    linked: dict[str, Any],
) -> None:
    robot, ground = linked["robot"], linked["ground"]
    on_robot, on_ground = Tally(), Tally()
    subscribers = [
        robot.declare_subscriber("0/limb1/**", on_robot),
        ground.declare_subscriber("0/limb1/**", on_ground),
    ]
    states, reads, marker = key("/limb1/joint_states"), key("/limb1/joint_read"), key("/limb1/x")
    try:
        # The route to the ground is whole once a marker crosses.
        wait_until(
            lambda: robot.put(marker, b"m") or on_ground.count(marker), 30, "the ground's route"
        )
        started = time.monotonic()
        sent = 300
        for _ in range(sent):  # 100 Hz, each topic
            robot.put(states, b"s" * 200)
            robot.put(reads, b"r" * 200)
            time.sleep(0.01)
        # A marker after the burst: once it is in, everything the burst sent is.
        robot.put(marker, b"end")
        wait_until(lambda: on_robot.sizes.get(marker, [0])[-1] == 3, 30, "the robot's marker")
        wait_until(lambda: on_ground.sizes.get(marker, [0])[-1] == 3, 30, "the ground's marker")
        elapsed = time.monotonic() - started
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
    assert on_robot.count(states) == sent and on_robot.count(reads) == sent
    # At most 10 a second each crossed (one more at each end of the window), and each topic
    # has its own budget: both got some.
    most = 10 * elapsed + 2
    assert 0 < on_ground.count(states) <= most, (on_ground.count(states), elapsed)
    assert 0 < on_ground.count(reads) <= most, (on_ground.count(reads), elapsed)


def test_a_large_publication_stays_on_the_robot_and_a_large_answer_crosses(
    linked: dict[str, Any],
) -> None:
    robot, ground = linked["robot"], linked["ground"]
    on_robot, on_ground = Tally(), Tally()
    subscribers = [
        robot.declare_subscriber("0/limb1/big/**", on_robot),
        ground.declare_subscriber("0/limb1/big/**", on_ground),
    ]
    answer = robot.declare_queryable(
        "0/limb1/big/service", lambda q: q.reply(q.key_expr, b"a" * 200_000), complete=True
    )
    image, marker = "0/limb1/big/image", "0/limb1/big/marker"
    try:
        wait_until(
            lambda: robot.put(marker, b"m") or on_ground.count(marker), 30, "the ground's route"
        )
        before = on_ground.count(marker)
        robot.put(image, b"i" * 100_000)
        robot.put(marker, b"m")
        wait_until(lambda: on_ground.count(marker) > before, 30, "the marker after the image")
        wait_until(lambda: on_robot.count(image) == 1, 30, "the image on the robot")
        assert on_ground.count(image) == 0
        replies = list(ground.get("0/limb1/big/service", timeout=10))
        assert [len(r.ok.payload.to_bytes()) for r in replies if r.ok] == [200_000]
    finally:
        answer.undeclare()
        for subscriber in subscribers:
            subscriber.undeclare()
