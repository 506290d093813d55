"""Injections for the Kinematics Manager: capabilities a limb is given by name from module data.

``analytic_guess``: the closed-form solutions of the chain's shape
(:mod:`components.kinematics_manager.analytic`) replace the solver's random restarts when the warm
start finds no solution within the jump bound, and the warm start itself for far targets. A
far target (a new pose picked in a GUI, a script's first target) is then solved in about one
short descent instead of five or more, and the solution is the nearest one the closed form
lists rather than the nearest of a few random ones. Named in the module type's data, so only
limbs of a known shape get it::

    injections = [{ name = "analytic_guess", component = "kinematics_manager" }]
"""

from __future__ import annotations

from typing import Any

from components.executor.registry import injection
from components.kinematics_manager.analytic import DEFAULT_SAMPLES, closed_form
from components.kinematics_manager.core import KinematicsCore

_PARAMS = {"samples"}


@injection("kinematics_manager", "analytic_guess", params={"samples": int})
def analytic_guess(core: KinematicsCore, params: dict[str, Any]) -> None:
    """Give the IK solver the closed-form first guess of the chain's shape.

    Params:
        samples: Swivel angles sampled around the shoulder-wrist line by 7-joint
            shoulder-elbow-wrist chains (default 72: every 5 degrees).

    Raises:
        ValueError: If the chain has no known closed form (the message names the joint that
            does not fit), or a parameter is unknown or out of range.
    """
    unknown = set(params) - _PARAMS
    if unknown:
        raise ValueError(
            f"analytic_guess injection: unknown parameter(s) {sorted(unknown)}; "
            f"known: {sorted(_PARAMS)}"
        )
    samples = params.get("samples", DEFAULT_SAMPLES)
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= 3600:
        raise ValueError(
            f"analytic_guess injection: samples must be a whole number from 1 to 3600, "
            f"not {samples!r}"
        )
    try:
        core.solver.guess = closed_form(core.chain, samples)
    except ValueError as exc:
        raise ValueError(f"analytic_guess injection for {core.name}: {exc}") from None
