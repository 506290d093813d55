"""Property-based tests of the operator commands that take files, names and payloads (issue 32,
"What to build" 4): ``build``, ``update``, ``topic``, ``service`` and ``bag``.

Hypothesis throws malformed manifests, ``.repos`` files, topic and service names, YAML
payloads, counts and corrupted bags at the real ``msctl`` entry point (``msctl.cli.main``, in
this process, so each example costs milliseconds, not an interpreter start), and checks the
contract every command keeps:

- never exit 70 (an internal error) and never a traceback: bad input is the operator's, and
  is answered in words;
- a failure is said (a non-zero exit comes with an ``error:`` line);
- nothing is written on a failure: no clone, no build state, no bag file changed.

The topic and service commands are pointed at a loopback port nothing listens on: an
example valid in every way ends at "no Zenoh router reachable" (exit 3) at once, which is
within the contract; with a live router, each valid example cost a session (seconds each on
a loaded machine, 9 minutes for the group). The valid paths are the business of
test_cli_plane. Example counts are bounded to keep the module to seconds per group.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msctl import cli

pytestmark = pytest.mark.timeout(600)

#: Examples per group: enough to find the classes of bad input, few enough for seconds.
EXAMPLES = {"build": 40, "update": 40, "topic": 30, "service": 20, "bag": 40}


def _settings(group: str) -> settings:
    return settings(
        max_examples=EXAMPLES[group],
        deadline=None,
        derandomize=False,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )


def msctl(*args: str) -> tuple[int, str, str]:
    """Run ``msctl ARGS`` through its real entry point in this process: exit code, stdout,
    stderr."""
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with (
        mock.patch.object(sys, "argv", ["msctl", *args]),
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
    ):
        try:
            cli.main()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return code, out.getvalue(), err.getvalue()


def keeps_the_contract(code: int, stderr: str, args: tuple[str, ...]) -> None:
    """No internal error, no traceback, and a failure says so."""
    assert code != 70, (args, stderr)
    assert "Traceback" not in stderr and "internal error" not in stderr, (args, stderr)
    if code != 0:
        assert stderr.strip(), (args, code)


def snapshot(root: Path) -> dict[str, str]:
    """Every file under ``root`` and a digest of its content."""
    if not root.exists():
        return {}
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def home(tmp_path: Path) -> Iterator[Path]:
    """A private MSCTL_HOME and no debug traceback, for every example of a test."""
    with mock.patch.dict(os.environ, {"MSCTL_HOME": str(tmp_path / "home"), "COLUMNS": "200"}):
        os.environ.pop("MSCTL_DEBUG", None)
        yield tmp_path


# --------------------------------------------------------------------------- strategies
#: Names: legal ones, near misses and junk.
NAMES = st.one_of(
    st.sampled_from(
        [
            "/chatter",
            "chatter",
            "/limb1/joint_set",
            "",
            "/",
            "//",
            "bad topic!",
            "/1limb",
            "~x",
            "/a/",
            "a//b",
            "/limb-1",
            "/ünïcode",
            "/a/b/c/d_e",
            "*",
            "/$x",
            "\x00",
        ]
    ),
    st.text(max_size=20),
    st.from_regex(r"/?[a-z_][a-z0-9_]{0,6}(/[a-z_0-9]{0,5}){0,3}", fullmatch=True),
)
#: YAML payloads: mappings that fit, that do not, and text that is no YAML at all.
PAYLOADS = st.one_of(
    st.sampled_from(
        [
            "{data: hi}",
            "{data: 1}",
            "{nope: 1}",
            "{data: [1, 2]}",
            "[1, 2]",
            "{",
            "data: : :",
            "{a: 1, b: 2}",
            "{a: x}",
            "{a: 99999999999999999999999}",
            "{a: .nan}",
            "!!python/object:os.system {}",
            "{data: !!binary aGk=}",
            "",
        ]
    ),
    st.text(max_size=30),
)
COUNTS = st.sampled_from(["-1", "0", "1", "-5", "x", "1.5", "99999999999999999999"])


# --------------------------------------------------------------------------- build
#: Pieces of a msctl-build.toml, most of them wrong in some way.
BUILD_FIELDS = {
    "name": st.sampled_from(['"limb_fw"', '"x y"', "1", '""', '"a"', "[]", '"../up"']),
    "depends": st.sampled_from(["[]", '["limb_msgs"]', '["nosuch"]', '"limb_msgs"', "[1]"]),
    "commands": st.sampled_from(
        [
            json.dumps([[sys.executable, "-c", "pass"]]),
            json.dumps([[sys.executable, "-c", "import sys; sys.exit(3)"]]),
            '[["no-such-tool-here"]]',
            '["make"]',
            "[]",
            '"make"',
            "[[]]",
        ]
    ),
    "sources": st.sampled_from(['["src/**"]', '["/etc/*"]', '["../x"]', "[1]", "[]"]),
    "colour": st.sampled_from(['"red"']),
}


@st.composite
def build_manifests(draw: st.DrawFn) -> str:
    keys = draw(st.lists(st.sampled_from(sorted(BUILD_FIELDS)), unique=True, max_size=5))
    text = "".join(f"{k} = {draw(BUILD_FIELDS[k])}\n" for k in keys)
    if draw(st.booleans()):
        # A cut or mangled file: the middle of it lost, as an editor crash leaves it.
        text = text[: draw(st.integers(0, len(text)))] + draw(st.text(max_size=8))
    return text


PYPROJECTS = st.one_of(
    st.sampled_from(
        [
            '[project]\nname = "limb-msgs"\ndependencies = ["numpy>=1"]\n',
            "[project]\nname = \ndependencies = 1\n",
            '[project]\nname = "limb-msgs"\ndependencies = ["not a requirement !!"]\n',
            '[project]\nname = "limb-msgs"\n[build-system]\nrequires = "setuptools"\n',
            "[tool.x]\n",
            "\x00\x01",
        ]
    ),
    st.text(max_size=40),
)
PACKAGE_XMLS = st.sampled_from(
    [
        "<package><name>limb_msgs</name></package>",
        "<package><name></name></package>",
        "<robot/>",
        "<package",
        "",
        "<package><name>limb_msgs</name><depend>limb_fw</depend></package>",
    ]
)


@_settings("build")
@given(
    manifest=build_manifests(),
    pyproject=st.one_of(st.none(), PYPROJECTS),
    package_xml=st.one_of(st.none(), PACKAGE_XMLS),
    extra=st.sampled_from([(), ("--list", "--json"), ("--timeout", "-1"), ("--jobs", "0")]),
)
def test_build_takes_any_manifest_without_an_internal_error(
    home: Path, manifest: str, pyproject: str | None, package_xml: str | None, extra: tuple
) -> None:
    ws = home / "ws"
    shutil.rmtree(ws, ignore_errors=True)
    (ws / "fw").mkdir(parents=True)
    (ws / "fw" / "msctl-build.toml").write_text(manifest)
    if pyproject is not None:
        (ws / "msgs").mkdir()
        (ws / "msgs" / "pyproject.toml").write_text(pyproject)
    if package_xml is not None:
        (ws / "ros").mkdir()
        (ws / "ros" / "package.xml").write_text(package_xml)
    args = ("build", "-w", str(ws), *extra)
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)
    if code == 2:
        # Refused as input: nothing built, no build state.
        assert not (ws / ".msctl" / "build").exists(), (args, stderr)


# --------------------------------------------------------------------------- update
REPOS_ENTRIES = st.fixed_dictionaries(
    {},
    optional={
        "type": st.sampled_from(["git", "svn", "", 1]),
        "url": st.sampled_from(
            [
                "file:///nonexistent/repo.git",
                "x;y",
                "https://example.org/a.git",
                "ext::sh -c x",
                "",
                "-oProxyCommand=x",
                1,
            ]
        ),
        "version": st.sampled_from(["main", "../x", "-f", "a b", "", 7, "v1.0"]),
        "colour": st.just("red"),
    },
)
REPOS_PATHS = st.sampled_from(["src/limb", "../escape", "/abs", "", "a/../../b", "ok", "-x"])


@st.composite
def repos_files(draw: st.DrawFn) -> str:
    import yaml

    shape = draw(st.sampled_from(["mapping", "list", "scalar", "text", "empty"]))
    if shape == "mapping":
        entries = draw(st.dictionaries(REPOS_PATHS, REPOS_ENTRIES, max_size=3))
        key = draw(st.sampled_from(["repositories", "repos", "repositories"]))
        return yaml.safe_dump({key: entries})
    if shape == "list":
        return yaml.safe_dump({"repositories": [1, 2]})
    if shape == "scalar":
        return "repositories: 3\n"
    if shape == "empty":
        return ""
    return draw(st.text(max_size=60))


@_settings("update")
@given(
    text=repos_files(),
    extra=st.sampled_from(
        [(), ("--jobs", "0"), ("--retry", "-1"), ("--status",), ("--lock", "{lock}")]
    ),
    lock=st.sampled_from(["exact.repos", "a-file/x.repos", "/proc/x.repos", "."]),
)
def test_update_takes_any_repos_file_without_an_internal_error(
    home: Path, text: str, extra: tuple, lock: str
) -> None:
    ws = home / "ws"
    shutil.rmtree(ws, ignore_errors=True)
    (home / "a-file").write_text("")
    repos = home / "fuzz.repos"
    repos.write_text(text)
    # A relative lock path is the test's home's, never the directory the tests run in.
    lock = lock if lock.startswith("/") else str(home / lock)
    args = ("update", str(repos), "-w", str(ws), *(a.format(lock=lock) for a in extra))
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)
    if code == 2:
        assert not ws.exists(), (args, stderr)  # refused before any clone


# --------------------------------------------------------------------------- topic, service
@pytest.fixture
def plane(home: Path) -> Iterator[Path]:
    """A loopback port nothing listens on (never 7447): a valid example fails at connect."""
    from conftest import free_port

    env = {
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    with mock.patch.dict(os.environ, env):
        yield home


TYPES = st.sampled_from(
    ["std_msgs/msg/String", "std_msgs/String", "std_msgs/msg/Strin", "nope", "a/b/c/d", ""]
)


@_settings("topic")
@given(
    verb=st.sampled_from(["pub", "echo", "hz"]),
    name=NAMES,
    type_name=TYPES,
    payload=PAYLOADS,
    count=COUNTS,
)
def test_topic_commands_take_any_name_and_payload_without_an_internal_error(
    plane: Path, verb: str, name: str, type_name: str, payload: str, count: str
) -> None:
    if verb == "pub":
        args = ("topic", "pub", name, type_name, payload, "--times", count, "--fire-and-forget")
        args += ("--rate", "50")
    elif verb == "echo":
        args = ("topic", "echo", name, type_name, "--times", count, "--timeout", "0.3")
    else:
        args = ("topic", "hz", name, type_name, "--for", "0.3")
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)


SERVICE_TYPES = st.sampled_from(
    ["std_srvs/srv/Trigger", "example_interfaces/srv/AddTwoInts", "std_srvs/Trigger", "x", ""]
)


@_settings("service")
@given(
    name=NAMES,
    type_name=SERVICE_TYPES,
    payload=PAYLOADS,
    timeout=st.sampled_from(["0.2", "0", "-1", "nan", "inf"]),
)
def test_service_call_takes_any_name_and_payload_without_an_internal_error(
    plane: Path, name: str, type_name: str, payload: str, timeout: str
) -> None:
    args = ("service", "call", name, type_name, payload, "--timeout", timeout)
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)


# --------------------------------------------------------------------------- bag
@pytest.fixture(scope="module")
def good_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished bag of 30 strings, written by msctl's own writer."""
    import time

    from components.comm.types import registry
    from components.messages import msg
    from components.recording.definitions import message_definition
    from components.recording.writer import BagWriter, TopicSpec

    directory = tmp_path_factory.mktemp("bags") / "good"
    string = "std_msgs/msg/String"
    serialize = registry().serializer(string)
    with BagWriter(directory) as writer:
        topic = writer.add_topic(
            TopicSpec(
                "/chatter", string, registry().type_hash(string), (), message_definition(string)
            )
        )
        start = time.time_ns()
        for i in range(30):
            writer.write(topic, start + i * 1_000_000, serialize(msg(string, data=f"m{i}")))
    return directory


