"""A neural operator as a served :class:`service.model.Model`: its ONNX session behind a dynamic
batcher (service/batching.py), the surrogate engine of :mod:`tdcr.surrogates.engine`, and its inverse
kinematics (Jacobian by central differences)."""

from __future__ import annotations

import numpy as np
import orjson
from starlette.concurrency import run_in_threadpool

from service.batching import Batcher
from service.model import INLINE_DESIGNS, InferenceRequest, InferenceResponse, Model
from service.oip import LOAD_INPUTS, SURROGATE_INPUTS, SURROGATE_OUTPUTS
from tdcr.api.checks import InvalidRequest, check_model_loads
from tdcr.api.validation import InverseProblem, Limits
from tdcr.search.inverse import answer, model_forward, model_tip_pose
from tdcr.surrogates import engine
from tdcr.surrogates.runtime import Surrogate


class SurrogateModel(Model):
    """One exported operator (``surrogate``, with its manifest entry) behind ``batcher``; a loaded
    operator also takes the OIP inputs ``gravity``, ``density``, ``tip_force`` and ``tip_moment``."""

    kind = "surrogate"
    platform = "onnxruntime_onnx"
    inputs = SURROGATE_INPUTS
    outputs = SURROGATE_OUTPUTS
    blocking = True  # infer_blocking answers on the caller's worker thread (/predict)

    def __init__(self, surrogate: Surrogate, *, limits: Limits, batcher: Batcher):
        self.name = surrogate.name
        self.surrogate, self.limits, self.batcher = surrogate, limits, batcher
        #: its error bound and the exact solver behind its tolerance (:meth:`guard_with`, at startup)
        self.guard: engine.Guard | None = None
        if surrogate.takes_loads:
            self.inputs = SURROGATE_INPUTS | LOAD_INPUTS

    def guard_with(self, companion: SurrogateModel | None, exact) -> None:
        """Bound its answers (its calibration, scored against the served ``companion``; none
        without a calibration) and keep tolerances with ``exact`` (a sub-request ->
        :class:`tdcr.physics.exact.ExactAnswer`, blocking)."""
        self.guard = engine.Guard(calibration=self.surrogate.calibration,
                                  companion=None if companion is None else companion.batcher, exact=exact)

    def parameters(self) -> dict:
        """The manifest's sha256, architecture and kind; metrics and ranges as JSON text."""
        entry = self.surrogate.entry
        return {"sha256": entry["sha256"], "architecture": entry["architecture"], "kind": entry["kind"],
                "metrics": orjson.dumps(entry.get("metrics")).decode(),
                "ranges": orjson.dumps(entry.get("ranges")).decode()} | (
                    {"load_ranges": orjson.dumps(entry.get("load_ranges")).decode()} if self.surrogate.takes_loads
                    else {}) | (
                    {"calibration": orjson.dumps(entry["calibration"]).decode()} if "calibration" in entry else {})

    async def infer(self, request: InferenceRequest) -> InferenceResponse:
        return await run_in_threadpool(self.infer_blocking, request)  # decode, run and encode in one thread hop

    def answers_inline(self, request: InferenceRequest) -> bool:
        """A few designs without a tolerance: one graph run (a tolerance may wait on the solver)."""
        peek = request.peek()
        return peek is not None and peek.designs <= INLINE_DESIGNS and not peek.tolerance

    def infer_blocking(self, request: InferenceRequest) -> InferenceResponse:
        decoded = request.codec.decode(request.payload, self.spec)
        prediction = engine.predict(self.batcher, decoded.task, model=self.name, guard_with=self.guard)
        guarded = prediction.n_designs if decoded.task.tolerance is not None else 0
        return InferenceResponse(request.codec.encode(decoded, prediction), prediction.n_designs, guarded=guarded,
                                 exact=prediction.n_exact)

    def inverse(self, problem: InverseProblem) -> list[dict]:
        """Inverse kinematics with this operator (blocking: run it off the event loop); the design's
        loads (``problem.loads``) need a loaded operator (:class:`InvalidRequest` naming the field else;
        loads given as zeros are none)."""
        loads = problem.loads
        if not self.surrogate.takes_loads:
            problems = check_model_loads(loads, np.zeros(1, dtype=int), model=self.name)
            if problems:
                raise InvalidRequest([p._replace(loc=("design",) + p.loc[2:]) for p in problems])
            loads = None
        # validated; the differences may leave the bounds
        tip_pose = model_tip_pose(self.batcher.predict, load_row=None if loads is None else loads.matrix(1))
        return answer(problem, model_forward(problem.design, tip_pose))

    def close(self) -> None:
        self.batcher.close()
