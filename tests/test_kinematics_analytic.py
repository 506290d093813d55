"""Closed-form first guesses of the shipped limb shapes and the solver that uses them (issue 16,
Cold IK): the guesses are exact and list what the limb can reach, a chain of another shape is
refused by name, and the solver with a guess solves at least what it solved without one, as
near the current angles, within the limits, in fewer iterations (counted, not timed).

Models come from the shipped ``minimal`` template resolved in memory, like
``test_kinematics.py``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from components.assembly import LOCK_NAME, URDF_NAME, encode_lock, load_assembly
from components.build import BuildError, build_component
from components.executor import registry as extensions
from components.kinematics_manager.analytic import ShoulderElbowWrist, closed_form
from components.kinematics_manager.core import KinematicsCore
from components.kinematics_manager.ik import IkResult, IkSettings, IkSolver
from components.kinematics_manager.injections import analytic_guess
from components.kinematics_manager.model import ChainModel, chain_model
from components.kinematics_manager.poses import apart

UNITS = {"G-line": "gl-limb-01", "H-line v1": "hlv1-limb-01", "H-line v2": "hlv2-limb-01"}
_resolved: dict[str, object] = {}


def resolution(unit: str) -> object:
    if unit not in _resolved:
        from msctl.assembler import resolve

        _resolved[unit] = resolve("minimal", {"limb1": unit})
    return _resolved[unit]


def chain_of(unit: str, tip: str = "limb1_tip_link") -> ChainModel:
    return chain_model(resolution(unit).urdf, "limb1_base_link", tip)  # type: ignore[attr-defined]


@pytest.fixture(params=sorted(UNITS), ids=sorted(UNITS))
def chain(request: pytest.FixtureRequest) -> ChainModel:
    return chain_of(UNITS[request.param])


def bend_joint3(urdf: str) -> str:
    """The URDF with limb1_joint3's origin 2 cm off its parent's x axis."""
    bent, count = re.subn(
        r'(<joint name="limb1_joint3".*?<origin xyz=")([^"]*)(")',
        r"\g<1>0.15 0 0.02\g<3>",
        urdf,
        count=1,
        flags=re.DOTALL,
    )
    assert count == 1
    return bent


def cold_cases(
    solver: IkSolver, count: int, seed: int, spread: float | None = None
) -> list[tuple[pin.SE3, np.ndarray]]:
    """(target, current): the target the tip of random angles within the limits, the current
    angles unrelated (``spread`` None) or up to ``spread`` rad from the target's per joint."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        wanted = rng.uniform(solver.lower, solver.upper)
        if spread is None:
            current = rng.uniform(solver.lower, solver.upper)
        else:
            current = solver.clamp(wanted + rng.uniform(-spread, spread, wanted.size))
        cases.append((solver.chain.tip(wanted), current))
    return cases


def on_target(chain: ChainModel, q: np.ndarray, target: pin.SE3) -> bool:
    """Within 1 mm, and 1 degree for chains of 6+ joints (the bench's acceptance)."""
    distance, angle = apart(chain.tip(q), target)
    return distance < 1e-3 and (chain.nq < 6 or math.degrees(angle) < 1.0)


def in_limits(solver: IkSolver, q: np.ndarray) -> bool:
    return bool(np.all(q >= solver.lower - 1e-12) and np.all(q <= solver.upper + 1e-12))


# ---------------------------------------------------------------------- closed forms
def test_every_closed_form_solution_puts_the_tip_on_the_target(chain: ChainModel) -> None:
    guess = closed_form(chain)
    rng = np.random.default_rng(4)
    for _ in range(20):
        target = chain.tip(rng.uniform(chain.lower, chain.upper))
        current = rng.uniform(chain.lower, chain.upper)
        solutions = guess(target, current)
        assert len(solutions) == (4 if chain.nq == 4 else 8 * 72)
        for q in solutions:
            distance, angle = apart(chain.tip(q), target)
            assert distance < 1e-9
            if chain.nq >= 6:
                assert angle < 1e-9
        if chain.nq == 4:
            # The last roll does not move the tip: it stays where it is.
            assert np.all(solutions[:, 3] == current[3])


