"""CLI benchmark: ``msctl topic list`` and ``msctl ps`` against a bare Zenoh session.

One simulated assembly (``msctl up TEMPLATE --sim --detach``) runs in its own ``MSCTL_HOME``
behind its own router on a random loopback port, with multicast scouting off. Against it,
each as a fresh subprocess of this interpreter, timed from start to exit:

  * bare: ``python -c "import zenoh; s = zenoh.open(conf); s.close()"``, ``conf`` the same
    connect endpoint, multicast scouting off, client mode (the mode msctl's CLI commands use:
    a short-lived command asks the router, it does not join as a peer);
  * ``msctl topic list`` and ``msctl ps``, as a user types them (the ``msctl`` script beside
    this interpreter, else ``python -m msctl``), output piped.

The three are run in turn, N rounds, so load that drifts over the run weighs on each alike;
msctl's sources are compiled first, as an installed msctl has them, whatever
``PYTHONDONTWRITEBYTECODE`` says (``bench._common.compiled_sources``), and a first round is
not counted (it warms the disk cache).
Every run must exit 0 with output (``ps`` must list the assembly's components, checked once
before timing). Printed: p50/p90 of each and its ratio to bare (target: p50 within 2x).
``msctl down`` runs at the end, always, also after Ctrl-C or SIGTERM; whatever it could not
stop is killed.

Run: ``python bench/cli.py [--runs 15] [--template dragon] [--json]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
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

HOST = "bench-laptop"  # none of the robots' computers: the whole assembly runs here, simulated
#: The bare session: the same settings msctl's CLI opens its session with.
BARE = """
import json, sys, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
s.close()
"""
#: The ``msctl`` a user types (the installed console script), else ``python -m msctl``.
_SCRIPT = shutil.which("msctl", path=str(Path(sys.executable).parent))
MSCTL = [_SCRIPT] if _SCRIPT else [sys.executable, "-m", "msctl"]
#: What each row runs, by name.
COMMANDS: dict[str, list[str]] = {
    "msctl topic list": [*MSCTL, "topic", "list"],
    "msctl ps": [*MSCTL, "ps"],
}


def _run(argv: list[str], env: dict[str, str], timeout: float) -> tuple[float, str]:
    """Run one command; its wall time (s) and stdout. Raises SystemExit if it fails."""
    started = time.perf_counter()
    done = subprocess.run(
        argv,
        env=env,
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    took = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.strip()[-800:]}")
    return took, done.stdout


def _kill_leftovers(home: Path) -> None:
    """SIGKILL the supervisor and every process group its state file names."""
    try:
        document = json.loads((home / "run" / "state.json").read_text())
    except (OSError, ValueError):
        return
    with contextlib.suppress(OSError, TypeError):
        os.kill(document.get("supervisor_pid"), signal.SIGKILL)
    for process in document.get("processes", []):
        with contextlib.suppress(OSError, TypeError):
            os.killpg(process.get("pgid"), signal.SIGKILL)


def _terminate(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")  # unwinds through the `finally` that stops it


def measure(runs: int, template: str, timeout: float) -> dict[str, Any]:
    """Bring ``template`` up, time every row ``runs`` times in turn, bring it down."""
    home = Path(tempfile.mkdtemp(prefix="msctl_bench_cli_"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    compiled_sources()
    env = msctl_env(home, endpoint, HOST)
    rows: dict[str, list[float]] = {"bare zenoh open+close": [], **{n: [] for n in COMMANDS}}
    previous = signal.signal(signal.SIGTERM, _terminate)
    components = 0
    try:
        started = time.monotonic()
        _run([*MSCTL, "up", template, "--sim", "--detach"], env, 180.0)
        up_s = time.monotonic() - started
        _, listing = _run([*MSCTL, "ps", "--json"], env, timeout)
        components = len(json.loads(listing)["components"])
        if not components:
            raise SystemExit(f"msctl ps lists no component after `msctl up {template}`")
        for round_ in range(runs + 1):
            # Round 0 is not counted: it warms the disk cache.
            took, _ = _run([sys.executable, "-c", BARE, endpoint], env, timeout)
            if round_:
                rows["bare zenoh open+close"].append(took)
            for name, argv in COMMANDS.items():
                took, text = _run(argv, env, timeout)
                if not text.strip():
                    raise SystemExit(f"{name} printed nothing")
                if round_:
                    rows[name].append(took)
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
    bare = percentile(rows["bare zenoh open+close"], 50)
    bare_p90 = percentile(rows["bare zenoh open+close"], 90)
    return {
        "template": template,
        "home": str(home),
        "components": components,
        "runs": runs,
        "up_s": up_s,
        "load": os.getloadavg()[0],
        "rows": [
            {
                "command": name,
                "p50_s": percentile(times, 50),
                "p90_s": percentile(times, 90),
                "p50_ratio": percentile(times, 50) / bare,
                "p90_ratio": percentile(times, 90) / bare_p90,
                "times_s": times,
            }
            for name, times in rows.items()
        ],
    }


def main() -> None:
    """Parse the arguments, run the benchmark, print a table or one JSON document."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--runs", type=int, default=15, help="Runs of each command.")
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
        f"CLI against {result['template']} ({result['components']} components), "
        f"{result['runs']} runs each, load {result['load']:.1f}",
        ("command", "p50", "p90", "p50 / bare", "p90 / bare"),
        [
            (
                r["command"],
                f"{r['p50_s'] * 1000:.0f} ms",
                f"{r['p90_s'] * 1000:.0f} ms",
                f"{r['p50_ratio']:.2f}x",
                f"{r['p90_ratio']:.2f}x",
            )
            for r in result["rows"]
        ],
    )
    print("\ntarget: msctl topic list and msctl ps p50 within 2x of bare")


if __name__ == "__main__":
    main()
