"""``msctl net``: the fleet CA and identities on disk, listings, configs; real subprocesses."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from msctl.net import acl, pki


def _msctl(home: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "MSCTL_HOME": str(home), "MSCTL_HOST": "hl-limb-01"}
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args], env=env, capture_output=True, text=True, timeout=60
    )


@pytest.fixture(scope="module")
def home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An MSCTL_HOME with dragon resolved and the fleet initialised for it."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path_factory.mktemp("home")
    write_resolution(home / "assembly", resolve("dragon", {}))
    done = _msctl(home, "net", "init", "--operator", "alice@ground1")
    assert done.returncode == 0, done.stderr
    return home


def test_init_makes_an_identity_per_host_and_operator_with_private_keys(home: Path) -> None:
    shown = json.loads(_msctl(home, "net", "show", "--json").stdout)
    names = [i["common_name"] for i in shown["identities"]]
    assert names == [
        "ground1",
        "hl-limb-01",
        "hl-limb-02",
        "hl-wheel-01",
        "hl-wheel-02",
        "operator:alice@ground1",
    ]
    assert all(i["days_left"] >= 364 for i in shown["identities"])
    for key in [*home.glob("net/identities/*/key.pem"), home / "net/ca/ca.key"]:
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    for identity in pki.identities(home):
        assert pki.verify(identity.cert, home) is None
        # The CN is the name and an issuance token: what the routers' ACL admits it by.
        assert pki.subject_cn(identity.cert) == identity.certificate_cn
        assert pki.name_of(identity.certificate_cn) == identity.common_name


def test_add_operator_then_revoke_changes_the_generated_acl(home: Path) -> None:
    assert _msctl(home, "net", "add-operator", "bob@ground1").returncode == 0
    config = json.loads(_msctl(home, "net", "config").stdout)
    operators = next(s for s in config["access_control"]["subjects"] if s["id"] == acl.OPERATORS)
    assert [pki.name_of(cn) for cn in operators["cert_common_names"]] == [
        "operator:alice@ground1",
        "operator:bob@ground1",
    ]
    assert _msctl(home, "net", "revoke", "bob@ground1").returncode == 0
    shown = json.loads(_msctl(home, "net", "show", "--json").stdout)
    assert {"common_name": "operator:bob@ground1", "revoked": True}.items() <= next(
        i for i in shown["identities"] if i["common_name"] == "operator:bob@ground1"
    ).items()
    config = json.loads(_msctl(home, "net", "config").stdout)
    operators = next(s for s in config["access_control"]["subjects"] if s["id"] == acl.OPERATORS)
    assert [pki.name_of(cn) for cn in operators["cert_common_names"]] == ["operator:alice@ground1"]


def test_config_is_written_and_zenoh_accepts_it(home: Path, tmp_path: Path) -> None:
    target = tmp_path / "ground1.json5"
    done = _msctl(home, "net", "config", "ground1", "-o", str(target))
    assert done.returncode == 0, done.stderr
    config = json.loads(target.read_text())
    assert config["mode"] == "router" and config["connect"]["endpoints"] == []
    assert config["scouting"]["multicast"]["enabled"] is False
    assert config["transport"]["link"]["tls"]["enable_mtls"] is True
    assert config["access_control"]["default_permission"] == "deny"
    zenoh.Config.from_file(str(target))  # raises on a key Zenoh does not know
    robot = json.loads(_msctl(home, "net", "config", "hl-wheel-01").stdout)
    assert robot["connect"]["endpoints"] == ["tls/ground1:7448"]
    # After a radio outage the link is tried again every second at most, not Zenoh's 4 s.
    assert robot["connect"]["retry"]["period_max_ms"] <= 1000
    component = json.loads(_msctl(home, "net", "config", "hl-wheel-01", "--component").stdout)
    assert component["mode"] == "client"


def test_bad_input_names_what_is_wrong(home: Path, tmp_path: Path) -> None:
    unknown = _msctl(home, "net", "config", "nowhere")
    assert unknown.returncode == 2 and "'nowhere'" in unknown.stderr
    assert "hl-limb-01" in unknown.stderr
    bad = _msctl(home, "net", "add-operator", "al ice")
    assert bad.returncode == 2 and "'al ice'" in bad.stderr
    assert _msctl(home, "net", "revoke", "carol").returncode == 2
    empty = _msctl(tmp_path, "net", "config", "ground1")
    assert empty.returncode == 2 and "msctl assemble" in empty.stderr


def test_ros_enclave_gets_an_identity_and_an_rmw_form_config(home: Path) -> None:
    done = _msctl(
        home,
        "net",
        "ros-enclave",
        "/field/viewer",
        "--router",
        "ground1",
        "--publish",
        "/chatter",
        "--subscribe",
        "/limb1/joint_read",
    )
    assert done.returncode == 0, done.stderr
    config = json.loads(done.stdout)
    assert config["connect"]["endpoints"] == ["tls/ground1:7448"]
    rules = {r["id"]: r for r in config["access_control"]["rules"]}
    assert rules["graph"]["key_exprs"] == ["@ros2_lv/0/**"]
    assert rules["publications"]["key_exprs"] == ["0/chatter/**"]
    shown = json.loads(_msctl(home, "net", "show", "--json").stdout)
    viewer = next(i for i in shown["identities"] if i["common_name"] == "/field/viewer")
    assert viewer["role"] == "ros enclave" and not viewer["revoked"]
    assert _msctl(home, "net", "ros-enclave", "viewer", "--router", "ground1").returncode == 2


def test_a_template_network_secure_is_checked_and_carried_in_the_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil

    from components.assembly import decode_lock, encode_lock
    from msctl.assembler import resolve
    from msctl.errors import InputError

    copy = tmp_path / "assemblies"
    root = Path(__file__).resolve().parents[1]
    shutil.copytree(root / "assemblies", copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(copy))
    template = copy / "minimal.toml"
    text = template.read_text()
    assert resolve("minimal").lock.secure is False
    template.write_text(text + "\n[network]\nsecure = true\n")
    lock = resolve("minimal").lock
    assert lock.secure is True and decode_lock(encode_lock(lock)).secure is True
    for bad, said in (
        ('secure = "yes"', "field network.secure is 'yes'"),
        ("tls = true", "field network.tls is not a network setting"),
    ):
        template.write_text(text + f"\n[network]\n{bad}\n")
        with pytest.raises(InputError) as caught:
            resolve("minimal")
        assert f"{template}: {said}" in str(caught.value)


def test_a_secure_template_refuses_a_host_too_long_for_a_certificate(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A host name a certificate's CN cannot carry (with its issuance token) is named with
    the limit when the template is resolved, only when the network is secure."""
    import shutil

    from msctl.assembler import resolve
    from msctl.errors import InputError

    copy = tmp_path / "assemblies"
    root = Path(__file__).resolve().parents[1]
    shutil.copytree(root / "assemblies", copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(copy))
    template = copy / "dragon.toml"
    long_host = "g" * 56
    text = template.read_text().replace('host = "ground1"', f'host = "{long_host}"')
    template.write_text(text)
    assert long_host in resolve("dragon").lock.hosts  # not secure: no certificate to carry it
    template.write_text(text + "\n[network]\nsecure = true\n")
    with pytest.raises(InputError) as caught:
        resolve("dragon")
    said = str(caught.value)
    assert f"{template}: field network.secure: host {long_host!r} is too long" in said, said
    assert "56 characters, at most 55" in said, said
    template.write_text(text.replace(long_host, long_host[:55]) + "\n[network]\nsecure = true\n")
    assert resolve("dragon").lock.secure is True


