"""ROS 2 type support made at run time from msctl's own type registry, for rclpy on Fast DDS.

rclpy needs, for every message and service type it publishes, takes or serves, a Python class
whose metaclass holds C type support (``_TYPE_SUPPORT``) and four conversion functions. They
come from each interface package's compiled C extension; the package index has wheels for the
standard ones (``ros-std-msgs`` ...) and none for ``msctl_msgs``, and building one needs a
compiler and colcon. So msctl makes its own, for any type its registry knows, with no compiler:

* the type support is ``rosidl_typesupport_fastrtps_c``'s: a table of four callbacks that
  rmw_fastrtps calls to serialize and deserialize a message (``message_type_support_callbacks_t``);
* the "ROS message" those callbacks handle is opaque to everything else, so here it is a
  handle to CDR bytes: serializing copies the bytes into Fast CDR's stream, deserializing
  copies them out;
* the Python side (:class:`Carrier`) is the CDR bytes too (``.cdr``, with the 4-byte
  encapsulation header), so a bridge relays a request without decoding it, and the executor
  decodes it with the same codec the Zenoh path uses.

The type name on the wire (``msctl_msgs::srv::dds_::Rezero_Request_``) is made by
rmw_fastrtps from the namespace and name in the table, exactly as for a compiled package, so
a real rclpy node with the compiled package and a msctl node with this type support meet.
Topics are published and taken as serialized bytes (rclpy's ``raw``), which never reaches the
callbacks at all; services go through them (rclpy converts requests and responses).

Two facts about Fast CDR 2.2 are used through ``ctypes``: the exported member functions
``Cdr::serialize_array(const char*, size_t)``, ``Cdr::get_current_position()`` and
``Cdr::jump(size_t)``, and where a ``Cdr`` keeps the end of its buffer, which is found at run
time (the iterator pairs ``offset_`` / ``origin_`` / ``end_``) and checked, never assumed.
Only imported on the rclpy path: rclpy must be importable.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from components.comm.types import normalize_type_name, registry
from components.ros.rosidl_structs import (
    _CREATE,
    _DESERIALIZE,
    _DESTROY,
    _FROM_PY,
    _GET_POINTER,
    _HANDLE_FUNCTION,
    _INTROSPECTION_IDS,
    _MAX_SIZE,
    _NESTED_ID,
    _SERIALIZE,
    _SIZE,
    _TO_PY,
    _Member,
    _Members,
    _MessageCallbacks,
    _MessageTypeSupport,
    _ServiceCallbacks,
    _ServiceMembers,
    _ServiceTypeSupport,
    _TypeHash,
)

log = logging.getLogger("msctl.ros")

#: CDR little-endian encapsulation (what the registry's codec writes).
_ENCAPSULATION = b"\x00\x01\x00\x00"
#: ``ROSIDL_TYPESUPPORT_FASTRTPS_UNBOUNDED_TYPE``: the size is known only per message.
_UNBOUNDED = 0


class TypeSupportError(RuntimeError):
    """A type support could not be made (a library or symbol is missing); says which."""


# ---------------------------------------------------------------------------- libraries
def _library(name: str) -> ctypes.CDLL:
    """Load one of the wheels' shared libraries (already loaded by rclpy, or from the
    environment's ``lib`` directory, where the ros-python-wheels put them)."""
    candidates = [name, str(Path(sys.prefix) / "lib" / name)]
    candidates += [
        str(Path(folder) / name) for folder in os.environ.get("LD_LIBRARY_PATH", "").split(":")
    ]
    for candidate in candidates:
        try:
            return ctypes.CDLL(candidate)
        except OSError:
            continue
    raise TypeSupportError(
        f"cannot load {name}: the rclpy path needs the ROS 2 wheels (pip install 'msctl[ros]')"
    )


