"""GET /models: the manifest (names, metrics, ranges, inputs and outputs), the default model and the
default for designs with loads (the router ``auto``, or a configured model), the operator the
router answers with, and the operators served (``loaded``)."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import State

router = APIRouter(tags=["models"])


@router.get("/models", summary="The model manifest")
def models(state: State) -> dict:
    # sync on purpose: FastAPI then encodes the manifest (tens of kB) on a worker thread, off the
    # event loop that answers one-design requests (a docstring here would be the OpenAPI description)
    return {"default_model": state.default_model, "default_loaded_model": state.default_loaded_model,
            "default_operator": state.default_operator, "default_loaded_operator": state.default_loaded_operator,
            "loaded": state.surrogates,
            "models": state.manifest.get("models", {})}
