"""The shipped data is right: every shipped unit resolves in every slot of every template it
fits, each component of its module builds (with its injections and overrides applied), and
the assembly's MuJoCo model loads."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import mujoco
import pytest

from components.assembly import LOCK_NAME, URDF_NAME, encode_lock, load_assembly
from components.build import build_component
from msctl.assembler import data, resolve
from msctl.assembler.store import write_assembly


def _placements() -> Iterator[tuple[str, str, dict[str, str]]]:
    """(unit, template, --use choices) for every slot each unit fits."""
    for serial in data.unit_serials():
        unit = data.load_unit(serial)
        for name in data.template_names():
            template = data.load_template(name)
            for slot in template.slots:
                if unit.module_type not in slot.fits:
                    continue
                uses = {slot.name: serial}
                # The unit may be another slot's default: that slot takes this one's.
                for other in template.slots:
                    if other.name != slot.name and other.default == serial:
                        if slot.default is None:
                            break
                        uses[other.name] = slot.default
                else:
                    yield serial, name, uses


PLACEMENTS = list(_placements())


def test_every_shipped_unit_has_somewhere_to_go() -> None:
    placed = {serial for serial, _, _ in PLACEMENTS}
    assert placed == set(data.unit_serials())


@pytest.mark.parametrize(
    ("serial", "template", "uses"),
    PLACEMENTS,
    ids=[f"{s}-in-{t}.{next(iter(u))}" for s, t, u in PLACEMENTS],
)
def test_unit_resolves_and_its_components_build(
    serial: str, template: str, uses: dict[str, str], tmp_path: Path
) -> None:
    resolution = resolve(template, uses)
    files = {URDF_NAME: resolution.urdf, LOCK_NAME: encode_lock(resolution.lock)}
    write_assembly(tmp_path, files)
    assembly = load_assembly(tmp_path)
    (slot,) = [s for s, u in uses.items() if u == serial]
    module = assembly.module(slot)
    assert module.unit == serial
    checked: list[str] = []
    for plan in assembly.components:
        if plan.module != slot:
            continue
        # The motor interface too: it builds its backend from the bus plan, and opens the
        # bus only when it starts.
        built = build_component(plan, assembly)
        built.close()
        checked.append(plan.kind)
    assert {"joint_manager", "motor_interface"} <= set(checked), checked


@pytest.mark.parametrize("template", data.template_names())
def test_each_template_with_its_defaults_loads_in_mujoco(template: str) -> None:
    model = mujoco.MjModel.from_xml_string(resolve(template).mjcf())
    assert model.njnt > 0
