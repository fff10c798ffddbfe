"""GET /models: the manifest (names, metrics, ranges, inputs and outputs), the default model and the
default for designs with loads (a loaded operator)."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import State

router = APIRouter(tags=["models"])


@router.get("/models", summary="The model manifest")
def models(state: State) -> dict:
    return {"default_model": state.default_model, "default_loaded_model": state.default_loaded_model,
            "loaded": state.surrogates, "models": state.manifest.get("models", {})}
