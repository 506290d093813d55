"""Kinematics benchmark: IK solves per second per limb, ours against a bare Pinocchio loop.

Run ``python bench/kinematics.py`` (about 20 s). For each limb type (H-line 7 joints, G-line
4 joints, resolved in memory from the ``minimal`` template) it draws targets as the forward
kinematics of random joint vectors within the limits and measures, in the same run and on
the same model, targets and tolerance:

1. **Bare loop**: a minimal hand-written Pinocchio damped-least-squares loop (the classic
   ``log6`` / ``Jlog6`` iteration: no limits, no restarts, no unwrap, no step control), from
   the same start as ours, up to the same iteration cap of one descent.
2. **Ours**: :class:`components.kinematics_manager.ik.IkSolver` with its default settings (limits
   with margin, LM damping, restarts within the budget, unwrap, jump bound), given what the
   limb's module data gives its kinematics manager: the ``analytic_guess`` injection (the
   closed-form solutions of the limb's shape seed far targets). ``--no-guess`` measures the
   solver without it (random restarts only: the figures before issue 16).

Two scenarios:

* **tracking**: the start is the target's joint vector plus noise (0.05 rad): what a limb
  following a stream of targets (teleop, an IK syncer) sees.
* **cold**: the start is an unrelated random configuration (a far target).

"Rate" is solves per second over all targets, failures included; "ok" counts the solutions
within 1 mm and 1 degree of the target (orientation for 6+ joints only). The two loops do not
do the same work, and the table shows where:

* The bare loop ignores the joint limits: in the cold scenario most of its "ok" solutions are
  outside them (column "bare ok in limits"), where the limb cannot go. Ours never returns an
  angle outside the limits (minus margin).
* The bare loop takes whatever solution its descent lands on; ours looks for the one nearest
  the current angles (the jump bound), so a far target costs it more than one descent.
* A failed bare solve costs the full iteration cap, a success returns early, so its rate
  counts failures at their cost. "ok/s ours/bare" divides successes per second (ours by the
  bare loop's, all its successes counted, in limits or not).

Targets (issue 16): tracking rate of ours >= 0.7x the bare loop and > 2,000 solves/s (7-joint
limb); cold rate of ours >= 0.3x the bare loop with at least its success count.

Syncer step overhead (:func:`bench_syncer_step`): the per-call cost of the joint syncer's
planner and of one joint / IK syncer tick (state, plan, IK, serialized ``joint_set``), against
a bare numpy clip step in the same run.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table

from components.kinematics_manager.core import KinematicsConfig, KinematicsCore
from components.kinematics_manager.ik import IkSettings, IkSolver
from components.kinematics_manager.model import ChainModel, chain_model

LIMBS = {"H-line (7 joints)": "hlv1-limb-01", "G-line (4 joints)": "gl-limb-01"}


def bare_dls(
    chain: ChainModel, settings: IkSettings
) -> Callable[[pin.SE3, np.ndarray], tuple[np.ndarray, bool]]:
    """The reference: the textbook Pinocchio DLS loop, as one would write it by hand."""
    model, data, frame = chain.model, chain.data, chain.tip_frame
    position_only = chain.nq < 6
    pos_tol, rot_tol = settings.position_tolerance, settings.orientation_tolerance
    iterations = settings.iterations
    eye = np.eye(3 if position_only else 6)
    damping = 1e-6

    def solve(target: pin.SE3, q: np.ndarray) -> tuple[np.ndarray, bool]:
        q = q.copy()
        for _ in range(iterations):
            pin.forwardKinematics(model, data, q)
            tip = pin.updateFramePlacement(model, data, frame)
            if position_only:
                err = target.translation - tip.translation
                if np.linalg.norm(err) < pos_tol:
                    return q, True
                pin.computeJointJacobians(model, data, q)
                J = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)[:3]
            else:
                gap = tip.actInv(target)
                err = pin.log6(gap).vector
                offset = np.linalg.norm(target.translation - tip.translation)
                if offset < pos_tol and np.linalg.norm(err[3:]) < rot_tol:
                    return q, True
                J = pin.Jlog6(gap.inverse()) @ pin.computeFrameJacobian(
                    model, data, q, frame, pin.LOCAL
                )
            q = q + J.T @ np.linalg.solve(J @ J.T + damping * eye, err)
        return q, False

    return solve


def product_solver(document: dict, chain: ChainModel, guess: bool = True) -> IkSolver:
    """The solver limb1's kinematics manager runs: default settings, the module data's
    injections applied (``guess=False``: none), restarts seeded with 1."""
    from components.assembly import from_document
    from components.executor.registry import apply_all

    core = KinematicsCore("limb1/kinematics_manager", "limb1", chain, KinematicsConfig(), seed=1)
    if guess:
        plan = from_document(document).component("limb1/kinematics_manager")
        apply_all(core, "kinematics_manager", plan.params.get("injections", ()))
    return core.solver


def make_cases(
    solver: IkSolver, count: int, noise: float | None, seed: int
) -> list[tuple[pin.SE3, np.ndarray]]:
    """(target, start) pairs: near the target's configuration (noise) or unrelated (None)."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        wanted = rng.uniform(solver.lower, solver.upper)
        if noise is None:
            start = rng.uniform(solver.lower, solver.upper)
        else:
            start = np.clip(
                wanted + rng.normal(0.0, noise, wanted.size), solver.lower, solver.upper
            )
        cases.append((solver.chain.tip(wanted), start))
    return cases


