"""The served default of ``/predict`` (and of OIP v2 as ``auto``): each request by the cheaper of the
exact solver and the default operator that still meets its tolerance
(:func:`tdcr.surrogates.engine.route`; every answer's ``source`` says which).  A request that names
an operator is that operator's, as asked.

The exact path runs in this process for small tendon-only batches (the compiled kernel releases the
GIL; a hand-off to a solver process would cost more than the solve), and in the solver processes,
with their admission and deadline, otherwise.
"""

from __future__ import annotations

import numpy as np
from starlette.concurrency import run_in_threadpool

from service.model import INLINE_DESIGNS, InferenceRequest, InferenceResponse, Model
from service.oip import LOAD_INPUTS, SURROGATE_INPUTS, SURROGATE_OUTPUTS
from service.solver import ExactModel
from service.surrogate import SurrogateModel
from tdcr.api.validation import ShapeRequest
from tdcr.physics.exact import DEFAULT_PATHS, ExactAnswer, solve_request, warm_up
from tdcr.surrogates import engine
from tdcr.surrogates.router import Cost, Costs
from tdcr.surrogates.runtime import solve_rows

#: The routed model's name.
AUTO_MODEL = "auto"
#: Tendon-only designs a request may have for the exact path to run in this process (about 40 us
#: each on a core); more, or any design with loads, go to the solver processes.
IN_PROCESS_DESIGNS = 256
#: The exact path runs in this process only where the admission's estimate is at most this share of
#: the deadline: a solve here cannot be killed (a solver process's can).
IN_PROCESS_SHARE_OF_DEADLINE = 0.1


class RoutedModel(Model):
    """The cheaper of ``exact`` and ``operator`` (designs without loads) / ``loaded`` (designs with
    loads) for each request; :meth:`measure` times the paths on this machine (at startup)."""

    name = AUTO_MODEL
    kind = "surrogate"
    platform = "tdcr_router"
    inputs = SURROGATE_INPUTS | LOAD_INPUTS
    outputs = SURROGATE_OUTPUTS
    blocking = True

    def __init__(self, exact: ExactModel, operator: SurrogateModel, loaded: SurrogateModel | None):
        self.exact, self.operator, self.loaded = exact, operator, loaded
        self.limits = operator.limits
        self.costs: Costs | None = None
        #: the exact path's kernels are loaded in this process (:meth:`measure`)
        self.exact_here = False

    def measure(self, *, exact: bool = True) -> None:
        """Time every path (blocking, about a second), or take ``TDCR_ROUTER_COSTS``; with ``exact``
        load the solver's default kernels here, else (the solver still starting) time the operators
        only: the solver is not chosen until it is ready."""
        settings = self.exact.settings
        loaded = None if self.loaded is None else self.loaded.surrogate
        if settings.router_costs is not None:
            self.costs = Costs(**{path: Cost.line(*line) for path, line in settings.router_costs.items()})
        elif not exact:
            self.costs = Costs.measure(self.operator.surrogate, loaded, exact=False)
        else:  # as this process solves (one thread); loaded designs in the solver processes: their admission's estimate
            self.costs = Costs.measure(self.operator.surrogate, loaded,
                                       exact=lambda f, s, m: solve_rows(f, s, m, workers=1),
                                       exact_loaded=Cost.line(0.0, settings.exact_seconds_per_loaded_design))
        if exact:
            with np.errstate(all="ignore"):
                warm_up(DEFAULT_PATHS)  # loads the kernels here (from the cache the solver processes wrote)
            self.exact_here = True

    def health(self) -> str | None:
        if self.costs is None:
            return "router: the paths are not timed yet"
        return None

    @property
    def starting(self) -> bool:
        """The solver is not on the router's paths yet (it joins once its processes are up)."""
        return not self.exact_here and not self.exact.failed

    def starting_note(self) -> str:
        return "answering by its operators; the solver joins once it is up"

    def parameters(self) -> dict:
        costs = self.costs
        timed = {} if costs is None else {
            f"{path}_seconds": cost.describe()
            for path, cost in (("exact", costs.exact), ("exact_loaded", costs.exact_loaded),
                               ("operator", costs.operator), ("loaded_operator", costs.loaded_operator))
            if cost is not None}
        return {"operator": self.operator.name, "loaded_operator": None if self.loaded is None else self.loaded.name,
                **timed}

    def admits(self, request: ShapeRequest) -> bool:
        """Whether the solver's admission takes ``request`` whole (else the router does not send it there)."""
        budget = self.exact.budget
        return budget.estimate(request) <= budget.max_seconds

    def solve(self, request: ShapeRequest) -> ExactAnswer:
        """The exact answer of ``request``: here for a small tendon-only batch well inside the deadline,
        else in the solver processes (their admission and deadline)."""
        deadline = self.exact.settings.exact_timeout_s
        if (self.exact_here and request.n_loaded == 0 and request.n_designs <= IN_PROCESS_DESIGNS
                and self.exact.budget.estimate(request) <= IN_PROCESS_SHARE_OF_DEADLINE * deadline):
            with np.errstate(all="ignore"):
                return solve_request(request)
        return self.exact.solve_from_thread(request)

    async def infer(self, request: InferenceRequest) -> InferenceResponse:
        return await run_in_threadpool(self.infer_blocking, request)

    def answers_inline(self, request: InferenceRequest) -> bool:
        """A few tendon-only designs without a tolerance, with the solver's kernels in this process:
        either path is then short (:meth:`solve` here, or one graph run)."""
        peek = request.peek()
        return (self.exact_here and peek is not None and peek.designs <= INLINE_DESIGNS and not peek.tolerance
                and not peek.loads)

    def infer_blocking(self, request: InferenceRequest) -> InferenceResponse:
        decoded = request.codec.decode(request.payload, self.spec)
        task = decoded.task
        model = self.loaded if task.n_loaded and self.loaded is not None else self.operator
        operator = engine.Operator(model.name, model.batcher, model.guard)
        prediction = engine.route(task, costs=self.costs, operator=operator, exact=self.solve,
                                  exact_ready=self.exact.ready() and self.admits(task))
        guarded = prediction.n_designs if task.tolerance is not None else 0
        return InferenceResponse(request.codec.encode(decoded, prediction), prediction.n_designs, guarded=guarded,
                                 exact=prediction.n_exact)
