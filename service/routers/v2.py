"""The Open Inference Protocol v2 over REST: thin routes over the one data plane, with the codec
:class:`service.oip.RestCodec`.  Every model path also takes the optional ``/versions/{version}``
segment (the only version is ``1``)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse

from service.deps import State
from service.errors import retry_headers
from service.metrics import HTTP
from service.model import InferenceError, InferenceRequest
from service.oip import HEADER_LENGTH, HTTP_STATUS, OipErrorBody, RestCodec
from service.state import ServiceState

router = APIRouter(prefix="/v2", tags=["v2"])
INFER = "/v2/models/{model}/infer"


def _error(state: ServiceState, route: str, exc: InferenceError) -> JSONResponse:
    """The one mapping of data-plane errors to OIP REST answers."""
    state.metrics.errors.labels(HTTP, route, exc.kind).inc()
    return JSONResponse({"error": exc.message}, status_code=HTTP_STATUS[exc.kind], headers=retry_headers(exc))


def _routes(path: str, **kwargs):
    """Register an endpoint at ``/models/{model}<path>`` and ``/models/{model}/versions/{version}<path>``."""
    def register(fn):
        for prefix in ("/models/{model}", "/models/{model}/versions/{version}"):
            router.add_api_route(prefix + path, fn, **kwargs)
        return fn
    return register


@router.get("/health/live", summary="OIP liveness")
async def live() -> dict:
    return {"live": True}


@router.get("/health/ready", summary="OIP readiness (every model loaded and the solver pool up)",
            responses={503: {"description": "not ready"}})
async def ready(state: State):
    ok = state.plane.server_ready()
    return JSONResponse({"ready": ok}, status_code=200 if ok else 503)


@router.get("", summary="OIP server metadata")
async def server_metadata(state: State) -> dict:
    return state.plane.server_metadata()


NOT_FOUND = {404: {"model": OipErrorBody, "description": "unknown model or version"}}


@_routes("", methods=["GET"], summary="OIP model metadata", responses=NOT_FOUND)
async def model_metadata(state: State, model: str, version: str | None = None):
    try:
        return state.plane.model_metadata(model, version)
    except InferenceError as exc:
        return _error(state, "/v2/models/{model}", exc)


@_routes("/ready", methods=["GET"], summary="OIP model readiness",
         responses=NOT_FOUND | {503: {"description": "the solver pool is down (model exact)"}})
async def model_ready(state: State, model: str, version: str | None = None):
    try:
        ok = state.plane.model_ready(model, version)
    except InferenceError as exc:
        return _error(state, "/v2/models/{model}/ready", exc)
    return JSONResponse({"name": model, "ready": ok}, status_code=200 if ok else 503)


@_routes("/infer", methods=["POST"], summary="OIP inference (JSON tensors or the binary tensor extension)",
         responses={200: {"content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
                    400: {"model": OipErrorBody}, 404: {"model": OipErrorBody}, 413: {"model": OipErrorBody},
                    503: {"model": OipErrorBody}, 504: {"model": OipErrorBody}},
         openapi_extra={"requestBody": {"required": True, "content": {
             "application/json": {"schema": {"$ref": "#/components/schemas/InferenceRequest"}},
             "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def infer(request: Request, state: State, model: str, version: str | None = None):
    body = await request.body()
    codec = RestCodec(header_length=request.headers.get(HEADER_LENGTH))
    try:
        answer = await state.plane.infer(model, InferenceRequest(body, codec), version=version, protocol=HTTP,
                                         endpoint=INFER)
    except InferenceError as exc:
        return _error(state, INFER, exc)
    payload, json_length = answer.body
    if json_length is None:
        return Response(payload, media_type="application/json")
    return Response(payload, media_type="application/octet-stream", headers={HEADER_LENGTH: str(json_length)})