class _Native:
    """The C functions and data this module uses, loaded once."""

    def __init__(self) -> None:
        runtime = _library("librosidl_runtime_c.so")
        fastrtps_c = _library("librosidl_typesupport_fastrtps_c.so")
        introspection_c = _library("librosidl_typesupport_introspection_c.so")
        fastcdr = _library("libfastcdr.so.2")
        self.identifier = self._string(fastrtps_c, "rosidl_typesupport_fastrtps_c__identifier")
        self.introspection = self._string(
            introspection_c, "rosidl_typesupport_introspection_c__identifier"
        )
        create_description = runtime.rosidl_runtime_c__type_description__TypeDescription__create
        create_description.restype = ctypes.c_void_p
        create_sources = runtime.rosidl_runtime_c__type_description__TypeSource__Sequence__create
        create_sources.restype = ctypes.c_void_p
        create_sources.argtypes = (ctypes.c_size_t,)
        # Empty, valid descriptions: rcl's type cache keeps them for the type description
        # service; the hash (below) is the real one.
        self.description = create_description()
        self.sources = create_sources(0)
        if not self.description or not self.sources:
            raise TypeSupportError("cannot allocate an empty type description")
        self.serialize_array = self._method(
            fastcdr,
            "_ZN8eprosima7fastcdr3Cdr15serialize_arrayEPKcm",
            ctypes.c_char_p,
            ctypes.c_size_t,
        )
        self.current_position = self._method(
            fastcdr, "_ZN8eprosima7fastcdr3Cdr20get_current_positionEv"
        )
        self.buffer_pointer = self._method(
            fastcdr, "_ZN8eprosima7fastcdr3Cdr18get_buffer_pointerEv"
        )
        self.jump = self._method(fastcdr, "_ZN8eprosima7fastcdr3Cdr4jumpEm", ctypes.c_size_t)
        self._end_offset: int | None = None
        self._lock = threading.Lock()

    @staticmethod
    def _string(library: ctypes.CDLL, symbol: str) -> int:
        """The address a ``const char *`` global holds (a type support identifier)."""
        address = ctypes.c_void_p.in_dll(library, symbol).value
        if not address:
            raise TypeSupportError(f"{symbol} is not set in {library._name}")
        return address

    @staticmethod
    def _method(library: ctypes.CDLL, symbol: str, *arguments: Any) -> Any:
        try:
            function = getattr(library, symbol)
        except AttributeError:
            raise TypeSupportError(
                f"Fast CDR has no {symbol}: msctl's rclpy path expects Fast CDR 2.2 "
                "(ros-fastcdr, installed with ros-rclpy[fastrtps]==7.1.6)"
            ) from None
        function.restype = ctypes.c_void_p
        function.argtypes = (ctypes.c_void_p, *arguments)
        return function

    def remaining(self, cdr: int) -> tuple[int, int]:
        """``(current position, bytes left)`` of a Fast CDR deserializer.

        Fast CDR keeps three buffer iterators in a row, each ``(buffer, position)``:
        ``offset_`` (now), ``origin_`` and ``end_``. The first time, the object is searched
        for ``(buffer, now)`` followed two iterators later by ``(buffer, end)``; that place
        is kept and checked on every later call.
        """
        start = self.buffer_pointer(cdr)
        now = self.current_position(cdr)
        words = (ctypes.c_void_p * 96).from_address(cdr)
        with self._lock:
            if self._end_offset is None:
                for index in range(0, len(words) - 5):
                    if (
                        words[index] == start
                        and words[index + 1] == now
                        and words[index + 2] == start
                        and words[index + 4] == start
                        and (words[index + 5] or 0) >= now
                    ):
                        self._end_offset = index + 5
                        break
                else:
                    raise TypeSupportError("cannot find the end of Fast CDR's buffer")
            offset = self._end_offset
        end = words[offset] or 0
        if words[offset - 1] != start or end < now:
            raise TypeSupportError("Fast CDR's buffer is not where it was")
        return now, end - now


_native: _Native | None = None
_native_lock = threading.Lock()


