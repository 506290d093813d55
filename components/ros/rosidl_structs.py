"""The C structures and callback types of ROS 2 type support, as ``ctypes`` declares them.

The layouts of ``rosidl_typesupport_fastrtps_c``'s callbacks table,
``rosidl_message_type_support_t`` and ``rosidl_typesupport_introspection_c``'s members
(Jazzy), used by :mod:`components.ros.typesupport` to make type support at run time.
"""

from __future__ import annotations

import ctypes


class _TypeHash(ctypes.Structure):
    _fields_ = (("version", ctypes.c_uint8), ("value", ctypes.c_uint8 * 32))


_SERIALIZE = ctypes.CFUNCTYPE(ctypes.c_bool, ctypes.c_void_p, ctypes.c_void_p)
_DESERIALIZE = ctypes.CFUNCTYPE(ctypes.c_bool, ctypes.c_void_p, ctypes.c_void_p)
_SIZE = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p)
_MAX_SIZE = ctypes.CFUNCTYPE(ctypes.c_size_t, ctypes.POINTER(ctypes.c_char))
_GET_POINTER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)
_CREATE = ctypes.CFUNCTYPE(ctypes.c_void_p)
_DESTROY = ctypes.CFUNCTYPE(None, ctypes.c_void_p)
_FROM_PY = ctypes.CFUNCTYPE(ctypes.c_bool, ctypes.py_object, ctypes.c_void_p)
_TO_PY = ctypes.CFUNCTYPE(ctypes.py_object, ctypes.c_void_p)


class _MessageCallbacks(ctypes.Structure):
    _fields_ = (
        ("message_namespace", ctypes.c_char_p),
        ("message_name", ctypes.c_char_p),
        ("cdr_serialize", _SERIALIZE),
        ("cdr_deserialize", _DESERIALIZE),
        ("get_serialized_size", _SIZE),
        ("max_serialized_size", _MAX_SIZE),
        ("key_callbacks", ctypes.c_void_p),
    )


class _MessageTypeSupport(ctypes.Structure):
    _fields_ = (
        ("typesupport_identifier", ctypes.c_void_p),
        ("data", ctypes.c_void_p),
        ("func", ctypes.c_void_p),
        ("get_type_hash_func", _GET_POINTER),
        ("get_type_description_func", _GET_POINTER),
        ("get_type_description_sources_func", _GET_POINTER),
    )


class _ServiceCallbacks(ctypes.Structure):
    _fields_ = (
        ("service_namespace", ctypes.c_char_p),
        ("service_name", ctypes.c_char_p),
        ("request_members", ctypes.c_void_p),
        ("response_members", ctypes.c_void_p),
    )


class _ServiceTypeSupport(ctypes.Structure):
    _fields_ = (
        ("typesupport_identifier", ctypes.c_void_p),
        ("data", ctypes.c_void_p),
        ("func", ctypes.c_void_p),
        ("request_typesupport", ctypes.c_void_p),
        ("response_typesupport", ctypes.c_void_p),
        ("event_typesupport", ctypes.c_void_p),
        ("event_message_create_handle_function", ctypes.c_void_p),
        ("event_message_destroy_handle_function", ctypes.c_void_p),
        ("get_type_hash_func", _GET_POINTER),
        ("get_type_description_func", _GET_POINTER),
        ("get_type_description_sources_func", _GET_POINTER),
    )


class _Member(ctypes.Structure):
    """``rosidl_typesupport_introspection_c__MessageMember`` (Jazzy)."""

    _fields_ = (
        ("name", ctypes.c_char_p),
        ("type_id", ctypes.c_uint8),
        ("string_upper_bound", ctypes.c_size_t),
        ("members", ctypes.c_void_p),
        ("is_key", ctypes.c_bool),
        ("is_array", ctypes.c_bool),
        ("array_size", ctypes.c_size_t),
        ("is_upper_bound", ctypes.c_bool),
        ("offset", ctypes.c_uint32),
        ("default_value", ctypes.c_void_p),
        ("size_function", ctypes.c_void_p),
        ("get_const_function", ctypes.c_void_p),
        ("get_function", ctypes.c_void_p),
        ("fetch_function", ctypes.c_void_p),
        ("assign_function", ctypes.c_void_p),
        ("resize_function", ctypes.c_void_p),
    )


class _Members(ctypes.Structure):
    """``rosidl_typesupport_introspection_c__MessageMembers`` (Jazzy)."""

    _fields_ = (
        ("message_namespace", ctypes.c_char_p),
        ("message_name", ctypes.c_char_p),
        ("member_count", ctypes.c_uint32),
        ("size_of", ctypes.c_size_t),
        ("has_any_key_member", ctypes.c_bool),
        ("members", ctypes.c_void_p),
        ("init_function", ctypes.c_void_p),
        ("fini_function", ctypes.c_void_p),
    )


_HANDLE_FUNCTION = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_char_p)

#: ``rosidl_typesupport_introspection_c`` field type ids, by ``.msg`` primitive (a ``char``
#: is IDL ``uint8``, as rosidl_adapter makes it).
_INTROSPECTION_IDS = {
    "float32": 1,
    "float64": 2,
    "float128": 3,
    "wchar": 5,
    "bool": 6,
    "byte": 7,
    "octet": 7,
    "char": 8,
    "uint8": 8,
    "int8": 9,
    "uint16": 10,
    "int16": 11,
    "uint32": 12,
    "int32": 13,
    "uint64": 14,
    "int64": 15,
    "string": 16,
    "wstring": 17,
}
_NESTED_ID = 18


class _ServiceMembers(ctypes.Structure):
    """``rosidl_typesupport_introspection_c__ServiceMembers`` (Jazzy)."""

    _fields_ = (
        ("service_namespace", ctypes.c_char_p),
        ("service_name", ctypes.c_char_p),
        ("request_members", ctypes.c_void_p),
        ("response_members", ctypes.c_void_p),
        ("event_members", ctypes.c_void_p),
    )
