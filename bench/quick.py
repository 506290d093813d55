"""The quick path's worth: ``msctl ps`` and ``msctl topic list`` with and without typer.

:mod:`msctl.quick` answers the plain forms of these two commands before typer is imported;
it is a second argv parser, kept in line with the typer commands by a test. This measures
whether that copy is worth keeping: each command as a user types it (the quick path) against
the same command through the canonical typer path in the same run. A trailing ``--`` (the
end of options, which click accepts and the quick path does not know) sends the same command,
with the same output, through typer.

One simulated assembly (``msctl up TEMPLATE --sim --detach``) runs in its own ``MSCTL_HOME``
behind its own router on a random loopback port (multicast scouting off), as in
``bench/cli.py``, whose helpers this uses. The four are run in turn, N rounds (the first not
counted); every run must exit 0 and print something, ``ps --json`` the same document keys
on both paths, and :mod:`msctl.quick` must take the one form and leave the other to typer
(checked before timing). Printed: p50/p90 of each, and the typer path's p50 over the quick
path's.

Run: ``python bench/quick.py [--runs 15] [--template dragon] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench._common import (  # noqa: E402
    compiled_sources,
    free_port,
    msctl_env,
    percentile,
    print_table,
)
from bench.cli import HOST, MSCTL, _kill_leftovers, _run, _terminate  # noqa: E402

#: Each command: its quick form and the same command through typer.
PAIRS: dict[str, tuple[list[str], list[str]]] = {
    "msctl ps --json": ([*MSCTL, "ps", "--json"], [*MSCTL, "ps", "--json", "--"]),
    "msctl topic list": ([*MSCTL, "topic", "list"], [*MSCTL, "topic", "list", "--"]),
}


def _check_paths() -> None:
    """Each pair's first form is the quick path's, its second typer's."""
    from msctl import quick

    for name, (fast, slow) in PAIRS.items():
        taken = [
            any(c.parse(argv[len(MSCTL) :]) is not None for c in quick.COMMANDS)
            for argv in (fast, slow)
        ]
        if taken != [True, False]:
            raise SystemExit(
                f"{name}: the quick path takes {taken} of its two forms, not [True, False]"
            )


def _rounds(runs: int, env: dict[str, str], timeout: float) -> dict[str, dict[str, list[float]]]:
    """Every pair's both paths, in turn, ``runs`` counted rounds."""
    times: dict[str, dict[str, list[float]]] = {n: {"quick": [], "typer": []} for n in PAIRS}
    for round_ in range(runs + 1):  # round 0 warms the disk cache
        for name, (quick, typer) in PAIRS.items():
            took_quick, fast = _run(quick, env, timeout)
            took_typer, slow = _run(typer, env, timeout)
            if not fast.strip() or (
                name.endswith("--json") and json.loads(fast).keys() != json.loads(slow).keys()
            ):
                raise SystemExit(f"{name}: the two paths printed different things")
            if round_:
                times[name]["quick"].append(took_quick)
                times[name]["typer"].append(took_typer)
    return times


def measure(runs: int, template: str, timeout: float) -> dict[str, Any]:
    """Bring ``template`` up, time both paths of every command, bring it down."""
    _check_paths()
    home = Path(tempfile.mkdtemp(prefix="msctl_bench_quick_"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    compiled_sources()
    env = msctl_env(home, endpoint, HOST)
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        _run([*MSCTL, "up", template, "--sim", "--detach"], env, 180.0)
        times = _rounds(runs, env, timeout)
    finally:
        try:
            done = subprocess.run(
                [*MSCTL, "down"],
                env=env,
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=60.0,
                check=False,
            )
            if done.returncode != 0:
                print(f"msctl down: {done.stderr.strip()}", file=sys.stderr)
                _kill_leftovers(home)
        except subprocess.TimeoutExpired:
            _kill_leftovers(home)
        signal.signal(signal.SIGTERM, previous)
    rows = []
    for name, paths in times.items():
        quick50, typer50 = percentile(paths["quick"], 50), percentile(paths["typer"], 50)
        rows.append(
            {
                "command": name,
                "quick_p50_s": quick50,
                "quick_p90_s": percentile(paths["quick"], 90),
                "typer_p50_s": typer50,
                "typer_p90_s": percentile(paths["typer"], 90),
                "typer_over_quick_p50": typer50 / quick50,
                "saved_p50_s": typer50 - quick50,
            }
        )
    return {
        "template": template,
        "runs": runs,
        "load": os.getloadavg()[0],
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "rows": rows,
    }


def main() -> None:
    """Parse the arguments, run the benchmark, print a table or one JSON document."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--runs", type=int, default=15, help="Counted runs of each path.")
    parser.add_argument("--template", default="dragon", help="The assembly to bring up.")
    parser.add_argument("--timeout", type=float, default=60.0, help="Bound on one command (s).")
    parser.add_argument("--json", action="store_true", help="Print one JSON document.")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    try:
        result = measure(args.runs, args.template, args.timeout)
    except KeyboardInterrupt:
        print("interrupted (the assembly was brought down)", file=sys.stderr)
        sys.exit(130)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print_table(
        f"quick path vs typer against {result['template']}, {result['runs']} runs each, "
        f"load {result['load']:.1f}",
        ("command", "quick p50", "quick p90", "typer p50", "typer p90", "typer / quick"),
        [
            (
                r["command"],
                f"{r['quick_p50_s'] * 1000:.0f} ms",
                f"{r['quick_p90_s'] * 1000:.0f} ms",
                f"{r['typer_p50_s'] * 1000:.0f} ms",
                f"{r['typer_p90_s'] * 1000:.0f} ms",
                f"{r['typer_over_quick_p50']:.2f}x",
            )
            for r in result["rows"]
        ],
    )


if __name__ == "__main__":
    main()
