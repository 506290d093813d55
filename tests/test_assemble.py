"""The Robot Assembler on the shipped data: every template resolves into models that Pinocchio,
yourdfpy and MuJoCo accept, with the joints, actuators, chains and components expected."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from components.assembly import (
    LOCK_NAME,
    MJCF_NAME,
    URDF_NAME,
    AssemblyError,
    ResolvedAssembly,
    encode_lock,
    from_document,
    load_assembly,
)
from msctl.assembler import data, resolve
from msctl.assembler.store import write_assembly

TEMPLATES = ["minimal", "dragon", "dragon_x4", "tricycle", "two_dragons"]


@pytest.fixture(autouse=True)
def isolated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Never touch the real home; always the shipped data."""
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("MSCTL_ASSEMBLIES_DIR", raising=False)
    monkeypatch.delenv("MSCTL_CALIBRATION_DIR", raising=False)
    return tmp_path / "home"


_written: dict[str, tuple[ResolvedAssembly, str]] = {}


@pytest.fixture(scope="module")
def resolved(tmp_path_factory: pytest.TempPathFactory):
    """Resolve and write every template once for the whole module: name -> (assembly, mjcf)."""

    def get(name: str) -> tuple[ResolvedAssembly, str]:
        if name not in _written:
            resolution = resolve(name)
            mjcf = resolution.mjcf()
            target = tmp_path_factory.mktemp(name) / "assembly"
            write_assembly(
                target,
                {
                    URDF_NAME: resolution.urdf,
                    MJCF_NAME: mjcf,
                    LOCK_NAME: encode_lock(resolution.lock),
                },
            )
            _written[name] = (load_assembly(target), mjcf)
        return _written[name]

    return get


def expected_joints(assembly: ResolvedAssembly) -> int:
    return sum(len(m.joints) for m in assembly.modules)


@pytest.mark.parametrize("name", TEMPLATES)
def test_urdf_loads_in_pinocchio_and_yourdfpy(resolved, name: str) -> None:
    import pinocchio as pin
    import yourdfpy

    assembly, _ = resolved(name)
    n = expected_joints(assembly)
    model = pin.buildModelFromUrdf(str(assembly.urdf_path))
    assert model.njoints - 1 == n  # universe is joint 0; fixed joints become frames
    robot = yourdfpy.URDF.load(str(assembly.urdf_path), load_meshes=False, build_scene_graph=True)
    assert robot.validate(), robot.errors
    assert len(robot.actuated_joints) == n
    for chain in (c for m in assembly.modules for c in m.chains):
        assert model.existFrame(chain.base_link) and model.existFrame(chain.tip_link)
        assert all(model.existJointName(j) for j in chain.joints)
        # The chain really joins base to tip: its joints are the tip's ancestors after the base.
        tip_joint = model.frames[model.getFrameId(chain.tip_link)].parentJoint
        ancestors = [model.names[j] for j in model.supports[tip_joint]]
        assert ancestors[-len(chain.joints) :] == list(chain.joints)


