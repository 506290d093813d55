"""``msctl build``: a doit task graph over the workspace's packages, incremental, offline.

One doit task per package (``build:<name>``), run programmatically
(``DoitMain(ModuleTaskLoader(...))``) with the json backend (doit's dbm backend breaks when
shared, pydoit #121) and threads, ``jobs`` at a time, in dependency order:

- ``file_dep``: the package's sources (doit compares content by MD5 once a file's time
  changed) and the stamps of the packages it depends on;
- ``targets``: its own stamp (``.msctl/build/stamps/<name>.stamp``), rewritten by each
  build, so every package depending on it is built again after it;
- ``uptodate``: how it is built (type, commands, mode, interpreter, the list of source
  files), so a new or removed file or another mode also builds it again.

A package whose sources and dependencies did not change is skipped, and a build with no
change runs nothing. A failure names the package, the step and the last lines of its log
(``.msctl/build/logs/<name>.log``); the packages that do not depend on it still build
(doit's ``--continue``), those that do are reported blocked, and the outcome is a failure.

Each step runs in a process group of its own, so a package's ``timeout`` or a
:meth:`Builder.stop` (``msctl build`` got SIGTERM or SIGINT) ends the step and every process
it started, and the build returns only once they are gone. doit rewrites its state file
in place, so a crash can leave it truncated: an unreadable one is set aside and the state
rebuilt from the packages (every package is built again), said in :attr:`BuildResult.notes`.

How each type builds:

- Python: its external requirements (``pip install``, offline from the wheelhouse: the
  missing ones are named before pip runs), then the package itself (``pip install
  --no-deps``, ``-e`` when editable), or a wheel (``pip wheel --no-deps``);
- ROS 2: ``colcon build --packages-select`` when ``colcon`` is on PATH, else skipped,
  named, with how to get colcon;
- command: the commands of its ``msctl-build.toml``, in its directory, no shell.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from msctl.workspace import state_dir
from msctl.workspace.build_processes import (
    end_group,
    read_from,
    set_aside_unreadable,
    signal_group,
    tail,
)
from msctl.workspace.build_reporter import Reporter, without_entry_point_plugins
from msctl.workspace.build_results import BuildResult, PackageResult
from msctl.workspace.build_steps import BuildOptions, Step, package_steps, pip_index
from msctl.workspace.packages import Graph, Package, source_files
from msctl.workspace.wheelhouse import (
    MANIFEST,
    download_command,
    installed,
    missing,
    pip,
    write_manifest,
)

#: How to get colcon when a ROS package needs it.
COLCON_HINT = (
    "colcon is not on PATH: source your ROS 2 setup (/opt/ros/jazzy/setup.bash) or "
    "`pip install colcon-common-extensions`, then build again"
)
#: Called with (package name, status or step, detail) as the build goes on.
Events = Callable[[str, str, str], None]


class _Failed(Exception):
    def __init__(self, step: str, message: str):
        super().__init__(message)
        self.step = step
        self.message = message


class Builder:
    """Builds a workspace's packages through doit.

    Args:
        graph: The workspace's packages.
        options: How to build.
        events: Called with (package name, step or status, detail) as the build goes on
            (from the build's threads).
    """

    def __init__(self, graph: Graph, options: BuildOptions, events: Events | None = None):
        self.graph = graph
        self.options = options
        self.events = events or (lambda _name, _status, _detail: None)
        self.state = state_dir(graph.root) / "build"
        self.results: dict[str, PackageResult] = {}
        self.wheelhouse_result: PackageResult | None = None
        self._serial = threading.Lock()
        self._environment: dict[str, str] | None = None
        self._environment_lock = threading.Lock()
        # The steps running now (each its own process group), and why the build stops.
        self._running: set[subprocess.Popen[bytes]] = set()
        # Reentrant: with one job doit runs a step in the main thread, where a signal
        # handler calling stop() may interrupt _call while it holds the lock.
        self._running_lock = threading.RLock()
        self._stopped = ""

    def stop(self, why: str) -> None:
        """Stop the build: every running step's process group gets SIGTERM (SIGKILL after
        :data:`~msctl.workspace.build_processes.STOP_GRACE_S`), and no further package
        starts. :meth:`run` returns once the running steps are gone. Safe from a signal
        handler or another thread."""
        self._stopped = self._stopped or why
        with self._running_lock:
            running = list(self._running)
        for process in running:
            signal_group(process, signal.SIGTERM)

    # ------------------------------------------------------------------ paths
    def stamp(self, key: str) -> Path:
        """The file a package's successful build rewrites (its doit target)."""
        return self.state / "stamps" / f"{key}.stamp"

    def log(self, key: str) -> Path:
        """A package's build log."""
        return self.state / "logs" / f"{key}.log"

    # ------------------------------------------------------------------ the graph
    def tasks(self, keys: Sequence[str]) -> tuple[list[dict[str, Any]], list[str]]:
        """The doit tasks building ``keys`` (in build order), and the keys skipped here
        (ROS packages without colcon; everything when only downloading).

        Pure: it reads the packages' files, runs nothing.
        """
        self.results = {
            k: PackageResult(self.graph.packages[k].name, self.graph.packages[k].type) for k in keys
        }
        tasks: list[dict[str, Any]] = []
        skipped: list[str] = []
        wheelhouse_task = self._wheelhouse_task(keys)
        if wheelhouse_task is not None:
            tasks.append(wheelhouse_task)
            self.wheelhouse_result = PackageResult("wheelhouse", "wheelhouse")
        if self.options.download_only:
            for key in keys:
                self._skip(key, "download only", "wheels for another platform: not built here")
            return tasks, list(keys)
        selected = set(keys)
        for key in keys:
            package = self.graph.packages[key]
            if package.type == "ros" and not self.options.colcon:
                skipped.append(key)
                self._skip(key, "colcon", COLCON_HINT)
                continue
            deps = [d for d in self.graph.edges[key] if d in selected and d not in skipped]
            files = self._inputs(package)
            recipe = {
                "type": package.type,
                "steps": [list(s.argv) for s in self.steps(package)],
                "files": sorted(str(p.relative_to(package.path)) for p in files),
                "python": self.options.python,
            }
            task: dict[str, Any] = {
                "basename": "build",
                "name": key,
                "actions": [(self._build, (key,))],
                "file_dep": [str(p) for p in files] + [str(self.stamp(d)) for d in deps],
                "targets": [str(self.stamp(key))],
                "uptodate": [_recipe(recipe)],
                "verbosity": 0,
                "io": {"capture": False},  # doit swaps sys.stdout when capturing: not in threads
                "doc": f"{package.type} package {package.name}",
            }
            if wheelhouse_task is not None and package.type == "python":
                task["task_dep"] = ["wheelhouse"]
            tasks.append(task)
        return tasks, skipped

    def steps(self, package: Package) -> list[Step]:
        """The commands building ``package`` (its external requirements' install aside,
        which is decided when it runs)."""
        return package_steps(package, self.graph, self.options)

    def _inputs(self, package: Package) -> list[Path]:
        if package.type == "python" and self.options.editable and not self.options.wheels:
            # Editable: the sources are used in place; only the metadata needs a reinstall.
            return [
                p
                for p in (package.manifest, package.path / "setup.py", package.path / "setup.cfg")
                if p.exists()
            ]
        return source_files(package)

    def _wheelhouse_task(self, keys: Sequence[str]) -> dict[str, Any] | None:
        options = self.options
        if options.wheelhouse is None or options.offline:
            return None
        requirements = self.download_requirements(keys)
        wanted = {
            "requirements": requirements,
            "platform": options.platform,
            "python_version": options.python_version,
        }
        return {
            "basename": "wheelhouse",
            "actions": [(self._download, (requirements,))],
            "targets": [str(options.wheelhouse / MANIFEST)],
            "uptodate": [_recipe(wanted)],
            "verbosity": 0,
            "io": {"capture": False},
            "doc": f"download {len(requirements)} requirements into {options.wheelhouse}",
        }

    def download_requirements(self, keys: Sequence[str]) -> list[str]:
        """Every external requirement and build requirement of the Python packages among
        ``keys``: what a wheelhouse needs to install them offline."""
        found: dict[str, None] = {}
        for key in keys:
            package = self.graph.packages[key]
            if package.type != "python":
                continue
            for requirement in [*self.graph.external_requirements(key), *package.build_requires]:
                found.setdefault(requirement)
            if any(r.lower().startswith("setuptools") for r in package.build_requires):
                # setuptools before 70.1 asks for `wheel` when building, beyond its requires.
                found.setdefault("wheel")
        return list(found)

    def _skip(self, key: str, step: str, why: str) -> None:
        result = self.results[key]
        result.status, result.step, result.message = "skipped", step, why
        # No doit task will report on it: say it here, or a progress view waits for it.
        self.events(result.name, "skipped", why)

    # ------------------------------------------------------------------ actions
    def _download(self, requirements: list[str]) -> Any:
        from doit.exceptions import TaskFailed

        options = self.options
        assert options.wheelhouse is not None
        options.wheelhouse.mkdir(parents=True, exist_ok=True)
        log = self.state / "logs" / "wheelhouse.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        self.events("wheelhouse", "downloading", f"{len(requirements)} requirements")
        started = time.monotonic()
        try:
            with log.open("w", encoding="utf-8") as out:
                if requirements:
                    argv = download_command(
                        options.python,
                        options.wheelhouse,
                        requirements,
                        options.platform,
                        options.python_version,
                    )
                    self._run(Step("download", tuple(argv), self.graph.root), out, log)
            write_manifest(
                options.wheelhouse, requirements, options.platform, options.python_version
            )
        except _Failed as failure:
            self.wheelhouse_result = PackageResult(
                "wheelhouse", "wheelhouse", "failed", failure.step, failure.message, str(log)
            )
            return TaskFailed(failure.message)
        self.wheelhouse_result = PackageResult(
            "wheelhouse", "wheelhouse", "built", log=str(log), seconds=time.monotonic() - started
        )
        return None

    def _build(self, key: str) -> Any:
        """doit's action for one package: its steps, its log, its stamp."""
        from doit.exceptions import TaskFailed

        package = self.graph.packages[key]
        result = self.results[key]
        if self._stopped:
            result.status, result.step, result.message = "failed", "stopped", self._stopped
            return TaskFailed(f"{package.name}: not started ({self._stopped})")
        log = self.log(key)
        log.parent.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        deadline = started + self.options.timeout if self.options.timeout else None
        try:
            with log.open("w", encoding="utf-8") as out:
                for step in self._all_steps(key, package):
                    if self._stopped:
                        raise _Failed(step.label, f"stopped before it ran ({self._stopped})")
                    self.events(package.name, step.label, "")
                    self._run(step, out, log, deadline, package.name)
        except _Failed as failure:
            result.status, result.step, result.message = "failed", failure.step, failure.message
            result.log, result.seconds = str(log), time.monotonic() - started
            return TaskFailed(f"{package.name}: {failure.step} failed")
        stamp = self.stamp(key)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        # A new content each time: the packages depending on this one see it changed.
        stamp.write_text(json.dumps({"package": package.name, "built": time.time_ns()}) + "\n")
        result.status, result.log = "built", str(log)
        result.seconds = time.monotonic() - started
        return None

    def _all_steps(self, key: str, package: Package) -> list[Step]:
        steps = self.steps(package)
        if package.type != "python" or self.options.wheels is not None:
            return steps
        before = []
        options = self.options
        if options.offline:
            self._check_offline(key, package)
        externals = self.graph.external_requirements(key)
        absent = missing(externals, None, self.environment())
        if absent:
            # One pip at a time installs shared dependencies: two would race on one file.
            argv = pip(options.python, "install", *pip_index(self.options), *absent)
            before.append(Step("dependencies", tuple(argv), package.path, serial=True))
        return before + steps

    def environment(self) -> dict[str, str]:
        """What is installed in the target environment (read once per build, then kept
        up to date by the builds themselves as pip reports them)."""
        with self._environment_lock:
            if self._environment is None:
                self._environment = installed(self.options.python)
            return self._environment

    def _check_offline(self, key: str, package: Package) -> None:
        options = self.options
        externals = self.graph.external_requirements(key)
        absent = missing(externals, options.wheelhouse, self.environment(), python=options.python)
        if options.wheelhouse is not None:
            # An isolated build installs its backend from the wheelhouse alone.
            absent += missing(package.build_requires, options.wheelhouse, {}, python=options.python)
        else:
            absent += missing(package.build_requires, None, self.environment())
        if absent:
            where = f"wheelhouse {options.wheelhouse}" if options.wheelhouse else "no wheelhouse"
            raise _Failed(
                "dependencies",
                f"offline, and neither this environment nor {where} has: "
                f"{', '.join(dict.fromkeys(absent))} — on a computer with the network, run "
                f"`msctl build --wheelhouse DIR` (with --platform/--python-version for this "
                "robot), copy DIR here, and build with --offline --wheelhouse DIR",
            )

    def _run(
        self,
        step: Step,
        out: Any,
        log: Path,
        deadline: float | None = None,
        package: str = "",
    ) -> None:
        out.write(f"$ {' '.join(step.argv)}\n")
        out.flush()
        start = out.tell()
        env = {
            **os.environ,
            "MSCTL_WORKSPACE": str(self.graph.root),
            "MSCTL_PYTHON": self.options.python,
            "PIP_NO_INPUT": "1",
        }
        try:
            if step.serial:
                with self._serial:
                    code = self._call(step, out, env, deadline)
            else:
                code = self._call(step, out, env, deadline)
        except FileNotFoundError:
            raise _Failed(step.label, f"{step.argv[0]} is not installed (not on PATH)") from None
        except subprocess.TimeoutExpired:
            out.write(f"\n[msctl build: stopped after --timeout {self.options.timeout:g} s]\n")
            out.flush()
            raise _Failed(
                step.label,
                f"{package or 'the package'} took longer than --timeout "
                f"{self.options.timeout:g} s: stopped it (and every process it started); "
                f"its log: {log}",
            ) from None
        if self._stopped:
            raise _Failed(step.label, f"stopped ({self._stopped}); its log: {log}")
        if code != 0:
            out.flush()
            raise _Failed(step.label, f"exit status {code}; last lines of {log}:\n{tail(log)}")
        if step.expect and step.expect not in read_from(log, start):
            raise _Failed(step.label, f"{step.unmet}; last lines of {log}:\n{tail(log)}")
        if step.serial:
            with self._environment_lock:
                self._environment = None  # pip installed things: read the environment again

    def _call(
        self, step: Step, out: Any, env: dict[str, str], deadline: float | None = None
    ) -> int:
        """Run one step in a process group of its own and wait for it; at ``deadline`` or
        a :meth:`stop`, its whole group is ended (a build tool's children too).

        Raises:
            subprocess.TimeoutExpired: When ``deadline`` passed (the group is gone).
        """
        with self._running_lock:
            if self._stopped:
                return -signal.SIGTERM
            process = subprocess.Popen(
                step.argv,
                cwd=step.cwd,
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                start_new_session=True,
            )
            self._running.add(process)
        ended = False
        try:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                code = process.wait(remaining)
            except subprocess.TimeoutExpired:
                signal_group(process, signal.SIGTERM)
                raise
            ended = not self._stopped
            return code
        finally:
            if not ended:
                end_group(process)
            with self._running_lock:
                self._running.discard(process)

    # ------------------------------------------------------------------ running
    def run(self, keys: Sequence[str]) -> BuildResult:
        """Build ``keys`` (and nothing else) through doit; see the module's description."""
        from doit.cmd_base import ModuleTaskLoader
        from doit.doit_cmd import DoitMain

        started = time.monotonic()
        tasks, _skipped = self.tasks(keys)
        reporter = Reporter(self)

        def task_msctl() -> Any:
            yield from tasks

        namespace = {
            "DOIT_CONFIG": {"reporter": reporter, "verbosity": 0},
            "task_msctl": task_msctl,
        }
        names = [f"{t['basename']}:{t['name']}" if "name" in t else t["basename"] for t in tasks]
        self.state.mkdir(parents=True, exist_ok=True)
        notes = []
        if names:
            note = set_aside_unreadable(self.state / "doit.json")
            if note:
                notes.append(note)
        if names:
            argv = [
                "run",
                "--backend",
                "json",
                "--db-file",
                str(self.state / "doit.json"),
                "--parallel-type",
                "thread",
                "--process",
                str(max(1, self.options.jobs)),
                "--continue" if self.options.keep_going else "--no-continue",
                *(["--always-execute"] if self.options.force else []),
                *names,
            ]
            with without_entry_point_plugins():
                code = DoitMain(ModuleTaskLoader(namespace), config_filenames=()).run(argv)
            if code not in (0, 1) and not reporter.errors:
                # 2 and 3: doit itself could not run the graph (it said why on stderr).
                reporter.errors.append(f"doit stopped with exit status {code}")
        return BuildResult(
            self.graph.root,
            [self.results[k] for k in keys],
            self.wheelhouse_result,
            time.monotonic() - started,
            reporter.errors,
            notes,
            self._stopped,
        )

    def _event(self, task_name: str, status: str, detail: str = "") -> None:
        """One of doit's events about a task (``building``, ``built``, ``up to date``,
        ``failed``, ``blocked``), kept in the results and passed on to :attr:`events`."""
        if task_name == "wheelhouse":
            if status in ("up to date", "blocked"):
                self.wheelhouse_result = PackageResult("wheelhouse", "wheelhouse", status)
                self.wheelhouse_result.message = detail
            self.events("wheelhouse", status, detail)
            return
        key = task_name[len("build:") :] if task_name.startswith("build:") else None
        result = self.results.get(key) if key is not None else None
        if result is None:
            return  # doit's group task "build"
        if status == "up to date":
            result.status = status
        elif status == "blocked":
            result.status, result.step, result.message = status, "dependencies", detail
        elif status == "failed" and result.status != "failed":
            # A failure outside the package's own steps (doit could not check or save it).
            result.status, result.step, result.message = status, "doit", detail
        self.events(result.name, status, result.message if status == "failed" else detail)


def _recipe(config: dict[str, Any]) -> Any:
    from doit.tools import config_changed

    return config_changed(config)
