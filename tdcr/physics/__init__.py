"""Static Cosserat-rod physics of tendon-driven continuum robots (float64, no torch)."""

from tdcr.physics.cosserat import (
    POISSON_RATIO,
    RodSolution,
    SolverOptions,
    TipSolver,
    internal_wrench,
    material,
    solve,
    tendon_routing,
)
from tdcr.physics.status import STATUS, Status

__all__ = ["POISSON_RATIO", "STATUS", "RodSolution", "SolverOptions", "Status", "TipSolver", "internal_wrench",
           "material", "solve", "tendon_routing"]
