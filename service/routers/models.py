"""GET /models: the manifest (names, metrics, ranges, inputs and outputs) and the default model."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import State

router = APIRouter(tags=["models"])


@router.get("/models", summary="The model manifest")
def models(state: State) -> dict:
    return {"default_model": state.default_model, "loaded": state.surrogates,
            "models": state.manifest.get("models", {})}
