"""ROS 2 names: qualifying topic and service names, and rmw_zenoh's mangling.

A relative name is resolved against the namespace (``joint_set`` in ``/limb1`` is
``/limb1/joint_set``); an absolute one (``/clock``) is kept; ``~/x`` is private to the node.
"""

from __future__ import annotations

import re

from components.errors import ConfigError

_COMPONENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class NameError_(ConfigError):
    """A topic, service, node or namespace name that ROS 2 would refuse."""


def _check_components(name: str, what: str) -> None:
    if "//" in name.strip("/"):
        # ROS refuses repeated slashes, and Zenoh refuses the empty key chunk they make.
        raise NameError_(f"invalid {what} {name!r}: it must not contain '//'")
    for part in name.strip("/").split("/"):
        if part and not _COMPONENT.match(part):
            raise NameError_(
                f"invalid {what} {name!r}: {part!r} must start with a letter or '_' and hold "
                "only letters, digits and '_'"
            )


def normalize_namespace(namespace: str) -> str:
    """``""``, ``"/"`` -> ``"/"``; ``"limb1"`` -> ``"/limb1"``; no trailing slash."""
    text = namespace.strip()
    if text in ("", "/", "%"):
        return "/"
    _check_components(text, "namespace")
    return "/" + text.strip("/")


def qualify(name: str, namespace: str = "/", node: str | None = None) -> str:
    """The fully qualified form of a topic or service name.

    Raises:
        NameError_: If the name or namespace is not a valid ROS 2 name.
    """
    text = name.strip()
    if not text or text == "/":
        raise NameError_("a topic or service name cannot be empty")
    ns = normalize_namespace(namespace)
    if text.startswith("~"):
        if not node:
            raise NameError_(f"private name {name!r} needs a node name")
        text = text[1:].lstrip("/")
        base = ns.rstrip("/") + "/" + node
        result = base + ("/" + text if text else "")
    elif text.startswith("/"):
        result = "/" + text.strip("/")
    else:
        result = ns.rstrip("/") + "/" + text.strip("/")
    _check_components(result, "name")
    return result


def check_node_name(name: str) -> str:
    """Validate a node name (one component)."""
    if not _COMPONENT.match(name):
        raise NameError_(
            f"invalid node name {name!r}: letters, digits and '_' only, not starting with a digit"
        )
    return name


def mangle(name: str) -> str:
    """rmw_zenoh's liveliness mangling: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def unmangle(text: str) -> str:
    """Inverse of :func:`mangle`."""
    return text.replace("%", "/")


def key_name(qualified: str) -> str:
    """The topic part of a data key: the qualified name without outer slashes."""
    return qualified.strip("/")
