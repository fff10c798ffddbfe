"""tdcr-surrogates: shapes of tendon-driven continuum robots, exactly or from neural operators.

Public API (everything else is private to its module)::

    from tdcr import DesignBatch, ExternalLoads, SolverOptions, RodSolution, solve
    from tdcr import sample_designs, TABLE_I
"""

from training.design_space import TABLE_I, sample_designs
from training.designs import DesignBatch, ExternalLoads
from training.physics import RodSolution, SolverOptions, solve

__all__ = ["TABLE_I", "DesignBatch", "ExternalLoads", "RodSolution", "SolverOptions", "sample_designs", "solve"]
__version__ = "0.1.0"
