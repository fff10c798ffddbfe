"""GET /healthz (alive), /readyz (models loaded, verified, warmed), /metrics (Prometheus)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness")
def healthz() -> dict:
    return {"status": "alive"}


@router.get("/readyz", summary="Readiness: every model loaded, checksum verified and warmed up",
            responses={503: {"description": "not ready"}})
def readyz(request: Request):
    state = request.app.state.service
    body = {"ready": state.ready, "models": sorted(state.models), "default_model": state.default_model,
            "problems": state.problems}
    return JSONResponse(body, status_code=200 if state.ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.service.metrics.registry), media_type=CONTENT_TYPE_LATEST)
