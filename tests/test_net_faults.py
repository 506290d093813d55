"""``msctl net`` and ``msctl doctor`` given what the field gives them: private keys copied
with loose modes, a broken fleet CA, a garbage certificate, no router, bad names and paths.

Each fault must end in one line naming the file, name or flag and what to do, a non-zero
exit that is not 70 (an internal error), and nothing written. The commands run in this
process (:mod:`cli_inprocess`) on a real fleet made by real openssl; ``msctl up`` runs as a
real subprocess.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from cli_inprocess import INTERNAL, msctl
from conftest import free_port

from msctl.net import pki

ROBOT = "hl-limb-01"
ENV = {"MSCTL_HOST": "ground1"}


def snapshot(*roots: Path) -> dict[str, tuple[int, bytes]]:
    """Every file and directory under ``roots``: its mode and bytes (to see nothing written)."""
    found: dict[str, tuple[int, bytes]] = {}
    for root in roots:
        for path in sorted([root, *root.rglob("*")]) if root.exists() else []:
            data = path.read_bytes() if path.is_file() else b""
            found[str(path)] = (path.stat().st_mode, data)
    return found


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dragon fleet (`msctl net init` for ground1, operator alice), copied per test."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path_factory.mktemp("made")
    write_resolution(home / "assembly", resolve("dragon", {}))
    done = msctl(home, "net", "init", "--operator", "alice@ground1", env=ENV)
    assert done.code == 0, done.stderr
    return home


@pytest.fixture
def home(made: Path, tmp_path: Path) -> Path:
    """This test's own copy of the fleet."""
    target = tmp_path / "home"
    shutil.copytree(made, target)
    return target


def _failed_well(ran: Any, code: int, *said: str) -> None:
    assert ran.code == code, (ran.code, ran.said)
    assert ran.code != INTERNAL and "Traceback" not in ran.stdout + ran.stderr
    for text in said:
        assert text in ran.said, (text, ran.said)


# ----------------------------------------------------------------------------- key modes
def test_keys_are_made_0600_and_a_loose_one_is_refused_naming_the_chmod(home: Path) -> None:
    keys = [*home.glob("net/identities/*/key.pem"), home / "net/ca/ca.key"]
    assert len(keys) > 2 and all(k.stat().st_mode & 0o777 == 0o600 for k in keys)
    robot_key = pki.identity_dir(ROBOT, home) / "key.pem"
    ca_key = home / "net/ca/ca.key"
    robot_key.chmod(0o644)
    ca_key.chmod(0o640)
    before = snapshot(home)
    fix_robot, fix_ca = f"`chmod 600 {robot_key}`", f"`chmod 600 {ca_key}`"
    # A listing flags both and exits 1; it writes nothing.
    shown = msctl(home, "net", "show", "--json", env=ENV)
    _failed_well(shown, 1, fix_robot, fix_ca, "mode 0644", "mode 0640")
    assert len(json.loads(shown.stdout)["problems"]) == 2
    # The router whose key it is: refused. Another router: made, the loose keys warned of.
    _failed_well(msctl(home, "net", "config", ROBOT, env=ENV), 2, fix_robot)
    other = msctl(home, "net", "config", "ground1", env=ENV)
    assert other.code == 0 and fix_robot in other.said and fix_ca in other.said
    # Signing reads the CA's key: refused.
    _failed_well(msctl(home, "net", "add-operator", "bob@ground1", env=ENV), 2, fix_ca)
    assert snapshot(home) == before
    # An operator's session reads its key: refused, naming the chmod.
    from components.comm.session import SessionConfigError, identity_tls

    alice_key = pki.identity_dir(pki.operator_cn("alice@ground1"), home) / "key.pem"
    alice_key.chmod(0o604)
    os.environ["MSCTL_HOME"], saved = str(home), os.environ.get("MSCTL_HOME")
    try:
        with pytest.raises(SessionConfigError, match=f"chmod 600 {alice_key}"):
            identity_tls("alice@ground1")
    finally:
        os.environ.pop("MSCTL_HOME") if saved is None else os.environ.update(MSCTL_HOME=saved)
    # The preflight: an ERROR per loose key, each with its chmod.
    report = json.loads(_doctor(home).stdout)
    loose = [f for f in report["findings"] if f["check"] == "key modes"]
    assert {f["status"] for f in loose} == {"ERROR"} and len(loose) == 3
    assert any(fix_robot in f["detail"] for f in loose)