def _load() -> _Native:
    global _native
    with _native_lock:
        if _native is None:
            _native = _Native()
        return _native


# ---------------------------------------------------------------------------- messages
class Carrier:
    """A message as rclpy sees it through this type support: its CDR bytes.

    Attributes:
        cdr: The serialized message, with its 4-byte encapsulation header.
    """

    #: The ROS type name (``msctl_msgs/srv/Rezero_Request``), set on each made class.
    type_name = ""

    __slots__ = ("cdr",)

    def __init__(self, cdr: bytes = b"") -> None:
        # rclpy makes an empty response for every request it hands a server; it is never
        # sent, so it is not encoded until something asks (default_cdr).
        self.cdr = cdr

    @classmethod
    def default_cdr(cls) -> bytes:
        """The CDR of a message of this type with every field at its default."""
        from components.messages import msg

        return registry().serializer(cls.type_name)(msg(cls.type_name))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self.cdr)} bytes)"


class _Messages:
    """Every ROS message rclpy has asked this type support to create: handle -> CDR bytes.

    A handle is the address of a small block owned here, so nothing that receives it can
    mistake it for freed memory while it lives.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._blocks: dict[int, ctypes.Array] = {}
        self._data: dict[int, bytes] = {}

    def create(self) -> int:
        block = ctypes.create_string_buffer(8)
        address = ctypes.addressof(block)
        with self._lock:
            self._blocks[address] = block
            self._data[address] = b""
        return address

    def destroy(self, address: int) -> None:
        with self._lock:
            self._blocks.pop(address, None)
            self._data.pop(address, None)

    def set(self, address: int, cdr: bytes) -> None:
        with self._lock:
            self._data[address] = cdr

    def get(self, address: int) -> bytes:
        with self._lock:
            return self._data[address]


_messages = _Messages()


def _guarded(default: Any, what: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """A callback that C calls must never raise into C: log and return ``default``."""

    def wrap(function: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            try:
                return function(*args)
            except Exception:
                log.exception("type support: %s failed", what)
                return default

        return call

    return wrap


class _Dispatch:
    """A type support's ``func``: hands out the handle made for the identifier asked for
    (``rosidl_typesupport_fastrtps_c`` to serialize, ``..._introspection_c`` for the Fast DDS
    type object), like rosidl_typesupport_c's dispatch does from compiled libraries."""

    def __init__(self) -> None:
        self.handles: dict[bytes, int] = {}
        self.function = _HANDLE_FUNCTION(self._find)

    def _find(self, handle: int, identifier: bytes | None) -> int | None:
        del handle
        return self.handles.get(identifier or b"")

    @property
    def address(self) -> int:
        return _function_address(self.function)


