"""POST /predict: surrogate shapes for a batch of designs (JSON, or .npy in and .npz out).

A thin codec: on one worker thread the body is validated (it names the model), the data plane runs
it on that surrogate (or the default) and :class:`service.codecs.PredictCodec` encodes the answer.
A small body (JSON or ``.npy``: a few designs) that finds the service idle is validated on the event
loop instead, and the data plane then answers it there too when its model may
(:meth:`service.dataplane.DataPlane.infer`).
"""

from __future__ import annotations

from contextlib import contextmanager

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.codecs import PredictCodec
from service.dataplane import DataPlane
from service.deps import State
from service.errors import from_inference, from_invalid, require_json
from service.metrics import HTTP
from service.model import InferenceError, InferenceRequest, InferenceResponse
from tdcr.api.schemas import ErrorResponse, PredictResponse
from tdcr.api.validation import InvalidRequest, Limits, ShapeRequest
from tdcr.surrogates.engine import NPY, NPZ, QUERY_FIELDS, prepare_json, prepare_npy

router = APIRouter(tags=["predict"])
#: A body of at most this many bytes (a few designs, JSON or ``.npy``) is validated on the event
#: loop when the service is idle: a hand-off to a worker thread costs more than that.
INLINE_BODY_BYTES = 4096


def _prepare(body: bytes, binary: bool, params: dict[str, list[str]], limits: Limits) -> ShapeRequest:
    """The one validation path of either body (it names the model)."""
    return prepare_npy(body, params, limits=limits) if binary else prepare_json(body, limits=limits)


def _inference(shapes: ShapeRequest, npz: bool) -> dict:
    """The data plane's arguments for validated ``shapes`` (:meth:`DataPlane.infer`)."""
    return {"name": shapes.model, "request": InferenceRequest(shapes, PredictCodec(npz=npz)), "kind": "surrogate",
            "loads": shapes.n_loaded > 0, "protocol": HTTP, "endpoint": "/predict"}


@contextmanager
def _http_errors(binary: bool):
    """Validation's and the data plane's errors as HTTP errors (a ``.npy`` body's options are in
    the query)."""
    query = QUERY_FIELDS if binary else ()
    try:
        yield
    except InvalidRequest as exc:
        raise from_invalid(exc, query=query) from None
    except InferenceError as exc:
        raise from_inference(exc, query=query) from None


def _answer(plane: DataPlane, body: bytes, binary: bool, params: dict[str, list[str]], limits: Limits,
            npz: bool) -> InferenceResponse:
    """On one worker thread: validate the body, then the data plane runs it."""
    with _http_errors(binary):
        return plane.infer_blocking(**_inference(_prepare(body, binary, params, limits), npz))


@router.post(
    "/predict",
    summary="Surrogate shapes for a batch of designs",
    description=(
        "JSON body (`PredictRequest`), or a `.npy` body (`Content-Type: application/x-npy`) holding raw SI "
        "designs `(B, 15)` = [E, r, L, offset_0..3, pitch_0..3, tension_0..3] with `model`, `points` or "
        "repeated `s`, and `outputs` (subset of backbone,rotation,tendons) as query parameters.  "
        "`Accept: application/x-npz` answers with float32 arrays s (B, n) (fractions of L), arclength (B, n) m, "
        "backbone (B, n, 3) m, "
        "rotation (B, n, 3, 3), tendons (B, n, 4, 3) m and in_distribution (B,)."
    ),
    responses={
        200: {"model": PredictResponse, "content": {NPZ: {"schema": {"type": "string", "format": "binary"}}}},
        404: {"model": ErrorResponse}, 413: {"model": ErrorResponse}, 415: {"model": ErrorResponse},
        422: {"model": ErrorResponse},
        503: {"model": ErrorResponse, "description": "the service is starting, or with a tolerance the exact solver "
                                                     "that answers the designs over it is saturated or starting: "
                                                     "retry after the Retry-After header's seconds"},
        504: {"model": ErrorResponse, "description": "with a tolerance: the exact solver did not finish within the "
                                                     "deadline"},
    },
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/PredictRequest"}},
        NPY: {"schema": {"type": "string", "format": "binary"}},
    }}},
)
async def predict(request: Request, state: State) -> Response:
    content_type = request.headers.get("content-type", "")
    binary = content_type.startswith(NPY)
    if not binary:
        require_json(content_type)
    body = await request.body()
    params = {k: request.query_params.getlist(k) for k in request.query_params}
    npz = NPZ in request.headers.get("accept", "")
    plane = state.plane
    if len(body) <= INLINE_BODY_BYTES and plane.idle:
        with _http_errors(binary):
            answer = await plane.infer(**_inference(_prepare(body, binary, params, state.settings.predict_limits()),
                                                    npz))
    else:
        answer = await run_in_threadpool(_answer, plane, body, binary, params, state.settings.predict_limits(), npz)
    if npz:
        return Response(answer.body.content, media_type=NPZ, headers={"X-TDCR-Model": answer.body.model})
    return Response(answer.body, media_type="application/json")
