"""GET /models: the manifest (names, metrics, ranges, inputs and outputs) and the default model."""

from __future__ import annotations

from fastapi import APIRouter, Request

router = APIRouter(tags=["models"])


@router.get("/models", summary="The model manifest")
def models(request: Request) -> dict:
    state = request.app.state.service
    return {"default_model": state.default_model, "loaded": sorted(state.models),
            "models": state.manifest.get("models", {})}