def test_a_target_out_of_reach_has_no_closed_form_solution(chain: ChainModel) -> None:
    here = chain.tip(np.zeros(chain.nq))
    far = pin.SE3(here.rotation, here.translation * 3.0)  # the limb lies along x at zero
    assert closed_form(chain)(far, np.zeros(chain.nq)).shape == (0, chain.nq)


def test_a_chain_of_another_shape_is_refused_naming_what_does_not_fit() -> None:
    three = chain_of(UNITS["G-line"], tip="limb1_link3")  # roll, pitch, pitch: no closed form
    with pytest.raises(ValueError, match="XYY"):
        closed_form(three)
    urdf = resolution(UNITS["G-line"]).urdf  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="limb1_joint3 is not placed along"):
        closed_form(chain_model(bend_joint3(urdf), "limb1_base_link", "limb1_tip_link"))


def test_the_shoulder_swivel_is_sampled_as_asked() -> None:
    chain = chain_of(UNITS["H-line v1"])
    target = chain.tip(np.full(7, 0.3))
    few = closed_form(chain, samples=4)(target, np.zeros(7))
    assert isinstance(closed_form(chain), ShoulderElbowWrist)
    assert len(few) == 8 * 4
    with pytest.raises(ValueError, match="samples"):
        closed_form(chain, samples=0)


# ---------------------------------------------------------------------- the solver with a guess
def solvers(chain: ChainModel, **settings: float) -> tuple[IkSolver, IkSolver]:
    """(without, with) the closed-form guess, same settings and restart seed."""
    tuned = IkSettings(**settings)
    return IkSolver(chain, tuned, seed=1), IkSolver(chain, tuned, seed=1, guess=closed_form(chain))


def test_cold_targets_the_restarts_missed_within_the_budget_are_solved(chain: ChainModel) -> None:
    # One descent's worth of budget: the random restarts cannot even start, the guess
    # needs one look at the start and one polishing iteration.
    without, with_guess = solvers(chain)
    cases = cold_cases(without, 40, seed=21)
    missed = [(t, c) for t, c in cases if not without.solve(t, c, budget=40).reachable]
    assert missed, "the seed set should hold targets the warm start alone does not reach"
    for target, current in missed:
        result = with_guess.solve(target, current, budget=40)
        assert result.reachable and on_target(chain, result.q, target)
        assert in_limits(with_guess, result.q)


@pytest.mark.parametrize("spread", [None, 1.0, 1.5], ids=["unrelated", "near", "nearish"])
def test_over_a_fixed_seed_set_the_guess_solves_at_least_as_much_as_near_and_cheaper(
    chain: ChainModel, spread: float | None
) -> None:
    without, with_guess = solvers(chain)
    cases = cold_cases(without, 40, seed=31, spread=spread)
    before = [without.solve(t, c) for t, c in cases]
    after = [with_guess.solve(t, c) for t, c in cases]

    def solved(results: list[IkResult]) -> int:
        return sum(on_target(chain, r.q, t) for r, (t, _) in zip(results, cases, strict=True))

    def within_bound(results: list[IkResult]) -> int:
        bound = without.settings.jump_bound
        return sum(r.reachable and r.jump <= bound for r in results)

    assert solved(after) >= solved(before)
    assert solved(after) == len(cases)
    assert within_bound(after) >= within_bound(before)
    assert sum(r.jump for r in after) <= sum(r.jump for r in before)
    assert sum(r.iterations for r in after) < sum(r.iterations for r in before)
    for result in after:
        assert in_limits(with_guess, result.q)
        # What it reports is what the angles do.
        distance, angle = apart(chain.tip(result.q), result.pose)
        assert distance < 1e-9 and angle < 1e-9


def test_a_near_target_still_takes_the_warm_start(chain: ChainModel) -> None:
    without, with_guess = solvers(chain)
    current = np.clip(np.full(chain.nq, 0.4), with_guess.lower, with_guess.upper)
    target = chain.tip(current + 0.05)
    guessed = with_guess.solve(target, current)
    assert guessed.attempts == 1 and guessed.reachable
    np.testing.assert_array_equal(guessed.q, without.solve(target, current).q)


