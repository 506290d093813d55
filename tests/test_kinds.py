"""The component-kind registry: one typed entry per kind, every list derived from it, and
kinds added by other packages through the ``msctl.component_kinds`` entry-point group."""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from components import kinds
from components.build import buildable
from components.executor import registry as extensions

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def fresh_registry() -> Iterator[None]:
    """A registry read again from the installed entries, and forgotten after the test."""
    kinds.reset()
    yield
    kinds.reset()


def test_every_builtin_kind_is_one_complete_entry() -> None:
    registry = kinds.registry()
    assert set(registry) >= {
        "motor_interface",
        "joint_manager",
        "health_monitor",
        "location_publisher",
        "kinematics_manager",
        "simulator",
        "human_operator",
        "autonomous_operator",
        "data_monitor",
        "data_archiver",
    }
    for name, entry in registry.items():
        assert entry.name == name and entry.summary, name
        if not entry.runnable:
            continue  # planned, reported by the launcher as not built yet
        assert buildable(name), name
        assert kinds.resolve(entry.builder) is not None, name  # type: ignore[arg-type]
        assert entry.interface and kinds.resolve(entry.interface) is not None, name
        for cls in entry.config_classes():
            assert hasattr(cls, "__dataclass_fields__"), (name, cls)
        assert set(entry.module_facts) <= set(kinds.MODULE_FACTS), name
        assert entry.parameter_names(), name


def test_the_lists_everyone_uses_are_derived_from_the_entries() -> None:
    assert kinds.replaced_in_simulation("motor_interface")
    assert not kinds.replaced_in_simulation("joint_manager")
    assert [k.name for k in kinds.simulators()] == ["simulator"]
    assert [k.name for k in kinds.stand_ins("motor_interface")] == ["simulator"]
    stations = {k.name for k in kinds.placed(kinds.Placement.STATION)}
    assert stations == {
        "human_operator",
        "autonomous_operator",
        "data_monitor",
        "data_archiver",
        "bridge",
    }
    modules = {k.name for k in kinds.placed(kinds.Placement.MODULE)}
    assert "joint_manager" in modules and not modules & stations
    assert kinds.get("simulator").component_name == "sim/simulator"
    assert kinds.extension_target({"name": "rezero"}) == kinds.DEFAULT_EXTENSION_TARGET
    assert kinds.extension_target({"name": "x", "component": "kinematics_manager"}) == (
        "kinematics_manager"
    )


def test_an_unknown_kind_names_the_known_ones() -> None:
    with pytest.raises(kinds.KindError, match=r"'joint_manger'.*joint_manager"):
        kinds.get("joint_manger")


def test_parameters_are_checked_against_the_kind() -> None:
    jm = kinds.get("joint_manager")
    kinds.check_params(jm, {"joints": ["limb1_joint1"]})
    with pytest.raises(kinds.KindError, match=r"no parameter 'speeed'.*known:"):
        kinds.check_params(jm, {"speeed": 1.0})
    numeric = next(
        p
        for p in jm.parameter_names()
        if p not in {*jm.module_facts, *jm.structural, *jm.checks}
        and p not in ("injections", "overrides")
    )
    with pytest.raises(kinds.KindError, match="finite"):
        kinds.check_params(jm, {numeric: math.nan})
    with pytest.raises(kinds.KindError, match="give a number"):
        kinds.check_params(jm, {numeric: [1, 2]})
    health = kinds.get("health_monitor")
    with pytest.raises(kinds.KindError, match="thresholds"):
        kinds.check_params(health, {"thresholds": {"max_temperature": "hot"}})


def test_injections_and_overrides_are_found_through_their_kind() -> None:
    extensions.check("override", "joint_manager", {"name": "locked_joint", "joint": "joint5"})
    with pytest.raises(extensions.RegistryError, match="known: locked_joint"):
        extensions.check("override", "joint_manager", {"name": "lock_joint"})
    with pytest.raises(extensions.RegistryError, match="kinematics_manager; known: none"):
        extensions.check("override", "kinematics_manager", {"name": "locked_joint"})
    with pytest.raises(extensions.RegistryError, match="position"):
        extensions.check(
            "override", "joint_manager", {"name": "locked_joint", "joint": "j", "position": "0"}
        )
    with pytest.raises(extensions.RegistryError, match="joint"):
        extensions.check("override", "joint_manager", {"name": "locked_joint"})


