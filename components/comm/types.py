"""ROS 2 message and service types: definitions, CDR codec and RIHS01 type hashes.

Message definitions come from the ROS 2 Jazzy type store of ``rosbags``; service definitions
(which that store lacks) and msctl's own types are shipped as ``.srv``/``.msg`` text under
``interfaces/`` and registered at start. Project code may register more from text.

Definitions are plain data until a type is used: building ``rosbags``' Jazzy store (its
Python classes for every type of six distributions) cost about 0.33 s of every process that
touched a message, every component and every ``msctl`` command, most of them using two or
three types. The Jazzy definitions are read from a snapshot shipped beside the interfaces
(``interfaces/jazzy_types.json``, checked against ``rosbags`` by the tests; an installed
``rosbags`` of another version is read directly instead), and a type's classes and codec are
made, with those of the types it uses, the first time it is encoded, decoded or built.

Type hashes follow REP 2011 and are computed here, not by ``rosbags``: its routine maps
``char`` to FIELD_TYPE_CHAR, whereas ROS maps a ``.msg`` ``char`` to IDL ``uint8``, which
breaks every service hash (``service_msgs/msg/ServiceEventInfo`` has a ``char[16]``).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from components.errors import NotFound

if TYPE_CHECKING:
    from components.comm.codec import Codec

# rosbags (about 0.1 s to import) is imported where a definition is parsed or a field
# description read: a process that only names types (a graph listing, a key) never needs it.

_INTERFACES = Path(__file__).with_name("interfaces")
#: The Jazzy store's definitions as data (see the module docstring, :func:`write_snapshot`).
JAZZY_SNAPSHOT = _INTERFACES / "jazzy_types.json"

# REP 2011 / type_description_interfaces FieldType ids.
_NESTED = 1
_BASE_IDS: dict[str, int] = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "float128": 12,
    # A .msg `char` is IDL `uint8` (rosidl_adapter), so it hashes as UINT8, not CHAR (13).
    "char": 3,
    "wchar": 14,
    "bool": 15,
    "byte": 16,
    "octet": 16,
    "string": 17,
    "wstring": 18,
}
_BOUNDED_STRING = {"string": 21, "wstring": 22}
_ARRAY, _BOUNDED_SEQUENCE, _UNBOUNDED_SEQUENCE = 48, 96, 144


class UnknownTypeError(NotFound):
    """A message or service type that no definition is registered for."""


class ServiceParts(NamedTuple):
    """The three message types a service is made of (names in ``pkg/srv/Name_X`` form)."""

    request: str
    response: str
    event: str


def normalize_type_name(name: str) -> str:
    """Return the canonical ``pkg/msg/Name`` form of a type name.

    Accepts ``pkg/msg/Name``, ``pkg/srv/Name``, ``pkg/Name`` (taken as a message) and the DDS
    form ``pkg::msg::dds_::Name_``.

    Raises:
        UnknownTypeError: If the name has none of those shapes.
    """
    text = name.strip().strip("/")
    if "::" in text:
        parts = [p for p in text.split("::") if p != "dds_"]
        if len(parts) == 3 and parts[2].endswith("_"):
            return f"{parts[0]}/{parts[1]}/{parts[2][:-1]}"
        raise UnknownTypeError(f"malformed DDS type name {name!r}")
    parts = text.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] in ("msg", "srv", "action"):
        return text
    raise UnknownTypeError(
        f"malformed type name {name!r}: expected 'package/msg/Name' or 'package/srv/Name'"
    )


def dds_type_name(name: str) -> str:
    """The DDS name rmw_zenoh puts in keys: ``sensor_msgs::msg::dds_::JointState_``."""
    pkg, kind, short = normalize_type_name(name).split("/")
    return f"{pkg}::{kind}::dds_::{short}_"


class TypeRegistry:
    """All message and service types known to this process, with codec and hashes.

    Thread-safe for reads; registrations take a lock. Use :func:`registry` for the shared one.
    """

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        # Every known definition, as data; the store holds only the types made so far.
        self._defs: dict[str, tuple[Any, Any]] = jazzy_definitions()
        self._store = get_typestore(Stores.EMPTY)
        self._lock = threading.RLock()
        self._services: dict[str, ServiceParts] = {}
        self._hashes: dict[str, str] = {}
        # Generated codecs per type (components.comm.codec), made on first use.
        # Each as (the type's codec, the registry's own stream of it).
        self._encoders: dict[str, tuple[Codec, Callable[[Any], bytes]]] = {}
        self._decoders: dict[str, tuple[Codec, Callable[[bytes], Any]]] = {}
        self._load_bundled()

    # ----------------------------------------------------------------- registration
    def _load_bundled(self) -> None:
        msgs = sorted(_INTERFACES.glob("*/msg/*.msg"))
        srvs = sorted(_INTERFACES.glob("*/srv/*.srv"))
        for path in msgs:
            self.register_msg(f"{path.parent.parent.name}/msg/{path.stem}", path.read_text())
        for path in srvs:
            self.register_srv(f"{path.parent.parent.name}/srv/{path.stem}", path.read_text())

    def register_msg(self, name: str, text: str) -> None:
        """Register a message type from ``.msg`` text (idempotent for the same name).

        Raises:
            ValueError: If the text does not parse as a ``.msg`` definition.
        """
        name = normalize_type_name(name)
        with self._lock:
            if name in self._defs:
                return
            if not _has_fields(text):
                # rosidl gives an empty structure one uint8 member; CDR and hash both see it.
                text = "uint8 structure_needs_at_least_one_member\n"
            from rosbags.typesys import get_types_from_msg

            try:
                types = get_types_from_msg(text, name)
            except Exception as exc:
                raise ValueError(f"cannot parse the definition of {name}: {exc}") from exc
            types = _fix_srv_names(types)
            for _, fields in types.values():
                for field_name, desc in fields:
                    nested = _nested_name(desc)
                    if nested and nested not in types and nested not in self._defs:
                        # Caught here, not later as a bare KeyError when the type is hashed.
                        raise ValueError(
                            f"the definition of {name} uses unknown type {nested} "
                            f"(field {field_name!r}); register that type first"
                        )
            self._defs.update(types)  # made into classes when first used (_ready)
            self._hashes.clear()

    def register_srv(self, name: str, text: str) -> None:
        """Register a service type from ``.srv`` text: request, response and event messages.

        Raises:
            ValueError: If the text is not ``request --- response``.
        """
        name = normalize_type_name(name)
        pkg, kind, short = name.split("/")
        if kind != "srv":
            raise ValueError(f"{name} is not a service name (expected 'package/srv/Name')")
        sections = _split_srv(text)
        if len(sections) != 2:
            raise ValueError(f"the definition of {name} must have one '---' separator")
        request, response = (f"{pkg}/srv/{short}_Request", f"{pkg}/srv/{short}_Response")
        event = f"{pkg}/srv/{short}_Event"
        event_text = (
            "service_msgs/msg/ServiceEventInfo info\n"
            f"{pkg}/srv/{short}_Request[<=1] request\n"
            f"{pkg}/srv/{short}_Response[<=1] response\n"
        )
        for part, body in ((request, sections[0]), (response, sections[1])):
            self.register_msg(part, body)
        self.register_msg(event, event_text)
        with self._lock:
            self._services[name] = ServiceParts(request, response, event)
            self._hashes.pop(name, None)

    # ----------------------------------------------------------------- queries
    def known(self, name: str) -> bool:
        """Whether a message or service type of that name is registered."""
        try:
            canonical = normalize_type_name(name)
        except UnknownTypeError:
            return False
        return canonical in self._defs or canonical in self._services

    def message_names(self) -> list[str]:
        """Every registered message type name."""
        return sorted(self._defs)

    def definition(self, name: str) -> tuple[Any, Any]:
        """``(constants, fields)`` of a message type, as ``rosbags`` describes them.

        Raises:
            UnknownTypeError: If the type is not registered.
        """
        return self._defs[self._known_msg(name)]

    def service_names(self) -> list[str]:
        """Every registered service type name."""
        return sorted(self._services)

    def service(self, name: str) -> ServiceParts:
        """The request/response/event message names of a service type.

        Raises:
            UnknownTypeError: If the service is not registered.
        """
        canonical = normalize_type_name(name)
        try:
            return self._services[canonical]
        except KeyError:
            raise UnknownTypeError(
                f"unknown service type {name!r}; known: {', '.join(self.service_names())}"
            ) from None

    def msg_class(self, name: str) -> type:
        """The dataclass of a message type (construct messages with it).

        Raises:
            UnknownTypeError: If the type is not registered.
        """
        canonical = self._require_msg(name)
        return self._store.types[canonical]

    def fields(self, name: str) -> list[tuple[str, Any]]:
        """The (field name, rosbags field description) pairs of a message type."""
        return list(self._defs[self._known_msg(name)][1])

    def serialize(self, message: Any, name: str) -> bytes:
        """CDR bytes (with the 4-byte encapsulation header) of a message."""
        return self.serializer(name)(message)

    def deserializer(self, name: str, stream: bool = False) -> Callable[[bytes], Any]:
        """The decoder of one type, CDR bytes (with header) -> message (hot receive paths).

        Generated for the type (:mod:`components.comm.codec`): ~2.5x faster than
        ``rosbags``' own on a JointState. Checks the encapsulation header, every length and
        the trailing bytes; big-endian payloads and types the generator does not write go
        through ``rosbags``.

        Args:
            name: The message type.
            stream: For one subscription: a decoder that remembers the layout of the last
                payload on its own (see :meth:`components.comm.codec.Codec.stream`); else
                the registry's own, shared by its callers.
        """
        return self._codec(self._require_msg(name), decoding=True, stream=stream)

    def serializer(self, name: str, stream: bool = False) -> Callable[[Any], bytes]:
        """The encoder of one type, message -> CDR bytes with header (hot publish paths).

        Generated for the type (:mod:`components.comm.codec`), byte for byte what
        ``rosbags`` writes, ~2x faster on a JointState.

        Args:
            name: The message type.
            stream: For one publisher: an encoder that remembers the shape of the last
                message on its own (see :meth:`components.comm.codec.Codec.stream`); else
                the registry's own, shared by its callers.
        """
        return self._codec(self._require_msg(name), decoding=False, stream=stream)

    def _codec(self, canonical: str, decoding: bool, stream: bool) -> Callable[[Any], Any]:
        """A stream of the type's codec: a new one, or the registry's shared one."""
        made = (self._decoders if decoding else self._encoders).get(canonical)
        if made is None:
            made = self._make_codec(canonical, decoding)
        if stream:
            return made[0].stream()
        return made[1]

    def _make_codec(self, canonical: str, decoding: bool) -> tuple[Codec, Callable[[Any], Any]]:
        from components.comm import codec

        store = self._store
        with self._lock:
            made = (self._decoders if decoding else self._encoders).get(canonical)
            if made is not None:
                return made
            try:
                if decoding:
                    generated = codec.decoder(
                        canonical,
                        self.fields,
                        self.msg_class,
                        lambda data: store.deserialize_cdr(data, canonical),
                    )
                else:
                    generated = codec.encoder(canonical, self.fields)
            except codec.Unsupported:
                generated = self._rosbags_codec(canonical, decoding)
            made = (generated, generated.stream())
            (self._decoders if decoding else self._encoders)[canonical] = made
            return made

    def _rosbags_codec(self, canonical: str, decoding: bool) -> Codec:
        """``rosbags``' generated little-endian codec of a type, bound (the generic
        ``serialize_cdr``/``deserialize_cdr`` look the type up on every call). It remembers
        no shape: its streams' memory stays unused."""
        from components.comm.codec import Codec

        store = self._store
        definition = store.get_msgdef(canonical)
        if decoding:
            decode_le, cls = definition.deserialize_cdr_le, definition.cls

            def decode(_memo: list[Any], data: bytes) -> Any:
                if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
                    raise ValueError("invalid or unsupported CDR encapsulation")
                if data[1] == 0:  # big-endian senders are rare; take the generic path
                    return store.deserialize_cdr(data, canonical)
                message, pos = decode_le(memoryview(data)[4:], 0, cls, store)
                if pos + 4 + 3 < len(data):
                    raise ValueError(f"{len(data) - pos - 4} trailing bytes after a {canonical}")
                return message

            return Codec(decode)
        size_of, encode_le = definition.getsize_cdr, definition.serialize_cdr_le

        def encode(_memo: list[Any], message: Any) -> bytes:
            buffer = bytearray(4 + size_of(0, message, store))
            buffer[1] = 1  # CDR little-endian encapsulation
            encode_le(memoryview(buffer)[4:], 0, message, store)
            return bytes(buffer)

        return Codec(encode)

    def deserialize(self, data: bytes, name: str) -> Any:
        """Decode CDR bytes (with header) into a message object."""
        return self.deserializer(name)(data)

    def prepare(self, name: str) -> None:
        """Make a message or service type's classes, codecs and hash now rather than on its
        first use (a service's: its request's and response's): a few milliseconds of CPU
        each, spent where a process has it to spare (a fork server before forking, a
        supervisor waiting for its workers' imports).

        Raises:
            UnknownTypeError: If the type is not registered.
            ValueError: If its definition cannot be made into a class or codec.
        """
        canonical = normalize_type_name(name)
        parts = self._services.get(canonical)
        for message in [canonical] if parts is None else [parts.request, parts.response]:
            self.serializer(message)
            self.deserializer(message)
        self.type_hash(canonical)

    def type_hash(self, name: str) -> str:
        """The ``RIHS01_<sha256 hex>`` hash of a message or service type (REP 2011)."""
        canonical = normalize_type_name(name)
        cached = self._hashes.get(canonical)
        if cached is not None:
            return cached
        if canonical in self._services:
            description = self._service_description(canonical)
        else:
            self._known_msg(canonical)
            description = self._message_description(canonical)
        referenced: dict[str, dict[str, Any]] = {}
        self._collect_references(description, referenced)
        document = {
            "type_description": description,
            "referenced_type_descriptions": [referenced[k] for k in sorted(referenced)],
        }
        text = json.dumps(document, separators=(", ", ": "), ensure_ascii=True)
        import hashlib  # here: OpenSSL's loading (~10 ms) is for processes that hash a type

        digest = "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()
        self._hashes[canonical] = digest
        return digest

    # ----------------------------------------------------------------- internals
    def _require_msg(self, name: str) -> str:
        """The canonical name of a message type, its classes and codec made (see
        :meth:`_ready`)."""
        canonical = self._known_msg(name)
        if canonical not in self._store.fielddefs:
            self._ready(canonical)
        return canonical

    def _ready(self, canonical: str) -> None:
        """Make the classes of a type and of every type it uses that is not made yet."""
        with self._lock:
            needed: dict[str, tuple[Any, Any]] = {}
            pending = [canonical]
            while pending:
                name = pending.pop()
                if name in needed or name in self._store.fielddefs:
                    continue
                needed[name] = self._defs[name]
                for _, desc in needed[name][1]:
                    nested = _nested_name(desc)
                    if nested:
                        pending.append(nested)
            if needed:
                self._store.register(needed)

    def _known_msg(self, name: str) -> str:
        canonical = normalize_type_name(name)
        if canonical not in self._defs:
            if canonical in self._services:
                raise UnknownTypeError(
                    f"{canonical} is a service type; use it with a service, not a topic"
                )
            raise UnknownTypeError(
                f"unknown message type {name!r} (not in the ROS 2 Jazzy set nor registered); "
                "check the spelling, e.g. 'sensor_msgs/msg/JointState'"
            )
        return canonical

    def _message_description(self, name: str) -> dict[str, Any]:
        _, fields = self._defs[name]
        described = [{"name": field, "type": _field_type(desc)} for field, desc in fields] or [
            {"name": "structure_needs_at_least_one_member", "type": _plain(3)}
        ]
        return {"type_name": name, "fields": described}

    def _service_description(self, name: str) -> dict[str, Any]:
        parts = self._services[name]
        return {
            "type_name": name,
            "fields": [
                {"name": "request_message", "type": _plain(_NESTED, nested=parts.request)},
                {"name": "response_message", "type": _plain(_NESTED, nested=parts.response)},
                {"name": "event_message", "type": _plain(_NESTED, nested=parts.event)},
            ],
        }

    def _collect_references(
        self, description: dict[str, Any], found: dict[str, dict[str, Any]]
    ) -> None:
        for field in description["fields"]:
            nested = field["type"]["nested_type_name"]
            if nested and nested not in found:
                found[nested] = self._message_description(nested)
                self._collect_references(found[nested], found)