def test_a_far_target_goes_to_the_guess_first() -> None:
    chain = chain_of(UNITS["H-line v1"])
    _, with_guess = solvers(chain)
    current = np.zeros(7)
    wanted = np.array([1.0, -0.8, 1.2, 1.5, -1.0, 0.7, 2.0])
    result = with_guess.solve(chain.tip(wanted), current)
    # A look from the start (far: given up), then the nearest guess, exact: one iteration.
    assert result.reachable and result.attempts == 2 and result.iterations == 2
    assert on_target(chain, result.q, chain.tip(wanted))
    # Given up only past far_target: with it farther than the target, the warm start runs.
    _, patient = solvers(chain, far_target=10.0)
    assert patient.solve(chain.tip(wanted), current).iterations > 2


def test_an_unreachable_target_with_a_guess_still_moves_within_the_bound(
    chain: ChainModel,
) -> None:
    _, with_guess = solvers(chain, jump_bound=0.5)
    current = np.clip(np.full(chain.nq, 0.3), with_guess.lower, with_guess.upper)
    here = chain.tip(current)
    far = pin.SE3(here.rotation, here.translation * 4.0)
    result = with_guess.solve(far, current)
    assert not result.reachable
    assert result.jump <= 0.5 + 1e-9
    assert apart(result.pose, far)[0] < apart(here, far)[0]


def test_far_target_must_be_positive() -> None:
    with pytest.raises(ValueError, match="far_target"):
        IkSettings(far_target=0.0)


# ---------------------------------------------------------------------- the injection
def test_the_shipped_limbs_kinematics_managers_get_the_guess_from_module_data(
    tmp_path: Path,
) -> None:
    from msctl.assembler.store import write_assembly

    for label, unit in UNITS.items():
        resolved = resolution(unit)
        home = tmp_path / unit
        write_assembly(
            home,
            {URDF_NAME: resolved.urdf, LOCK_NAME: encode_lock(resolved.lock)},  # type: ignore[attr-defined]
        )
        assembly = load_assembly(home)
        plan = assembly.component("limb1/kinematics_manager")
        assert plan.params["injections"] == [{"name": "analytic_guess"}], label
        built = build_component(plan, assembly)
        try:
            assert built.core.solver.guess is not None, label
        finally:
            built.close()


def test_the_injection_checks_its_parameters_and_the_chain() -> None:
    extensions.check("injection", "kinematics_manager", {"name": "analytic_guess", "samples": 36})
    with pytest.raises(extensions.RegistryError, match="samples"):
        extensions.check(
            "injection", "kinematics_manager", {"name": "analytic_guess", "samples": "many"}
        )
    core = KinematicsCore("limb1/kinematics_manager", "limb1", chain_of(UNITS["H-line v1"]))
    with pytest.raises(ValueError, match="samples must be"):
        analytic_guess(core, {"samples": 0})
    with pytest.raises(ValueError, match="unknown parameter"):
        analytic_guess(core, {"sample": 36})
    analytic_guess(core, {"samples": 12})
    assert isinstance(core.solver.guess, ShoulderElbowWrist)
    short = KinematicsCore(
        "limb1/kinematics_manager", "limb1", chain_of(UNITS["G-line"], tip="limb1_link3")
    )
    with pytest.raises(ValueError, match=r"limb1/kinematics_manager.*XYY"):
        analytic_guess(short, {})


def test_a_module_naming_the_guess_for_a_chain_of_another_shape_fails_its_build(
    tmp_path: Path,
) -> None:
    from msctl.assembler.store import write_assembly

    resolved = resolution(UNITS["G-line"])
    urdf = bend_joint3(resolved.urdf)  # type: ignore[attr-defined]
    write_assembly(tmp_path, {URDF_NAME: urdf, LOCK_NAME: encode_lock(resolved.lock)})  # type: ignore[attr-defined]
    assembly = load_assembly(tmp_path)
    with pytest.raises(BuildError, match=r"limb1/kinematics_manager.*analytic_guess.*limb1_joint3"):
        build_component(assembly.component("limb1/kinematics_manager"), assembly)