# ----------------------------------------------------------------------------- the CA
@pytest.mark.parametrize(
    ("fault", "said"),
    [
        ("garbage ca.pem", "ca.pem is not a certificate"),
        ("garbage ca.key", "ca.key is not a private key"),
        ("another fleet's key", "is not the key of"),
        ("no ca.key", "holds the fleet CA's certificate but not its key"),
        ("no ca.pem", "is here but not the CA's certificate"),
    ],
)
def test_init_verifies_an_existing_ca_before_using_it(
    home: Path, tmp_path: Path, fault: str, said: str
) -> None:
    ca = home / "net" / "ca"
    if fault == "garbage ca.pem":
        (ca / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\nnot one\n")
    elif fault == "garbage ca.key":
        (ca / "ca.key").write_bytes(os.urandom(200))
    elif fault == "another fleet's key":
        pki.init_fleet([], [], home=tmp_path / "other")
        shutil.copy(tmp_path / "other" / "net" / "ca" / "ca.key", ca / "ca.key")
    elif fault == "no ca.key":
        (ca / "ca.key").unlink()
    else:
        (ca / "ca.pem").unlink()
    shutil.rmtree(pki.identity_dir("hl-wheel-02", home))  # something init would make
    before = snapshot(home)
    ran = msctl(home, "net", "init", env=ENV)
    _failed_well(ran, 2, said)
    assert "all existed" not in ran.said and snapshot(home) == before


# ----------------------------------------------------------------------------- doctor
def _doctor(home: Path) -> Any:
    """``msctl doctor --json`` with no router where it looks (a free port on loopback)."""
    env = {**ENV, "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}"}
    ran = msctl(home, "doctor", "--json", "--clock-timeout", "0.1", env=env)
    assert ran.code != INTERNAL and "Traceback" not in ran.stdout + ran.stderr, ran.said
    return ran


def test_doctor_with_a_garbage_certificate_and_no_router_checks_everything(home: Path) -> None:
    cert = pki.identity_dir("hl-wheel-01", home) / "cert.pem"
    cert.write_text("garbage\n")
    ran = _doctor(home)
    assert ran.code == 1
    report = json.loads(ran.stdout)
    by_check = {f["check"]: f for f in report["findings"]}
    # Every check reported with its result, the router's failure among them.
    for check in ("msctl version", "assembly lock", "router", "clock", "key modes", "disk",
                  "python", f"cert {ROBOT}", "cert ground1"):  # fmt: skip
        assert check in by_check and by_check[check]["status"] in ("OK", "WARN", "ERROR")
    assert by_check["router"]["status"] == "ERROR"
    assert ".rs:" not in by_check["router"]["detail"] and "msctl up" in by_check["router"]["detail"]
    broken = by_check["cert hl-wheel-01"]
    assert broken["status"] == "ERROR" and str(cert) in broken["detail"]
    assert by_check[f"cert {ROBOT}"]["status"] == "OK"


# ----------------------------------------------------------------------------- bad input
def test_net_show_names_a_garbage_certificate(home: Path) -> None:
    cert = pki.identity_dir("hl-wheel-01", home) / "cert.pem"
    cert.write_bytes(os.urandom(64))
    (cert.parent / "cn").unlink()  # nothing beside it says whose it is either
    before = snapshot(home)
    shown = msctl(home, "net", "show", env=ENV)
    _failed_well(shown, 1, str(cert), "not a readable certificate")
    assert ROBOT in shown.stdout  # the others are still listed
    assert snapshot(home) == before


def test_net_config_with_an_output_it_cannot_write(home: Path, tmp_path: Path) -> None:
    before = snapshot(home, tmp_path / "out")
    (tmp_path / "out").mkdir()
    for target in (tmp_path / "nowhere" / "r.json5", tmp_path / "out"):
        ran = msctl(home, "net", "config", ROBOT, "-o", str(target), env=ENV)
        _failed_well(ran, 2, f"cannot write {target}")
    assert snapshot(home) == before and not list((tmp_path / "out").iterdir())


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["bad name", "--router", "ground1"], "enclave 'bad name' is not a path"),
        (["/field/bad name", "--router", "ground1"], "is not a path like /field/viewer"),
        (["//x", "--router", "ground1"], "is not a path"),
        (["/field/", "--router", "ground1"], "is not a path"),
        (["/field/viewer", "--router", "nowhere"], "--router 'nowhere' is no computer"),
        (["/field/viewer", "--router", "ground1", "--publish", "bad topic!"], "--publish"),
        (["/field/viewer", "--router", "ground1", "--call", "/a//b"], "--call"),
    ],
)
def test_ros_enclave_refuses_bad_names_before_writing_anything(
    home: Path, tmp_path: Path, args: list[str], said: str
) -> None:
    output = tmp_path / "viewer.json5"
    before = snapshot(home)
    ran = msctl(home, "net", "ros-enclave", *args, "-o", str(output), env=ENV)
    _failed_well(ran, 2, said)
    assert snapshot(home) == before and not output.exists()


