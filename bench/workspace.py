"""Benchmark of ``msctl update`` and ``msctl build`` against the tools they replace.

All local, no network: ten bare git repositories (file:// URLs, a few dozen commits each)
and ten interdependent Python packages (the tests' own build backend, so pip needs no index).
In the same run, each figure the median of ``--repeat`` runs, the two tools alternating
which goes first:

- update, fresh clone of 10 repositories: ``msctl update`` vs ``vcs import`` (vcs2l) of the
  same .repos file, both as commands, each into an empty directory;
- update with nothing to do: ``msctl update`` again vs ``vcs import`` again on the same,
  already up-to-date workspace (the command, end to end);
- build of 10 interdependent packages, each run into a fresh virtual environment:
  ``msctl build`` (doit graph, ``--jobs``) vs a plain sequential ``pip install`` of each
  package in dependency order (``--no-index --no-deps``, as msctl's own install step);
- no-op rebuild: ``msctl build`` with nothing changed, the command and in-process.

Both tools run with a bytecode cache (``PYTHONPYCACHEPREFIX`` in the run's temporary
directory, after one untimed run each), as installed tools have: vcs2l's modules were
compiled when pip installed it, while msctl is an editable checkout, and a machine with
``PYTHONDONTWRITEBYTECODE`` set would compile every msctl module on every start. Besides
wall time, the CPU time of each command (its processes and their children) is shown: on a
loaded machine it varies far less than wall time, and the load averages at the start and
end of the run are printed with the figures.

Run: ``python bench/workspace.py [--repeat N] [--jobs N]``. Targets: a fresh clone at most
1.0x vcs2l's time; an update with nothing to do under 1 s; a no-op rebuild under 0.5 s.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _common import print_table
from workspace_rigs import Remote, make_venv, pip_env, python_package, repos_text

REPOS = 10
COMMITS = 30


def _timed(argv: list[str], env: dict[str, str], cwd: Path) -> tuple[float, float]:
    """Run a command; its wall time and CPU time (its processes and their children)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    result = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:4])} failed:\n{result.stdout}\n{result.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return elapsed, cpu


def _median(runs: list[tuple[float, float]]) -> tuple[float, float]:
    """The median wall time and the median CPU time of some runs."""
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def _remotes(root: Path) -> Path:
    entries: dict[str, tuple[str, str | None]] = {}
    for i in range(REPOS):
        remote = Remote(root, f"repo{i}")
        for c in range(COMMITS):
            remote.commit({f"src/file{c % 7}.py": f"VALUE = {c}\n" * 50}, f"commit {c}")
        remote.push({"CHANGELOG": "x"}, "last")
        entries[f"src/repo{i}"] = (remote.url, "main")
    repos = root / "ws.repos"
    repos.write_text(repos_text(entries))
    return repos


def bench_update(root: Path, repeat: int, env: dict[str, str]) -> list[list[object]]:
    repos = _remotes(root)
    msctl = [sys.executable, "-m", "msctl", "update", str(repos), "--jobs", "8"]
    vcs = [str(Path(sys.executable).parent / "vcs"), "import", "--input", str(repos)]

    def command(name: str, target: Path) -> list[str]:
        return [*msctl, "-w", str(target)] if name == "msctl" else [*vcs, str(target)]

    for name in ("msctl", "vcs"):  # untimed: fills the bytecode cache, warms the page cache
        (root / f"warm-{name}").mkdir()
        _timed(command(name, root / f"warm-{name}"), env, root)
    fresh: dict[str, list[tuple[float, float]]] = {"msctl": [], "vcs": []}
    noop: dict[str, list[tuple[float, float]]] = {"msctl": [], "vcs": []}
    for n in range(repeat):
        # Alternate who goes first: the page cache favours the second.
        for name in ("msctl", "vcs")[:: 1 - 2 * (n % 2)]:
            target = root / f"{name}-{n}"
            target.mkdir()
            fresh[name].append(_timed(command(name, target), env, root))
        for name in ("msctl", "vcs")[:: 1 - 2 * (n % 2)]:
            noop[name].append(_timed(command(name, root / f"warm-{name}"), env, root))
    rows = []
    for label, runs, target in (
        ("update: fresh clone, 10 repos", fresh, "target <= 1.0x"),
        ("update: nothing to do, 10 repos", noop, "target < 1 s"),
    ):
        (ours, ours_cpu), (theirs, theirs_cpu) = _median(runs["msctl"]), _median(runs["vcs"])
        rows.append(
            [
                label,
                f"{ours:.2f} s (cpu {ours_cpu:.2f} s)",
                f"vcs import {theirs:.2f} s (cpu {theirs_cpu:.2f} s)",
                f"{ours / theirs:.2f}x, cpu {ours_cpu / theirs_cpu:.2f}x ({target})",
            ]
        )
    return rows


def _packages(ws: Path) -> list[str]:
    """Ten packages in four layers: each depends on one or two of the layer before."""
    names = [f"bench-pkg{i}" for i in range(REPOS)]
    layers = [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9]]
    for depth, layer in enumerate(layers):
        for index in layer:
            below = layers[depth - 1] if depth else []
            deps = [names[d] for d in below if (d + index) % 2 == 0 or d == below[0]]
            python_package(ws, names[index], depends=deps)
    return [names[i] for layer in layers for i in layer]


