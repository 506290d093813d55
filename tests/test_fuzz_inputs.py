"""Property-based fuzzing of what reaches msctl from outside: CDR payloads and rmw_zenoh
attachments on every message type a component subscribes to or serves, supervisor request
arguments, and the static data files (module types, templates, units).

Properties: nothing but the documented error escapes (a malformed sample is dropped and
counted, a bad request is a RequestError, bad data an InputError naming the file), and every
sample is accounted for (delivered, or counted as dropped).
"""

from __future__ import annotations

import shutil
import struct
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, wait_until
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from components import kinds
from components.comm.attachment import Attachment, AttachmentError
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.comm.stats import drops
from components.comm.types import registry
from components.executor.interface import InterfaceSpec
from components.messages import JOINT_STATE, JointSample, joint_state, msg
from components.supervision.contract import RequestError
from components.supervision.protocol import VERBS, parse_request
from msctl.errors import MsctlError

REPO = Path(__file__).resolve().parents[1]
FUZZ = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


def _inbound_types() -> list[str]:
    """Every type a component reads: its subscriptions and its services' requests."""
    found = {JOINT_STATE}  # the simulator's inputs (its interface is made per assembly)
    for entry in kinds.registry().values():
        if not entry.interface:
            continue
        spec = kinds.resolve(entry.interface)
        if not isinstance(spec, InterfaceSpec):
            continue
        found |= {s.msg_type for s in spec.subscribe}
        found |= {f"{s.srv_type}_Request" for s in spec.serve}
    known = set(registry().message_names())
    return sorted(t for t in found if t in known)


INBOUND = _inbound_types()


def _valid_payload(type_name: str) -> bytes:
    """One well-formed sample of ``type_name`` (a JointState with content, else defaults)."""
    if type_name == JOINT_STATE:
        message = joint_state([JointSample("limb1_joint1", 0.5, 0.1, 0.0)])
    else:
        message = msg(type_name)
    return registry().serializer(type_name)(message)


@st.composite
def mutated(draw: st.DrawFn, base: bytes) -> bytes:
    """``base`` bit-flipped, truncated, extended, or with a length field made huge."""
    data = bytearray(base)
    for _ in range(draw(st.integers(0, 4))):
        if not data:
            break
        action = draw(st.sampled_from(["flip", "cut", "grow", "length"]))
        at = draw(st.integers(0, len(data) - 1))
        if action == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif action == "cut":
            del data[at:]
        elif action == "grow":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif len(data) >= at + 4:
            data[at : at + 4] = struct.pack(
                "<I", draw(st.sampled_from([2**31 - 1, 2**32 - 1, 2**24]))
            )
    return bytes(data)


@pytest.mark.parametrize("type_name", INBOUND)
def test_any_payload_decodes_or_raises_an_ordinary_error(type_name: str) -> None:
    deserialize = registry().deserializer(type_name)
    base = _valid_payload(type_name)

    @FUZZ
    @given(st.one_of(st.binary(max_size=256), mutated(base)))
    def check(payload: bytes) -> None:
        try:
            deserialize(payload)
        except Exception:
            pass  # Subscription turns this into a counted drop

    assert deserialize(base) is not None
    check()


@FUZZ
@given(st.binary(max_size=80))
def test_any_attachment_decodes_or_raises_attachment_error(data: bytes) -> None:
    try:
        attachment = Attachment.decode(data)
    except AttachmentError:
        return
    assert len(attachment.source_gid) == 16


@FUZZ
@given(
    st.sampled_from(VERBS),
    st.one_of(
        st.text(max_size=200),
        st.recursive(
            st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
            lambda inner: (
                st.lists(inner, max_size=4)
                | st.dictionaries(st.text(max_size=10), inner, max_size=4)
            ),
            max_leaves=30,
        ).map(lambda value: __import__("json").dumps(value)),
        st.integers(1, 20_000).map(lambda depth: "[" * depth + "]" * depth),
        st.integers(1, 20_000).map(lambda depth: '{"component":' + "[" * depth + "]" * depth + "}"),
    ),
)
def test_supervisor_request_arguments_parse_or_are_refused(verb: str, text: str) -> None:
    try:
        request = parse_request(verb, text)
    except RequestError:
        return
    assert request.verb == verb and isinstance(request.args, dict)


# --------------------------------------------------------------------------- on the wire


