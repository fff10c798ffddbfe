"""tdcr-surrogates: shapes of tendon-driven continuum robots, exactly or from neural operators.

Public API (re-exported here; everything else is reached through its module, e.g.
``tdcr.physics.STATUS``, ``tdcr.validation``, ``tdcr.client.Client``)::

    from tdcr import DesignBatch, ExternalLoads, SolverOptions, RodSolution, solve
    from tdcr import Surrogate, sample_designs, TABLE_I, relative_l2

Importing ``tdcr`` loads numpy only: no torch, FastAPI, uvicorn or onnxruntime (a
:class:`Surrogate` imports onnxruntime when it loads a model).
"""

from importlib.metadata import PackageNotFoundError, version

from tdcr.design_space import TABLE_I, sample_designs
from tdcr.designs import DesignBatch, ExternalLoads
from tdcr.metrics import relative_l2
from tdcr.physics import RodSolution, SolverOptions, solve
from tdcr.runtime import Surrogate

__all__ = ["TABLE_I", "DesignBatch", "ExternalLoads", "RodSolution", "SolverOptions", "Surrogate", "relative_l2",
           "sample_designs", "solve"]

try:
    __version__ = version("tdcr-surrogates")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
