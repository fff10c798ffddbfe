"""Exact (physics) answers to validated requests: solves each tendon-count group as one batch."""

from __future__ import annotations

import sys

import numpy as np

from tdcr.physics import RodSolution, SolverOptions, solve
from tdcr.validation import ShapeRequest


def solve_request(request: ShapeRequest, *, options: SolverOptions | None = None) -> list[dict]:
    """Solve every design of ``request`` at its arclength fractions ``(n,)``; one dict per design, in order.

    Each dict holds ``s`` (m, (n,)), ``backbone`` ((n, 3) m), ``rotation`` ((n, 3, 3)),
    ``tendons`` ((n, N_t, 3) m), ``converged`` and ``residual`` (N), as nested lists.
    """
    results: list[dict | None] = [None] * request.n_designs
    for group in request.groups:
        with np.errstate(all="ignore"):  # overflow of an extreme design is reported in its flags
            sol = solve(group.designs, request.fractions, loads=group.loads, options=options)
        for j, i in enumerate(group.rows):
            results[i] = solution_to_dict(sol, j)
    return results  # type: ignore[return-value]


#: The residual reported for a design whose residual is not finite (JSON has no inf or NaN).
NOT_FINITE_RESIDUAL = sys.float_info.max


def solution_to_dict(sol: RodSolution, j: int) -> dict:
    """Design ``j`` of a :class:`RodSolution` as JSON-ready lists, numbers only: a design with
    non-finite values is reported not converged, with those values as 0 and the residual as
    :data:`NOT_FINITE_RESIDUAL`."""
    arrays = {"s": sol.s[j], "backbone": sol.backbone[j], "rotation": sol.rotation[j], "tendons": sol.tendons[j]}
    finite = bool(all(np.isfinite(v).all() for v in arrays.values()) and np.isfinite(sol.residual[j]))
    if not finite:
        arrays = {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in arrays.items()}
    return {**{k: v.tolist() for k, v in arrays.items()},
            "converged": bool(sol.converged[j]) and finite,
            "residual": float(sol.residual[j]) if np.isfinite(sol.residual[j]) else NOT_FINITE_RESIDUAL}


def warm_up() -> bool:
    """Import and run the solver once (used to warm up worker processes)."""
    from tdcr.design_space import sample_designs

    solve(sample_designs(2, seed=0), np.linspace(0.0, 1.0, 5))
    return True