class _MessageSupport:
    """The C type support and the Python class of one message type (kept alive here)."""

    def __init__(self, native: _Native, type_name: str) -> None:
        self.type_name = type_name
        package, subfolder, name = type_name.split("/")
        self._name = name.encode()
        self._hash = _type_hash(type_name)
        self._dispatch = _Dispatch()
        self._get_hash = _GET_POINTER(lambda _: ctypes.addressof(self._hash))
        self._get_description = _GET_POINTER(lambda _: native.description)
        self._get_sources = _GET_POINTER(lambda _: native.sources)

        @_guarded(False, f"serializing a {type_name}")
        def serialize(message: int, cdr: int) -> bool:
            body = _messages.get(message)[4:]
            native.serialize_array(cdr, body, len(body))
            return True

        @_guarded(False, f"deserializing a {type_name}")
        def deserialize(cdr: int, message: int) -> bool:
            position, left = native.remaining(cdr)
            body = ctypes.string_at(position, left)
            native.jump(cdr, left)
            _messages.set(message, _ENCAPSULATION + body)
            return True

        @_guarded(0, f"sizing a {type_name}")
        def size(message: int) -> int:
            return len(_messages.get(message)) - 4

        @_guarded(0, f"bounding a {type_name}")
        def max_size(bounds: Any) -> int:
            bounds[0] = bytes([_UNBOUNDED])
            return 0

        self._callbacks = _MessageCallbacks(
            f"{package}::{subfolder}".encode(),
            self._name,
            _SERIALIZE(serialize),
            _DESERIALIZE(deserialize),
            _SIZE(size),
            _MAX_SIZE(max_size),
            None,
        )
        self.handle = self._handle(native.identifier, ctypes.addressof(self._callbacks))
        self.address = ctypes.addressof(self.handle)
        self._fields = self._introspection(f"{package}__{subfolder}".encode())
        self.members = ctypes.addressof(self._members)
        self.introspection = self._handle(native.introspection, self.members)
        self._dispatch.handles[ctypes.string_at(native.identifier)] = self.address
        self._dispatch.handles[ctypes.string_at(native.introspection)] = ctypes.addressof(
            self.introspection
        )
        self.cls = self._python_class()

    def _handle(self, identifier: int, data: int) -> _MessageTypeSupport:
        return _MessageTypeSupport(
            identifier,
            data,
            self._dispatch.address,
            self._get_hash,
            self._get_description,
            self._get_sources,
        )

    def _introspection(self, namespace: bytes) -> list[Any]:
        """The field table Fast DDS builds its type object from (names, kinds, bounds,
        nested types); offsets and accessors stay empty: no message is ever read through it."""
        fields = registry().fields(self.type_name)
        keep: list[Any] = []
        members = (_Member * max(len(fields), 1))()
        for index, (field_name, desc) in enumerate(fields):
            member = members[index]
            encoded = field_name.encode()
            keep.append(encoded)
            member.name = encoded
            node, detail = desc
            if node.name in ("ARRAY", "SEQUENCE"):
                inner, size = detail
                member.is_array = True
                member.array_size = size
                member.is_upper_bound = node.name == "SEQUENCE" and bool(size)
                node, detail = inner
            if node.name == "NAME":
                member.type_id = _NESTED_ID
                member.members = ctypes.addressof(message_support(detail).introspection)
            else:
                base, bound = detail
                member.type_id = _INTROSPECTION_IDS[base]
                member.string_upper_bound = bound if base in ("string", "wstring") else 0
        keep.append(members)
        self._members = _Members(
            namespace, self._name, len(fields), 0, False, ctypes.addressof(members), None, None
        )
        return keep

    def _python_class(self) -> type:
        @_guarded(False, f"converting a {self.type_name} from Python")
        def from_py(value: Any, message: int) -> bool:
            cdr = value.cdr if isinstance(value, Carrier) else bytes(value)
            _messages.set(message, cdr or self.cls.default_cdr())
            return True

        def to_py(message: int) -> Any:
            return self.cls(_messages.get(message))

        self._create = _CREATE(_messages.create)
        self._destroy = _DESTROY(_messages.destroy)
        self._from_py = _FROM_PY(from_py)
        self._to_py = _TO_PY(to_py)
        metaclass = type(
            f"Metaclass_{self._name.decode()}",
            (type,),
            {
                "_TYPE_SUPPORT": _capsule(self.address),
                "_CREATE_ROS_MESSAGE": _capsule(_function_address(self._create)),
                "_CONVERT_FROM_PY": _capsule(_function_address(self._from_py)),
                "_CONVERT_TO_PY": _capsule(_function_address(self._to_py)),
                "_DESTROY_ROS_MESSAGE": _capsule(_function_address(self._destroy)),
                "__import_type_support__": classmethod(lambda cls: None),
            },
        )
        return metaclass(
            self._name.decode(), (Carrier,), {"__slots__": (), "type_name": self.type_name}
        )


