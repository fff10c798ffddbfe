"""Exact (physics) answers to validated requests: solves each tendon-count group as one batch."""

from __future__ import annotations

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
        sol = solve(group.designs, request.fractions, loads=group.loads, options=options)
        for j, i in enumerate(group.rows):
            results[i] = solution_to_dict(sol, j)
    return results  # type: ignore[return-value]


def solution_to_dict(sol: RodSolution, j: int) -> dict:
    """Design ``j`` of a :class:`RodSolution` as JSON-ready lists."""
    return {
        "s": sol.s[j].tolist(),
        "backbone": sol.backbone[j].tolist(),
        "rotation": sol.rotation[j].tolist(),
        "tendons": sol.tendons[j].tolist(),
        "converged": bool(sol.converged[j]),
        "residual": float(sol.residual[j]),
    }


def warm_up() -> bool:
    """Import and run the solver once (used to warm up worker processes)."""
    from tdcr.design_space import sample_designs

    solve(sample_designs(2, seed=0), np.linspace(0.0, 1.0, 5))
    return True
