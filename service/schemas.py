"""Request and response bodies of the HTTP API (designs and arclengths as in ``training.schemas``)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from training.schemas import SolveRequest


class PredictRequest(SolveRequest):
    """Designs, arclengths and the surrogate to use (default: the most accurate in the manifest)."""

    model_config = ConfigDict(extra="forbid")
    model: str | None = Field(None, description="deeponet, deeponet_pose, fno or fno_pose", examples=["deeponet"])


class ExactRequest(SolveRequest):
    """Designs (optionally with gravity and tip loads) and arclengths for the physics solver."""


class PredictedShape(BaseModel):
    s: list[float] = Field(description="arclengths, m")
    backbone: list[list[float]] = Field(description="(n, 3) backbone positions, m")
    rotation: list[list[list[float]]] = Field(description="(n, 3, 3) frames, body axes as columns")
    tendons: list[list[list[float]]] = Field(description="(n, N_t, 3) tendon positions, m")
    in_distribution: bool = Field(description="every parameter inside the trained ranges")
    warnings: list[str] = Field(description="one line per parameter outside the trained ranges")


class PredictResponse(BaseModel):
    model: str
    results: list[PredictedShape]


class ExactShape(BaseModel):
    s: list[float]
    backbone: list[list[float]]
    rotation: list[list[list[float]]]
    tendons: list[list[list[float]]]
    converged: bool
    residual: float = Field(description="wrench-balance residual, N")


class ExactResponse(BaseModel):
    results: list[ExactShape]


class ErrorItem(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ErrorResponse(BaseModel):
    """Every 4xx/5xx body: a one-line ``message`` and, for 422, the items naming each bad field."""

    message: str
    detail: list[ErrorItem] | str
