"""Build a location publisher from its plan: which links, of which module."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent, node_name
from components.kinematics_manager.model import ModelError, module_model, mount_of
from components.location_publisher.core import LocationConfig, LocationCore, StaticEdge
from components.location_publisher.interface import location_interface


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A :class:`LocationCore` for the link(s) in ``plan.params``.

    Params: ``link`` (one link) or ``links`` (several), assembly names; without either, the
    module's interesting links and its root link. :class:`LocationConfig` fields may be given
    too.

    The publisher of the module's root link also carries its static edges on ``tf``: the mount
    joint it hangs from in the composed URDF, or, for the robot's own root, the module's
    connectors that are fixed to it, so it has something for ROS tools on ``tf`` as well.

    Raises:
        BuildError: If the module or a link is missing or a param is invalid.
    """
    if plan.module is None:
        raise BuildError(f"{plan.name}: a location publisher needs a module")
    module = assembly.module(plan.module)
    params = dict(plan.params)
    if "links" in params:
        links = list(params["links"])
    elif "link" in params:
        links = [params["link"]]
    else:
        links = list(dict.fromkeys([module.root_link, *module.interesting_links]))
    try:
        urdf = assembly.urdf_path.read_text(encoding="utf-8")
    except OSError as exc:
        raise BuildError(f"{plan.name}: cannot read {assembly.urdf_path}: {exc}") from exc
    root = module.root_link or f"{module.slot}_base_link"
    mounts = [c.joint for c in assembly.connections]
    try:
        model = module_model(urdf, root, f"{module.slot}_", stop_joints=mounts)
        edges: list[StaticEdge] = []
        if root in links:
            mount = mount_of(urdf, root)
            if mount is not None:
                edges.append(StaticEdge(mount[0], root, mount[1]))
            else:
                for link in module.connectors.values():
                    if not model.supporting_joints(link):
                        (placement,) = model.placements(model.configuration({}), [link])
                        edges.append(StaticEdge(root, link, placement))
        config = LocationConfig(
            **{k: float(v) for k, v in params.items() if k in LocationConfig.__dataclass_fields__}
        )
        core = LocationCore(plan.name, module.slot, model, links, edges, config)
    except (ModelError, KeyError, TypeError, ValueError) as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    return BuiltComponent(
        core, location_interface(core.topics), module.namespace, node_name(plan.name)
    )
