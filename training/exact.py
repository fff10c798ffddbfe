"""Exact (physics) answers to JSON requests: groups designs by tendon count and solves each group."""

from __future__ import annotations

import numpy as np

from training.physics import RodSolution, SolverOptions, solve
from training.schemas import Design, group_by_tendon_count, to_batch, to_loads


def solve_designs(designs: list[Design], fractions: np.ndarray, *, options: SolverOptions | None = None) -> list[dict]:
    """Solve every design at the arclength fractions ``(n,)``; one result dict per design, in order.

    Each dict holds ``s`` (m, (n,)), ``backbone`` ((n, 3) m), ``rotation`` ((n, 3, 3)),
    ``tendons`` ((n, N_t, 3) m), ``converged`` and ``residual`` (N), as nested lists.
    """
    results: list[dict | None] = [None] * len(designs)
    for _, idx in group_by_tendon_count(designs).items():
        group = [designs[i] for i in idx]
        sol = solve(to_batch(group), fractions, loads=to_loads(group), options=options)
        for j, i in enumerate(idx):
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


def solve_request_dicts(designs: list[dict], fractions: list[float]) -> list[dict]:
    """Process-pool entry point: designs as validated JSON dicts."""
    from training.schemas import Design

    return solve_designs([Design.model_validate(d) for d in designs], np.asarray(fractions))


def warm_up() -> bool:
    """Import and run the solver once (used to warm up worker processes)."""
    from training.design_space import sample_designs

    solve(sample_designs(2, seed=0), np.linspace(0.0, 1.0, 5))
    return True
