"""GET /healthz (alive), /readyz (models loaded, verified, warmed), /metrics (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.deps import State

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness")
async def healthz() -> dict:
    return {"status": "alive"}


@router.get("/readyz", summary="Readiness: every model loaded, checksum verified and warmed up; the solver may "
                              "still be starting (listed under `starting`: /exact says 503 meanwhile) or "
                              "compiling its other paths (under `compiling`: a request on one says 503)",
            responses={503: {"description": "not ready"}})
async def readyz(state: State):
    ready = state.plane.server_ready()
    body = {"ready": ready, "models": state.surrogates, "default_model": state.default_model,
            "problems": state.problems + state.plane.problems(), "starting": state.plane.starting_models(),
            "compiling": state.plane.compiling()}
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
def metrics(state: State) -> Response:
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
