"""JSON schemas of designs, requests and solutions (pydantic), shared by the CLI and the service.

Units are SI: E in Pa, r, L and offsets in m, pitch in rad/m, tension in N, gravity in m/s^2,
density in kg/m^3, tip force in N, tip moment in N m, arclengths ``s`` as fractions of L.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from training.designs import DesignBatch, ExternalLoads

MAX_POINTS = 1000
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Vector3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]


class Tendon(BaseModel):
    """One tendon: radial offset (m), helical pitch (rad/m) and tension (N, >= 0)."""

    model_config = ConfigDict(extra="forbid")
    offset: Positive = Field(description="distance of the tendon from the backbone axis, m")
    pitch: Finite = Field(0.0, description="helical pitch of the routing, rad/m")
    tension: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(description="tendon tension, N")


class Design(BaseModel):
    """A TDCR design in SI units, with optional external loads for the physics solver."""

    model_config = ConfigDict(extra="forbid")
    E: Positive = Field(description="Young's modulus, Pa")
    r: Positive = Field(description="backbone radius, m")
    L: Positive = Field(description="backbone length, m")
    tendons: list[Tendon] = Field(min_length=1, max_length=64)
    gravity: Vector3 | None = Field(None, description="gravitational acceleration, base frame, m/s^2")
    density: Positive | None = Field(None, description="backbone density, kg/m^3 (with gravity)")
    tip_force: Vector3 | None = Field(None, description="tip force, base frame, N")
    tip_moment: Vector3 | None = Field(None, description="tip moment, base frame, N m")

    @model_validator(mode="after")
    def _gravity_needs_density(self) -> Design:
        if self.gravity is not None and any(self.gravity) and self.density is None:
            raise ValueError("gravity needs a density (kg/m^3)")
        return self

    def has_loads(self) -> bool:
        return any(v is not None and any(v) for v in (self.tip_force, self.tip_moment)) or (
            self.gravity is not None and any(self.gravity)
        )


class SolveRequest(BaseModel):
    """A batch of designs and the arclengths wanted: ``points`` equispaced, or explicit ``s``."""

    model_config = ConfigDict(extra="forbid")
    designs: list[Design] = Field(min_length=1)
    points: Annotated[int, Field(ge=2, le=MAX_POINTS)] | None = Field(
        None, description="number of equispaced arclengths on [0, L] (default 42)")
    s: Annotated[list[Finite], Field(min_length=1, max_length=MAX_POINTS)] | None = Field(
        None, description="arclengths as fractions of L, each in [0, 1]")

    @field_validator("s")
    @classmethod
    def _fractions(cls, s: list[float] | None) -> list[float] | None:
        if s is not None:
            for i, v in enumerate(s):
                if not 0.0 <= v <= 1.0:
                    raise ValueError(f"s[{i}] = {v} is not a fraction of L in [0, 1]")
        return s

    @model_validator(mode="after")
    def _points_or_s(self) -> SolveRequest:
        if self.points is not None and self.s is not None:
            raise ValueError("give either 'points' or 's', not both")
        return self

    def fractions(self) -> np.ndarray:
        """Requested arclength fractions, ``(n,)``."""
        if self.s is not None:
            return np.asarray(self.s, dtype=np.float64)
        return np.linspace(0.0, 1.0, self.points or 42)


class RodResult(BaseModel):
    """One design's equilibrium: s (m), backbone (n, 3) m, rotation (n, 3, 3), tendons (n, N_t, 3) m."""

    s: list[float]
    backbone: list[list[float]]
    rotation: list[list[list[float]]]
    tendons: list[list[list[float]]]
    converged: bool | None = None
    residual: float | None = None


def group_by_tendon_count(designs: list[Design]) -> dict[int, list[int]]:
    """Indices of the designs, grouped by their number of tendons."""
    groups: dict[int, list[int]] = {}
    for i, d in enumerate(designs):
        groups.setdefault(len(d.tendons), []).append(i)
    return groups


def to_batch(designs: list[Design]) -> DesignBatch:
    """Arrays of designs that all have the same number of tendons."""
    counts = {len(d.tendons) for d in designs}
    if len(counts) != 1:
        raise ValueError("all designs in one batch must have the same number of tendons")
    return DesignBatch(
        E=[d.E for d in designs], r=[d.r for d in designs], L=[d.L for d in designs],
        offset=[[t.offset for t in d.tendons] for d in designs],
        pitch=[[t.pitch for t in d.tendons] for d in designs],
        tension=[[t.tension for t in d.tendons] for d in designs],
    )


def to_loads(designs: list[Design]) -> ExternalLoads | None:
    """External loads of the batch, or ``None`` when no design has any."""
    if not any(d.has_loads() for d in designs):
        return None
    zero3 = [0.0, 0.0, 0.0]
    return ExternalLoads(
        gravity=np.array([d.gravity or zero3 for d in designs]),
        density=np.array([d.density or 0.0 for d in designs]),
        tip_force=np.array([d.tip_force or zero3 for d in designs]),
        tip_moment=np.array([d.tip_moment or zero3 for d in designs]),
    )


def format_error_location(loc: tuple) -> str:
    """Pydantic error location -> 'designs[3].tendons[1].tension'."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out
