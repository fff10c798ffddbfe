"""POST /exact: the physics solver, in a bounded process pool with a per-request deadline."""

from __future__ import annotations

import logging
import time

import orjson
from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.deps import State
from service.errors import ApiError, from_invalid, require_json
from service.settings import Settings
from service.solver_pool import WorkerDied
from tdcr.design_space import DEFAULT_POINTS
from tdcr.exact import solve_request
from tdcr.schemas import ErrorResponse, ExactResponse
from tdcr.validation import InvalidRequest, Limits, ShapeRequest, validate_json

router = APIRouter(tags=["exact"])
log = logging.getLogger("tdcr.service")


def _estimated_seconds(request: ShapeRequest, settings: Settings) -> float:
    """Solver time of a request on one process: tendon-only designs scale with the points, loaded
    designs (shooting) with their count."""
    tendon_only = request.n_designs - request.n_loaded
    points = max(request.fractions.size, DEFAULT_POINTS) / DEFAULT_POINTS
    return (tendon_only * points * settings.exact_seconds_per_design
            + request.n_loaded * settings.exact_seconds_per_loaded_design)


def _prepare(body: bytes, limits: Limits) -> ShapeRequest:
    try:
        return validate_json(body, target="solver", limits=limits)
    except InvalidRequest as exc:
        raise from_invalid(exc) from None


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
    if state.exact_slots.locked():
        raise ApiError(503, "the solver is saturated; retry later", kind="saturated")
    require_json(request.headers.get("content-type", ""))
    body = await request.body()
    shape_request = await run_in_threadpool(_prepare, body, settings.exact_limits())  # parsing off the loop
    estimate = _estimated_seconds(shape_request, settings)
    if estimate > settings.exact_admission_factor * settings.exact_timeout_s:
        raise ApiError(413, f"these designs would take the solver about {estimate:.3g} s, more than "
                            f"{settings.exact_admission_factor:g} x its deadline of {settings.exact_timeout_s:g} s; "
                            "send fewer designs or points", kind="too_much_work")
    started = time.perf_counter()
    async with state.exact_slots:
        try:
            results = await state.pool.run(solve_request, shape_request, timeout=settings.exact_timeout_s)
        except TimeoutError:  # the worker was killed: its work stops with the deadline
            raise ApiError(504, f"the solver did not finish within {settings.exact_timeout_s} s",
                           kind="deadline") from None
        except WorkerDied as exc:
            raise ApiError(503, str(exc), kind="unavailable") from None
        except RuntimeError as exc:
            log.error("solver failed: %s", exc)
            raise ApiError(503, "the solver failed on this request", kind="solver") from None
    state.metrics.latency.labels("/exact", "solver").observe(time.perf_counter() - started)
    state.metrics.designs.labels("/exact", "solver").inc(shape_request.n_designs)
    return Response(orjson.dumps({"results": results}), media_type="application/json")
