"""POST /exact: the physics solver, in a bounded process pool with a per-request deadline."""

from __future__ import annotations

import asyncio
import time
from concurrent.futures.process import BrokenProcessPool

import orjson
from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.errors import ApiError
from service.schemas import ErrorResponse, ExactRequest, ExactResponse
from service.state import ServiceState, new_pool
from training.exact import solve_request_dicts

router = APIRouter(tags=["exact"])


@router.post(
    "/exact",
    summary="Exact equilibria from the Cosserat solver",
    response_model=ExactResponse,
    responses={413: {"model": ErrorResponse}, 422: {"model": ErrorResponse}, 503: {"model": ErrorResponse},
               504: {"model": ErrorResponse}},
)
async def exact(body: ExactRequest, request: Request) -> Response:
    state: ServiceState = request.app.state.service
    settings = state.settings
    if len(body.designs) > settings.exact_max_designs:
        raise ApiError(413, f"{len(body.designs)} designs exceed the /exact limit of {settings.exact_max_designs}")
    sigma = body.fractions()
    if sigma.size > settings.max_points:
        raise ApiError(413, f"{sigma.size} points exceed the limit of {settings.max_points}")
    if state.pool is None or state.exact_slots is None:
        raise ApiError(503, "the solver pool is not running", kind="unavailable")
    if state.exact_slots.locked():
        raise ApiError(503, "the solver is saturated; retry later", kind="saturated")
    designs = [d.model_dump() for d in body.designs]
    started = time.perf_counter()
    async with state.exact_slots:
        loop = asyncio.get_running_loop()
        future = loop.run_in_executor(state.pool, solve_request_dicts, designs, sigma.tolist())
        try:
            results = await asyncio.wait_for(future, timeout=settings.exact_timeout_s)
        except TimeoutError:
            raise ApiError(504, f"the solver did not finish within {settings.exact_timeout_s} s",
                           kind="deadline") from None
        except BrokenProcessPool:
            state.pool = await run_in_threadpool(new_pool, settings)  # never block the event loop
            raise ApiError(503, "a solver process died; the pool was restarted", kind="unavailable") from None
    state.metrics.latency.labels("/exact", "solver").observe(time.perf_counter() - started)
    state.metrics.designs.labels("/exact", "solver").inc(len(designs))
    return Response(orjson.dumps({"results": results}), media_type="application/json")
