"""POST /inverse: tensions that put a design's tip on each target of a path (tdcr/inverse.py).

``model: exact`` runs in the solver processes of /exact (its slots, deadline and admission); an
operator runs in a worker thread through its batcher, with its Jacobian by central differences,
and ``polish: true`` finishes each of its answers with exact steps in a solver process.
"""

from __future__ import annotations

import time

import orjson
from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.dataplane import ModelNotFound
from service.deps import Plane, State
from service.errors import ApiError, from_invalid, require_json, solver_errors
from service.metrics import HTTP
from tdcr.inverse import answer, model_forward
from tdcr.schemas import EXACT_MODEL, ErrorResponse, InverseResponse
from tdcr.validation import InvalidRequest, InverseProblem, validate_inverse

router = APIRouter(tags=["inverse"])
ROUTE = "/inverse"


def _operator(plane, problem: InverseProblem) -> list[dict]:
    """An operator's answers (blocking: run off the event loop)."""
    _, predictor = plane.resolve(problem.model)

    def tip_pose(features):
        out = predictor.predict(features, [1.0], pose=True)
        return out["backbone"][:, -1].astype(float), out["rotation"][:, -1].astype(float)

    return answer(problem, model_forward(problem.design, tip_pose))


@router.post(
    ROUTE,
    summary="Inverse kinematics: tensions that reach each target (bounded, least sum of squared tensions)",
    response_model=InverseResponse,
    responses={404: {"model": ErrorResponse}, 413: {"model": ErrorResponse}, 415: {"model": ErrorResponse},
               422: {"model": ErrorResponse}, 503: {"model": ErrorResponse}, 504: {"model": ErrorResponse}},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/InverseRequest"}}}}},
)
async def inverse(request: Request, state: State, plane: Plane) -> Response:
    require_json(request.headers.get("content-type", ""))
    body = await request.body()
    started = time.perf_counter()
    try:
        problem = await run_in_threadpool(validate_inverse, body)
        starts = None
        if problem.model != EXACT_MODEL:
            try:
                results = await run_in_threadpool(_operator, plane, problem)
            except ModelNotFound as exc:
                raise ApiError(404, str(exc), kind="not_found") from None
            starts = [r["tensions"] for r in results]
        if problem.model == EXACT_MODEL or problem.polish:
            results = await _exact(state, body, starts)
    except InvalidRequest as exc:
        raise from_invalid(exc) from None
    state.metrics.latency.labels(HTTP, ROUTE, problem.model).observe(time.perf_counter() - started)
    state.metrics.designs.labels(HTTP, ROUTE, problem.model).inc(problem.n_targets)
    return Response(orjson.dumps({"model": problem.model, "results": results}), media_type="application/json")


async def _exact(state, body: bytes, starts: list | None) -> list[dict]:
    """The exact answers (or the polish of ``starts``) in a solver process, within /exact's limits."""
    settings = state.settings
    if state.pool is None or state.exact_slots is None:
        raise ApiError(503, "the solver pool is not running", kind="unavailable")
    if state.exact_slots.locked():
        raise ApiError(503, "the solver is saturated; retry later", kind="saturated", headers={"retry-after": "1"})
    async with state.exact_slots:
        with solver_errors(settings.exact_timeout_s):
            return await state.inverse_json(body, starts)
