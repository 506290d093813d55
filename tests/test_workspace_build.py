"""``msctl build`` with real pip into a fresh virtual environment, with no index at all:
external dependencies come from wheelhouses built here from tiny packages."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from workspace_rigs import (
    TERMINAL,
    backend_package,
    build_wheel,
    imports,
    make_venv,
    pip_env,
    progress_rows,
    python_package,
)

from msctl.workspace.build import Builder, BuildOptions, BuildResult
from msctl.workspace.packages import find_packages

#: Every test runs pip; a pip install takes seconds, many on a loaded machine.
pytestmark = [pytest.mark.e2e, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> str:
    """One environment for the module (each test installs packages of its own names)."""
    return make_venv(tmp_path_factory.mktemp("venv") / "env")


@pytest.fixture(autouse=True)
def no_index(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """pip in these tests never reaches an index, whatever this machine's configuration."""
    for key in list(os.environ):
        if key.startswith("PIP_"):
            monkeypatch.delenv(key)
    for key, value in pip_env().items():
        if key.startswith("PIP_"):
            monkeypatch.setenv(key, value)
    yield


def _build(ws: Path, python: str, **options: object) -> BuildResult:
    graph = find_packages(ws)
    return Builder(graph, BuildOptions(python=python, jobs=2, **options)).run(graph.order())  # type: ignore[arg-type]


def _statuses(result: BuildResult) -> dict[str, str]:
    return {p.name: p.status for p in result.packages}


def test_a_graph_builds_in_order_then_only_what_changed(tmp_path: Path, venv: str) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "inc-base")
    python_package(ws, "inc-left", depends=["inc-base"])
    python_package(ws, "inc-right", depends=["inc_base"])
    python_package(ws, "inc-top", depends=["inc-left", "inc-right"])
    python_package(ws, "inc-alone")
    first = _build(ws, venv)
    assert first.ok, [p.message for p in first.packages]
    assert set(_statuses(first).values()) == {"built"}
    assert imports(venv, "inc_top") == "inc-top 0.1.0"
    second = _build(ws, venv)
    assert second.nothing_done and set(_statuses(second).values()) == {"up to date"}
    # A change in inc-left: it and inc-top again, nothing else.
    (ws / "inc-left" / "inc_left" / "__init__.py").write_text('VALUE = "left, changed"\n')
    third = _build(ws, venv)
    assert _statuses(third) == {
        "inc-base": "up to date",
        "inc-left": "built",
        "inc-right": "up to date",
        "inc-top": "built",
        "inc-alone": "up to date",
    }
    assert imports(venv, "inc_left") == "left, changed"
    # A file touched with the same content is not a change (content, not time).
    init = ws / "inc-right" / "inc_right" / "__init__.py"
    init.write_text(init.read_text())
    os.utime(init, (1, 1))
    assert _build(ws, venv).nothing_done
    # A new file is.
    (ws / "inc-alone" / "inc_alone" / "extra.py").write_text("X = 1\n")
    assert _statuses(_build(ws, venv))["inc-alone"] == "built"


def test_a_failure_names_package_step_and_log_and_the_rest_builds(
    tmp_path: Path, venv: str
) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "fail-base")
    broken = python_package(ws, "fail-broken", depends=["fail-base"])
    (broken / "_backend" / "rig_backend.py").write_text(
        "def build_wheel(*a, **k):\n    raise RuntimeError('the limb driver does not compile')\n"
    )
    python_package(ws, "fail-user", depends=["fail-broken"])
    python_package(ws, "fail-other")
    result = _build(ws, venv)
    assert not result.ok
    statuses = _statuses(result)
    assert statuses == {
        "fail-base": "built",
        "fail-broken": "failed",
        "fail-other": "built",
        "fail-user": "blocked",
    }
    failure = next(p for p in result.packages if p.name == "fail-broken")
    assert failure.step == "install"
    assert "the limb driver does not compile" in failure.message
    assert failure.log and Path(failure.log).is_file()
    blocked = next(p for p in result.packages if p.name == "fail-user")
    assert "fail-broken failed" in blocked.message
    assert imports(venv, "fail_other") == "fail-other 0.1.0"


