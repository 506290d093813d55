"""The agent's CDR: the hand-written ``AgentRequest`` codec against the canonical one.

:mod:`components.supervision.wire` writes a supervisor request and reads its response as CDR
by hand (two strings out; a bool and two strings back) instead of through the type registry
and its generated codec (:mod:`components.comm.codec`). This measures whether that copy is
worth keeping, both ways in the same run:

* **per call**: encode a request and decode a response, in a loop, in this process, each
  path warmed first: a ``ps`` (an empty request, the answer of a 12-component run) and an
  ``up`` (a resolved assembly of about 18 KB, a short answer). Printed: the p50 of a call
  (median over rounds of ``--calls`` calls, the paths taking turns) and canonical / hand.
* **first call**: what a command pays for its first request (``msctl ps`` makes one): a
  fresh interpreter, the supervisor client's module already imported (both paths need it),
  then the imports and set-up each path needs and one encode and decode. Printed: the p50 of
  ``--starts`` fresh processes per path, and canonical / hand.

Both paths are checked to write the same bytes and read the same fields before anything is
timed. Run: ``python bench/agent_wire.py [--calls N] [--rounds N] [--starts N] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench._common import compiled_sources, print_table  # noqa: E402

AGENT_SRV = "msctl_msgs/srv/AgentRequest"


def _ps_document(components: int = 12) -> str:
    """A ``ps`` answer of a run of ``components`` components, as a supervisor sends it."""
    rows = [
        {
            "name": f"limb{i // 4 + 1}/component_{i}",
            "kind": "joint_manager",
            "host": "hl-limb-01",
            "process": f"limb{i // 4 + 1}",
            "state": "running",
            "pid": 40000 + i,
            "uptime": 1234.5,
            "restarts": 0,
            "last_error": "",
        }
        for i in range(components)
    ]
    return json.dumps({"host": "hl-limb-01", "state": "running", "components": rows})


def _cases() -> dict[str, tuple[str, str, tuple[bool, str, str]]]:
    """Each case: the request (verb, args) and the response (success, message, payload)."""
    assembly = json.dumps({"template": "dragon", "modules": ["x" * 60] * 300})  # ~18 KB
    return {
        "ps": ("ps", "{}", (True, "", _ps_document())),
        "up": ("up", json.dumps({"assembly": assembly}), (True, "started", '{"template":"d"}')),
    }


def _hand() -> tuple[Callable[[str, str], bytes], Callable[[bytes], Any]]:
    from components.supervision.wire import decode_response, encode_request

    return encode_request, decode_response


def _canonical() -> tuple[Callable[[str, str], bytes], Callable[[bytes], Any]]:
    from components.comm.types import registry

    parts = registry().service(AGENT_SRV)
    request_class = registry().msg_class(parts.request)
    serialize = registry().serializer(parts.request)
    deserialize = registry().deserializer(parts.response)

    def encode(verb: str, args: str) -> bytes:
        return serialize(request_class(verb=verb, args=args))

    return encode, deserialize


def _response_bytes(success: bool, message: str, payload: str) -> bytes:
    from components.comm.types import registry

    parts = registry().service(AGENT_SRV)
    response = registry().msg_class(parts.response)(
        success=success, message=message, payload=payload
    )
    return registry().serializer(parts.response)(response)


def _check(paths: dict[str, Any], cases: dict[str, Any]) -> None:
    """Both paths write the same bytes and read the same fields, or nothing is timed."""
    for verb, args, answer in cases.values():
        data = _response_bytes(*answer)
        (hand_encode, hand_decode), (canon_encode, canon_decode) = paths["hand"], paths["canon"]
        assert hand_encode(verb, args) == canon_encode(verb, args), verb
        read = canon_decode(data)
        assert tuple(hand_decode(data)) == (read.success, read.message, read.payload), verb


def per_call(calls: int, rounds: int) -> dict[str, dict[str, float]]:
    """Seconds per encode+decode, by case and path: the median of each round's mean."""
    cases = _cases()
    paths = {"hand": _hand(), "canon": _canonical()}
    _check(paths, cases)
    results: dict[str, dict[str, float]] = {}
    for case, (verb, args, answer) in cases.items():
        data = _response_bytes(*answer)
        samples: dict[str, list[float]] = {name: [] for name in paths}
        for _ in range(rounds + 1):  # the first round warms, and is not counted
            for name, (encode, decode) in paths.items():
                started = time.perf_counter()
                for _ in range(calls):
                    encode(verb, args)
                    decode(data)
                samples[name].append((time.perf_counter() - started) / calls)
        results[case] = {name: statistics.median(s[1:]) for name, s in samples.items()}
    return results


#: A fresh interpreter's first request: imports and set-up of one path, one encode and one
#: decode, timed from after the client's module (needed by both) is imported.
_FIRST_CALL = """
import json, sys, time
sys.path.insert(0, {root!r})
import components.supervision.wire
from bench.agent_wire import _canonical, _hand
data = bytes.fromhex({data!r})
started, cpu = time.perf_counter(), time.process_time()
encode, decode = {path}()
encode("ps", "{{}}")
decode(data)
print(json.dumps([time.perf_counter() - started, time.process_time() - cpu]))
"""


def first_call(starts: int) -> dict[str, dict[str, float]]:
    """Seconds of a fresh process's first encode+decode, by path: wall clock and CPU (the
    CPU time tells less of a shared machine's load), each the p50 of ``starts``."""
    data = _response_bytes(True, "", _ps_document()).hex()
    samples: dict[str, list[list[float]]] = {"hand": [], "canon": []}
    for _ in range(starts):
        for name, path in (("hand", "_hand"), ("canon", "_canonical")):
            script = _FIRST_CALL.format(root=str(ROOT), data=data, path=path)
            done = subprocess.run(
                [sys.executable, "-c", script], capture_output=True, text=True, check=True
            )
            samples[name].append(json.loads(done.stdout))
    return {
        name: {
            "wall": statistics.median(s[0] for s in runs),
            "cpu": statistics.median(s[1] for s in runs),
        }
        for name, runs in samples.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000, help="calls per round")
    parser.add_argument("--rounds", type=int, default=7, help="rounds per case")
    parser.add_argument("--starts", type=int, default=7, help="fresh processes per path")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    options = parser.parse_args()
    compiled_sources()
    calls = per_call(options.calls, options.rounds)
    first = first_call(options.starts)
    document = {
        "per_call_s": calls,
        "per_call_ratio": {c: t["canon"] / t["hand"] for c, t in calls.items()},
        "first_call_s": first,
        "first_call_ratio": {k: first["canon"][k] / first["hand"][k] for k in ("wall", "cpu")},
    }
    if options.json:
        print(json.dumps(document, indent=2))
        return
    print_table(
        "encode+decode per call (p50 over rounds)",
        ("case", "hand-written", "canonical codec", "canonical / hand"),
        [
            (
                c,
                f"{t['hand'] * 1e6:.1f} us",
                f"{t['canon'] * 1e6:.1f} us",
                f"{t['canon'] / t['hand']:.2f}x",
            )
            for c, t in calls.items()
        ],
    )
    print_table(
        "first call of a fresh process (imports + set-up + one encode and decode; p50)",
        ("clock", "hand-written", "canonical codec", "canonical / hand"),
        [
            (
                clock,
                f"{first['hand'][clock] * 1e3:.2f} ms",
                f"{first['canon'][clock] * 1e3:.1f} ms",
                f"{document['first_call_ratio'][clock]:.0f}x",
            )
            for clock in ("wall", "cpu")
        ],
    )


if __name__ == "__main__":
    main()
