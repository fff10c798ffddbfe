"""POST /predict: surrogate shapes for a batch of designs (JSON, or .npy in and .npz out).

Thin: the data plane (service/dataplane.py) prepares, runs and encodes, off the event loop.
"""

from __future__ import annotations

import time

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from service.dataplane import NPY, NPZ, QUERY_FIELDS, DataPlane, ModelNotFound
from service.deps import Plane, State
from service.errors import ApiError, from_invalid, require_json
from service.metrics import HTTP
from tdcr.schemas import ErrorResponse, PredictResponse
from tdcr.validation import InvalidRequest

router = APIRouter(tags=["predict"])


def _answer(plane: DataPlane, body: bytes, content_type: str, accept: str, params: dict[str, list[str]]):
    """prepare -> run -> encode (blocking); ``(response, model, designs)``."""
    binary = content_type.startswith(NPY)
    if not binary:
        require_json(content_type)
    try:
        request = plane.prepare_npy(body, params) if binary else plane.prepare_json(body)
        prediction = plane.run(request)
    except InvalidRequest as exc:
        raise from_invalid(exc, query=QUERY_FIELDS if binary else ()) from None
    except ModelNotFound as exc:
        raise ApiError(404, str(exc), kind="not_found") from None
    if NPZ in accept:
        response = Response(plane.encode_npz(prediction), media_type=NPZ, headers={"X-TDCR-Model": prediction.model})
    else:
        response = Response(plane.encode_json(prediction), media_type="application/json")
    return response, prediction.model, prediction.n_designs


@router.post(
    "/predict",
    summary="Surrogate shapes for a batch of designs",
    description=(
        "JSON body (`PredictRequest`), or a `.npy` body (`Content-Type: application/x-npy`) holding raw SI "
        "designs `(B, 15)` = [E, r, L, offset_0..3, pitch_0..3, tension_0..3] with `model`, `points` or "
        "repeated `s`, and `outputs` (subset of backbone,rotation,tendons) as query parameters.  "
        "`Accept: application/x-npz` answers with float32 arrays s (B, n) m, backbone (B, n, 3) m, "
        "rotation (B, n, 3, 3), tendons (B, n, 4, 3) m and in_distribution (B,)."
    ),
    responses={
        200: {"model": PredictResponse, "content": {NPZ: {"schema": {"type": "string", "format": "binary"}}}},
        404: {"model": ErrorResponse}, 413: {"model": ErrorResponse}, 415: {"model": ErrorResponse},
        422: {"model": ErrorResponse},
    },
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/PredictRequest"}},
        NPY: {"schema": {"type": "string", "format": "binary"}},
    }}},
)
async def predict(request: Request, state: State, plane: Plane) -> Response:
    body = await request.body()
    params = {k: request.query_params.getlist(k) for k in request.query_params}
    started = time.perf_counter()
    response, name, n = await run_in_threadpool(
        _answer, plane, body, request.headers.get("content-type", ""),
        request.headers.get("accept", ""), params)
    state.metrics.latency.labels(HTTP, "/predict", name).observe(time.perf_counter() - started)
    state.metrics.designs.labels(HTTP, "/predict", name).inc(n)
    return response