def _plain(type_id: int, capacity: int = 0, string_capacity: int = 0, nested: str = "") -> dict:
    return {
        "type_id": type_id,
        "capacity": capacity,
        "string_capacity": string_capacity,
        "nested_type_name": nested,
    }


def _field_type(desc: Any) -> dict[str, Any]:
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        inner, size = detail
        base = _field_type(inner)
        if node == Nodetype.ARRAY:
            offset = _ARRAY
        else:
            offset = _BOUNDED_SEQUENCE if size else _UNBOUNDED_SEQUENCE
        base["type_id"] += offset
        base["capacity"] = size
        return base
    if node == Nodetype.NAME:
        return _plain(_NESTED, nested=detail)
    base_name, bound = detail
    if bound and base_name in _BOUNDED_STRING:
        return _plain(_BOUNDED_STRING[base_name], string_capacity=bound)
    try:
        return _plain(_BASE_IDS[base_name])
    except KeyError:
        raise UnknownTypeError(f"unsupported primitive type {base_name!r}") from None


def _nested_name(desc: Any) -> str | None:
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _nested_name(detail[0])
    return detail if node == Nodetype.NAME else None


def _has_fields(text: str) -> bool:
    return any(line.split("#", 1)[0].strip() for line in text.splitlines())


def _fix_srv_names(types: dict[str, Any]) -> dict[str, Any]:
    """rosbags files ``pkg/srv/X`` parts as ``pkg/srv/msg/X``; put them back where ROS has them."""

    def fix(value: Any) -> Any:
        if isinstance(value, str):
            return value.replace("/srv/msg/", "/srv/")
        if isinstance(value, tuple | list):
            return type(value)(fix(v) for v in value)
        return value

    return {fix(name): fix(definition) for name, definition in types.items()}