def _install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, body: str) -> None:
    """An installed distribution declaring one entry of the kinds group (as pip would)."""
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(body))
    info = tmp_path / f"{name}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{kinds.ENTRY_POINT_GROUP}]\n{name} = {name}\n")
    monkeypatch.syspath_prepend(str(tmp_path))


def test_another_package_adds_a_kind_through_the_entry_point_group(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fresh_registry: None
) -> None:
    _install(
        tmp_path,
        monkeypatch,
        "msctl_sonar",
        """
        from components.kinds import ComponentKind, Placement

        KIND = ComponentKind(
            name="sonar_mapper",
            summary="maps the field with sonar",
            placement=Placement.STATION,
        )
        """,
    )
    kinds.reset()
    assert "sonar_mapper" in kinds.names()
    entry = kinds.get("sonar_mapper")
    assert entry.placement is kinds.Placement.STATION and not entry.runnable
    assert not buildable("sonar_mapper")  # planned; the launcher says it is not built


def test_an_entry_point_redeclaring_a_kind_is_refused_naming_both(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fresh_registry: None
) -> None:
    _install(
        tmp_path,
        monkeypatch,
        "msctl_clash",
        """
        from components.kinds import ComponentKind, Placement

        KIND = ComponentKind(name="joint_manager", summary="mine", placement=Placement.MODULE)
        """,
    )
    kinds.reset()
    with pytest.raises(kinds.KindError, match=r"'joint_manager' is declared twice.*msctl_clash"):
        kinds.registry()


def test_a_process_yields_the_cpu_as_its_most_important_kind_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fresh_registry: None
) -> None:
    assert kinds.get("data_archiver").niceness == 10
    assert kinds.get("data_monitor").niceness == 5
    assert kinds.process_niceness(["data_archiver"]) == 10
    assert kinds.process_niceness(["data_monitor", "data_archiver"]) == 5
    # A module's process holds its joint manager: the safety path's 0, whatever else.
    assert kinds.process_niceness(["health_monitor", "joint_manager", "data_monitor"]) == 0
    assert kinds.process_niceness([]) == 0
    _install(
        tmp_path,
        monkeypatch,
        "msctl_greedy",
        """
        from components.kinds import ComponentKind, Placement

        KIND = ComponentKind(
            name="greedy", summary="wants more", placement=Placement.STATION, niceness=-5
        )
        """,
    )
    kinds.reset()
    with pytest.raises(
        kinds.KindError, match=r"msctl_greedy.*kind 'greedy' has niceness -5; use .* 0 .* 19"
    ):
        kinds.registry()


def test_a_kind_preloads_module_names_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fresh_registry: None
) -> None:
    # What a health monitor imports once running, the fork server imports for every worker.
    assert "psutil" in kinds.get("health_monitor").preload
    _install(
        tmp_path,
        monkeypatch,
        "msctl_sloppy",
        """
        from components.kinds import ComponentKind, Placement

        KIND = ComponentKind(
            name="sloppy", summary="a path", placement=Placement.STATION, preload=("a/b.py",)
        )
        """,
    )
    kinds.reset()
    with pytest.raises(
        kinds.KindError, match=r"msctl_sloppy.*kind 'sloppy' has preload \('a/b.py',\); use a tuple"
    ):
        kinds.registry()


def test_an_entry_point_that_is_not_a_kind_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fresh_registry: None
) -> None:
    _install(tmp_path, monkeypatch, "msctl_junk", "KIND = 'a string'\n")
    kinds.reset()
    with pytest.raises(kinds.KindError, match=r"msctl_junk.*not a ComponentKind"):
        kinds.registry()


#: Kind names compared as strings outside the registry: allowed only in these places
#: (each a kind's own declaration or builder naming itself, or the default extension target).
_KIND_LITERAL = re.compile(
    r"""kind\s*(==|!=)\s*["']|(?<!for )\bkind\s+(not\s+)?in\s+[(\[{]\s*["']"""
    r"""|["']\s*(==|!=)\s*\w*kind\b"""
)


def test_no_code_outside_the_registry_compares_kind_names() -> None:
    offenders = []
    for root in ("msctl", "components"):
        for path in sorted((REPO / root).rglob("*.py")):
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if _KIND_LITERAL.search(line) and not line.lstrip().startswith("#"):
                    text = line.strip()
                    # Not component kinds: the CLI's topic/service and urdf/mjcf switches, a
                    # QoS history kind, an interface file kind.
                    if any(w in text for w in ('"topic"', '"urdf"', "history_kind", '"srv"')):
                        continue
                    offenders.append(f"{path.relative_to(REPO)}:{number}: {text}")
    assert offenders == []
