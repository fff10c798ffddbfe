"""POST /exact: the physics solver, in a bounded process pool with a per-request deadline."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response

from service.deps import State
from service.errors import ApiError, from_invalid, require_json, solver_errors
from service.metrics import HTTP
from tdcr.schemas import ErrorResponse, ExactResponse
from tdcr.validation import InvalidRequest

router = APIRouter(tags=["exact"])


@router.post(
    "/exact",
    summary="Exact equilibria from the Cosserat solver",
    response_model=ExactResponse,
    responses={413: {"model": ErrorResponse, "description": "too many designs, or more work than the deadline allows"},
               415: {"model": ErrorResponse}, 422: {"model": ErrorResponse},
               503: {"model": ErrorResponse},
               504: {"model": ErrorResponse}},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/ExactRequest"}}}}},
)
async def exact(request: Request, state: State) -> Response:
    settings = state.settings
    if state.pool is None or state.exact_slots is None:
        raise ApiError(503, "the solver pool is not running", kind="unavailable")
    if state.exact_slots.locked():  # admission before the body is read
        # closing the connection stops the upload of a body nobody will read
        raise ApiError(503, "the solver is saturated; retry later", kind="saturated",
                       headers={"connection": "close", "retry-after": "1"})
    async with state.exact_slots:  # held from reading the body to the answer
        require_json(request.headers.get("content-type", ""))
        body = await request.body()
        started = time.perf_counter()
        try:  # parsing, validation, admission and solving all run in a solver process
            with solver_errors(settings.exact_timeout_s):
                designs, answer = await state.exact_response(body)
        except InvalidRequest as exc:
            raise from_invalid(exc) from None
    state.metrics.latency.labels(HTTP, "/exact", "solver").observe(time.perf_counter() - started)
    state.metrics.designs.labels(HTTP, "/exact", "solver").inc(designs)
    return Response(answer, media_type="application/json")
