"""Build a kinematics manager from its module's chain in the resolved assembly."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent
from components.kinematics_manager.core import KinematicsConfig, KinematicsCore
from components.kinematics_manager.interface import KINEMATICS_MANAGER
from components.kinematics_manager.model import ModelError, chain_model
from components.roles import bind


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A :class:`KinematicsCore` for the chain ``plan.params["chain"]`` of ``plan.module``.

    Plan params may also carry :class:`KinematicsConfig` and
    :class:`~components.kinematics_manager.ik.IkSettings` fields (``jump_bound``, ``budget``...).

    Raises:
        BuildError: If the module, chain or URDF do not fit together, or a param is invalid.
    """
    if plan.module is None:
        raise BuildError(f"{plan.name}: a kinematics manager needs a module")
    module = assembly.module(plan.module)
    wanted = plan.params.get("chain")
    chains = [c for c in module.chains if wanted in (None, c.name)]
    if not chains:
        raise BuildError(
            f"{plan.name}: module {module.slot} has no chain {wanted!r}; "
            f"chains: {[c.name for c in module.chains]}"
        )
    chain = chains[0]
    try:
        urdf = assembly.urdf_path.read_text(encoding="utf-8")
    except OSError as exc:
        raise BuildError(f"{plan.name}: cannot read {assembly.urdf_path}: {exc}") from exc
    try:
        model = chain_model(urdf, chain.base_link, chain.tip_link, chain.joints or None)
        config = KinematicsConfig.from_params(plan.params)
        # The solver keeps the joint manager's margin from the limits, so what it proposes
        # is what the joints do rather than a clamped variant of it.
        if "limit_margin" not in plan.params:
            manager = _joint_manager_margin(assembly, module.slot)
            if manager is not None:
                config = KinematicsConfig.from_params({**plan.params, "limit_margin": manager})
        core = KinematicsCore(plan.name, module.slot, model, config)
    except (ModelError, TypeError, ValueError) as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    # ik_target is a command input (its role): while the limb is claimed, only its holder.
    spec = bind(KINEMATICS_MANAGER, assembly, module.slot)
    return BuiltComponent(core, spec, module.namespace, "kinematics_manager")


def _joint_manager_margin(assembly: ResolvedAssembly, slot: str) -> float | None:
    """The ``position_margin`` the module's joint manager is planned with, if the plan says.

    Without one the joint manager uses its default, which :class:`IkSettings` mirrors. Only
    the joint manager's parameters have that name (its config), so no kind is named here.
    """
    for component in assembly.components:
        if component.module == slot and "position_margin" in component.params:
            margin = component.params.get("position_margin")
            return None if margin is None else float(margin)
    return None
