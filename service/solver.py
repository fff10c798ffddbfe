"""The physics as served models: the exact solver (``exact``) and its inverse kinematics
(``inverse``).  The exact model owns the solver processes (service/solver_pool.py), their
admission slots and the deadline; the inverse model runs on them.

A request's whole work runs in a solver process (:func:`exact_job`): the codec's decoding and
validation, the admission by estimated work (:class:`tdcr.physics.exact.WorkBudget`), the solve and the
codec's encoding, so that a large body never costs the server's interpreter and a deadline kills
the work with its process.
"""

from __future__ import annotations

import logging

import anyio.from_thread
import orjson
from starlette.concurrency import run_in_threadpool

from service.model import (
    RETRY_SATURATED_S,
    RETRY_STARTING_S,
    InferenceError,
    InferenceRequest,
    InferenceResponse,
    InverseAnswer,
    Model,
    ModelSpec,
)
from service.oip import EXACT_INPUTS, EXACT_OUTPUTS, INVERSE_INPUTS, INVERSE_OUTPUTS, INVERSE_STATUS
from service.settings import Settings
from service.solver_pool import NoFreeWorker, SolverPool, WorkerDied, cold_paths
from tdcr.api.schemas import EXACT_MODEL
from tdcr.api.validation import InvalidRequest, ShapeRequest
from tdcr.physics.exact import ExactAnswer, TooMuchWork, WorkBudget, admit, paths_of, solve_request
from tdcr.search.inverse import answer_exact, finish

log = logging.getLogger("tdcr.service")
#: The inverse-kinematics model's name.
INVERSE_MODEL = "inverse"
#: What the solver models say while their processes start.
STARTING = "starting: the solver processes are starting (a machine's first start compiles the solver, about a minute)"
#: Exceptions of the solver processes' work that come back as they are.
EXPECTED = (InvalidRequest, TooMuchWork, InferenceError)


def _refuse_cold(request) -> None:
    """In a solver process that still compiles a path the request needs (a machine's first start):
    "unavailable" (503, retry) at once, not a wait for the compiler that the deadline would cut."""
    if not isinstance(request, ShapeRequest):
        return
    cold = cold_paths(paths_of(request))
    if cold:
        raise InferenceError("unavailable", f"starting: the solver compiles its {' and '.join(cold)} path "
                             "(a machine's first start, about two minutes on 2 cores); retry shortly",
                             retry_after=RETRY_STARTING_S)


def exact_job(codec, payload, spec: ModelSpec, budget: WorkBudget) -> tuple[object, int]:
    """The exact model's whole work on one request, in a solver process: decode, admit, solve, encode."""
    decoded = codec.decode(payload, spec)
    _refuse_cold(decoded.task)
    admit(decoded.task, budget)
    solved = solve_request(decoded.task)
    return codec.encode(decoded, solved), solved.n_designs


def solve_job(request: ShapeRequest, budget: WorkBudget) -> ExactAnswer:
    """A validated request's exact answer, in a solver process: admit, solve (the designs a
    surrogate's tolerance sends to the solver)."""
    _refuse_cold(request)
    admit(request, budget)
    return solve_request(request)