def test_offline_from_a_wheelhouse_and_missing_wheels_named(tmp_path: Path, venv: str) -> None:
    source = tmp_path / "source"
    wheelhouse = tmp_path / "wh"
    build_wheel(python_package(source, "off-extdep", version="1.2"), wheelhouse)
    build_wheel(backend_package(source), wheelhouse)
    ws = tmp_path / "ws"
    # Built in isolation: its build backend (rig-backend) comes from the wheelhouse too.
    python_package(ws, "off-control", depends=["off-extdep>=1.0"], backend="wheel")
    python_package(ws, "off-needs-more", depends=["off-absent>=2", "off-extdep"])
    python_package(ws, "off-independent")
    result = _build(ws, venv, offline=True, wheelhouse=wheelhouse)
    statuses = _statuses(result)
    assert statuses["off-control"] == "built" and statuses["off-independent"] == "built"
    assert imports(venv, "off_extdep") == "off-extdep 1.2"
    assert statuses["off-needs-more"] == "failed"
    failure = next(p for p in result.packages if p.name == "off-needs-more")
    assert failure.step == "dependencies"
    assert "off-absent>=2" in failure.message and str(wheelhouse) in failure.message
    assert "msctl build --wheelhouse DIR" in failure.message


def test_a_wheelhouse_is_downloaded_for_the_workspace(tmp_path: Path, venv: str) -> None:
    index = tmp_path / "index"  # stands for the package index: pip finds links here
    build_wheel(python_package(tmp_path / "src", "dl-extdep"), index)
    build_wheel(backend_package(tmp_path / "src"), index)
    ws = tmp_path / "ws"
    python_package(ws, "dl-control", depends=["dl-extdep"], backend="wheel")
    wheelhouse = tmp_path / "wh"
    os.environ["PIP_FIND_LINKS"] = str(index)
    try:
        # For another Python: the download only, nothing built here.
        other = _build(ws, venv, wheelhouse=wheelhouse, python_version="3.11")
    finally:
        del os.environ["PIP_FIND_LINKS"]
    assert other.ok and other.wheelhouse is not None and other.wheelhouse.status == "built"
    assert _statuses(other) == {"dl-control": "skipped"}
    files = sorted(p.name for p in wheelhouse.iterdir())
    assert "dl_extdep-0.1.0-py3-none-any.whl" in files
    assert "rig_backend-0.1.0-py3-none-any.whl" in files
    manifest = json.loads((wheelhouse / "msctl-wheelhouse.json").read_text())
    assert manifest["requirements"] == ["dl-extdep", "rig-backend"]
    # The robot: offline, from that wheelhouse alone.
    robot = _build(ws, venv, offline=True, wheelhouse=wheelhouse)
    assert robot.ok and imports(venv, "dl_control") == "dl-control 0.1.0"


def test_command_packages_run_their_commands_in_order(tmp_path: Path, venv: str) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "cmd-lib")
    firmware = ws / "firmware"
    firmware.mkdir(parents=True)
    script = (
        "import os, pathlib; pathlib.Path('built.txt').write_text(os.environ['MSCTL_WORKSPACE'])"
    )
    (firmware / "msctl-build.toml").write_text(
        'name = "limb_firmware"\ndepends = ["cmd-lib"]\n'
        f'commands = [[{json.dumps(sys.executable)}, "-c", {json.dumps(script)}]]\n'
    )
    result = _build(ws, venv)
    assert _statuses(result) == {"cmd-lib": "built", "limb_firmware": "built"}
    assert (firmware / "built.txt").read_text() == str(ws)
    (firmware / "msctl-build.toml").write_text(
        'name = "limb_firmware"\ncommands = [["no-such-compiler-here"]]\n'
    )
    failed = _build(ws, venv)
    firmware_result = next(p for p in failed.packages if p.name == "limb_firmware")
    assert firmware_result.status == "failed"
    assert "no-such-compiler-here is not installed" in firmware_result.message


#: A command package's command: say it started, then wait for the other packages named
#: to have started too (so it ends only if they run at the same time), then say it is done.
RENDEZVOUS = """\
import pathlib, sys, time
marks, me, *others = sys.argv[1:]
marks = pathlib.Path(marks)
(marks / f"{me}.started").write_text("")
deadline = time.monotonic() + 300
while not all((marks / f"{o}.started").exists() for o in others):
    if time.monotonic() > deadline:
        sys.exit(f"{me}: {others} never started while {me} ran: built one at a time")
    time.sleep(0.01)
(marks / f"{me}.done").write_text("")
"""
#: A command package's command: fail unless the packages named are done already.
AFTER = """\
import pathlib, sys
marks, me, *before = sys.argv[1:]
missing = [b for b in before if not (pathlib.Path(marks) / f"{b}.done").exists()]
if missing:
    sys.exit(f"{me} ran before {missing} were done")
(pathlib.Path(marks) / f"{me}.done").write_text("")
"""


def _command_package(ws: Path, name: str, script: str, *args: str, depends: list[str] = ()):
    folder = ws / name
    folder.mkdir(parents=True)
    (folder / "run.py").write_text(script)
    argv = [sys.executable, "run.py", *args]
    (folder / "msctl-build.toml").write_text(
        f"name = {json.dumps(name)}\ndepends = {json.dumps(list(depends))}\n"
        f"commands = [{json.dumps(argv)}]\n"
    )


