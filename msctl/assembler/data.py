"""Static data: module types, assembly templates and physical units, loaded and checked.

This is where the rest of msctl reads the assembler's inputs. Each file is decoded into its
typed model (:mod:`msctl.assembler.models`) and then checked across fields and files; every
problem is raised as an :class:`~msctl.errors.InputError` or
:class:`~msctl.errors.NotFoundError` naming the file, the field and the fix. Parsed files are
cached by modification time, so resolving again in the same process only stats them.

Where the data lives: the ``assemblies`` and ``calibration`` packages shipped with msctl, or the
directories named by ``MSCTL_ASSEMBLIES_DIR`` and ``MSCTL_CALIBRATION_DIR`` (a field team may
keep its calibration in its own repository).

The work is done by one module per file kind: :mod:`~msctl.assembler.module_types`,
:mod:`~msctl.assembler.templates` (with :mod:`~msctl.assembler.stations`) and
:mod:`~msctl.assembler.units`; :mod:`~msctl.assembler.files` finds and caches the files.
"""

from __future__ import annotations

from msctl.assembler.files import (
    assemblies_dir,
    calibration_dir,
    clear_cache,
    modules_dir,
    read_toml,
)
from msctl.assembler.models import HOST_RE, NAME_RE
from msctl.assembler.module_types import (
    CONTROL_MODES,
    MAX_EFFORT,
    MAX_VELOCITY,
    TYPE_TRAVEL,
    ComponentDef,
    JointDef,
    ModuleType,
    load_module_type,
    module_type_names,
)
from msctl.assembler.stations import StationDef
from msctl.assembler.templates import (
    CLAIM_POLICIES,
    NETWORK_KEYS,
    OPERATOR_TIMEOUT,
    TEMPLATE_SAFETY_KEYS,
    ConnectionDef,
    SlotDef,
    Template,
    load_template,
    template_names,
)
from msctl.assembler.units import (
    SERIAL_RE,
    JointCalibrationDef,
    Unit,
    check_unit,
    load_unit,
    merged_bus,
    unit_exists,
    unit_serials,
    units_searched,
)

__all__ = [
    "CLAIM_POLICIES",
    "CONTROL_MODES",
    "HOST_RE",
    "MAX_EFFORT",
    "MAX_VELOCITY",
    "NAME_RE",
    "NETWORK_KEYS",
    "OPERATOR_TIMEOUT",
    "SERIAL_RE",
    "TEMPLATE_SAFETY_KEYS",
    "TYPE_TRAVEL",
    "ComponentDef",
    "ConnectionDef",
    "JointCalibrationDef",
    "JointDef",
    "ModuleType",
    "SlotDef",
    "StationDef",
    "Template",
    "Unit",
    "assemblies_dir",
    "calibration_dir",
    "check_unit",
    "clear_cache",
    "load_module_type",
    "load_template",
    "load_unit",
    "merged_bus",
    "module_type_names",
    "modules_dir",
    "read_toml",
    "template_names",
    "unit_exists",
    "unit_serials",
    "units_searched",
]