def bench_build(root: Path, repeat: int, jobs: int) -> list[list[object]]:
    from msctl.workspace.build import Builder, BuildOptions
    from msctl.workspace.packages import find_packages

    ws = root / "ws"
    order = _packages(ws)
    plain_env = pip_env()
    first: dict[str, list[tuple[float, float]]] = {"msctl": [], "pip": []}
    ours_env = ""
    for n in range(repeat):
        for name in ("msctl", "pip")[:: 1 - 2 * (n % 2)]:
            python = make_venv(root / f"venv-{name}-{n}")
            if name == "msctl":
                ours_env = python
                shutil.rmtree(ws / ".msctl", ignore_errors=True)  # a first build each time
                run_env = pip_env(
                    VIRTUAL_ENV=str(Path(python).parents[1]), MSCTL_HOME=str(root / "home")
                )
                argv = [sys.executable, "-m", "msctl", "build", "-w", str(ws), "--jobs", str(jobs)]
                first[name].append(_timed(argv, run_env, root))
            else:
                runs = [
                    _timed(
                        [
                            python,
                            "-m",
                            "pip",
                            "install",
                            "--no-index",
                            "--no-deps",
                            "-q",
                            str(ws / p),
                        ],
                        plain_env,
                        root,
                    )
                    for p in order
                ]
                first[name].append((sum(r[0] for r in runs), sum(r[1] for r in runs)))
    # The no-op rebuilds: of the last msctl build's environment, nothing changed since.
    run_env = pip_env(VIRTUAL_ENV=str(Path(ours_env).parents[1]), MSCTL_HOME=str(root / "home"))
    argv = [sys.executable, "-m", "msctl", "build", "-w", str(ws), "--jobs", str(jobs)]
    noop_cli = [_timed(argv, run_env, root) for _ in range(repeat)]
    os.environ.update({k: v for k, v in run_env.items() if k.startswith("PIP_")})
    graph = find_packages(ws)
    options = BuildOptions(python=ours_env, jobs=jobs)
    noop_in = []
    for _ in range(repeat):
        start = time.perf_counter()
        result = Builder(graph, options).run(graph.order())
        noop_in.append(time.perf_counter() - start)
        assert result.nothing_done
    (ours, ours_cpu), (plain, plain_cpu) = _median(first["msctl"]), _median(first["pip"])
    noop, noop_cpu = _median(noop_cli)
    return [
        [
            f"build: 10 packages, first (--jobs {jobs})",
            f"{ours:.1f} s (cpu {ours_cpu:.1f} s)",
            f"sequential pip {plain:.1f} s (cpu {plain_cpu:.1f} s)",
            f"{ours / plain:.2f}x, cpu {ours_cpu / plain_cpu:.2f}x",
        ],
        [
            "build: no-op, command",
            f"{noop:.2f} s (cpu {noop_cpu:.2f} s)",
            "-",
            "target < 0.5 s (includes startup)",
        ],
        ["build: no-op, in-process", f"{statistics.median(noop_in):.3f} s", "-", "target < 0.5 s"],
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per figure (median)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 2, help="build jobs")
    args = parser.parse_args()
    if shutil.which("vcs", path=str(Path(sys.executable).parent)) is None:
        raise SystemExit("vcs2l is not installed: pip install -e '.[test]'")
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        # Every command of the run (and pip_env's copies) inherits the bytecode cache.
        os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
        os.environ["PYTHONPYCACHEPREFIX"] = str(root / "pyc")
        env = {**os.environ, "MSCTL_HOME": str(root / "home"), "LC_ALL": "C"}
        rows = bench_update(root / "update", args.repeat, env)
        rows += bench_build(root / "build", args.repeat, args.jobs)
    load_after = os.getloadavg()
    print_table(
        f"msctl update / build ({os.cpu_count()} CPUs, median of {args.repeat}; load average "
        f"{load_before[0]:.1f} at the start, {load_after[0]:.1f} at the end)",
        ["figure", "msctl", "baseline", "ratio"],
        rows,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
