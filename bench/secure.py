"""Security benchmark: an operator commanding a module through its router, plain vs secure.

In one run, in one process, on loopback: the module side is a client of its router on
loopback TCP (as a component is); the operator is a client over plain TCP with no access
control (plain), or over mutual TLS through the router ``msctl net config`` generates for
dragon's ``hl-limb-01``, ACL on (secure). Measured both ways:
  * round trip (p50/p99) of a 300-byte ``joint_set`` answered on ``joint_read``;
  * one-way throughput of ``joint_set`` puts, operator -> module, reliable.

Both paths are open at once and the round trips alternate between them in ``--rounds``
rounds, so load that drifts during the run (2 shared cores) weighs on both alike; the p50
over all rounds and each round's own ratio are printed. Target (issue 15): secure p50
within 1.3x of plain.

Run: ``python bench/secure.py [--pings N] [--rounds N] [--messages N]``.
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


class Link:
    """An operator -> module path through one router, plain or secure; close it when done.

    Both links are open at once, so the run can alternate between them: a machine whose load
    drifts (other work on 2 shared cores) then weighs on both alike, instead of on whichever
    ran second.
    """

    def __init__(self, secure: bool, home: Path) -> None:
        router_config, module_config, operator_config = _configs(secure, home)
        self.router = _open(router_config)
        self.module = _open(module_config)
        self.operator = _open(operator_config)
        self._answered = threading.Event()
        self._echo = self.module.declare_subscriber(
            SET, lambda s: self.module.put(READ, s.payload.to_bytes())
        )
        self._pong = self.operator.declare_subscriber(READ, lambda _s: self._answered.set())
        for _ in range(200):  # routes first: the first samples may find none
            self._answered.clear()
            self.operator.put(SET, PAYLOAD)
            if self._answered.wait(0.05):
                break

    def pings(self, count: int) -> list[float]:
        """Round trips, microseconds."""
        rtts = []
        for _ in range(count):
            self._answered.clear()
            start = time.perf_counter()
            self.operator.put(SET, PAYLOAD)
            if not self._answered.wait(5.0):
                raise RuntimeError("a ping got no answer in 5 s")
            rtts.append((time.perf_counter() - start) * 1e6)
        return rtts

    def flood(self, messages: int) -> tuple[float, int]:
        """One-way puts, reliable: (messages per second received, lost)."""
        import zenoh

        self._echo.undeclare()
        self._pong.undeclare()
        count = [0]
        done = threading.Event()

        def on_flood(_sample: object) -> None:
            count[0] += 1
            if count[0] == messages:
                done.set()

        flood = self.module.declare_subscriber(SET, on_flood)
        try:
            # Let the subscription reach the operator's side before flooding.
            for _ in range(200):
                self.operator.put(SET, PAYLOAD)
                if count[0] or done.wait(0.01):
                    break
            count[0] = 0
            start = time.perf_counter()
            block = zenoh.CongestionControl.BLOCK  # reliable all the way: no drop on a full queue
            for _ in range(messages):
                self.operator.put(SET, PAYLOAD, congestion_control=block)
            done.wait(60.0)
            elapsed = time.perf_counter() - start
        finally:
            flood.undeclare()
        return count[0] / elapsed, max(0, messages - count[0])

    def close(self) -> None:
        """Close the three sessions."""
        self.operator.close()
        self.module.close()
        self.router.close()


def main() -> None:
    """Plain and secure, alternating rounds of pings; then each flood; then the ratio."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pings", type=int, default=4000, help="round trips per flavour")
    parser.add_argument("--rounds", type=int, default=20, help="alternations of the two")
    parser.add_argument("--messages", type=int, default=50_000)
    args = parser.parse_args()
    rtts: dict[str, list[float]] = {"plain": [], "secure": []}
    ratios = []
    with tempfile.TemporaryDirectory() as scratch:
        links = {"plain": Link(False, Path(scratch)), "secure": Link(True, Path(scratch))}
        try:
            per_round = max(1, args.pings // args.rounds)
            for n in range(args.rounds):
                order = ("plain", "secure") if n % 2 == 0 else ("secure", "plain")
                this_round = {name: links[name].pings(per_round) for name in order}
                for name, values in this_round.items():
                    rtts[name].extend(values)
                ratios.append(
                    summary(this_round["secure"])["p50"] / summary(this_round["plain"])["p50"]
                )
            floods = {name: links[name].flood(args.messages) for name in ("plain", "secure")}
        finally:
            for link in links.values():
                link.close()
    stats = {name: summary(values) for name, values in rtts.items()}
    rows = [
        [
            label,
            f"{stats[name]['p50']:.0f}",
            f"{stats[name]['p99']:.0f}",
            f"{floods[name][0]:,.0f}",
            floods[name][1],
        ]
        for name, label in (("plain", "plain tcp"), ("secure", "mTLS + ACL"))
    ]
    print_table(
        "operator -> module through its router", ["", "p50 us", "p99 us", "msg/s", "lost"], rows
    )
    ratios.sort()
    print(
        f"secure/plain p50: {stats['secure']['p50'] / stats['plain']['p50']:.2f}x over "
        f"{args.rounds} alternating rounds (per round: median {ratios[len(ratios) // 2]:.2f}x, "
        f"range {ratios[0]:.2f}-{ratios[-1]:.2f}x) (target <= 1.3x)"
    )


if __name__ == "__main__":
    main()