def test_independent_packages_build_at_once_and_dependents_after(tmp_path: Path, venv: str) -> None:
    ws, marks = tmp_path / "ws", tmp_path / "marks"
    marks.mkdir()
    # limb and wheel wait for each other to start: with 2 jobs they run side by side.
    _command_package(ws, "limb_firmware", RENDEZVOUS, str(marks), "limb_firmware", "wheel_fw")
    _command_package(ws, "wheel_fw", RENDEZVOUS, str(marks), "wheel_fw", "limb_firmware")
    _command_package(
        ws,
        "dragon_image",
        AFTER,
        str(marks),
        "dragon_image",
        "limb_firmware",
        "wheel_fw",
        depends=["limb_firmware", "wheel_fw"],
    )
    result = _build(ws, venv)
    assert result.ok, [(p.name, p.message) for p in result.packages]
    assert _statuses(result) == {
        "limb_firmware": "built",
        "wheel_fw": "built",
        "dragon_image": "built",
    }


def test_editable_installs_and_wheels(tmp_path: Path, venv: str) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "ed-pkg")
    assert _build(ws, venv, editable=True).ok
    (ws / "ed-pkg" / "ed_pkg" / "__init__.py").write_text('VALUE = "edited in place"\n')
    assert imports(venv, "ed_pkg") == "edited in place"
    assert _build(ws, venv, editable=True).nothing_done  # the sources are used in place
    wheels = tmp_path / "wheels"
    assert _build(ws, venv, wheels=wheels).ok
    assert [p.name for p in wheels.iterdir()] == ["ed_pkg-0.1.0-py3-none-any.whl"]


def _path_without_colcon() -> str:
    """PATH with no directory holding ``colcon``: these runs take the no-colcon path."""
    return os.pathsep.join(
        d for d in os.environ.get("PATH", "").split(os.pathsep) if not (Path(d) / "colcon").exists()
    )


def _msctl(tmp_path: Path, venv: str, *args: str, **extra: str) -> subprocess.CompletedProcess[str]:
    env = pip_env(MSCTL_HOME=str(tmp_path / "home"), VIRTUAL_ENV=str(Path(venv).parents[1]))
    env.update({"COLUMNS": "200", "PATH": _path_without_colcon(), **extra})
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def test_msctl_build_end_to_end(tmp_path: Path, venv: str) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "cli-base")
    python_package(ws, "cli-top", depends=["cli-base"])
    other = python_package(ws, "cli-other")
    ros = ws / "cli_msgs"
    ros.mkdir()
    (ros / "package.xml").write_text(
        "<package format='3'><name>cli_msgs</name><version>1.0.0</version></package>"
    )
    listing = _msctl(tmp_path, venv, "build", "-w", "ws", "--list", "--json")
    assert listing.returncode == 0, listing.stderr
    packages = {p["name"]: p for p in json.loads(listing.stdout)["packages"]}
    assert packages["cli-top"]["depends"] == ["cli-base"]
    first = _msctl(tmp_path, venv, "build", "-w", "ws", "--json", **TERMINAL)
    assert first.returncode == 0, first.stderr
    document = json.loads(first.stdout)
    results = {p["name"]: p["status"] for p in document["packages"]}
    assert results == {
        "cli-base": "built",
        "cli-other": "built",
        "cli-top": "built",
        "cli_msgs": "skipped",
    }
    message = next(p for p in document["packages"] if p["name"] == "cli_msgs")["message"]
    assert "colcon is not on PATH" in message and "pip install colcon-common-extensions" in message
    # A progress row per package on stderr, each ending in its result.
    assert progress_rows(first.stderr) == results
    second = _msctl(tmp_path, venv, "build", "-w", "ws")
    assert second.returncode == 0, second.stderr
    assert "nothing to build: 4 packages up to date" in second.stderr
    assert "skipped cli_msgs: colcon is not on PATH" in second.stderr
    # A failure: the package, its step and its log's last lines named; what does not depend
    # on it still builds; exit status 1.
    (ws / "cli-base" / "_backend" / "rig_backend.py").write_text(
        "def build_wheel(*a, **k):\n    raise RuntimeError('the wheel driver does not compile')\n"
    )
    (other / "cli_other" / "__init__.py").write_text('VALUE = "changed"\n')
    failed = _msctl(tmp_path, venv, "build", "-w", "ws")
    assert failed.returncode == 1, failed.stderr
    stderr = " ".join(failed.stderr.split())
    assert "cli-base failed at install: exit status 1; last lines of" in stderr
    assert "cli-base.log" in stderr and "the wheel driver does not compile" in stderr
    assert "failed: cli-base; not built (a dependency failed): cli-top" in stderr
    rows = {line.split("│")[1].strip(): line for line in failed.stdout.splitlines()[3:-1]}
    assert "built" in rows["cli-other"] and "blocked" in rows["cli-top"]
    assert imports(venv, "cli_other") == "changed"
    (ws / "cli-base" / "pyproject.toml").write_text("[project]\nname = \n")
    bad = _msctl(tmp_path, venv, "build", "-w", "ws")
    assert bad.returncode == 2
    assert "cli-base/pyproject.toml: not valid TOML" in bad.stderr