def within(chain: ChainModel, q: np.ndarray, target: pin.SE3) -> bool:
    """The acceptance test of the issue: 1 mm, and 1 degree for chains of 6+ joints."""
    tip = chain.tip(q)
    if np.linalg.norm(tip.translation - target.translation) >= 1e-3:
        return False
    if chain.nq < 6:
        return True
    return math.degrees(np.linalg.norm(pin.log3(tip.rotation.T @ target.rotation))) < 1.0


def in_limits(solver: IkSolver, q: np.ndarray) -> bool:
    """Whether ``q`` is within the joint limits (the limb can go there at all)."""
    chain = solver.chain
    return bool(np.all(q >= chain.lower) and np.all(q <= chain.upper))


def timed(
    solvers: dict[str, Callable[[pin.SE3, np.ndarray], np.ndarray]],
    solver: IkSolver,
    cases: list[tuple[pin.SE3, np.ndarray]],
    repeats: int,
) -> dict[str, tuple[float, int, int]]:
    """Best-of-``repeats`` solves per second of each solver over ``cases``, how many met the
    tolerance, and how many of those are within the joint limits. Passes alternate between
    the solvers, so a busy machine slows both alike."""
    best = dict.fromkeys(solvers, math.inf)
    ok = dict.fromkeys(solvers, 0)
    ok_in_limits = dict.fromkeys(solvers, 0)
    for _ in range(repeats):
        for name, solve in solvers.items():
            began = time.perf_counter()
            solutions = [solve(target, start) for target, start in cases]
            best[name] = min(best[name], time.perf_counter() - began)
            good = [
                q for q, (t, _) in zip(solutions, cases, strict=True) if within(solver.chain, q, t)
            ]
            ok[name] = len(good)
            ok_in_limits[name] = sum(in_limits(solver, q) for q in good)
    return {name: (len(cases) / best[name], ok[name], ok_in_limits[name]) for name in solvers}


