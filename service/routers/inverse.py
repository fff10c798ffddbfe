"""POST /inverse: tensions that put a design's tip on each target of a path (tdcr/search/inverse.py).

A thin codec over the ``inverse`` model (service/solver.py): ``model: exact`` runs in the solver
processes of /exact (its slots, deadline and admission); an operator runs in a worker thread,
with its Jacobian by central differences, and ``polish: true`` finishes each of its answers with
exact steps in a solver process.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from service.codecs import InverseCodec
from service.deps import State
from service.routers import json_route
from tdcr.api.schemas import ErrorResponse, InverseResponse

router = APIRouter(tags=["inverse"])
ROUTE = "/inverse"


@router.post(
    ROUTE,
    summary="Inverse kinematics: tensions that reach each target (bounded, least sum of squared tensions)",
    response_model=InverseResponse,
    responses={404: {"model": ErrorResponse}, 413: {"model": ErrorResponse}, 415: {"model": ErrorResponse},
               422: {"model": ErrorResponse}, 503: {"model": ErrorResponse, "description": json_route.UNAVAILABLE},
               504: {"model": ErrorResponse}},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/InverseRequest"}}}}},
)
async def inverse(request: Request, state: State) -> Response:
    return await json_route.answer(request, state, InverseCodec(), kind="inverse", endpoint=ROUTE)
