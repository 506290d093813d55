"""The workspace's packages, their graph, and the doit tasks built from it (no processes)."""

from __future__ import annotations

from pathlib import Path

import pytest
from workspace_rigs import python_package

from msctl.errors import InputError, NotFoundError
from msctl.workspace.build import COLCON_HINT, Builder, BuildOptions
from msctl.workspace.packages import canonical, find_packages, source_files
from msctl.workspace.wheelhouse import missing


def _ros(root: Path, name: str, depends: list[str] = (), build_type: str = "ament_cmake") -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    tags = "".join(f"<depend>{d}</depend>" for d in depends)
    (folder / "package.xml").write_text(
        f'<?xml version="1.0"?><package format="3"><name>{name}</name><version>0.1.0</version>'
        f"{tags}<exec_depend>rclpy</exec_depend>"
        f"<export><build_type>{build_type}</build_type></export></package>"
    )
    return folder


def _command(root: Path, name: str, text: str) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    (folder / "msctl-build.toml").write_text(text)
    return folder


def _workspace(root: Path) -> Path:
    """limb_msgs (ROS) <- limb-control (Python, needs numpy) <- limb_firmware (command)."""
    ws = root / "ws"
    _ros(ws / "src", "limb_msgs")
    python_package(ws / "src", "limb-control", depends=["limb_msgs", "numpy>=1.26"])
    python_package(ws / "src", "wheel-control", depends=["Limb.Control"])
    _command(
        ws / "firmware",
        "limb_firmware",
        'name = "limb_firmware"\ndepends = ["limb-control"]\n'
        'commands = [["make", "-j2"], ["make", "install"]]\nsources = ["src/**", "Makefile"]\n',
    )
    return ws