def bench_ik(count: int, repeats: int, guess: bool = True) -> list[list[object]]:
    """IK solves/s per limb and scenario, bare loop vs ours."""
    from msctl.assembler import resolve

    rows: list[list[object]] = []
    for label, unit in LIMBS.items():
        resolved = resolve("minimal", {"limb1": unit})
        chain = chain_model(resolved.urdf, "limb1_base_link", "limb1_tip_link")
        solver = product_solver(resolved.document, chain, guess)
        bare = bare_dls(chain, solver.settings)
        for scenario, noise in (("tracking", 0.05), ("cold", None)):
            cases = make_cases(solver, count, noise, seed=11)
            rates = timed(
                {
                    "bare": lambda t, s, bare=bare: bare(t, s)[0],
                    "ours": lambda t, s, solver=solver: solver.solve(t, s).q,
                },
                solver,
                cases,
                repeats,
            )
            (bare_rate, bare_ok, bare_in), (ours_rate, ours_ok, _) = rates["bare"], rates["ours"]
            ok_ratio = (ours_rate * ours_ok) / (bare_rate * bare_ok) if bare_ok else math.inf
            rows.append(
                [
                    label,
                    scenario,
                    f"{bare_rate:,.0f}",
                    f"{bare_ok}/{count}",
                    f"{bare_in}/{count}",
                    f"{ours_rate:,.0f}",
                    f"{ours_ok}/{count}",
                    f"{ours_rate / bare_rate:.2f}x",
                    f"{ok_ratio:.2f}x",
                ]
            )
    return rows


class _Recorder:
    """A publisher that serializes what it is given (the real CDR cost) and keeps nothing."""

    def __init__(self) -> None:
        from components.comm.types import registry
        from components.messages import JOINT_STATE

        self._serialize = registry().serializer(JOINT_STATE)
        self.bytes = 0

    def publish(self, message: object) -> None:
        self.bytes += len(self._serialize(message))

    def close(self) -> None:
        pass


class _Node:
    """Just enough of a comm Node for a JointHandler: publishers serialize, no Zenoh."""

    def publisher(self, _topic: str, _type: str) -> _Recorder:
        return _Recorder()

    def subscription(self, _topic: str, _type: str, _callback: object) -> _Recorder:
        return _Recorder()


def _per_call(step: Callable[[int], object], calls: int, repeats: int) -> float:
    """Best-of-``repeats`` microseconds per call of ``step(i)``."""
    best = math.inf
    for _ in range(repeats):
        began = time.perf_counter()
        for i in range(calls):
            step(i)
        best = min(best, time.perf_counter() - began)
    return best / calls * 1e6


def bench_syncer_step(calls: int = 2000, repeats: int = 5) -> list[list[object]]:
    """Syncer step overhead per call, against a bare numpy step in the same run.

    Per limb type, with no I/O (a handler whose publisher serializes the CDR and drops it):

    * **bare numpy**: ``np.clip(target, measured - delta, measured + delta)``, the least a
      bounded step can cost;
    * **planner lerp**: :meth:`SyncPlanner.step` (ball, line, speed cap, limits, arrival);
    * **joint tick**: one :class:`JointSyncer` tick as it runs: read the latest states from
      the handler, plan, build and serialize ``joint_set``;
    * **IK tick**: one :class:`IkSyncer` tick: FK of the measured joints, the waypoint on the
      line, one warm-started IK solve, the joint step, ``joint_set``;
    * **IK solve alone**: the same solve from the same start, for reference.

    The target moves each call (a tracking motion), so nothing is solved twice.
    """
    rows: list[list[object]] = []
    for label, unit in LIMBS.items():
        rows.extend(_syncer_rows(label, unit, calls, repeats))
    return rows


