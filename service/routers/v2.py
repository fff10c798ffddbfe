"""The Open Inference Protocol v2 over REST (service/oip.py): health, metadata and inference for
every operator and for the physics solver as the model ``exact``.  Every model path also takes the
optional ``/versions/{version}`` segment (the only version is ``1``)."""

from __future__ import annotations

import time

import numpy as np
import orjson
from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

import tdcr
from service.dataplane import ModelNotFound
from service.deps import State
from service.oip import (
    EXACT_OUTPUTS,
    HEADER_LENGTH,
    LOAD_INPUTS,
    SURROGATE_INPUTS,
    SURROGATE_OUTPUTS,
    OipError,
    OipErrorBody,
    decode,
    encode,
    tensor_metadata,
)
from service.solver_pool import WorkerDied
from service.state import ServiceState
from tdcr.design_space import range_warnings
from tdcr.designs import DesignBatch
from tdcr.exact import TooMuchWork
from tdcr.validation import OUTPUTS, InvalidRequest, validate_features

router = APIRouter(prefix="/v2", tags=["v2"])
EXACT = "exact"
VERSION = "1"
EXACT_INPUTS = SURROGATE_INPUTS | LOAD_INPUTS


def _error(state: ServiceState, route: str, status: int, message: str, kind: str) -> JSONResponse:
    state.metrics.errors.labels(route, kind).inc()
    return JSONResponse({"error": message}, status_code=status)


def _check_model(state: ServiceState, model: str, version: str | None) -> None:
    if model != EXACT and model not in state.models:
        raise OipError(404, f"unknown model {model[:64]!r}; available: {sorted(state.models) + [EXACT]}")
    if version not in (None, VERSION):
        raise OipError(404, f"model {model!r} has only version {VERSION}, not {version[:16]!r}")


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
def ready(state: State):
    ok = state.ready and state.pool_healthy
    return JSONResponse({"ready": ok}, status_code=200 if ok else 503)


@router.get("", summary="OIP server metadata")
def server_metadata() -> dict:
    return {"name": "tdcr-surrogates", "version": tdcr.__version__, "extensions": ["binary_tensor_data"]}


NOT_FOUND = {404: {"model": OipErrorBody, "description": "unknown model or version"}}


@_routes("", methods=["GET"], summary="OIP model metadata", responses=NOT_FOUND)
def model_metadata(state: State, model: str, version: str | None = None):
    try:
        _check_model(state, model, version)
    except OipError as exc:
        return _error(state, "/v2/models/{model}", exc.status, exc.message, "not_found")
    if model == EXACT:
        return {"name": EXACT, "versions": [VERSION], "platform": "tdcr_cosserat_solver",
                "inputs": tensor_metadata(EXACT_INPUTS), "outputs": tensor_metadata(EXACT_OUTPUTS),
                "parameters": {"deadline_s": state.settings.exact_timeout_s}}
    entry = state.manifest["models"][model]
    return {"name": model, "versions": [VERSION], "platform": "onnxruntime_onnx",
            "inputs": tensor_metadata(SURROGATE_INPUTS), "outputs": tensor_metadata(SURROGATE_OUTPUTS),
            "parameters": {"sha256": entry["sha256"], "architecture": entry["architecture"], "kind": entry["kind"],
                           "metrics": orjson.dumps(entry.get("metrics")).decode(),
                           "ranges": orjson.dumps(entry.get("ranges")).decode()}}


@_routes("/ready", methods=["GET"], summary="OIP model readiness",
         responses=NOT_FOUND | {503: {"description": "the solver pool is down (model exact)"}})
def model_ready(state: State, model: str, version: str | None = None):
    try:
        _check_model(state, model, version)
    except OipError as exc:
        return _error(state, "/v2/models/{model}/ready", exc.status, exc.message, "not_found")
    ok = state.pool_healthy if model == EXACT else True
    return JSONResponse({"name": model, "ready": ok}, status_code=200 if ok else 503)


