"""Benchmark of ``msctl update`` and ``msctl build`` against the tools they replace.

All local, no network: ten bare git repositories (file:// URLs, a few dozen commits each)
and ten interdependent Python packages (the tests' own build backend, so pip needs no index).
In the same run:

- update, fresh clone of 10 repositories: ``msctl update`` vs ``vcs import`` (vcs2l) of the
  same .repos file, both as commands, each into an empty directory (median of --repeat);
- update with nothing to do: ``msctl update`` again (the command, end to end);
- build of 10 interdependent packages into a fresh virtual environment: ``msctl build``
  (doit graph, ``--jobs``) vs a plain sequential ``pip install`` of each package in
  dependency order (``--no-index --no-deps``, as msctl's own install step);
- no-op rebuild: ``msctl build`` with nothing changed, the command and in-process.

Run: ``python bench/workspace.py [--repeat N] [--jobs N]``. Targets: a fresh clone at most
1.0x vcs2l's time; an update with nothing to do under 1 s; a no-op rebuild under 0.5 s.
"""

from __future__ import annotations

import argparse
import os
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


def _timed(argv: list[str], env: dict[str, str], cwd: Path) -> float:
    start = time.perf_counter()
    result = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:4])} failed:\n{result.stdout}\n{result.stderr}")
    return elapsed


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
    ours, theirs = [], []
    for n in range(repeat):
        # Alternate who goes first: the page cache favours the second.
        for name, argv, times in (("msctl", msctl, ours), ("vcs", vcs, theirs))[:: 1 - 2 * (n % 2)]:
            target = root / f"{name}-{n}"
            target.mkdir()
            command = [*argv, "-w", str(target)] if name == "msctl" else [*argv, str(target)]
            times.append(_timed(command, env, root))
    last = root / f"msctl-{repeat - 1}"
    noop = [_timed([*msctl, "-w", str(last)], env, root) for _ in range(repeat)]
    clone_ratio = statistics.median(ours) / statistics.median(theirs)
    return [
        [
            "update: fresh clone, 10 repos",
            f"{statistics.median(ours):.2f} s",
            f"vcs import {statistics.median(theirs):.2f} s",
            f"{clone_ratio:.2f}x (target <= 1.0x)",
        ],
        ["update: nothing to do", f"{statistics.median(noop):.2f} s", "-", "target < 1 s"],
    ]


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
    ours_env, plain_env = make_venv(root / "venv-msctl"), make_venv(root / "venv-pip")
    env = pip_env(VIRTUAL_ENV=str(Path(ours_env).parents[1]), MSCTL_HOME=str(root / "home"))
    msctl = [sys.executable, "-m", "msctl", "build", "-w", str(ws), "--jobs", str(jobs)]
    first = _timed(msctl, env, root)
    start = time.perf_counter()
    for name in order:
        subprocess.run(
            [plain_env, "-m", "pip", "install", "--no-index", "--no-deps", "-q", str(ws / name)],
            env=pip_env(),
            check=True,
            capture_output=True,
        )
    plain = time.perf_counter() - start
    noop_cli = [_timed(msctl, env, root) for _ in range(repeat)]
    os.environ.update({k: v for k, v in env.items() if k.startswith("PIP_")})
    graph = find_packages(ws)
    options = BuildOptions(python=ours_env, jobs=jobs)
    noop_in = []
    for _ in range(repeat):
        start = time.perf_counter()
        result = Builder(graph, options).run(graph.order())
        noop_in.append(time.perf_counter() - start)
        assert result.nothing_done
    return [
        [
            f"build: 10 packages, first (--jobs {jobs})",
            f"{first:.1f} s",
            f"sequential pip {plain:.1f} s",
            f"{first / plain:.2f}x",
        ],
        ["build: no-op, command", f"{statistics.median(noop_cli):.2f} s", "-", "includes startup"],
        ["build: no-op, in-process", f"{statistics.median(noop_in):.3f} s", "-", "target < 0.5 s"],
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (median)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 2, help="build jobs")
    args = parser.parse_args()
    if shutil.which("vcs", path=str(Path(sys.executable).parent)) is None:
        raise SystemExit("vcs2l is not installed: pip install -e '.[test]'")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        env = {**os.environ, "MSCTL_HOME": str(root / "home"), "LC_ALL": "C"}
        rows = bench_update(root / "update", args.repeat, env)
        rows += bench_build(root / "build", args.repeat, args.jobs)
    print_table(
        f"msctl update / build ({os.cpu_count()} CPUs)",
        ["figure", "msctl", "baseline", "ratio"],
        rows,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
