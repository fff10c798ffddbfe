"""Static Cosserat-rod physics of tendon-driven continuum robots (float64, no torch)."""

from tdcr.physics.cosserat import STATUS, RodSolution, SolverOptions, TipSolver, material, solve, tendon_routing

__all__ = ["STATUS", "RodSolution", "SolverOptions", "TipSolver", "material", "solve", "tendon_routing"]
