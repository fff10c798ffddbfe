"""The Open Inference Protocol v2 over REST: thin routes over :class:`service.v2plane.V2Plane` and the
codec of service/oip.py.  Every model path also takes the optional ``/versions/{version}`` segment
(the only version is ``1``)."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from service.deps import State
from service.metrics import HTTP
from service.oip import HEADER_LENGTH, OipError, OipErrorBody, decode, encode
from service.state import ServiceState
from service.v2plane import SOLVER_MODELS, V2Plane

router = APIRouter(prefix="/v2", tags=["v2"])


def get_plane(state: State) -> V2Plane:
    return V2Plane(state)


Plane = Annotated[V2Plane, Depends(get_plane)]


def _error(state: ServiceState, route: str, exc: OipError) -> JSONResponse:
    state.metrics.errors.labels(HTTP, route, exc.kind).inc()
    return JSONResponse({"error": exc.message}, status_code=exc.status)


def _routes(path: str, **kwargs):
    """Register an endpoint at ``/models/{model}<path>`` and ``/models/{model}/versions/{version}<path>``."""
    def register(fn):
        for prefix in ("/models/{model}", "/models/{model}/versions/{version}"):
            router.add_api_route(prefix + path, fn, **kwargs)
        return fn
    return register


@router.get("/health/live", summary="OIP liveness")
def live() -> dict:
    return {"live": True}


@router.get("/health/ready", summary="OIP readiness (every model loaded and the solver pool up)",
            responses={503: {"description": "not ready"}})
def ready(plane: Plane):
    ok = plane.server_ready()
    return JSONResponse({"ready": ok}, status_code=200 if ok else 503)


@router.get("", summary="OIP server metadata")
def server_metadata(plane: Plane) -> dict:
    return plane.server_metadata()


NOT_FOUND = {404: {"model": OipErrorBody, "description": "unknown model or version"}}


@_routes("", methods=["GET"], summary="OIP model metadata", responses=NOT_FOUND)
def model_metadata(plane: Plane, model: str, version: str | None = None):
    try:
        return plane.model_metadata(model, version)
    except OipError as exc:
        return _error(plane.state, "/v2/models/{model}", exc)


@_routes("/ready", methods=["GET"], summary="OIP model readiness",
         responses=NOT_FOUND | {503: {"description": "the solver pool is down (model exact)"}})
def model_ready(plane: Plane, model: str, version: str | None = None):
    try:
        ok = plane.model_ready(model, version)
    except OipError as exc:
        return _error(plane.state, "/v2/models/{model}/ready", exc)
    return JSONResponse({"name": model, "ready": ok}, status_code=200 if ok else 503)


def _surrogate(plane: V2Plane, model: str, body: bytes, header_length: str | None):
    inputs, outputs, required = plane.tensors(model)
    request = decode(body, header_length, inputs=inputs, outputs=outputs, required=required)
    tensors, n = plane.surrogate(model, request)
    return encode(model, tensors, request.outputs, request.id), n


def _solver_request(plane: V2Plane, model: str, body: bytes, header_length: str | None):
    inputs, outputs, required = plane.tensors(model)
    request = decode(body, header_length, inputs=inputs, outputs=outputs, required=required)
    return request, *plane.solver_body(model, request)


@_routes("/infer", methods=["POST"], summary="OIP inference (JSON tensors or the binary tensor extension)",
         responses={200: {"content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
                    400: {"model": OipErrorBody}, 404: {"model": OipErrorBody}, 413: {"model": OipErrorBody},
                    503: {"model": OipErrorBody}, 504: {"model": OipErrorBody}},
         openapi_extra={"requestBody": {"required": True, "content": {
             "application/json": {"schema": {"$ref": "#/components/schemas/InferenceRequest"}},
             "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def infer(request: Request, plane: Plane, model: str, version: str | None = None):
    route = "/v2/models/{model}/infer"
    body = await request.body()
    header_length = request.headers.get(HEADER_LENGTH)
    started = time.perf_counter()
    try:
        plane.check_model(model, version)
        if model in SOLVER_MODELS:  # decoding and the solver request off the loop, the solve in the pool
            decoded, features, solver_body = await run_in_threadpool(_solver_request, plane, model, body,
                                                                     header_length)
            tensors, n = await plane.solver(model, decoded, features, solver_body)
            payload, json_length = encode(model, tensors, decoded.outputs, decoded.id)
        else:  # decode, run and encode in one thread hop
            (payload, json_length), n = await run_in_threadpool(_surrogate, plane, model, body, header_length)
    except OipError as exc:
        return _error(plane.state, route, exc)
    metrics = plane.state.metrics
    metrics.latency.labels(HTTP, route, model).observe(time.perf_counter() - started)
    metrics.designs.labels(HTTP, route, model).inc(n)
    if json_length is None:
        return Response(payload, media_type="application/json")
    return Response(payload, media_type="application/octet-stream", headers={HEADER_LENGTH: str(json_length)})