class _ServiceSupport:
    """The C type support and the Python class of one service type."""

    def __init__(self, native: _Native, type_name: str) -> None:
        parts = registry().service(type_name)
        self.type_name = type_name
        package, subfolder, name = type_name.split("/")
        self.request = message_support(parts.request)
        self.response = message_support(parts.response)
        self._hash = _type_hash(type_name)
        self._dispatch = _Dispatch()
        self._callbacks = _ServiceCallbacks(
            f"{package}::{subfolder}".encode(),
            name.encode(),
            self.request.address,
            self.response.address,
        )
        self._members = _ServiceMembers(
            f"{package}__{subfolder}".encode(),
            name.encode(),
            self.request.members,
            self.response.members,
            None,
        )
        self._get_hash = _GET_POINTER(lambda _: ctypes.addressof(self._hash))
        self._get_description = _GET_POINTER(lambda _: native.description)
        self._get_sources = _GET_POINTER(lambda _: native.sources)
        self.handle = self._handle(native.identifier, ctypes.addressof(self._callbacks))
        self.introspection = self._handle(native.introspection, ctypes.addressof(self._members))
        self._dispatch.handles[ctypes.string_at(native.identifier)] = ctypes.addressof(self.handle)
        self._dispatch.handles[ctypes.string_at(native.introspection)] = ctypes.addressof(
            self.introspection
        )
        metaclass = type(
            f"Metaclass_{name}",
            (type,),
            {
                "_TYPE_SUPPORT": _capsule(ctypes.addressof(self.handle)),
                "__import_type_support__": classmethod(lambda cls: None),
            },
        )
        self.cls = metaclass(
            name,
            (),
            {
                "Request": self.request.cls,
                "Response": self.response.cls,
                "type_name": type_name,
                "__doc__": f"{type_name} through msctl's run-time type support",
            },
        )

    def _handle(self, identifier: int, data: int) -> _ServiceTypeSupport:
        return _ServiceTypeSupport(
            identifier,
            data,
            self._dispatch.address,
            self.request.address,
            self.response.address,
            None,  # no service introspection (its event messages) for these types
            None,
            None,
            self._get_hash,
            self._get_description,
            self._get_sources,
        )


def _type_hash(type_name: str) -> _TypeHash:
    text = registry().type_hash(type_name)
    version, _, hexdigest = text.partition("_")
    value = (ctypes.c_uint8 * 32).from_buffer_copy(bytes.fromhex(hexdigest))
    return _TypeHash(int(version.removeprefix("RIHS")), value)


def _function_address(function: Any) -> int:
    return ctypes.cast(function, ctypes.c_void_p).value or 0


_capsule_new = ctypes.pythonapi.PyCapsule_New
_capsule_new.restype = ctypes.py_object
_capsule_new.argtypes = (ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p)


def _capsule(address: int) -> Any:
    """A nameless capsule around a C pointer, as rosidl's generated extensions make them."""
    return _capsule_new(address, None, None)


_made: dict[str, Any] = {}
_made_lock = threading.RLock()


def message_support(type_name: str) -> _MessageSupport:
    """The type support of a message type (made once per process, then kept).

    Raises:
        UnknownTypeError: If msctl's registry does not know the type.
        TypeSupportError: If the ROS 2 libraries are missing.
    """
    name = normalize_type_name(type_name)
    with _made_lock:
        made = _made.get(name)
        if made is None:
            registry().msg_class(name)  # unknown types fail here, with the known ones named
            made = _made[name] = _MessageSupport(_load(), name)
        return made


def message_class(type_name: str) -> type:
    """The class to give rclpy for a message type (``create_publisher(cls, ...)``)."""
    return message_support(type_name).cls


def service_class(type_name: str) -> type:
    """The class to give rclpy for a service type (``create_service(cls, ...)``).

    Raises:
        UnknownTypeError: If msctl's registry does not know the service.
        TypeSupportError: If the ROS 2 libraries are missing.
    """
    name = normalize_type_name(type_name)
    with _made_lock:
        made = _made.get(name)
        if made is None:
            made = _made[name] = _ServiceSupport(_load(), name)
        return made.cls