# --------------------------------------------------------------------------- colcon
#: A ROS 2 ament_python package (what colcon builds with no ROS installed).
_PACKAGE_XML = """<?xml version="1.0"?>
<package format="3">
  <name>{name}</name>
  <version>0.1.0</version>
  <description>{name}</description>
  <maintainer email="{email}">rig</maintainer>
  <license>Apache-2.0</license>
  {depends}
  <export><build_type>{build_type}</build_type></export>
</package>
"""
#: Its setup.py; a dependent imports its dependency while it builds (not while colcon only
#: reads its metadata, with --dry-run), so it builds only in its dependencies' environment.
_SETUP_PY = """import sys
from setuptools import setup
if "--dry-run" not in sys.argv:
    for needed in {needs!r}:
        __import__(needed)
setup(
    name="{name}",
    version="0.1.0",
    packages=["{name}"],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/{name}"]),
        ("share/{name}", ["package.xml"]),
    ],
)
"""


def _ament_python(
    root: Path, name: str, depends: list[str] = (), needs: list[str] | None = None
) -> Path:
    """An ament_python package ``root/name``; ``needs``: what its build imports (default:
    its dependencies)."""
    folder = root / name
    (folder / name).mkdir(parents=True)
    (folder / "resource").mkdir()
    (folder / "resource" / name).write_text("")
    (folder / name / "__init__.py").write_text(f"VALUE = {name!r}\n")
    tags = "".join(f"<depend>{d}</depend>" for d in depends)
    (folder / "package.xml").write_text(
        _PACKAGE_XML.format(
            name=name, email="rig@example.org", depends=tags, build_type="ament_python"
        )
    )
    needed = list(depends if needs is None else needs)
    (folder / "setup.py").write_text(_SETUP_PY.format(name=name, needs=needed))
    return folder


@pytest.mark.skipif(
    shutil.which("colcon") is None,
    reason="colcon is not on PATH (pip install colcon-core colcon-ros colcon-python-setup-py "
    "colcon-package-selection colcon-parallel-executor colcon-recursive-crawl)",
)
def test_ros_packages_build_through_colcon_in_their_dependencies_environment(
    tmp_path: Path, venv: str
) -> None:
    ws = tmp_path / "ws"
    _ament_python(ws / "src", "limb_msgs_py")
    _ament_python(ws / "src", "limb_driver_py", depends=["limb_msgs_py"])
    # Its build needs limb_msgs_py too, a dependency of a dependency.
    _ament_python(
        ws / "src",
        "limb_control_py",
        depends=["limb_driver_py"],
        needs=["limb_driver_py", "limb_msgs_py"],
    )
    # A manifest colcon cannot parse (an invalid maintainer email): colcon skips it and exits
    # 0; msctl names it failed.
    ghost = ws / "src" / "ghost_msgs"
    ghost.mkdir(parents=True)
    (ghost / "package.xml").write_text(
        _PACKAGE_XML.format(name="ghost_msgs", email="nobody", depends="", build_type="ament_cmake")
    )
    result = _build(ws, venv)
    assert _statuses(result) == {
        "ghost_msgs": "failed",
        "limb_msgs_py": "built",
        "limb_driver_py": "built",
        "limb_control_py": "built",
    }, [(p.name, p.message) for p in result.packages]
    ghost_result = next(p for p in result.packages if p.name == "ghost_msgs")
    assert ghost_result.step == "colcon"
    assert "colcon exited 0 without building ghost_msgs" in ghost_result.message
    site = next((ws / "install" / "limb_control_py" / "lib").glob("python*/site-packages"))
    assert (site / "limb_control_py" / "__init__.py").is_file()
    # Nothing changed: colcon is not run again (the ghost is still named).
    assert _statuses(_build(ws, venv)) == {
        "ghost_msgs": "failed",
        "limb_msgs_py": "up to date",
        "limb_driver_py": "up to date",
        "limb_control_py": "up to date",
    }
