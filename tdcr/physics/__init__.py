"""Static Cosserat-rod physics of tendon-driven continuum robots (float64, no torch)."""

from tdcr.physics.cosserat import RodSolution, SolverOptions, TipSolver, material, solve, tendon_routing

__all__ = ["RodSolution", "SolverOptions", "TipSolver", "material", "solve", "tendon_routing"]