def _syncer_rows(label: str, unit: str, calls: int, repeats: int) -> list[list[object]]:
    """:func:`bench_syncer_step` for one limb type."""
    from components.api.ik_syncer import IkSyncer, Line
    from components.api.joints import JointHandler, JointInfo, JointState
    from components.api.planner import LERP, SyncPlanner, SyncSettings
    from components.api.syncer import JointSyncer
    from components.assembly import from_document
    from msctl.assembler import resolve

    rows: list[list[object]] = []
    resolved = resolve("minimal", {"limb1": unit})
    module = from_document(resolved.document).module("limb1")
    chain_plan = module.chains[0]
    chain = chain_model(resolved.urdf, chain_plan.base_link, chain_plan.tip_link)
    names = list(chain.joint_names)
    infos = [
        JointInfo(j.name, j.spec.type, j.spec.lower, j.spec.upper, j.spec.max_velocity,
                  j.spec.max_effort)
        for j in module.joints
        if j.name in names
    ]  # fmt: skip
    handler = JointHandler(_Node(), "limb1", infos)
    rng = np.random.default_rng(3)
    lower = np.array([i.lower for i in infos]) + 0.1
    upper = np.array([i.upper for i in infos]) - 0.1
    home = rng.uniform(lower, upper) * 0.3
    now = time.monotonic()
    handler._states = {
        n: JointState(float(q), 0.0, 0.0, now) for n, q in zip(names, home, strict=True)
    }
    settings = SyncSettings()
    targets = [home + rng.normal(0.0, 0.3, home.size) for _ in range(64)]
    measured = home.copy()
    delta = settings.delta

    def bare(i: int) -> object:
        return np.clip(targets[i % 64], measured - delta, measured + delta)

    planner = SyncPlanner(
        names, [i.lower for i in infos], [i.upper for i in infos],
        [i.max_velocity for i in infos], settings,
    )  # fmt: skip

    def plan(i: int) -> object:
        return planner.step(LERP, measured, settings.period, target=targets[i % 64])

    syncer = JointSyncer([handler], settings)
    tick_planner = syncer.planner(names)

    def joint_tick(i: int) -> None:
        current = syncer.measured(names)
        q = np.array([current[n] for n in names])
        step = tick_planner.step(LERP, q, settings.period, target=targets[i % 64])
        syncer.send(names, step.command)

    ik = IkSyncer([(handler, chain_plan)], resolved.urdf)
    limb = ik.limbs["limb1"]
    tip = limb.solver.chain.tip(home)
    goals = [pin.SE3(tip.rotation, tip.translation + rng.normal(0.0, 0.03, 3)) for _ in range(64)]

    def ik_tick(i: int) -> None:
        limb.last_q = None
        ik.step("lerp", {"limb1": Line(tip, goals[i % 64])}, {}, settings.period)

    # The waypoints a tick solves: one step of the line at the syncer's tip speed.
    reach = ik.settings.speed * settings.period
    waypoints = [
        Line(tip, g).at(min(1.0, reach / float(np.linalg.norm(g.translation - tip.translation))))
        for g in goals
    ]

    def ik_alone(i: int) -> object:
        return limb.solver.solve(waypoints[i % 64], home, budget=ik.settings.ik_budget)

    base = _per_call(bare, calls, repeats)
    for what, step, count in (
        ("bare numpy clip", bare, calls),
        ("planner lerp step", plan, calls),
        ("JointSyncer tick (state, plan, joint_set)", joint_tick, calls),
        ("IkSyncer tick (FK, waypoint, IK, plan, joint_set)", ik_tick, calls // 4),
        ("IK solve alone (same waypoint, same start)", ik_alone, calls // 4),
    ):
        micros = base if step is bare else _per_call(step, count, repeats)
        rows.append([label, what, f"{micros:,.1f}", f"{micros / base:,.1f}x"])
    return rows


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print its tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=400, help="targets per limb and scenario")
    parser.add_argument("--repeats", type=int, default=5, help="best of this many passes")
    parser.add_argument(
        "--no-guess",
        action="store_true",
        help="ours without the module data's analytic_guess injection (random restarts only)",
    )
    parser.add_argument("--ik-only", action="store_true", help="skip the syncer step table")
    args = parser.parse_args(argv)
    rows = bench_ik(args.count, args.repeats, guess=not args.no_guess)
    print_table(
        "IK solves per second (same model, targets, start and tolerance; best of passes)"
        + (" - ours WITHOUT the analytic guess" if args.no_guess else ""),
        [
            "limb",
            "scenario",
            "bare DLS/s",
            "bare ok",
            "bare ok in limits",
            "ours/s",
            "ours ok",
            "ours/bare",
            "ok/s ours/bare",
        ],
        rows,
    )
    if args.ik_only:
        return 0
    print_table(
        "Syncer step overhead per call (no I/O; a 40 Hz syncer has 25,000 µs per tick)",
        ["limb", "what", "µs per call", "vs bare"],
        bench_syncer_step(repeats=args.repeats),
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
