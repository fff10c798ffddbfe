"""Exact (physics) answers to validated requests: solves each tendon-count group as one batch."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from tdcr.design_space import DEFAULT_POINTS
from tdcr.physics import STATUS, RodSolution, SolverOptions, solve
from tdcr.validation import Limits, ShapeRequest, validate_json


@dataclass(frozen=True)
class WorkBudget:
    """Admission by estimated solver time on one process: tendon-only designs cost
    ``seconds_per_design`` at 42 points, loaded designs (shooting) ``seconds_per_loaded_design``,
    both scaling with more points (the step grid holds every requested arclength); a request
    estimated over ``max_seconds`` is refused."""

    seconds_per_design: float
    seconds_per_loaded_design: float
    max_seconds: float

    def estimate(self, request: ShapeRequest) -> float:
        """Estimated seconds of ``request``."""
        tendon_only = request.n_designs - request.n_loaded
        points = max(request.fractions.size, DEFAULT_POINTS) / DEFAULT_POINTS
        return points * (tendon_only * self.seconds_per_design + request.n_loaded * self.seconds_per_loaded_design)


class TooMuchWork(ValueError):
    """A request whose estimated solver time exceeds its :class:`WorkBudget`."""

    def __init__(self, estimate: float, max_seconds: float):
        self.estimate, self.max_seconds = estimate, max_seconds
        super().__init__(f"these designs would take the solver about {estimate:.3g} s, more than the {max_seconds:g} s "
                         "it admits; send fewer designs or points")

    def __reduce__(self):
        return (TooMuchWork, (self.estimate, self.max_seconds))


def answer_json(body: bytes, *, limits: Limits, budget: WorkBudget | None = None) -> list[dict]:
    """Validate a JSON ``SolveRequest`` and solve it: the whole of /exact's work, run in a solver
    process so that parsing large bodies never costs the server's own interpreter.

    Raises :class:`tdcr.validation.InvalidRequest` or :class:`TooMuchWork`.
    """
    request = validate_json(body, target="solver", limits=limits)
    if budget is not None and (estimate := budget.estimate(request)) > budget.max_seconds:
        raise TooMuchWork(estimate, budget.max_seconds)
    return solve_request(request)


def solve_request(request: ShapeRequest, *, options: SolverOptions | None = None) -> list[dict]:
    """Solve every design of ``request`` at its arclength fractions ``(n,)``; one dict per design, in order.

    Each dict holds ``s`` (m, (n,)), ``backbone`` ((n, 3) m), ``rotation`` ((n, 3, 3)),
    ``tendons`` ((n, N_t, 3) m), ``converged``, ``residual`` (N), ``status`` (a name of
    :data:`tdcr.physics.STATUS`) and ``error_estimate`` (relative l2, or None), as nested lists.
    """
    results: list[dict | None] = [None] * request.n_designs
    # the tip Jacobian is that of s = L: solved as one more arclength when it is not asked for
    fractions = request.fractions
    tip = np.nonzero(fractions == 1.0)[0]
    if request.jacobian and tip.size == 0:
        fractions = np.append(fractions, 1.0)
    tip_index = int(tip[0]) if tip.size else fractions.size - 1
    n = request.fractions.size
    for group in request.groups:
        with np.errstate(all="ignore"):  # overflow of an extreme design is reported in its flags
            sol = solve(group.designs, fractions, loads=group.loads, options=options, jacobian=request.jacobian)
        for j, i in enumerate(group.rows):
            results[i] = solution_to_dict(sol, j, points=n)
            if request.jacobian:
                results[i]["tip_jacobian"] = np.nan_to_num(sol.jacobian[j, tip_index]).tolist()
    return results  # type: ignore[return-value]


#: The residual reported for a design whose residual is not finite (JSON has no inf or NaN).
NOT_FINITE_RESIDUAL = sys.float_info.max


def solution_to_dict(sol: RodSolution, j: int, *, points: int | None = None) -> dict:
    """Design ``j`` of a :class:`RodSolution` (its first ``points`` arclengths; all by default) as
    JSON-ready lists, numbers only: a design with non-finite values is reported not converged, with
    those values as 0 and the residual as :data:`NOT_FINITE_RESIDUAL`."""
    n = slice(points)
    arrays = {"s": sol.s[j, n], "backbone": sol.backbone[j, n], "rotation": sol.rotation[j, n],
              "tendons": sol.tendons[j, n]}
    finite = bool(all(np.isfinite(v).all() for v in arrays.values()) and np.isfinite(sol.residual[j]))
    if not finite:
        arrays = {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in arrays.items()}
    out = {**{k: v.tolist() for k, v in arrays.items()},
           "converged": bool(sol.converged[j]) and finite,
           "residual": float(sol.residual[j]) if np.isfinite(sol.residual[j]) else NOT_FINITE_RESIDUAL}
    if sol.status is not None:
        out["status"] = STATUS[int(sol.status[j])] if finite else "not_finite"
    if sol.error_estimate is not None:
        estimate = float(sol.error_estimate[j])
        out["error_estimate"] = estimate if np.isfinite(estimate) else None
    return out


def warm_up() -> bool:
    """Import and run the solver once, tendon-only and loaded (warms worker processes up; compiles
    the numba kernels into their cache on first use)."""
    from tdcr.design_space import sample_designs
    from tdcr.designs import ExternalLoads

    designs, sigma = sample_designs(2, seed=0), np.linspace(0.0, 1.0, 5)
    solve(designs, sigma)
    solve(designs, sigma, loads=ExternalLoads(tip_force=np.array([[0.0, 0.01, 0.0]] * 2)))
    return True
