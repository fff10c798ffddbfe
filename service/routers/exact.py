"""POST /exact: the physics solver, in a bounded process pool with a per-request deadline.

A thin codec: the raw body goes to the data plane with :class:`service.codecs.ExactCodec`; the
solver model parses, validates, admits, solves and encodes it in one of its processes.  While every
solver slot is taken, the ``ExactAdmission`` middleware (service/app.py) answers 503 before the
body is read.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from service.codecs import ExactCodec
from service.deps import State
from service.routers import json_route
from tdcr.api.schemas import ErrorResponse, ExactResponse

router = APIRouter(tags=["exact"])
ROUTE = "/exact"


@router.post(
    ROUTE,
    summary="Exact equilibria from the Cosserat solver",
    response_model=ExactResponse,
    responses={413: {"model": ErrorResponse, "description": "too many designs, or more work than the deadline allows"},
               415: {"model": ErrorResponse}, 422: {"model": ErrorResponse},
               503: {"model": ErrorResponse, "description": json_route.UNAVAILABLE},
               504: {"model": ErrorResponse}},
    description="A request (ExactRequest), or a robot file (RobotFile, e.g. what `tdcr fit` writes): its design "
                "at the default arclengths, once the whole file passes the checks of `tdcr replay`.",
    openapi_extra={"requestBody": {"required": True, "content": {"application/json": {"schema": {"anyOf": [
        {"$ref": "#/components/schemas/ExactRequest"}, {"$ref": "#/components/schemas/RobotFile"}]}}}}},
)
async def exact(request: Request, state: State) -> Response:
    return await json_route.answer(request, state, ExactCodec(), kind="solver", endpoint=ROUTE)