def test_up_secure_without_net_init_fails_at_once_saying_to_run_it(tmp_path: Path) -> None:
    """No fleet CA at all: the secure router is never started (no restarts), and the one
    line says what to run."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    write_resolution(tmp_path / "assembly", resolve("minimal", {}))
    env = {
        **os.environ,
        "MSCTL_HOME": str(tmp_path),
        "MSCTL_HOST": "laptop",
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_NET_TLS_PORT": str(free_port()),
    }
    done = subprocess.run(
        [sys.executable, "-m", "msctl", "up", "--secure", "--detach"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    line = " ".join(done.stderr.split())
    assert "msctl net init" in line and "Traceback" not in line, line
    assert not (tmp_path / "run" / "logs" / "router.log").exists()  # never started


# ----------------------------------------------------------------------------- name lengths
# A certificate's CN is the name, '#' and an 8-digit issuance token within X.509's 64
# characters: 55 for a host or an enclave, 46 for an operator (its CN adds 'operator:').
LONG_HOST = "h" * 56
LONG_OPERATOR = "o" * 47


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (
            ["init", "--host", LONG_HOST],
            f"host {LONG_HOST!r} is too long: 56 characters, at most 55",
        ),
        (
            ["init", "--host", ROBOT, "--operator", LONG_OPERATOR],
            f"operator {LONG_OPERATOR!r} is too long: 47 characters, at most 46",
        ),
        (["add-operator", LONG_OPERATOR], "at most 46 for operator names"),
        (
            ["ros-enclave", "/" + "e" * 55, "--router", "ground1"],
            "at most 55 for ros enclave names",
        ),
    ],
)
def test_a_name_too_long_for_a_certificate_is_named_with_its_limit(
    home: Path, args: list[str], said: str
) -> None:
    """Refused in one line naming the name and the limit, before anything is written (was:
    the operator's limit said as 55 'with its prefix', a long name passing the name check)."""
    before = snapshot(home)
    ran = msctl(home, "net", *args, env=ENV)
    _failed_well(ran, 2, said, "choose a shorter name")
    assert len(ran.said.strip().splitlines()) == 1, ran.said
    assert snapshot(home) == before


def test_the_longest_names_get_certificates(home: Path) -> None:
    """At the limits, a certificate whose CN is 64 characters."""
    ran = msctl(home, "net", "add-operator", "o" * 46, env=ENV)
    assert ran.code == 0, ran.said
    identity = pki.read_identity(pki.operator_cn("o" * 46), home)
    assert len(identity.certificate_cn) == 64, identity.certificate_cn
