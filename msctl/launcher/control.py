"""The operator CLI's names for the supervision protocol (:mod:`components.supervision`).

The protocol itself (the service, the requests and answers, the client) is the runtime's;
the CLI's commands import what they use of it from here or from there. Only the light names
are here: ``msctl ps`` imports this module and must not pay for msgspec (see
:mod:`msctl.quick`); the typed requests are in :mod:`components.supervision.protocol`.
"""

from __future__ import annotations

from components.supervision.contract import (
    AGENT_SRV,
    MAX_ARGS_BYTES,
    MAX_ARGS_DEPTH,
    RequestError,
    args_size,
    encode_args,
    host_namespace,
)
from components.supervision.wire import call_supervisor

__all__ = [
    "AGENT_SRV",
    "MAX_ARGS_BYTES",
    "MAX_ARGS_DEPTH",
    "RequestError",
    "args_size",
    "call_supervisor",
    "encode_args",
    "host_namespace",
]