@pytest.fixture(scope="module")
def wire() -> Iterator[dict[str, Any]]:
    """A router-less pair of peer sessions on loopback: a subscriber and a raw publisher."""
    port = free_port()
    listen = SessionSettings(connect=(), listen=(f"tcp/127.0.0.1:{port}",), multicast=False)
    connect = SessionSettings(connect=(f"tcp/127.0.0.1:{port}",), multicast=False)
    receiver, sender = open_session(listen), open_session(connect)
    node = Node(receiver, "fuzz_sink", "/fuzz")
    got: list[Any] = []
    subscription = node.subscription("joint_commands", JOINT_STATE, got.append)
    # Reliable and blocking: Zenoh's default congestion control drops a sample the sending
    # queue cannot take within a millisecond, which a loaded machine reaches (a fuzz sample
    # then lost on the sender's side, neither delivered nor counted here).
    import zenoh

    publisher = sender.declare_publisher(
        subscription.key,
        reliability=zenoh.Reliability.RELIABLE,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    try:
        yield {"subscription": subscription, "publisher": publisher, "got": got}
    finally:
        publisher.undeclare()
        node.close()
        sender.close()
        receiver.close()


@FUZZ
@given(
    payload=st.one_of(st.binary(max_size=128), mutated(_valid_payload(JOINT_STATE))),
    attachment=st.one_of(
        st.none(),
        st.binary(max_size=48),
        st.builds(
            lambda n, t, g: Attachment(n, t, g).encode(),
            st.integers(0, 2**63 - 1),
            st.integers(0, 2**63 - 1),
            st.binary(min_size=16, max_size=16),
        ),
    ),
)
def test_every_sample_on_the_wire_is_delivered_or_counted(
    wire: dict[str, Any], payload: bytes, attachment: bytes | None
) -> None:
    subscription = wire["subscription"]
    topic = subscription.topic
    before = subscription.received + drops.count(topic)
    if attachment is None:
        wire["publisher"].put(payload)
    else:
        wire["publisher"].put(payload, attachment=attachment)
    # Drops notify nobody, so poll: a sample neither delivered nor counted fails here.
    wait_until(
        lambda: subscription.received + drops.count(topic) > before,
        timeout=10.0,
        what="the sample delivered or counted as dropped",
        interval=0.001,
    )
    assert subscription.received + drops.count(topic) == before + 1


# --------------------------------------------------------------------------- static data

_NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**63), 2**63 - 1),
    st.text(max_size=8),
    st.booleans(),
    st.lists(st.integers(-5, 5), max_size=3),
)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if value != value:
            return "nan"
        if value in (float("inf"), float("-inf")):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.encode("unicode_escape").decode("ascii").replace('"', '\\"') + '"'
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


@pytest.fixture(scope="module")
def data_copy(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path]]:
    root = tmp_path_factory.mktemp("fuzz_data")
    for folder in ("assemblies", "calibration"):
        shutil.copytree(REPO / folder, root / folder)
    patch = pytest.MonkeyPatch()
    patch.setenv("MSCTL_ASSEMBLIES_DIR", str(root / "assemblies"))
    patch.setenv("MSCTL_CALIBRATION_DIR", str(root / "calibration"))
    yield {"assemblies": root / "assemblies", "calibration": root / "calibration"}
    patch.undo()


def _assignments(path: Path) -> list[int]:
    """Line numbers of ``key = value`` lines (the values a fuzzer may replace)."""
    lines = path.read_text().splitlines()
    return [
        i
        for i, line in enumerate(lines)
        if "=" in line and not line.lstrip().startswith(("#", "["))
    ]


FILES = [
    "assemblies/modules/hl_limb_v1.toml",
    "assemblies/modules/gl_limb.toml",
    "assemblies/dragon.toml",
    "calibration/hlv1-limb-03.toml",
    "calibration/gl-limb-01.toml",
]


# Resolving real files a few hundred times takes seconds: outside the inner loop.
@pytest.mark.e2e
@pytest.mark.parametrize("relative", FILES)
def test_a_data_file_with_any_value_changed_resolves_or_names_the_file(
    relative: str, data_copy: dict[str, Path]
) -> None:
    from msctl.assembler import data, resolve

    root, _, rest = relative.partition("/")
    path = data_copy[root] / rest
    original = path.read_text()
    lines = original.splitlines()
    candidates = _assignments(path)
    uses = {"limb1": path.stem} if root == "calibration" else {}
    if "gl_limb" in relative:
        uses = {"limb1": "gl-limb-01", "limb2": "gl-limb-02"}

    @FUZZ
    @given(st.sampled_from(candidates), _NUMBERS)
    def check(line: int, value: Any) -> None:
        key = lines[line].split("=", 1)[0]
        changed = [*lines[:line], f"{key}= {_toml_value(value)}", *lines[line + 1 :]]
        path.write_text("\n".join(changed) + "\n")
        data.clear_cache()
        try:
            try:
                tomllib.loads(path.read_text())
            except tomllib.TOMLDecodeError:
                return  # the fuzzer wrote something TOML cannot hold (a key path, say)
            resolve("dragon", uses)
        except MsctlError as exc:
            assert str(exc), "an error with no message"
        finally:
            path.write_text(original)

    check()
    data.clear_cache()
