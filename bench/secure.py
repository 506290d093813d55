"""Security benchmark: an operator commanding a module through its router, plain vs secure.

In one run, in one process, on loopback: the module side is a client of its router on
loopback TCP (as a component is); the operator is a client over plain TCP with no access
control (plain), or over mutual TLS through the router ``msctl net config`` generates for
dragon's ``hl-limb-01``, ACL on (secure). Measured both ways:
  * round trip (p50/p99) of a 300-byte ``joint_set`` answered on ``joint_read``;
  * one-way throughput of ``joint_set`` puts, operator -> module, reliable.

Target (issue 15): secure p50 within 1.3x of plain.

Run: ``python bench/secure.py [--pings N] [--messages N]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench._common import free_port, print_table, summary

SET, READ = "0/limb1/joint_set/bench/h", "0/limb1/joint_read/bench/h"
PAYLOAD = bytes(300)


def _open(config: dict) -> object:
    import zenoh

    return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))


def _configs(secure: bool, home: Path) -> tuple[dict, dict, dict]:
    """Router, module-side and operator configs."""
    from msctl.net import config as netconfig
    from msctl.net import pki
    from tests.conftest import resolved_assembly

    ports = netconfig.Ports(local=free_port(), tls=free_port())
    module = netconfig.component_config("hl-limb-01", ports)
    if not secure:
        router = {
            "mode": "router",
            "listen": {"endpoints": [f"tcp/127.0.0.1:{ports.local}"]},
            "scouting": {"multicast": {"enabled": False}, "delay": 0},
        }
        return router, module, module
    assembly = resolved_assembly(home / "asm", "dragon")
    if not pki.initialised(home):
        pki.init_fleet(list(assembly.hosts), ["bench"], home=home)
    router = netconfig.router_config(assembly, "hl-limb-01", home=home, ports=ports)
    operator = netconfig.operator_config("bench", "hl-limb-01", home, ports)
    operator["connect"]["endpoints"] = [f"tls/127.0.0.1:{ports.tls}"]
    return router, module, operator


def run(secure: bool, pings: int, messages: int, home: Path) -> dict[str, float]:
    """One flavour's figures."""
    import zenoh

    router_config, module_config, operator_config = _configs(secure, home)
    router = _open(router_config)
    module = _open(module_config)
    operator = _open(operator_config)
    try:
        echo = module.declare_subscriber(SET, lambda s: module.put(READ, s.payload.to_bytes()))
        answered = threading.Event()
        pong = operator.declare_subscriber(READ, lambda _s: answered.set())
        for _ in range(200):  # routes first: the first samples may find none
            answered.clear()
            operator.put(SET, PAYLOAD)
            if answered.wait(0.05):
                break
        rtts = []
        for _ in range(pings):
            answered.clear()
            start = time.perf_counter()
            operator.put(SET, PAYLOAD)
            if not answered.wait(5.0):
                raise RuntimeError("a ping got no answer in 5 s")
            rtts.append((time.perf_counter() - start) * 1e6)
        echo.undeclare()
        pong.undeclare()
        count = [0]
        done = threading.Event()

        def on_flood(_sample: object) -> None:
            count[0] += 1
            if count[0] == messages:
                done.set()

        flood = module.declare_subscriber(SET, on_flood)
        # Let the subscription reach the operator's side before flooding.
        for _ in range(200):
            operator.put(SET, PAYLOAD)
            if count[0] or done.wait(0.01):
                break
        count[0] = 0
        start = time.perf_counter()
        block = zenoh.CongestionControl.BLOCK  # reliable all the way: no drop on a full queue
        for _ in range(messages):
            operator.put(SET, PAYLOAD, congestion_control=block)
        done.wait(60.0)
        elapsed = time.perf_counter() - start
        flood.undeclare()
        stats = summary(rtts)
        return {
            "p50_us": stats["p50"],
            "p99_us": stats["p99"],
            "msgs_per_s": count[0] / elapsed,
            "lost": max(0, messages - count[0]),
        }
    finally:
        operator.close()
        module.close()
        router.close()


def main() -> None:
    """Plain, then secure, then the ratio."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pings", type=int, default=2000)
    parser.add_argument("--messages", type=int, default=50_000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        plain = run(False, args.pings, args.messages, Path(scratch))
        secure = run(True, args.pings, args.messages, Path(scratch))
    rows = [
        [name, f"{r['p50_us']:.0f}", f"{r['p99_us']:.0f}", f"{r['msgs_per_s']:,.0f}", r["lost"]]
        for name, r in (("plain tcp", plain), ("mTLS + ACL", secure))
    ]
    print_table(
        "operator -> module through its router", ["", "p50 us", "p99 us", "msg/s", "lost"], rows
    )
    print(f"secure/plain p50: {secure['p50_us'] / plain['p50_us']:.2f}x (target <= 1.3x)")


if __name__ == "__main__":
    main()
