"""The solves of a bundle fit (`Solved`): the free parameters (neither held nor in a null
direction of the normal matrix at the start), the solve with the fit's weights, then the
IRLS passes of a robust loss on the noise-normalised residual. Each solve runs the one
engine (`robtraj.estimate.solve`) from the problem's current values and re-centres the
problem at its estimate."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .._errors import UserError
from . import _calib_problem as cp
from ._calib_frames import Weights
from ._calib_problem import BundleData, bundle_normal
from ._calib_setup import Setup
from ._solve import Solution, default_solver, gauss_newton_step, solve
from ._uncertainty import identifiability

ROBUST = ("huber", "cauchy")
#: parameter groups `fit` can hold at their start values
HOLDABLE = ("camera_from_base", "flange_from_tool", "constellation")
_ROBUST_K = {"huber": 2.0, "cauchy": 2.0}
#: IRLS passes of a robust loss at most (they stop when a solve takes two steps or fewer)
_ROBUST_PASSES = 5


@dataclasses.dataclass(frozen=True)
class SolveSettings:
    """How a fit solves: the Optimistix `solver`, its name in the progress lines
    (`method`), the steps allowed per solve, the robust loss (None or one of `ROBUST`),
    the parameter groups held at their start values (`HOLDABLE`), and whether the fit is
    one Gauss–Newton step from its start (`one_step`) instead of a solve."""

    solver: Any
    method: str
    max_steps: int
    robust: str | None
    hold: tuple[str, ...]
    one_step: bool = False


@dataclasses.dataclass(frozen=True)
class Solved:
    """The fit after its solves: the problem at the estimate (`bundle`), the `free` mask
    of θ and the identifiability report at the start, the weights of the last solve
    (`weights`: the IRLS ones after a robust pass) and those of the noise model
    (`noise_weights`), and the solutions in order."""

    bundle: BundleData
    free: np.ndarray
    identifiability: dict[str, Any]
    weights: Weights
    noise_weights: Weights
    solutions: tuple[Solution, ...]

    @property
    def converged(self) -> bool:
        return all(s.converged for s in self.solutions)

    @property
    def convergence(self) -> str:
        """Why the solves stopped: the last one's reason, or that of the first that did
        not converge."""
        failed = [s for s in self.solutions if not s.converged]
        return failed[0].reason if failed else self.solutions[-1].reason

    @property
    def iterations(self) -> int:
        return sum(s.steps for s in self.solutions)


def solve_settings(
    solver, max_iter: int, robust: str | None, hold: Sequence[str], one_step: bool = False
) -> SolveSettings:
    """The solves' settings (default solver: Levenberg–Marquardt, `default_solver`);
    `UserError` for an unknown robust loss or parameter group; `ValueError` for one
    Gauss–Newton step with a robust loss (whose passes are solves)."""
    if one_step and robust is not None:
        raise ValueError("one Gauss–Newton step takes no robust loss")
    if robust is not None and robust not in ROBUST:
        raise UserError(f"unknown robust loss {robust!r} (choose from {', '.join(ROBUST)})")
    bad = [h for h in hold if h not in HOLDABLE]
    if bad:
        raise UserError(f"cannot hold {', '.join(bad)} (choose from {', '.join(HOLDABLE)})")
    method = type(solver).__name__ if solver else "Levenberg–Marquardt"
    if one_step:
        method = "one Gauss–Newton step"
    return SolveSettings(
        solver or default_solver(), method, max_iter, robust, tuple(hold), one_step
    )


def weighted_solve(st: Setup, how: SolveSettings, say: Callable[[str], None]) -> Solved:
    """The solve with the fit's weights, from the start, of the parameters neither held
    (`how.hold`) nor in a null direction of the normal matrix there (fixed at their
    start values and reported, `identifiability`)."""
    held = np.array([n.split(".", 1)[0] in how.hold for n in st.names_theta])
    if not np.any(st.has_column & st.in_model & ~held):
        raise UserError("nothing to fit: every parameter of the problem is held")
    free, ident = identifiability(
        st.h0, st.phi_names, st.has_column & st.in_model & ~held, st.droppable
    )
    if ident["dropped"]:
        say("not identifiable, fixed: " + ", ".join(d["parameter"] for d in ident["dropped"]))
    label = {"user_weights": "fit", "uniform": "uniformly weighted fit"}.get(
        st.noise_info["kind"], "noise-weighted fit"
    )
    say(f"{label}: {how.method}")
    if how.one_step:
        sol = gauss_newton_step(np.zeros(len(st.names_theta)), free, st.normal0)
        problem = cp.recentre(st.bundle.problem, sol.theta, st.bundle.basis)
        return Solved(
            dataclasses.replace(st.bundle, problem=problem),
            free,
            ident,
            st.w_user,
            st.w_user,
            (sol,),
        )
    bundle, sol = _solve_pass(st, st.bundle, free, how, st.normal0)
    return Solved(bundle, free, ident, st.w_user, st.w_user, (sol,))


def robust_passes(
    st: Setup, solved: Solved, how: SolveSettings, say: Callable[[str], None]
) -> Solved:
    """With a robust loss, IRLS passes: each reweights the observations by the loss's
    weight of their noise-normalised residual at the last estimate and solves again,
    until a solve takes two steps or fewer (`_ROBUST_PASSES` at most)."""
    if how.robust is None:
        return solved
    bundle, w, sols = solved.bundle, solved.weights, list(solved.solutions)
    for it in range(_ROBUST_PASSES):
        w = _robust_weights(st, solved, bundle, how.robust)
        bundle = bundle.with_frames(bundle.chunks.replace(weights=w))
        say(f"robust ({how.robust}) pass {it + 1}: {how.method}")
        bundle, sol = _solve_pass(st, bundle, solved.free, how)
        sols.append(sol)
        if sol.steps <= 2:
            break
    return dataclasses.replace(solved, bundle=bundle, weights=w, solutions=tuple(sols))


def _robust_weights(st: Setup, solved: Solved, bundle: BundleData, robust: str) -> Weights:
    """The IRLS weights at `bundle`'s values: the noise weights times the loss's weight
    of each observation's residual normalised by its noise and the variance factor
    ``Σ w r² / dof`` of the weights of the last solve (those of `bundle`'s frames). The
    loss's weights are held `(frames, leds)`; the noise weights are recomputed per block."""
    dof = max(1, 3 * int(st.used.sum()) - int(solved.free.sum()))
    u2 = np.zeros((st.data.n_frames, st.data.n_leds))
    total = [0.0]

    def visit(block, d, _theta):
        sq = np.einsum("fli,fli->fl", d, d)
        total[0] += float(np.sum(block.weights * sq))
        u2[block.a : block.b] = block.noise * sq / 3.0

    cp.over_residuals(bundle, st.q, visit)
    s2 = total[0] / dof
    # in place: one (frames, leds) array at a time
    u = np.sqrt(np.divide(u2, max(s2, 1e-300), out=u2), out=u2)
    k = _ROBUST_K[robust]
    if robust == "huber":
        rho = np.minimum(1.0, np.divide(k, np.maximum(u, 1e-12, out=u), out=u), out=u)
    else:
        rho = np.divide(1.0, np.add(1.0, np.square(np.divide(u, k, out=u), out=u), out=u), out=u)
    return dataclasses.replace(solved.noise_weights, factor=np.multiply(rho, st.used, out=rho))


def _solve_pass(st: Setup, bundle: BundleData, free, how: SolveSettings, start=None):
    """One engine solve from `bundle`'s current values (`start`: the normal equations
    there, if known); returns the re-centred bundle and the solution."""
    sol = solve(
        bundle_normal,
        bundle,
        np.zeros(len(st.names_theta)),
        free,
        n_residuals=st.n_residuals,
        solver=how.solver,
        max_steps=how.max_steps,
        start=start,
        size=len(st.names_theta),
    )
    problem = cp.recentre(bundle.problem, sol.theta, bundle.basis)
    return dataclasses.replace(bundle, problem=problem), sol