METADATA_TEXTS = st.one_of(
    st.none(),
    st.sampled_from(
        [
            "",
            "rosbag2_bagfile_information: 3\n",
            "rosbag2_bagfile_information:\n  relative_file_paths: [nowhere.mcap]\n",
            "rosbag2_bagfile_information:\n  topics_with_message_count: [1]\n",
            "{",
            "\x00",
        ]
    ),
    st.text(max_size=40),
)


@_settings("bag")
@given(
    metadata=METADATA_TEXTS,
    cut=st.one_of(st.none(), st.integers(0, 4000)),
    flips=st.lists(st.tuples(st.integers(0, 4000), st.integers(1, 255)), max_size=4),
    verb=st.sampled_from(["info", "recover", "recover-file", "info-file"]),
)
def test_bag_commands_take_any_damage_without_an_internal_error(
    home: Path,
    good_bag: Path,
    metadata: str | None,
    cut: int | None,
    flips: list[tuple[int, int]],
    verb: str,
) -> None:
    bag = home / "bag"
    shutil.rmtree(bag, ignore_errors=True)
    shutil.copytree(good_bag, bag)
    (mcap,) = bag.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    for at, xor in flips:
        if at < len(data):
            data[at] ^= xor
    if cut is not None:
        data = data[:cut]
    mcap.write_bytes(bytes(data))
    if metadata is not None:
        (bag / "metadata.yaml").write_text(metadata)
    before = snapshot(bag)
    target = str(mcap) if verb.endswith("-file") else str(bag)
    args = ("bag", verb.removesuffix("-file"), target)
    code, _, stderr = msctl(*args)
    keeps_the_contract(code, stderr, args)
    if code != 0 or args[1] == "info":
        assert snapshot(bag) == before, (args, stderr)