def test_packages_are_found_by_their_manifests_and_linked(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    assert {p.name: p.type for p in graph.packages.values()} == {
        "limb_msgs": "ros",
        "limb-control": "python",
        "wheel-control": "python",
        "limb_firmware": "command",
    }
    # limb_msgs (package.xml) and Limb.Control (pyproject) match by PEP 503 name.
    assert graph.edges[canonical("limb-control")] == ("limb-msgs",)
    assert graph.edges["wheel-control"] == ("limb-control",)
    assert graph.edges["limb-firmware"] == ("limb-control",)
    assert graph.order() == ["limb-msgs", "limb-control", "limb-firmware", "wheel-control"]
    assert graph.external_requirements("limb-control") == ["numpy>=1.26"]


def test_packages_up_to_takes_the_dependencies_in_build_order(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    assert graph.up_to(["wheel-control"]) == ["limb-msgs", "limb-control", "wheel-control"]
    with pytest.raises(NotFoundError) as caught:
        graph.up_to(["wheel-contrl"])
    assert "did you mean 'wheel-control'" in str(caught.value)


def test_the_search_skips_build_output_hidden_and_ignored_directories(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    python_package(ws, "kept")
    python_package(ws / "build", "colcon-output")
    python_package(ws / ".venv", "hidden")
    python_package(ws / "ignored", "vendored")
    (ws / "ignored" / "COLCON_IGNORE").write_text("")
    python_package(ws / "kept" / "tests", "fixture")  # inside a package: part of it
    (ws / "tools").mkdir()
    (ws / "tools" / "pyproject.toml").write_text("[tool.ruff]\nline-length = 100\n")
    graph = find_packages(ws)
    assert graph.names() == ["kept"]
    assert any("tools/pyproject.toml: no [project] name" in n for n in graph.notes)


def test_one_directory_prefers_msctl_build_then_package_xml(tmp_path: Path) -> None:
    folder = _ros(tmp_path / "ws", "both")
    (folder / "pyproject.toml").write_text('[project]\nname = "both-py"\nversion = "1"\n')
    assert find_packages(tmp_path / "ws").names() == ["both"]


@pytest.mark.parametrize(
    ("manifest", "text", "expected"),
    [
        ("msctl-build.toml", 'name = "x"\ncommands = "make"\n', ["'commands'", "no shell"]),
        ("msctl-build.toml", 'name = "x"\ncomands = [["make"]]\n', ["'comands'", "'commands'"]),
        ("msctl-build.toml", 'commands = [["make"]]\n', ["'name'"]),
        (
            "msctl-build.toml",
            'name = "x"\ncommands = [["make"]]\nsources = ["../secret"]\n',
            ["leaves the package"],
        ),
        ("msctl-build.toml", "name = \n", ["not valid TOML"]),
        ("package.xml", "<package><name>x</name>", ["not valid XML"]),
        ("package.xml", "<notapackage/>", ["not a ROS package manifest"]),
        (
            "pyproject.toml",
            '[project]\nname = "x"\nversion = "1"\ndependencies = ["numpy >>> 1"]\n',
            ["'numpy >>> 1'", "not valid"],
        ),
    ],
)
def test_a_malformed_manifest_names_the_file_and_field(
    tmp_path: Path, manifest: str, text: str, expected: list[str]
) -> None:
    folder = tmp_path / "ws" / "pkg"
    folder.mkdir(parents=True)
    (folder / manifest).write_text(text)
    with pytest.raises(InputError) as caught:
        find_packages(tmp_path / "ws")
    assert str(folder / manifest) in str(caught.value)
    for part in expected:
        assert part in str(caught.value)


def test_two_packages_of_one_name_are_refused_naming_both(tmp_path: Path) -> None:
    python_package(tmp_path / "ws" / "a", "same")
    python_package(tmp_path / "ws" / "b", "same")
    with pytest.raises(InputError) as caught:
        find_packages(tmp_path / "ws")
    text = str(caught.value)
    assert "a/same/pyproject.toml" in text and "b/same/pyproject.toml" in text


def test_a_dependency_cycle_is_named(tmp_path: Path) -> None:
    python_package(tmp_path / "ws", "alpha", depends=["beta"])
    python_package(tmp_path / "ws", "beta", depends=["gamma"])
    python_package(tmp_path / "ws", "gamma", depends=["alpha"])
    python_package(tmp_path / "ws", "free")
    with pytest.raises(InputError) as caught:
        find_packages(tmp_path / "ws")
    assert "dependency cycle: alpha -> beta -> gamma -> alpha" in str(caught.value)


def test_sources_leave_out_caches_and_follow_declared_globs(tmp_path: Path) -> None:
    folder = python_package(tmp_path / "ws", "pkg")
    (folder / "pkg" / "__pycache__").mkdir()
    (folder / "pkg" / "__pycache__" / "x.pyc").write_bytes(b"")
    (folder / "pkg.egg-info").mkdir()
    (folder / "pkg.egg-info" / "PKG-INFO").write_text("")
    names = {
        p.relative_to(folder).as_posix()
        for p in source_files(find_packages(folder.parent).packages["pkg"])
    }
    assert names == {"pyproject.toml", "pkg/__init__.py", "_backend/rig_backend.py"}
    firmware = _command(
        tmp_path / "fw",
        "fw",
        'name = "fw"\ncommands = [["make"]]\nsources = ["src/*.c"]\n',
    )
    (firmware / "src").mkdir()
    (firmware / "src" / "main.c").write_text("int main(){}")
    (firmware / "notes.txt").write_text("not a source")
    package = find_packages(tmp_path / "fw").packages["fw"]
    assert [p.name for p in source_files(package)] == ["msctl-build.toml", "main.c"]


# --------------------------------------------------------------------------- the task graph
def _tasks(graph, **options):  # type: ignore[no-untyped-def]
    builder = Builder(graph, BuildOptions(python="/env/bin/python", jobs=2, **options))
    tasks, skipped = builder.tasks(graph.order())
    return builder, {t.get("name", t["basename"]): t for t in tasks}, skipped


def test_each_package_is_a_doit_task_on_its_sources_and_its_dependencies_stamps(
    tmp_path: Path,
) -> None:
    graph = find_packages(_workspace(tmp_path))
    builder, tasks, skipped = _tasks(graph, colcon="/usr/bin/colcon")
    assert skipped == []
    control = tasks["limb-control"]
    assert control["basename"] == "build"
    assert control["targets"] == [str(builder.stamp("limb-control"))]
    assert str(builder.stamp("limb-msgs")) in control["file_dep"]
    assert str(graph.packages["limb-control"].manifest) in control["file_dep"]
    assert str(builder.stamp("limb-firmware")) not in tasks["wheel-control"]["file_dep"]
    assert control["io"] == {"capture": False}
    assert [s.label for s in builder.steps(graph.packages["limb-firmware"])] == [
        "command 1 (make)",
        "command 2 (make)",
    ]
    (colcon,) = builder.steps(graph.packages["limb-msgs"])
    assert colcon.argv[:2] == ("/usr/bin/colcon", "build")
    assert "--packages-select" in colcon.argv and "limb_msgs" in colcon.argv


def test_colcon_sees_every_ros_package_a_package_depends_on(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    msgs, driver, bringup = (
        _ros(ws, "limb_msgs"),
        _ros(ws, "limb_driver", ["limb_msgs"]),
        _ros(ws, "limb_bringup", ["limb_driver"]),
    )
    graph = find_packages(ws)
    builder = Builder(graph, BuildOptions(python="/p", colcon="/usr/bin/colcon"))
    (step,) = builder.steps(graph.packages["limb-bringup"])
    argv = list(step.argv)
    # Its own directory and those of its ROS dependencies, direct or not: colcon builds it in
    # their installs' environment; only it is selected.
    paths = argv[argv.index("--base-paths") + 1 : argv.index("--packages-select")]
    assert paths == [str(bringup), str(msgs), str(driver)]
    assert argv[argv.index("--packages-select") + 1] == "limb_bringup"
    # colcon exits 0 for a package it did not find: its own line for the package is required.
    assert step.expect == "Finished <<< limb_bringup"


def test_ros_packages_without_colcon_are_skipped_and_named(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    builder, tasks, skipped = _tasks(graph, colcon=None)
    assert skipped == ["limb-msgs"] and "limb-msgs" not in tasks
    result = builder.results["limb-msgs"]
    assert (result.status, result.message) == ("skipped", COLCON_HINT)
    # Its dependents still build, without waiting on its stamp.
    assert str(builder.stamp("limb-msgs")) not in tasks["limb-control"]["file_dep"]


def test_offline_pip_uses_no_index_and_the_wheelhouse(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    wheelhouse = tmp_path / "wh"
    builder, _, _ = _tasks(graph, offline=True, wheelhouse=wheelhouse)
    (install,) = builder.steps(graph.packages["limb-control"])
    assert install.argv[:4] == ("/env/bin/python", "-m", "pip", "install")
    assert "--no-index" in install.argv and "--no-deps" in install.argv
    assert install.argv[install.argv.index("--find-links") + 1] == str(wheelhouse)
    # Offline without a wheelhouse: the environment's own build backend.
    builder, _, _ = _tasks(graph, offline=True)
    (install,) = builder.steps(graph.packages["limb-control"])
    assert "--no-build-isolation" in install.argv and "--find-links" not in install.argv


def test_a_wheelhouse_download_is_one_task_every_python_build_waits_for(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    wheelhouse = tmp_path / "wh"
    _builder, tasks, _ = _tasks(graph, wheelhouse=wheelhouse)
    assert tasks["wheelhouse"]["targets"] == [str(wheelhouse / "msctl-wheelhouse.json")]
    assert tasks["limb-control"]["task_dep"] == ["wheelhouse"]
    assert "task_dep" not in tasks["limb-firmware"]
    builder = Builder(graph, BuildOptions(python="/p", wheelhouse=wheelhouse))
    assert builder.download_requirements(graph.order()) == ["numpy>=1.26"]
    # For another platform: the download only.
    builder, tasks, skipped = _tasks(graph, wheelhouse=wheelhouse, platform="manylinux2014_aarch64")
    assert list(tasks) == ["wheelhouse"] and len(skipped) == 4


def test_editable_installs_depend_on_the_metadata_only(tmp_path: Path) -> None:
    graph = find_packages(_workspace(tmp_path))
    _builder, tasks, _ = _tasks(graph, editable=True)
    manifest = str(graph.packages["limb-control"].manifest)
    assert [f for f in tasks["limb-control"]["file_dep"] if not f.endswith(".stamp")] == [manifest]


def test_missing_names_what_neither_environment_nor_wheelhouse_holds(tmp_path: Path) -> None:
    wheelhouse = tmp_path / "wh"
    wheelhouse.mkdir()
    for name in (
        "numpy-1.26.4-py3-none-any.whl",
        "pyyaml-6.0.1.tar.gz",
        "exotic-1.0-cp311-cp311-win_amd64.whl",
        "notes.txt",
    ):
        (wheelhouse / name).write_text("")
    wanted = [
        "numpy>=1.26",
        "numpy>=2",
        "PyYAML",
        "exotic",
        "rich>=13",
        "scipy",
        'pywin32; sys_platform == "win32"',
    ]
    absent = missing(wanted, wheelhouse, {"rich": "13.7.0"})
    assert absent == ["numpy>=2", "exotic", "scipy"]