def _surrogate(state: ServiceState, model: str, body: bytes, header_length: str | None):
    request = decode(body, header_length, inputs=SURROGATE_INPUTS, outputs=SURROGATE_OUTPUTS)
    arrays_wanted = [n for n in request.outputs if n in OUTPUTS]
    try:
        shape_request = validate_features(request.inputs["design"], target="surrogate", model=model,
                                          s=request.inputs.get("s"), outputs=arrays_wanted or ["tendons"],
                                          limits=state.settings.predict_limits())
        prediction = state.dataplane.run(shape_request)
    except InvalidRequest as exc:
        raise OipError(413 if exc.too_large else 400, f"input 'design' or 's': {exc.message}") from None
    except ModelNotFound as exc:
        raise OipError(404, str(exc)) from None
    values = {"in_distribution": ("BOOL", np.array([not w for w in prediction.warnings]))}
    values |= {k: ("FP32", v) for k, v in prediction.arrays.items()}
    return encode(model, {n: values[n] for n in request.outputs}, request.outputs, request.id), len(prediction.s)


def _solve_request(body: bytes, header_length: str | None):
    """The decoded v2 request, its designs ``(B, 15)`` and the equivalent JSON ``SolveRequest``."""
    request = decode(body, header_length, inputs=EXACT_INPUTS, outputs=EXACT_OUTPUTS)
    features = np.asarray(request.inputs["design"], dtype=np.float64)
    designs = DesignBatch.from_features(features).to_dicts()
    for name in LOAD_INPUTS:
        if name in request.inputs:
            values = request.inputs[name]
            if len(values) != len(designs):
                raise OipError(400, f"input {name!r} has {len(values)} rows, 'design' has {len(designs)}")
            for d, v in zip(designs, values.tolist(), strict=True):
                d[name] = v
    solve_body = {"designs": designs} | ({"s": request.inputs["s"].tolist()} if "s" in request.inputs else {})
    return request, features, orjson.dumps(solve_body)


async def _exact(state: ServiceState, body: bytes, header_length: str | None):
    request, features, solve_body = await run_in_threadpool(_solve_request, body, header_length)  # off the loop
    if state.pool is None or state.exact_slots is None or state.exact_slots.locked():
        raise OipError(503, "the solver is saturated or not running; retry later")
    async with state.exact_slots:
        try:
            results = await state.solve_json(solve_body)
        except InvalidRequest as exc:
            raise OipError(413 if exc.too_large else 400, f"inputs: {exc.message}") from None
        except TooMuchWork as exc:
            raise OipError(413, str(exc)) from None
        except TimeoutError:
            raise OipError(504, f"the solver did not finish within {state.settings.exact_timeout_s} s") from None
        except (WorkerDied, RuntimeError):
            raise OipError(503, "the solver failed on this request; retry later") from None
    values = {"backbone": ("FP32", np.array([r["backbone"] for r in results])),
              "rotation": ("FP32", np.array([r["rotation"] for r in results])),
              "tendons": ("FP32", np.array([r["tendons"] for r in results])),
              "in_distribution": ("BOOL", np.array([not w for w in range_warnings(features)])),
              "converged": ("BOOL", np.array([r["converged"] for r in results])),
              "residual": ("FP64", np.array([r["residual"] for r in results]))}
    return encode(EXACT, {n: values[n] for n in request.outputs}, request.outputs, request.id), len(results)


@_routes("/infer", methods=["POST"], summary="OIP inference (JSON tensors or the binary tensor extension)",
         responses={200: {"content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
                    400: {"model": OipErrorBody}, 404: {"model": OipErrorBody}, 413: {"model": OipErrorBody},
                    503: {"model": OipErrorBody}, 504: {"model": OipErrorBody}},
         openapi_extra={"requestBody": {"required": True, "content": {
             "application/json": {"schema": {"$ref": "#/components/schemas/InferenceRequest"}},
             "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def infer(request: Request, state: State, model: str, version: str | None = None):
    route = "/v2/models/{model}/infer"
    body = await request.body()
    header_length = request.headers.get(HEADER_LENGTH)
    started = time.perf_counter()
    try:
        _check_model(state, model, version)
        if model == EXACT:
            (payload, json_length), n = await _exact(state, body, header_length)
        else:
            (payload, json_length), n = await run_in_threadpool(_surrogate, state, model, body, header_length)
    except OipError as exc:
        return _error(state, route, exc.status, exc.message, f"oip_{exc.status}")
    state.metrics.latency.labels("/v2 infer", model).observe(time.perf_counter() - started)
    state.metrics.designs.labels("/v2 infer", model).inc(n)
    if json_length is None:
        return Response(payload, media_type="application/json")
    return Response(payload, media_type="application/octet-stream", headers={HEADER_LENGTH: str(json_length)})
