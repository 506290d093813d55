"""Configs in the form rmw_zenoh's ``zenoh_security_tools generate_configs`` writes, so a
ROS 2 node with an enclave identity from the fleet CA joins the fleet's routers.

That tool turns an sros2 policy into one Zenoh session config per enclave: mutual TLS with the
enclave's key and certificate, and an ``access_control`` block, default deny, allowing the
enclave's own publications, subscriptions, services and clients on ``<domain>/<topic>/**``,
and its graph tokens on ``@ros2_lv/<domain>/**``. The enclave's certificate CN is its path
(``/field/viewer``), which the routers' ACL names as a subject like any computer's.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from msctl.net import acl, pki

#: A ROS enclave is a path; its CN is that path.
ENCLAVE_PREFIX = "/"


def is_enclave(common_name: str) -> bool:
    """Whether a CN names a ROS enclave (``/field/viewer``)."""
    return common_name.startswith(ENCLAVE_PREFIX)


def enclave_config(
    enclave: str,
    router_endpoint: str,
    publish: Sequence[str] = (),
    subscribe: Sequence[str] = (),
    serve: Sequence[str] = (),
    call: Sequence[str] = (),
    domain: int = 0,
    home: Path | None = None,
) -> dict[str, Any]:
    """The session config of one enclave, as ``generate_configs`` would write it.

    Args:
        enclave: Its path, also its certificate's CN (issue it with :func:`pki.issue`).
        router_endpoint: The fleet router it joins (``tls/ground1:7448``).
        publish, subscribe, serve, call: Its topics and services (fully qualified).
        domain: ROS domain id.
        home: MSCTL_HOME holding the fleet CA and the enclave's identity.
    """
    from msctl.net.config import tls_block

    identity = pki.read_identity(enclave, home)

    def keys(topics: Sequence[str]) -> list[str]:
        return [acl.key_expr(t, domain) for t in topics]

    graph = [f"@ros2_lv/{domain}/**"]
    rules = [
        {
            "id": "graph",
            "permission": "allow",
            "flows": ["egress", "ingress"],
            "messages": ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": graph,
        },
    ]
    for rule_id, messages, topics in (
        ("publications", ["put", "delete"], publish),
        ("subscriptions", ["declare_subscriber", "put", "delete"], subscribe),
        ("services", ["declare_queryable", "query", "reply"], serve),
        ("clients", ["query", "reply"], call),
    ):
        if topics:
            rules.append(
                {
                    "id": rule_id,
                    "permission": "allow",
                    "flows": ["egress", "ingress"],
                    "messages": messages,
                    "key_exprs": keys(topics),
                }
            )
    return {
        "mode": "client",
        "connect": {"endpoints": [router_endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls_block(identity, home)}},
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": [{"id": "router", "link_protocols": ["tls"]}],
            "policies": [{"rules": [r["id"] for r in rules], "subjects": ["router"]}],
        },
    }