def _split_srv(text: str) -> list[str]:
    sections: list[list[str]] = [[]]
    for line in text.splitlines():
        if line.strip() == "---":
            sections.append([])
        else:
            sections[-1].append(line)
    return ["\n".join(lines) + "\n" for lines in sections]


def jazzy_definitions() -> dict[str, tuple[Any, Any]]:
    """The ROS 2 Jazzy type store's definitions: from :data:`JAZZY_SNAPSHOT` when it was
    written from the installed ``rosbags``, else from ``rosbags`` itself (slower)."""
    from importlib.metadata import PackageNotFoundError, version

    from rosbags.typesys import Stores, get_typestore

    try:
        installed = version("rosbags")
    except PackageNotFoundError:
        installed = ""
    try:
        snapshot = json.loads(JAZZY_SNAPSHOT.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        snapshot = {}
    if installed and snapshot.get("rosbags") == installed:
        return {
            name: (
                [tuple(c) for c in consts],
                [(field, _desc(desc)) for field, desc in fields],
            )
            for name, (consts, fields) in snapshot["types"].items()
        }
    return dict(get_typestore(Stores.ROS2_JAZZY).fielddefs)


def write_snapshot(path: Path = JAZZY_SNAPSHOT) -> None:
    """Write :data:`JAZZY_SNAPSHOT` from the installed ``rosbags`` (after upgrading it)."""
    from importlib.metadata import version

    from rosbags.typesys import Stores, get_typestore

    types = dict(sorted(get_typestore(Stores.ROS2_JAZZY).fielddefs.items()))
    document = {"rosbags": version("rosbags"), "types": types}
    path.write_text(json.dumps(document, separators=(",", ":")) + "\n", encoding="utf-8")


def _desc(value: Any) -> tuple[Any, Any]:
    """A field description read back from JSON: ``(Nodetype, detail)`` with tuples."""
    from rosbags.typesys.base import Nodetype

    node = Nodetype(value[0])
    detail = value[1]
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return node, (_desc(detail[0]), detail[1])
    if node == Nodetype.NAME:
        return node, detail
    return node, tuple(detail)


@cache
def registry() -> TypeRegistry:
    """The process-wide type registry (built on first use)."""
    return TypeRegistry()
