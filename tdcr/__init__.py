"""tdcr-surrogates: shapes of tendon-driven continuum robots, exactly or from neural operators.

Public API (re-exported here; everything else is reached through its module, e.g.
``tdcr.physics.STATUS``, ``tdcr.api.validation``, ``tdcr.clients.Client``).  The core, by what
it holds: ``tdcr.robot`` (designs, loads, the design space), ``tdcr.physics`` (the solver and its
answers to requests), ``tdcr.api`` (schemas, checks, the one validation path), ``tdcr.surrogates``
(the ONNX operators, their error bounds, the engine), ``tdcr.search`` (inverse kinematics, design
search), ``tdcr.clients`` (the service's client, the load test), ``tdcr.cli``::

    from tdcr import DesignBatch, ExternalLoads, SolverOptions, RodSolution, solve
    from tdcr import Router, Surrogate, sample_designs, TABLE_I, relative_l2
    from tdcr import Robot, load_robot, read_recording, replay, fit   # a real robot (fit: scipy)

Importing ``tdcr`` loads numpy only: no torch, FastAPI, uvicorn or onnxruntime (a
:class:`Surrogate` imports onnxruntime when it loads a model).
"""

from importlib.metadata import PackageNotFoundError, version

from tdcr.metrics import relative_l2
from tdcr.physics import RodSolution, SolverOptions, solve
from tdcr.physics.replay import replay
from tdcr.robot import design_space
from tdcr.robot.design_space import TABLE_I, sample_designs
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.robot.real import Robot, load_robot, read_recording
from tdcr.search.fit import fit
from tdcr.surrogates.router import Router
from tdcr.surrogates.runtime import Surrogate

__all__ = ["TABLE_I", "DesignBatch", "ExternalLoads", "Robot", "RodSolution", "Router", "SolverOptions", "Surrogate",
           "design_space", "fit", "load_robot", "read_recording", "relative_l2", "replay", "sample_designs", "solve"]

try:
    __version__ = version("tdcr-surrogates")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
