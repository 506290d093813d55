"""The MuJoCo model of a resolved assembly, through MuJoCo's own URDF import.

The composed URDF is imported with static bodies kept (connectors and limb tips stay bodies
that kinematics and the simulator can find by their URDF link names), then edited:

- mobile assemblies get a free joint on each robot's root body, lifted so its lowest geom
  rests on the ground; fixed ones are welded to the world at the template's place;
- a ground plane and a light;
- one actuator per actuated joint, named like the joint: a position servo (``kp``, ``kv``) or,
  for velocity-controlled joints (wheels), a velocity servo, with force range = max effort;
- robot geoms collide with the ground only (no self-collision: modules are bolted together and
  their primitive shapes touch at every connector).

Gains are chosen so a joint saturates at max effort ``SATURATION`` away from its target, with a
0.1 s damping time constant, capped by what a 2 ms step can hold for the joint's own inertia
(``STABLE_DAMPING``): the implicit-fast integrator treats a servo's damping implicitly only
while its force is inside the force range. At the range's end (a move at max effort) the
damping is explicit, and a light joint's (a 0.11 kg finger with kv = 400 N s/m: kv dt / m =
7.3, stable only below 2) flips its velocity every step, the force banging between its two
limits: the finger then held wherever it was, 4-9 mm short of its target.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from msctl.errors import InputError

#: Position error at which a position servo reaches max effort (rad, or m for prismatic).
SATURATION = {"revolute": 0.05, "continuous": 0.05, "prismatic": 0.01}
#: Damping time constant of position servos (kv = TIME_CONSTANT * kp), seconds.
TIME_CONSTANT = 0.1
#: Largest kv * timestep / inertia of a position servo: explicit damping is stable below 2, and
#: at its force limit a servo's damping is explicit (see the module's description).
STABLE_DAMPING = 1.5
#: Velocity servos reach max effort at this fraction of max velocity off target.
VELOCITY_SATURATION = 0.2
#: Height of a mobile robot's lowest geom above the ground at the start (m).
CLEARANCE = 0.002

_COMPILER = (
    '<mujoco><compiler fusestatic="false" discardvisual="true" strippath="true" '
    'balanceinertia="true"/></mujoco>'
)


def build_mjcf(document: Mapping[str, Any], urdf: str) -> str:
    """MJCF text for a lock document and its composed URDF.

    Raises:
        InputError: If MuJoCo rejects the model (the message says which part).
    """
    import mujoco

    head, sep, rest = (
        urdf.partition(
            ">\n",
        )
        if urdf.startswith("<?xml")
        else ("", "", urdf)
    )
    start = rest.index(">", rest.index("<robot")) + 1
    urdf_for_mujoco = head + sep + rest[:start] + _COMPILER + rest[start:]
    try:
        spec = mujoco.MjSpec.from_string(urdf_for_mujoco)
    except Exception as exc:  # MuJoCo raises ValueError with its parser's message
        raise InputError(
            f"MuJoCo cannot import the composed URDF of {document['template']}: {exc}"
        ) from exc
    spec.modelname = document["template"]
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.timestep = 0.002

    joints = {j["name"]: j for m in document["modules"] for j in m["joints"]}
    for joint in spec.joints:
        plan = joints.get(joint.name)
        if plan is not None:
            joint.armature = plan["armature"]
    for geom in spec.geoms:
        # Collide with the ground only: (contype & other.conaffinity) is zero robot-to-robot.
        geom.contype, geom.conaffinity = 1, 0

    world = spec.worldbody
    ground = world.add_geom()
    ground.name = "ground"
    ground.type = mujoco.mjtGeom.mjGEOM_PLANE
    ground.size = [0.0, 0.0, 0.05]
    ground.contype, ground.conaffinity = 0, 1
    ground.rgba = [0.35, 0.33, 0.3, 1.0]
    light = world.add_light()
    light.pos = [0.0, 0.0, 4.0]
    light.dir = [0.0, 0.0, -1.0]

    tops = list(world.bodies)
    robots = document.get("robots", [])
    if len(robots) == 1 and len(tops) == 1:
        # One robot: its root link is the top body; the template's place puts it in the world.
        from msctl.assembler.transforms import rpy_matrix

        tops[0].pos = list(robots[0]["xyz"])
        tops[0].quat = _quat(rpy_matrix(*robots[0]["rpy"]))
    if document["mobile"]:
        for body in tops:
            # Named after the body it frees, so tools can find the floating base by name.
            body.add_freejoint(name=f"{body.name}_floating")

    for name, plan in joints.items():
        if not plan["actuated"]:
            continue
        act = spec.add_actuator()
        act.name = name
        act.target = name
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        effort = plan["max_effort"]
        if plan["control"] == "velocity":
            act.set_to_velocity(kv=effort / (VELOCITY_SATURATION * plan["max_velocity"]))
            act.ctrlrange = [-plan["max_velocity"], plan["max_velocity"]]
        else:
            kp = effort / SATURATION.get(plan["type"], 0.1)
            act.set_to_position(kp=kp, kv=TIME_CONSTANT * kp)
            if plan["lower"] is not None and plan["upper"] is not None:
                act.ctrlrange = [plan["lower"], plan["upper"]]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-effort, effort]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE

    model = _compile(spec, document)
    _cap_damping(spec, model)
    model = _compile(spec, document)
    if document["mobile"]:
        lows = _lowest_points(model)
        for index, body in enumerate(tops, start=1):  # body ids: world is 0, tops follow
            low = lows.get(model.body(body.name).id if body.name else index)
            if low is not None:
                body.pos = [body.pos[0], body.pos[1], body.pos[2] - low + CLEARANCE]
        _compile(spec, document)
    return spec.to_xml()


def _cap_damping(spec: Any, model: Any) -> None:
    """Lower each position servo's kv to what a time step holds for its joint's inertia
    (:data:`STABLE_DAMPING`); kp stays, so the joint still saturates where it did."""
    for act in spec.actuators:
        kv = -act.biasprm[2]
        if act.biasprm[1] == 0.0 or kv <= 0.0:
            continue  # a velocity servo: no position gain to keep a damping ratio for
        joint = model.actuator(act.name).trnid[0]
        inertia = float(model.dof_M0[model.jnt_dofadr[joint]])
        stable = STABLE_DAMPING * inertia / model.opt.timestep
        if kv > stable:
            bias = list(act.biasprm)
            bias[2] = -stable
            act.biasprm = bias


def _compile(spec: Any, document: Mapping[str, Any]) -> Any:
    try:
        return spec.compile()
    except Exception as exc:
        raise InputError(f"MuJoCo rejects the model of {document['template']}: {exc}") from exc


def _lowest_points(model: Any) -> dict[int, float]:
    """Lowest world z of the geoms of each top-level body's subtree, at the initial pose."""
    import mujoco
    import numpy as np

    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    lows: dict[int, float] = {}
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        root = int(model.body_rootid[model.geom_bodyid[g]])
        if root == 0:
            continue
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        rot = data.geom_xmat[g].reshape(3, 3)
        z = data.geom_xpos[g][2] + rot[2] @ center - np.abs(rot[2]) @ half
        lows[root] = min(lows.get(root, math.inf), float(z))
    return lows


def _quat(r: tuple) -> list[float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    trace = r[0][0] + r[1][1] + r[2][2]
    if trace > 0:
        s = math.sqrt(trace + 1.0) * 2
        q = [0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2]) * 2
        q = [(r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    elif r[1][1] > r[2][2]:
        s = math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2]) * 2
        q = [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s]
    else:
        s = math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1]) * 2
        q = [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s]
    return q