class ExactModel(Model):
    """The Cosserat solver, in ``settings.exact_workers`` killable processes with
    ``exact_max_pending`` admission slots and the deadline ``exact_timeout_s``."""

    name = EXACT_MODEL
    kind = "solver"
    platform = "tdcr_cosserat_solver"
    inputs = EXACT_INPUTS
    outputs = EXACT_OUTPUTS

    def __init__(self, settings: Settings):
        self.settings = settings
        self.limits = settings.exact_limits()
        self.budget = settings.exact_budget()
        self.pool: SolverPool | None = None
        self.in_flight = 0  #: requests holding a slot (of exact_max_pending): waiting for a process or in one
        self.failed = False  #: the processes did not start (a problem /readyz reports)

    def start(self) -> None:
        """Start the solver processes (blocks for their start, about a second each)."""
        self.pool = SolverPool(self.settings.exact_workers, preload=(__name__,))  # the jobs below

    @property
    def starting(self) -> bool:
        """The processes are starting (on a machine's first start they compile the solver)."""
        return self.pool is None and not self.failed

    def health(self) -> str | None:
        """Why the model cannot answer now, or None."""
        if self.starting:
            return STARTING
        if self.pool is None:
            return "solver pool: not running"
        return None if self.pool.healthy else "solver pool: a worker is being replaced"

    def compiling(self) -> list[str]:
        return [] if self.pool is None else self.pool.compiling()

    def parameters(self) -> dict:
        return {"deadline_s": self.settings.exact_timeout_s}

    @property
    def saturated(self) -> bool:
        return self.in_flight >= self.settings.exact_max_pending

    async def run(self, fn, *args, **kwargs):
        """``fn(*args, **kwargs)`` in a solver process, within a slot and the deadline; the
        process's failures as :class:`InferenceError` (its ``EXPECTED`` exceptions as they are)."""
        if self.pool is None:
            if self.starting:
                raise InferenceError("unavailable", f"{STARTING}; retry shortly", retry_after=RETRY_STARTING_S)
            raise InferenceError("unavailable", "the solver pool is not running")
        if self.saturated:  # (the slot is taken below with no await between: the event loop's thread only)
            raise InferenceError("saturated", "the solver is saturated; retry later", retry_after=RETRY_SATURATED_S)
        timeout = self.settings.exact_timeout_s
        self.in_flight += 1
        try:
            return await self.pool.run(fn, *args, timeout=timeout, expected=EXPECTED, **kwargs)
        except TooMuchWork as exc:
            raise InferenceError("too_large", str(exc)) from None
        except TimeoutError:  # the worker was killed: the work stops with the deadline
            raise InferenceError("deadline", f"the solver did not finish within {timeout} s") from None
        except NoFreeWorker as exc:  # e.g. the only process restarting after a deadline: not started
            raise InferenceError("saturated", f"the solver is saturated: {exc}; retry later",
                                 retry_after=RETRY_SATURATED_S) from None
        except WorkerDied as exc:
            raise InferenceError("unavailable", str(exc)) from None
        except RuntimeError as exc:
            log.error("solver failed: %s", exc)
            raise InferenceError("unavailable", "the solver failed on this request; retry later") from None
        finally:
            self.in_flight -= 1

    async def infer(self, request: InferenceRequest) -> InferenceResponse:
        body, count = await self.run(exact_job, request.codec, request.payload, self.spec, self.budget)
        return InferenceResponse(body, count)

    def solve_from_thread(self, request: ShapeRequest) -> ExactAnswer:
        """``request`` solved in a solver process, within a slot, its admission and the deadline, for
        a worker thread of the event loop (a surrogate keeping a tolerance); blocks that thread."""
        return anyio.from_thread.run(self.run, solve_job, request, self.budget)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()


class InverseModel(Model):
    """Inverse kinematics (tdcr/search/inverse.py): the tensions that reach each target.  A request names
    its forward model: ``exact`` runs in the exact model's solver processes; an operator runs in a
    worker thread, and its answers are then finished there (:func:`tdcr.search.inverse.finish`: checked in
    exact physics, a target they miss finished by exact steps; with ``polish`` every target)."""

    name = INVERSE_MODEL
    kind = "inverse"
    platform = "tdcr_inverse_kinematics"
    inputs = INVERSE_INPUTS
    outputs = INVERSE_OUTPUTS
    required = ("design", "position")

    def __init__(self, exact: ExactModel, operators):
        """``operators(name)``: the surrogate model ``name`` (:class:`InferenceError` ``not_found`` else)."""
        self.exact, self.operators = exact, operators

    def ready(self) -> bool:  # the exact model reports the pool's health
        return self.exact.ready()

    @property
    def starting(self) -> bool:
        return self.exact.starting

    def health(self) -> str | None:
        return self.exact.health()

    def parameters(self) -> dict:
        return self.exact.parameters() | {"status": orjson.dumps(INVERSE_STATUS).decode()}

    async def infer(self, request: InferenceRequest) -> InferenceResponse:
        codec = request.codec
        decoded = await run_in_threadpool(codec.decode, request.payload, self.spec)
        problem = decoded.task
        settings = self.exact.settings
        limits = {"max_seconds": self.exact.budget.max_seconds, "seconds_per_design": settings.exact_seconds_per_design}
        if problem.model == EXACT_MODEL:
            results = await self.exact.run(answer_exact, problem, **limits)
        else:  # the operator's answers, then exact physics keeps the tolerance (or polishes each)
            results = await run_in_threadpool(self.operators(problem.model).inverse, problem)
            results = await self.exact.run(finish, problem, results, **limits)
        return InferenceResponse(codec.encode(decoded, InverseAnswer(problem.model, results)), problem.n_targets)
