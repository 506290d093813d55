"""Inverse kinematics of one limb chain: damped least squares with joint limits.

Pure numpy and Pinocchio: no clock, no I/O. The compute budget is a number of iterations
passed in, so a solve takes the same path on every machine and in every test.

How one solve goes (:meth:`IkSolver.solve`):

1. Descend from the current joint angles (warm start). Each iteration takes a damped
   least-squares step, caps its size, and clamps the angles into the limits, so the solver
   never proposes an angle the joint manager would clamp differently.
2. While the budget lasts (and fewer than ``far_solutions`` converged solutions beyond the
   jump bound were found), restart from random angles within the limits; each result is
   unwrapped toward the current angles (a revolute joint with more than a turn of range can
   reach the same pose at ``q`` and ``q + 2*pi``; the nearer one avoids a needless swing).
3. The first converged solution whose largest joint jump (from the current angles) is under
   ``jump_bound`` wins; else the converged one with the smallest jump.
4. If nothing converged the target is unreachable: descend once more from the current angles
   inside a box of ``jump_bound`` around them, and return the closest pose found within the
   bound. An unreachable target therefore moves the limb toward it, never makes it jump.

A chain of a known shape may be given a closed-form guess (:attr:`IkSolver.guess`, set by the
``analytic_guess`` injection from module data; :mod:`components.kinematics_manager.analytic`): it
lists the target's solutions (sampling any redundant direction), those within the limits are
unwrapped toward the current angles, and the nearest (smallest largest-joint jump) is polished
by a descent (the next ones should it not converge). It replaces the random restarts of step 2
when the warm start gives no converged solution within the jump bound, and it replaces the
warm start itself for a target farther than ``far_target`` from the tip: the nearest of the
listed solutions answers "is there a solution within the jump bound" far more often than a
descent from the current angles, which has to cross the distance in capped steps and then
often lands on a far solution anyway. When it lists no solution within the limits, steps 1
to 4 run as above.

Chains with fewer than 6 joints cannot hold an arbitrary orientation, so they solve for the
tip position alone and ignore the target's orientation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from components.config import require
from components.kinematics_manager.analytic import Guess
from components.kinematics_manager.model import ChainModel

_TWO_PI = 2.0 * math.pi
#: Closed-form solutions polished, nearest first, before falling back to random restarts
#: (the first converges unless it sits at a singularity).
_GUESS_TRIES = 3


@dataclass(frozen=True)
class IkSettings:
    """Tuning of the solver. Angles in rad, lengths in m.

    Attributes:
        position_tolerance: A solution is converged when the tip is this close to the target.
        orientation_tolerance: ...and, for chains of 6+ joints, its orientation this close
            (angle of the rotation between them).
        damping: Damping of the least-squares step (added to J Jᵀ); larger is steadier near
            singularities and slower to converge.
        max_step: Largest change of any joint in one iteration (larger steps are scaled down).
        reach_step: Largest tip translation (m) one iteration aims for: a farther target
            is approached in steps of this size (keeps damped least squares steady on far
            and unreachable targets).
        turn_step: Largest tip rotation (rad) one iteration aims for.
        orientation_weight: Meters one radian of orientation error counts for when poses
            are compared (which of two unreachable solutions is closer).
        iterations: Iteration cap of one descent.
        budget: Iterations shared by the warm start and the random restarts.
        jump_bound: A solution whose largest joint change exceeds this is a "jump": taken only
            when no converged solution within the bound exists, and never for an unreachable
            target.
        far_solutions: Stop restarting after this many converged solutions beyond the jump
            bound (the target is far in joint space: more restarts rarely find a near one,
            and each costs a descent), and take the one with the smallest jump.
        limit_margin: Distance kept from every joint limit (match the joint manager's
            ``position_margin`` so what IK proposes is what the joints do).
        far_target: With a closed-form guess, a target farther than this from the tip
            (m, orientation counted at ``orientation_weight``) is tried from the guess before
            the warm start: reaching it from the current angles would take many capped steps,
            and often ends at a far solution anyway.
    """

    position_tolerance: float = 1e-4
    orientation_tolerance: float = 1e-3
    damping: float = 1e-6
    max_step: float = 0.6
    reach_step: float = 0.1
    turn_step: float = 0.5
    orientation_weight: float = 0.1
    iterations: int = 40
    budget: int = 400
    jump_bound: float = 1.0
    far_solutions: int = 3
    limit_margin: float = 0.02
    far_target: float = 0.2

    def __post_init__(self) -> None:
        require(
            self,
            positive=(
                "position_tolerance",
                "orientation_tolerance",
                "max_step",
                "reach_step",
                "turn_step",
                "jump_bound",
                "iterations",
                "budget",
                "far_solutions",
                "far_target",
            ),
            non_negative=("damping", "limit_margin", "orientation_weight"),
        )


@dataclass(frozen=True)
class IkResult:
    """What a solve found.

    Attributes:
        q: Joint angles in the chain's configuration order, within the limits (minus margin).
        pose: The tip pose those angles give, in the chain's base frame.
        position_error: Distance from the tip to the target (m).
        orientation_error: Angle between the tip's and the target's orientation (rad); 0 for
            position-only chains.
        reachable: Whether the solution is within tolerance (False: closest pose found).
        jump: Largest joint change from the current angles (rad or m).
        attempts: Descents run (warm start, restarts, the bounded one).
        iterations: Iterations spent in all.
    """

    q: np.ndarray
    pose: pin.SE3
    position_error: float
    orientation_error: float
    reachable: bool
    jump: float
    attempts: int
    iterations: int


@dataclass
class _Descent:
    q: np.ndarray
    pose: pin.SE3
    position_error: float
    orientation_error: float
    converged: bool
    iterations: int
    cost: float
    #: Stopped at the start because the target was farther than asked (see ``give_up_above``).
    gave_up: bool = False


class IkSolver:
    """Damped least-squares IK with limits, restarts and a jump bound, for one chain.

    Args:
        chain: The chain's model (its data is used as scratch: one solver per chain model).
        settings: Solver tuning.
        seed: Seed of the restart generator (restarts are reproducible).
        guess: Closed-form solutions of the chain's shape, tried instead of random restarts
            (see :mod:`components.kinematics_manager.analytic`); None: random restarts only.

    Attributes:
        guess: As the argument; the ``analytic_guess`` injection sets it.
    """

    def __init__(
        self,
        chain: ChainModel,
        settings: IkSettings | None = None,
        seed: int = 0,
        guess: Guess | None = None,
    ):
        self.chain = chain
        self.guess = guess
        self.settings = settings or IkSettings()
        self.position_only = chain.nq < 6
        margin = self.settings.limit_margin
        self.lower = chain.lower + margin
        self.upper = chain.upper - margin
        if np.any(self.lower > self.upper):
            bad = [
                n
                for n, lo, hi in zip(chain.joint_names, self.lower, self.upper, strict=True)
                if lo > hi
            ]
            raise ValueError(f"joints {bad}: range narrower than twice the limit margin {margin}")
        self._rng = np.random.default_rng(seed)
        # Guessed angles lie in [-pi, pi]: whole turns matter only to a joint whose range
        # reaches beyond that.
        self._turns_matter = bool(
            np.any(chain.revolute & ((self.lower < -math.pi) | (self.upper > math.pi)))
        )
        self._identity = np.eye(3 if self.position_only else 6)
        self._least_regular = self.settings.damping * self._identity
        s = self.settings
        # Read once per descent as one tuple: a dozen attribute lookups per solve add up at
        # tens of thousands of solves per second.
        self._constants = (
            chain.model,
            chain.data,
            chain.tip_frame,
            self.position_only,
            s.position_tolerance,
            s.orientation_tolerance,
            s.max_step,
            s.reach_step,
            s.turn_step,
            self._identity,
            s.orientation_weight,
            s.damping,
        )

    def clamp(self, q: np.ndarray) -> np.ndarray:
        """``q`` clamped into the limits (minus margin)."""
        # minimum/maximum: a third of np.clip's overhead on arrays of a few joints.
        return np.minimum(np.maximum(q, self.lower), self.upper)

    def solve(self, target: pin.SE3, current: np.ndarray, budget: int | None = None) -> IkResult:
        """Joint angles putting the tip at ``target`` (in the base frame), near ``current``.

        Args:
            target: Desired tip pose in the chain's base frame (orientation ignored for
                chains of fewer than 6 joints).
            current: The joints' current angles (warm start and reference for jumps).
            budget: Iterations for warm start plus restarts (default: settings.budget).

        Returns:
            The chosen solution (see the module docstring for how it is chosen).
        """
        s = self.settings
        budget = s.budget if budget is None else budget
        current = np.asarray(current, dtype=float)
        start = self.clamp(current)
        guess = self.guess
        attempts, spent = 1, 0
        first = self._descend(
            start,
            target,
            self.lower,
            self.upper,
            min(s.iterations, budget),
            give_up_above=math.inf if guess is None else s.far_target,
        )
        spent += first.iterations
        jump = self._jump(first.q, current)
        if first.converged and jump <= s.jump_bound:
            return self._result(first, target, current, attempts, spent, jump)
        if guess is not None and spent < budget:
            guessed, tried, used = self._nearest_guess(target, current, budget - spent)
            attempts += tried
            spent += used
            if guessed is not None:
                if first.converged and jump < self._jump(guessed.q, current):
                    return self._result(first, target, current, attempts, spent, jump)
                return self._result(guessed, target, current, attempts, spent)
            if first.gave_up and spent < budget:
                # Out of the guess's reach (or of the limits): the warm start after all.
                attempts += 1
                first = self._descend(
                    start, target, self.lower, self.upper, min(s.iterations, budget - spent)
                )
                spent += first.iterations
                jump = self._jump(first.q, current)
                if first.converged and jump <= s.jump_bound:
                    return self._result(first, target, current, attempts, spent, jump)
        candidates = [first]
        while spent < budget:
            attempts += 1
            seed = self._random_start(current)
            found = self._descend(
                seed, target, self.lower, self.upper, min(s.iterations, budget - spent)
            )
            spent += found.iterations
            found.q = self._unwrap(found.q, current)
            if found.converged and self._jump(found.q, current) <= s.jump_bound:
                return self._result(found, target, current, attempts, spent)
            candidates.append(found)
            if sum(c.converged for c in candidates) >= s.far_solutions:
                break
        converged = [c for c in candidates if c.converged]
        if converged:
            best = min(converged, key=lambda c: self._jump(c.q, current))
            return self._result(best, target, current, attempts, spent)
        # Unreachable: the closest pose the limb reaches without jumping.
        lo = np.maximum(self.lower, current - s.jump_bound)
        hi = np.minimum(self.upper, current + s.jump_bound)
        lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
        attempts += 1
        bounded = self._descend(np.clip(start, lo, hi), target, lo, hi, 2 * s.iterations)
        spent += bounded.iterations
        near = [c for c in candidates if self._jump(c.q, current) <= s.jump_bound]
        best = min([bounded, *near], key=lambda c: c.cost)
        return self._result(best, target, current, attempts, spent)

    # ------------------------------------------------------------------ internals
    def _descend(
        self,
        q: np.ndarray,
        target: pin.SE3,
        lo: np.ndarray,
        hi: np.ndarray,
        iterations: int,
        give_up_above: float = math.inf,
    ) -> _Descent:
        """Damped least squares from ``q``, clamped to ``[lo, hi]`` every iteration.

        Levenberg-Marquardt style: a step that leaves the tip farther from the target is
        taken back and retried with more damping (near a singular configuration the
        linearisation lies, and an undamped step flings the joints); a step that helps lowers
        the damping again toward ``settings.damping``.

        When the start is farther from the target than ``give_up_above`` (its cost), it stops
        after that first look (``gave_up``): the caller has a better way to far targets.
        """
        (
            model, data, frame, position_only, pos_tol, rot_tol, max_step,
            reach_step, turn_step, identity, weight, least,
        ) = self._constants  # fmt: skip
        damping = least
        regular = self._least_regular  # rebuilt only when the damping changes
        goal = target.translation
        q = q.copy()
        base_q, base_cost, base_pos, base_rot = q, math.inf, math.inf, math.inf
        base_tip = None
        jacobian = error = None
        done = 0
        for done in range(1, iterations + 1):
            # Forward kinematics only: the Jacobian is needed only when this configuration
            # is kept and stepped from (not for the final, converged one, nor a rejected one).
            pin.forwardKinematics(model, data, q)
            tip = pin.updateFramePlacement(model, data, frame)
            offset = goal - tip.translation
            pos_err = math.sqrt(offset @ offset)
            if position_only:
                rot_err = 0.0
                gap = None
            else:
                gap = tip.actInv(target)
                twist = pin.log6(gap).vector
                rot_err = math.sqrt(twist[3:] @ twist[3:])
            cost = pos_err + weight * rot_err
            if cost > give_up_above and done == 1:
                return _Descent(q, tip.copy(), pos_err, rot_err, False, 1, cost, gave_up=True)
            if cost >= base_cost:
                # Worse: back to the last good configuration, damp more, try a shorter step
                # (its Jacobian and error, computed when it was kept, are still at hand).
                damping = min(damping * 10.0, 1.0)
                regular = damping * identity
                q = base_q
            else:
                if damping > least:
                    damping = max(damping * 0.3, least)
                    regular = damping * identity
                base_q, base_cost, base_pos, base_rot = q, cost, pos_err, rot_err
                base_tip = tip
                if pos_err < pos_tol and rot_err < rot_tol:
                    return _Descent(q, tip.copy(), pos_err, rot_err, True, done, cost)
                # Without q: reuses this iteration's forward kinematics instead of redoing it.
                pin.computeJointJacobians(model, data)
                if position_only:
                    error = offset
                    jacobian = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)[:3]
                else:
                    error = twist
                    jacobian = pin.Jlog6(gap.inverse()) @ pin.getFrameJacobian(
                        model, data, frame, pin.LOCAL
                    )
                # Far (or unreachable) targets: aim at most reach_step / turn_step away per
                # iteration, where the linearisation still holds.
                lin = pos_err if position_only else math.sqrt(error[:3] @ error[:3])
                scale = 1.0
                if lin > reach_step:
                    scale = reach_step / lin
                if rot_err > turn_step:
                    scale = min(scale, turn_step / rot_err)
                if scale < 1.0:
                    error = error * scale
            step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + regular, error)
            largest = np.abs(step).max()
            if largest > max_step:
                step *= max_step / largest
            moved = q + step
            inside = np.minimum(np.maximum(moved, lo), hi)
            if (inside != moved).any():
                # A joint pressed against a limit and asked to go further would waste the
                # step (clamping undoes it): solve again without it, so the others make up.
                blocked = ((q >= hi) & (step > 0)) | ((q <= lo) & (step < 0))
                if blocked.any():
                    free = jacobian.copy()
                    free[:, blocked] = 0.0
                    step = free.T @ np.linalg.solve(free @ free.T + regular, error)
                    largest = np.abs(step).max()
                    if largest > max_step:
                        step *= max_step / largest
                moved = np.minimum(np.maximum(q + step, lo), hi)
                if np.abs(moved - q).max() < 1e-9:
                    break  # stuck against the limits
            q = moved
        if base_tip is None:
            return _Descent(q, self.chain.tip(q), math.inf, math.inf, False, done, math.inf)
        # base_tip is Pinocchio's frame placement, overwritten by later iterations: recompute.
        pose = self.chain.tip(base_q)
        return _Descent(base_q, pose, base_pos, base_rot, False, done, base_cost)

    def _nearest_guess(
        self, target: pin.SE3, current: np.ndarray, budget: int
    ) -> tuple[_Descent | None, int, int]:
        """The nearest closed-form solution within the limits, polished by a descent.

        Returns:
            The converged descent (None: no solution within the limits, or none of the
            nearest few converged), descents run, iterations spent.
        """
        assert self.guess is not None
        candidates = self.guess(target, current)
        if not len(candidates):
            return None, 0, 0
        lower, upper = self.lower, self.upper
        if self._turns_matter:
            candidates = self._unwrap(candidates, current)
            for turn in (_TWO_PI, -_TWO_PI):
                # An angle outside the limits may be inside them a turn away (a joint whose
                # range is not centred on zero).
                turned = candidates + turn
                fits = self.chain.revolute & ((candidates < lower) | (candidates > upper))
                fits &= (turned >= lower) & (turned <= upper)
                candidates = np.where(fits, turned, candidates)
        inside = ((candidates >= lower) & (candidates <= upper)).all(axis=1)
        candidates = candidates[inside]
        jumps = np.abs(candidates - current).max(axis=1)
        attempts = spent = 0
        for i in np.argsort(jumps)[:_GUESS_TRIES]:
            if spent >= budget:
                break
            attempts += 1
            found = self._descend(
                candidates[i], target, lower, upper, min(self.settings.iterations, budget - spent)
            )
            spent += found.iterations
            if found.converged:
                if self._turns_matter:
                    found.q = self._unwrap(found.q, current)
                return found, attempts, spent
        return None, attempts, spent

    def _random_start(self, current: np.ndarray) -> np.ndarray:
        # Unbounded joints restart within half a turn of where they are.
        lo = np.where(np.isfinite(self.lower), self.lower, current - math.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, current + math.pi)
        return self._rng.uniform(lo, hi)

    def _unwrap(self, q: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Each revolute angle moved by whole turns toward ``current``, staying in limits."""
        turns = np.round((current - q) / _TWO_PI)
        shifted = q + turns * _TWO_PI
        ok = self.chain.revolute & (shifted >= self.lower) & (shifted <= self.upper)
        return np.where(ok, shifted, q)

    @staticmethod
    def _jump(q: np.ndarray, current: np.ndarray) -> float:
        return float(np.abs(q - current).max()) if q.size else 0.0

    def _result(
        self,
        found: _Descent,
        target: pin.SE3,
        current: np.ndarray,
        attempts: int,
        spent: int,
        jump: float | None = None,
    ) -> IkResult:
        return IkResult(
            q=found.q,
            pose=found.pose,
            position_error=found.position_error,
            orientation_error=found.orientation_error,
            reachable=found.converged,
            jump=self._jump(found.q, current) if jump is None else jump,
            attempts=attempts,
            iterations=spent,
        )