@pytest.mark.parametrize("name", TEMPLATES)
def test_mjcf_compiles_with_one_actuator_per_actuated_joint(resolved, name: str) -> None:
    import mujoco

    assembly, mjcf = resolved(name)
    model = mujoco.MjModel.from_xml_string(mjcf)
    actuated = [j.name for m in assembly.modules for j in m.joints if j.actuated]
    names = [model.actuator(i).name for i in range(model.nu)]
    assert sorted(names) == sorted(actuated)
    for i in range(model.nu):  # each actuator drives the joint of its name
        joint_id = model.actuator_trnid[i][0]
        assert model.joint(joint_id).name == names[i]
        plan = assembly.joint(names[i])
        assert model.actuator_forcerange[i][1] == pytest.approx(plan.spec.max_effort)
    free = sum(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    assert free == (len(assembly.root_links) if assembly.mobile else 0)
    for chain in (c for m in assembly.modules for c in m.chains):
        assert model.body(chain.base_link).id > 0 and model.body(chain.tip_link).id > 0
    for module in assembly.modules:
        for link in module.connectors.values():
            assert model.body(link).id > 0
    assert assembly.mjcf_path.read_text() == mjcf


def test_dragon_rests_on_the_ground_in_simulation(resolved) -> None:
    import mujoco
    import numpy as np

    assembly, mjcf = resolved("dragon")
    model = mujoco.MjModel.from_xml_string(mjcf)
    state = mujoco.MjData(model)
    state.ctrl[:] = 0.0  # every position servo holds zero, every wheel holds still
    root = model.body(assembly.root_links[0]).id
    for _ in range(int(1.0 / model.opt.timestep)):
        mujoco.mj_step(model, state)
    assert not np.isnan(state.qpos).any()
    assert 0.05 < state.xpos[root][2] < 0.3  # on its wheels, neither sunk nor launched
    assert np.abs(state.qvel).max() < 0.05  # at rest
    assert abs(state.xpos[root][0]) < 0.01 and abs(state.xpos[root][1]) < 0.01


def test_dragon_geometry(resolved) -> None:
    """Limbs lie along x on either side of their joined bases, a wheel beyond each tip."""
    import pinocchio as pin

    assembly, _ = resolved("dragon")
    model = pin.buildModelFromUrdf(str(assembly.urdf_path))
    state = model.createData()
    pin.framesForwardKinematics(model, state, pin.neutral(model))

    def pos(link: str):
        return state.oMf[model.getFrameId(link)].translation

    assert pos("limb1_tip_link")[0] == pytest.approx(1.2)
    assert pos("limb2_tip_link")[0] == pytest.approx(-1.2)
    assert pos("wheel1_body_link")[0] > pos("limb1_tip_link")[0]
    assert pos("wheel2_body_link")[0] < pos("limb2_tip_link")[0]
    for link in ("limb2_base_link", "wheel1_body_link", "wheel2_body_link"):
        rot = state.oMf[model.getFrameId(link)].rotation
        assert rot[2][2] == pytest.approx(1.0)  # every module upright


def test_two_dragons_plan_counts_the_papers_60_components(resolved) -> None:
    assembly, _ = resolved("two_dragons")
    counts: dict[str, int] = {}
    for c in assembly.components:
        counts[c.kind] = counts.get(c.kind, 0) + 1
    assert counts == {
        "motor_interface": 8,
        "joint_manager": 8,
        "kinematics_manager": 4,
        "health_monitor": 8,
        "location_publisher": 16,
        "human_operator": 3,
        "autonomous_operator": 6,
        "data_monitor": 5,
        "data_archiver": 2,
    }
    assert len(assembly.components) == 60
    assert len({c.name for c in assembly.components}) == 60
    assert sum(len(assembly.components_on(h)) for h in assembly.hosts) == 60
    # One computer per module, and the three ground stations.
    assert len(assembly.hosts) == 8 + 3
    limb = assembly.module("d1_limb1")
    on_limb = {c.kind for c in assembly.components_on(limb.host)}
    assert on_limb == {
        "motor_interface",
        "joint_manager",
        "health_monitor",
        "location_publisher",
        "kinematics_manager",
    }
    assert len(assembly.root_links) == 2


def test_loader_exposes_the_per_host_plan(resolved) -> None:
    assembly, _ = resolved("dragon")
    limb = assembly.module("limb1")
    assert limb.namespace == "/limb1" and limb.kind == "limb" and limb.family == "H-line"
    assert limb.bus.kind == "canopen" and limb.bus.channel == "can0" and limb.bus.bitrate
    assert [j.name for j in limb.joints][:2] == ["limb1_joint1", "limb1_joint2"]
    joint = limb.joint("joint3")
    unit = data.load_unit(limb.unit)
    assert joint.calibration.zero_offset == unit.joints["joint3"].zero_offset
    assert joint.control == "position" and joint.spec.bounded
    specs = limb.motor_specs()
    assert [s.joint for s in specs] == [j.raw_name for j in limb.joints]
    assert [s.motor_id for s in specs] == list(range(1, 10))
    assert limb.calibration_file.endswith(f"{limb.unit}.toml")
    (chain,) = limb.chains
    assert (chain.base_link, chain.tip_link) == ("limb1_base_link", "limb1_tip_link")
    assert chain.joints == tuple(f"limb1_joint{i}" for i in range(1, 8))
    wheel = assembly.module("wheel1")
    assert {j.control for j in wheel.joints} == {"velocity"}
    assert math.isinf(wheel.joints[0].spec.upper)  # continuous: null in JSON, inf here
    manager = assembly.component("limb1/joint_manager")
    assert manager.host == limb.host and manager.params["joints"] == [j.name for j in limb.joints]
    assert manager.params["injections"] == [
        {"name": "rezero", "max_shift": 0.07, "max_shift_linear": 0.002}
    ]
    kin = assembly.component("limb1/kinematics_manager")
    assert kin.params["tip_link"] == "limb1_tip_link"
    ground = assembly.components_on("ground1")
    assert {c.kind for c in ground} == {"human_operator", "data_monitor"}
    assert all(c.module is None for c in ground)


def test_unit_overrides_reach_the_joint_manager() -> None:
    resolution = resolve("dragon", {"limb1": "hlv1-limb-03"})
    assembly = from_document(resolution.document)
    lock = {"name": "locked_joint", "joint": "limb1_joint5", "position": 0.0}
    assert assembly.component("limb1/joint_manager").params["overrides"] == [lock]
    # Overrides live only with the component that applies them.
    others = [c for c in assembly.components_on("hl-limb-03") if c.kind != "joint_manager"]
    assert others and not any("overrides" in c.params for c in others)


def test_g_line_dragon_shares_one_computer() -> None:
    resolution = resolve("dragon", {"limb1": "gl-limb-01", "limb2": "gl-limb-02"})
    assembly = from_document(resolution.document)
    limb1, limb2 = assembly.module("limb1"), assembly.module("limb2")
    assert limb1.host == limb2.host == "gl-pi-01"
    assert limb1.bus.kind == "dynamixel" and limb1.bus.baudrate and limb1.bus.options["protocol"]
    assert {limb1.bus.channel, limb2.bus.channel} == {"/dev/ttyUSB0", "/dev/ttyUSB1"}
    assert len(limb1.joints) == 6 and limb1.joints[0].motor_model == "XM430-W350"
    assert len(assembly.components_on("gl-pi-01")) == 12


def test_swap_changes_only_that_slot() -> None:
    first = resolve("dragon_x4").document
    second = resolve("dragon_x4", {"limb3": "hlv1-limb-04"}, previous=first["units"]).document
    assert second["units"] == {**first["units"], "limb3": "hlv1-limb-04"}
    for before, after in zip(first["modules"], second["modules"], strict=True):
        if before["slot"] != "limb3":
            assert before == after
    changed = [
        a["name"] for a, b in zip(first["components"], second["components"], strict=True) if a != b
    ]
    assert changed and all(name.startswith("limb3/") for name in changed)
    # A third resolution with no --use keeps the swap (the previous resolution wins over defaults).
    third = resolve("dragon_x4", previous=second["units"]).document
    assert third == second


def test_module_masses_and_inertias_match_their_shapes() -> None:
    """Every link's inertia is the one of its collision primitive (mass at its centre)."""
    import numpy as np

    def rpy_matrix(r: float, p: float, y: float):
        cr, sr, cp, sp, cy, sy = (
            math.cos(r),
            math.sin(r),
            math.cos(p),
            math.sin(p),
            math.cos(y),
            math.sin(y),
        )
        return np.array(
            [
                [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                [-sp, cp * sr, cp * cr],
            ]
        )

    totals = {}
    for key in data.module_type_names():
        module = data.load_module_type(key)
        total = 0.0
        for link in module.urdf.links.values():
            inertial = link.find("inertial")
            if inertial is None:
                continue
            mass = float(inertial.find("mass").get("value"))
            total += mass
            geometry = link.find("collision/geometry")[0]
            origin = link.find("collision/origin")
            if geometry.tag == "box":
                x, y, z = (float(v) for v in geometry.get("size").split())
                local = np.diag([y * y + z * z, x * x + z * z, x * x + y * y]) * mass / 12
            else:
                assert geometry.tag == "cylinder"
                r, length = float(geometry.get("radius")), float(geometry.get("length"))
                side = mass * (3 * r * r + length * length) / 12
                local = np.diag([side, side, mass * r * r / 2])
            rot = rpy_matrix(*(float(v) for v in origin.get("rpy").split()))
            expected = rot @ local @ rot.T
            i = inertial.find("inertia").attrib
            given = np.array(
                [
                    [i["ixx"], i["ixy"], i["ixz"]],
                    [i["ixy"], i["iyy"], i["iyz"]],
                    [i["ixz"], i["iyz"], i["izz"]],
                ],
                dtype=float,
            )
            assert np.allclose(given, expected, rtol=1e-5, atol=1e-9), (key, link.get("name"))
            assert inertial.find("origin").get("xyz") == origin.get("xyz")
        totals[key] = total
    assert 8.0 <= totals["hl_limb_v1"] <= 10.0 and 8.0 <= totals["hl_limb_v2"] <= 10.0
    assert totals["gl_limb"] == pytest.approx(1.5)
    assert totals["hl_wheel_v1"] == pytest.approx(5.0) == totals["hl_wheel_v2"]


def test_module_families_as_specified() -> None:
    def movable(key: str, jtype: str) -> int:
        return sum(j.type == jtype for j in data.load_module_type(key).joints.values())

    for key in ("hl_limb_v1", "hl_limb_v2"):
        assert movable(key, "revolute") == 7 and movable(key, "prismatic") == 2
        assert data.load_module_type(key).bus["kind"] == "canopen"
    assert movable("gl_limb", "revolute") == 4 and movable("gl_limb", "prismatic") == 2
    assert data.load_module_type("gl_limb").bus["kind"] == "dynamixel"
    assert movable("hl_wheel_v1", "continuous") == 2 and movable("hl_wheel_v1", "revolute") == 0
    assert movable("hl_wheel_v2", "continuous") == 2 and movable("hl_wheel_v2", "revolute") == 2


def test_urdf_is_deterministic_and_well_formed() -> None:
    a, b = resolve("dragon"), resolve("dragon")
    assert a.urdf == b.urdf and encode_lock(a.lock) == encode_lock(b.lock)
    root = ET.fromstring(a.urdf)
    names = [e.get("name") for e in root if e.tag in ("link", "joint")]
    assert len(names) == len(set(names))
    assert all(n.split("_")[0] in a.document["units"] for n in names)


def test_load_assembly_without_a_resolution_says_what_to_run(isolated: Path) -> None:
    with pytest.raises(AssemblyError, match="msctl assemble dragon"):
        load_assembly()
