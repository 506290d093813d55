"""Helpers shared by the benchmarks: a loopback router, free ports, percentiles, tables."""

from __future__ import annotations

import os
import socket
import statistics
from collections.abc import Sequence
from pathlib import Path

#: The checkout, put on the msctl processes' PYTHONPATH.
ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    """A TCP port free a moment ago on 127.0.0.1."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def compiled_sources() -> None:
    """Compile msctl's sources once, as an installed msctl has them, before anything is timed.

    ``pip install`` writes every module's compiled form; a checkout run with
    ``PYTHONDONTWRITEBYTECODE`` (as these machines set it) compiled every module of every
    ``msctl`` process from source instead, on each run. The compiled files go where Python
    looks for them (``__pycache__``, ignored by git).
    """
    import compileall

    for package in ("msctl", "components"):
        compileall.compile_dir(ROOT / package, quiet=2)


def msctl_env(home: Path, endpoint: str, host: str = "bench-laptop") -> dict[str, str]:
    """The environment of an ``msctl`` run of a benchmark: its own MSCTL_HOME, a host that is
    none of the assembly's computers (everything simulated), and only its own loopback
    router (random port, no multicast); compiled modules read and written as an installed
    msctl's are (see :func:`compiled_sources`)."""
    environ = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {
        **environ,
        "MSCTL_HOME": str(home),
        "MSCTL_HOST": host,
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) of ``values`` by nearest rank."""
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    index = min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))
    return ordered[index]


def summary(values: Sequence[float]) -> dict[str, float]:
    """p50, p99, mean of a sample."""
    return {
        "p50": percentile(values, 50),
        "p99": percentile(values, 99),
        "mean": statistics.fmean(values) if values else float("nan"),
    }


def print_table(title: str, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Print a plain fixed-width table (benchmarks print, they do not log)."""
    print(f"\n{title}")
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(header)]
    print("  ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)))
    for row in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)))
