"""The topics that reach this computer downsampled on a radio link.

A recorder here sees such a topic's sequence numbers jump by design: those jumps are no
losses. Read from the resolved assembly (its lock's link classes) and this computer's run.
"""

from __future__ import annotations

import json
import os
import socket
from typing import Any

from components.links import Network, thinned_topics
from components.paths import state_dir


def radio_thinned(here: str | None = None) -> dict[str, float]:
    """Topic -> rate of each topic of this computer's assembly that reaches it sampled on a
    radio link (:func:`components.links.thinned_topics`); none when nothing is resolved here,
    the fleet is not secure (only the generated TLS/QUIC links filter: the template says so,
    or this computer's run, started with ``MSCTL_SECURE=1``), this computer is not one of the
    assembly's, or it runs the whole assembly itself (off-robot: no radio)."""
    from components.assembly import AssemblyError, load_assembly

    # This computer's identity, as the launcher names it: MSCTL_HOST or the hostname.
    here = here or os.environ.get("MSCTL_HOST") or socket.gethostname()
    try:
        assembly = load_assembly()
    except (AssemblyError, OSError, ValueError):
        return {}
    run = _run_state()
    # The template's [network] secure, or this computer's run (its agent's MSCTL_SECURE=1).
    secure = assembly.secure or bool(run.get("secure")) or os.environ.get("MSCTL_SECURE") == "1"
    if not secure or here not in assembly.hosts:
        return {}
    if run.get("off_robot") and run.get("state") == "running" and not run.get("agent"):
        return {}
    network = Network.from_dict(assembly.lock.network)
    return thinned_topics(network, {m.slot: m.host for m in assembly.modules}, here)


def _run_state() -> dict[str, Any]:
    # The supervisor's state file (msctl.launcher.state writes it); none or unreadable: {}.
    try:
        return json.loads((state_dir() / "run" / "state.json").read_text(encoding="utf-8")) or {}
    except (OSError, ValueError):
        return {}