def test_an_off_robot_router_links_to_no_real_robot(home: Path) -> None:
    from components.assembly import load_assembly
    from msctl.net import config as netconfig

    assembly = load_assembly(home / "assembly")
    pki.init_fleet(["laptop"], [], home=home / "laptop-net")  # its own identity
    on_robot = netconfig.router_config(assembly, "hl-wheel-01", home=home)
    assert on_robot["connect"]["endpoints"] == ["tls/ground1:7448"]
    # The laptop simulates the whole assembly: its router must not reach the real robots.
    off = netconfig.router_config(assembly, "laptop", home=home / "laptop-net", off_robot=True)
    assert off["connect"]["endpoints"] == []


def test_a_computer_with_the_ca_certificate_but_not_its_key(tmp_path: Path) -> None:
    """A robot computer gets MSCTL_HOME/net without ca/ca.key: it trusts the fleet (its router
    config is made) but cannot mint identities, and says where they are made."""
    home = tmp_path / "ground"
    pki.init_fleet(["robot1"], ["alice@ground"], home)
    robot = tmp_path / "robot"
    shutil.copytree(pki.net_dir(home), pki.net_dir(robot), ignore=shutil.ignore_patterns("ca.key"))
    assert pki.trusts(robot) and not pki.initialised(robot)
    with pytest.raises(pki.PkiError, match="not its key") as refused:
        pki.issue("robot2", robot)
    assert "robot2" in str(refused.value)
