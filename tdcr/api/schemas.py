"""JSON schemas of requests and answers (pydantic), shared by the CLI, the clients and the service.

The schemas check *types and structure* only.  Every value check (finite, admissible physical
bounds, arclengths, sizes) runs afterwards, vectorised, in :mod:`tdcr.api.validation`, the one
validation path of every entry point; the bounds still appear in the JSON schema (and so in
``openapi/openapi.json``), generated from :mod:`tdcr.robot.design_space`.

Units are SI: E in Pa, r, L and offsets in m, pitch in rad/m, tension in N, gravity in m/s^2,
density in kg/m^3, tip force in N, tip moment in N m, arclengths ``s`` as fractions of L.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, create_model

from tdcr.physics.cosserat import TERMINATIONS
from tdcr.robot.design_space import (
    DEFAULT_POINTS,
    FRACTION_ROUNDING,
    LOADS,
    MAX_POINTS,
    MAX_TENDONS,
    N_TENDONS,
    TABLE_I,
)
from tdcr.robot.fields import FEATURES, OPTIONAL, DesignField
from tdcr.surrogates.bounds import EXACT_TOLERANCE

#: Longest model name a request may carry.
MAX_MODEL_NAME = 64
#: The physics solver's name where a request names a model (/inverse, the v2 protocol).
EXACT_MODEL = "exact"


def _bounds(low: float, high: float, exclusive_min: bool) -> dict:
    """JSON-schema bounds (documentation for clients and fuzzers; enforced by tdcr.api.validation)."""
    return {"exclusiveMinimum" if exclusive_min else "minimum": low, "maximum": high}


def _number(bound):
    low, high = bound.admissible
    return Annotated[float, Field(strict=True, json_schema_extra=_bounds(low, high, bound.exclusive_min))]


def _vector3(bound):
    low, high = bound.admissible
    item = Annotated[float, Field(strict=True, json_schema_extra=_bounds(low, high, bound.exclusive_min))]
    return Annotated[list[item], Field(min_length=3, max_length=3)]


#: An arclength fraction: [0, 1], within rounding (``FRACTION_ROUNDING``; clamped onto [0, 1]).
#: An arclength in metres (in [0, L], checked against each design).
_Metres = Annotated[float, Field(strict=True, json_schema_extra={"minimum": 0.0,
                                                                 "maximum": TABLE_I["L"].admissible[1]})]
_Fraction = Annotated[float, Field(strict=True, json_schema_extra={"minimum": -FRACTION_ROUNDING,
                                                                   "maximum": 1.0 + FRACTION_ROUNDING})]


def _layout(bound):
    """An optional field of the general design (:data:`tdcr.robot.fields.OPTIONAL`), with its bounds."""
    low, high = bound.admissible
    extra = {"exclusiveMinimum" if bound.exclusive_min else "minimum": low,
             "exclusiveMaximum" if bound.exclusive_max else "maximum": high}
    unit = f", {bound.unit}" if bound.unit else ""
    return Field(None, description=f"{bound.description}{unit}", json_schema_extra=extra)


_FloatOrNone = Annotated[float | None, Field(strict=True)]


def _field(field: DesignField, *, replaced_by: str | None = None):
    """``(annotation, FieldInfo)`` of a registry field: a feature as a strict number with its
    admissible bounds (``replaced_by``: another field may drive the tendon instead, so it may be
    absent), an optional field as a number or null with its bounds and default in words."""
    if field.choices:
        return (Literal[tuple(field.choices)] | None,
                Field(None, description=f"{field.description} (default {field.default_words!r})"))
    if not field.feature:
        return _FloatOrNone, _layout(field)
    description = f"{field.description}, {field.unit}"
    if replaced_by is not None:
        return _number(field) | None, Field(None, description=f"{description} (or give {replaced_by})")
    return _number(field), (Field(description=description) if field.default is None
                            else Field(field.default, description=description))


def _model(name: str, base: type[BaseModel], doc: str, fields: dict, schema_extra: dict | None = None):
    """A request model ``name`` derived from the registry: ``base``'s fields, then ``fields``
    (name -> ``(annotation, FieldInfo)``); unknown keys are refused."""
    config = type(f"_{name}Config", (base,), {"model_config": ConfigDict(extra="forbid",
                                                                          json_schema_extra=schema_extra)})
    return create_model(name, __base__=config, __doc__=" ".join(doc.split()), __module__=__name__, **fields)


def _tendon_fields(*, optional: bool, alternatives: bool) -> dict:
    """A tendon's fields of the registry: the features; with ``optional`` the general design's
    tendon fields an inverse-kinematics design may give; with ``alternatives`` also the fields
    that drive a tendon instead of a feature (then the feature they replace may be absent)."""
    replacing = {f.alternative_to: f.name for f in OPTIONAL if f.alternative_to and alternatives}
    out = {f.name: _field(f, replaced_by=replacing.get(f.name)) for f in FEATURES if f.per == "tendon"}
    return out | {f.name: _field(f) for f in OPTIONAL if f.per == "tendon" and optional
                  and (f.inverse or alternatives)}


def _design_fields(tendon: type[BaseModel], *, optional: bool, inverse: bool = False, counts=(1, MAX_TENDONS)):
    """A design's fields of the registry: the features, the general design's design fields
    (``optional``; for an inverse-kinematics design those it may give), and ``tendons``."""
    out = {f.name: _field(f) for f in FEATURES if f.per == "design"}
    out |= {f.name: _field(f) for f in OPTIONAL if f.per == "design" and optional and (f.inverse or not inverse)}
    return out | {"tendons": (list[tendon], Field(min_length=counts[0], max_length=counts[1]))}


#: JSON schema: a tendon gives a feature or the field that replaces it (tension or displacement), not both.
_ONE_OF_ALTERNATIVES = {"oneOf": [{"required": [k], "properties": {k: {"type": "number"}}}
                                  for f in OPTIONAL if f.alternative_to for k in (f.alternative_to, f.name)]}

SurrogateTendon = _model("SurrogateTendon", BaseModel, """One tendon of the surrogates' layout: radial offset (m),
    helical pitch (rad/m) and tension (N, >= 0), at the default angle 2 pi i / 4 and ending at the tip.""",
                         _tendon_fields(optional=False, alternatives=False))
InverseTendon = _model("InverseTendon", SurrogateTendon, """A tendon of a design for inverse kinematics: any angle and
    end (the exact model).""", _tendon_fields(optional=True, alternatives=False))
Tendon = _model("Tendon", InverseTendon, """One tendon of any robot: radial offset (m), helical pitch (rad/m), its angle
    at s = 0 (rad) and where it ends (m), driven by its tension (N, >= 0) or by its displacement (m).""",
                _tendon_fields(optional=True, alternatives=True), schema_extra=_ONE_OF_ALTERNATIVES)


#: A gravity vector needs a density (JSON Schema of every design with loads).
_GRAVITY_NEEDS_DENSITY = {"if": {"properties": {"gravity": {"type": "array"}}, "required": ["gravity"]},
                          "then": {"properties": {"density": {"type": "number"}}, "required": ["density"]}}


class _Loads(BaseModel):
    """Optional external loads of a design, base frame, SI (a gravity vector needs a density)."""

    gravity: _vector3(LOADS["gravity"]) | None = Field(  # type: ignore[valid-type]
        None, description="gravitational acceleration, base frame, m/s^2")
    density: _number(LOADS["density"]) | None = Field(  # type: ignore[valid-type]
        None, description="backbone density, kg/m^3 (with gravity)")
    tip_force: _vector3(LOADS["tip_force"]) | None = Field(None, description="tip force, base frame, N")  # type: ignore[valid-type]
    tip_moment: _vector3(LOADS["tip_moment"]) | None = Field(  # type: ignore[valid-type]
        None, description="tip moment, base frame, N m")


SurrogateDesign = _model("SurrogateDesign", _Loads, """A TDCR design in SI units with the surrogates' 4 tendons; loads
    (gravity, tip wrench) only for a loaded operator (``*_loaded``).""",
                         _design_fields(SurrogateTendon, optional=False, counts=(N_TENDONS, N_TENDONS)),
                         schema_extra=_GRAVITY_NEEDS_DENSITY)
Design = _model("Design", _Loads, """A TDCR design in SI units -- any number of tendons (up to MAX_TENDONS), each at any
    angle and ending anywhere (segments), driven by tension or displacement, and the material's Poisson ratio -- with
    optional external loads for the physics solver (a gravity vector needs a density).""",
                _design_fields(Tendon, optional=True), schema_extra=_GRAVITY_NEEDS_DENSITY)


def _integral_float(value):
    """JSON Schema counts 2.0 as an integer: accept it as 2 (strings and booleans stay refused)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


#: The format of the answers: 2 gives ``s`` as fractions of L and ``arclength`` in metres beside it
#: (format 1, before 2026-12: ``s`` in metres).
RESPONSE_FORMAT_VERSION = 2

#: JSON schema: at most one of ``points``, ``s`` and ``arclength`` is given (any may be null).
_POINTS_OR_S = {"not": {"anyOf": [
    {"properties": {a: {"type": t} for a, t in pair}, "required": [a for a, _ in pair]}
    for pair in ((("points", "integer"), ("s", "array")), (("points", "integer"), ("arclength", "array")),
                 (("s", "array"), ("arclength", "array")))]}}


class _Arclengths(BaseModel):
    points: Annotated[int, BeforeValidator(_integral_float), Field(
        strict=True, json_schema_extra={"minimum": 2, "maximum": MAX_POINTS})] | None = Field(
        None, description=f"number of equispaced arclengths on [0, L] (default {DEFAULT_POINTS})")
    s: list[_Fraction] | None = Field(None, min_length=1, max_length=MAX_POINTS,
                                      description="arclengths as fractions of L, each in [0, 1] (instead of points)")
    arclength: list[_Metres] | None = Field(None, min_length=1, max_length=MAX_POINTS,
                                            description="arclengths in metres, each in [0, L], for designs that "
                                                        "share one L (instead of points or s)")


_JACOBIAN = Field(False, description="add tip_jacobian to each result: (6, N_t), rows 0-2 d p(L) / d tau (m/N), "
                                     "rows 3-5 the tip's rotation vector d R(L) R(L)^T / d tau (rad/N), base frame "
                                     "(tendon loads only)")


#: JSON schema: a Jacobian is asked only of designs without external loads.
_JACOBIAN_WITHOUT_LOADS = {
    "if": {"properties": {"jacobian": {"const": True}}, "required": ["jacobian"]},
    "then": {"properties": {"designs": {"items": {"properties": {
        "gravity": {"type": "null"}, "tip_force": {"type": "null"}, "tip_moment": {"type": "null"}}}}}}}


#: JSON schema: the Jacobian is the consistent model's under tension actuation.
_NO_DISPLACEMENT = {"items": {"properties": {"tendons": {"items": {"properties": {"displacement": {"type": "null"}}}}}}}
_JACOBIAN_CONSISTENT = {"if": {"properties": {"jacobian": {"const": True}}, "required": ["jacobian"]},
                        "then": {"properties": {"termination": {"const": "exact"}, "designs": _NO_DISPLACEMENT}}}
#: JSON schema: displacement actuation covers consistent termination (loads or none).
_DISPLACEMENT_CONSISTENT = {"if": {"properties": {"designs": {"contains": {"properties": {"tendons": {"contains": {
    "properties": {"displacement": {"type": "number"}}, "required": ["displacement"]}}}}}}},
    "then": {"properties": {"termination": {"const": "exact"}}}}

_TERMINATION = Field("exact", description=(
    "how a tendon that ends before the tip loads the rod: exact (default) -- the consistent equilibrium, the "
    "total wrench across any cut through rod and tendons continuous: the ending tendon's pull and the kink "
    "forces of the tendons that continue past it -- or rucker_webster, the common shortcut (e.g. "
    "tdcr-modeling) that applies only the ending tendon's pull, for comparison with codes that use it"))


class SolveRequest(_Arclengths):
    """A batch of designs and the arclengths wanted: ``points`` equispaced, or explicit ``s``."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_POINTS_OR_S | _JACOBIAN_WITHOUT_LOADS | {
        "allOf": [_JACOBIAN_CONSISTENT, _DISPLACEMENT_CONSISTENT]})
    designs: list[Design] = Field(min_length=1)
    jacobian: bool = _JACOBIAN
    termination: Literal[TERMINATIONS] = _TERMINATION  # type: ignore[valid-type]


#: JSON schema: a tolerance is kept without the operator's tip Jacobian.
_TOLERANCE_WITHOUT_JACOBIAN = {"not": {"properties": {"jacobian": {"const": True}, "tolerance": {"type": "number"}},
                                       "required": ["jacobian", "tolerance"]}}


class PredictRequest(_Arclengths):
    """Designs, arclengths and the surrogate to use (default: the most accurate in the manifest; for
    designs with loads, the most accurate loaded operator)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_POINTS_OR_S | _JACOBIAN_WITHOUT_LOADS | {
        "allOf": [_TOLERANCE_WITHOUT_JACOBIAN]})
    designs: list[SurrogateDesign] = Field(min_length=1)
    model: str | None = Field(None, min_length=1, max_length=MAX_MODEL_NAME,
                              description="deeponet, deeponet_pose, fno or fno_pose; for designs with loads "
                                          "deeponet_pose_loaded or fno_pose_loaded (the default then)",
                              examples=["deeponet"])
    jacobian: bool = Field(False, description="add tip_jacobian to each result (as for /exact), by central "
                                              "differences of the operator")
    tolerance: float | None = Field(None, ge=EXACT_TOLERANCE, allow_inf_nan=False, description=(
        "relative l2 error of the tendon positions a surrogate answer may have: designs whose calibrated 99 % "
        "error_bound exceeds it (or that have none: outside the calibrated region) are answered by the exact "
        f"solver, in order (each result's source says which); at least {EXACT_TOLERANCE:g}, what the exact "
        "solver guarantees"), examples=[0.001])


class ExactRequest(SolveRequest):
    """Designs (optionally with gravity and tip loads) and arclengths for the physics solver."""


_S_OUT = Field(description="(n,) the arclengths as fractions of L")
_ARCLENGTH_OUT = Field(description="(n,) the arclengths, m")


class PredictedShape(BaseModel):
    s: list[float] = _S_OUT
    arclength: list[float] = _ARCLENGTH_OUT
    backbone: list[list[float]] = Field(description="(n, 3) backbone positions, m")
    rotation: list[list[list[float]]] = Field(description="(n, 3, 3) frames, body axes as columns")
    tendons: list[list[list[float]]] = Field(description="(n, N_t, 3) tendon positions, m")
    in_distribution: bool = Field(description="every parameter inside the trained ranges")
    warnings: list[str] = Field(description="one line per parameter outside the trained ranges")
    tip_jacobian: list[list[float]] | None = Field(None, description="(6, N_t) with jacobian: true")
    finite: bool = Field(True, description="the surrogate's answer is finite; when false (far outside the "
                                           "trained ranges) the arrays hold zeros and must not be used")
    error_bound: float | None = Field(None, description=(
        "calibrated 99 % upper bound of this answer's relative l2 error of the tendon positions (42 equispaced "
        f"arclengths); null: none (outside the calibrated region); {EXACT_TOLERANCE:g} for an exact answer"))
    source: Literal["surrogate", "exact"] = Field("surrogate", description="who answered: the surrogate, or the "
                                                  "exact solver (the bound exceeded the request's tolerance)")


class PredictResponse(BaseModel):
    format_version: int = Field(RESPONSE_FORMAT_VERSION, description="2: s as fractions of L, arclength in m")
    model: str
    results: list[PredictedShape]


class ExactShape(BaseModel):
    s: list[float] = _S_OUT
    arclength: list[float] = _ARCLENGTH_OUT
    backbone: list[list[float]]
    rotation: list[list[list[float]]]
    tendons: list[list[list[float]]]
    converged: bool = Field(description="the solver met its tolerances; false for a design it could not solve "
                                        "(then non-finite coordinates are returned as 0)")
    residual: float = Field(description="wrench-balance residual, N (1.8e308 when it is not finite)")
    status: str = Field("converged", description="the solver's verdict: converged, newton_failed, not_finite, "
                        "step_tol_not_met, residual_too_large, shooting_failed, multiple_equilibria, "
                        "tendon_collapsed (a tendon would pass its centre of curvature: no equilibrium with a taut "
                        "tendon) or displacement_not_met")
    tension: list[float] = Field(description="(N_t,) every tendon's tension, N: as given, or found for its "
                                             "displacement")
    displacement: list[float] = Field(description="(N_t,) every tendon's displacement, m: its path length on the "
                                                  "straight rod minus its path length at the equilibrium")
    tension_profile: list[list[float]] = Field(description="(n, N_t) every tendon's tension at each arclength, N: "
                                               "its tension where it acts without friction, tension exp(-/+ mu "
                                               "theta(s)) with friction (theta its wrap angle), 0 beyond its end")
    slack: list[bool] | None = Field(None, description="(N_t,) with displacement actuation: the tendon would need "
                                                       "a push to reach its displacement, so hangs slack at tension 0")
    error_estimate: float | None = Field(None, description="estimated relative l2 error of the tendon positions "
                                         "due to the integration step (null where not estimated)")
    tip_jacobian: list[list[float]] | None = Field(None, description="(6, N_t) with jacobian: true")


class ExactResponse(BaseModel):
    format_version: int = Field(RESPONSE_FORMAT_VERSION, description="2: s as fractions of L, arclength in m")
    results: list[ExactShape]


#: Most targets of one inverse-kinematics request, and the bound of a target coordinate (m).
MAX_TARGETS = 1000
MAX_TARGET_COORDINATE = TABLE_I["L"].admissible[1]
_Coordinate = Annotated[float, Field(strict=True, json_schema_extra={"minimum": -MAX_TARGET_COORDINATE,
                                                                     "maximum": MAX_TARGET_COORDINATE})]


class TipTarget(BaseModel):
    """A tip target in the base frame: position p(L), m, and optionally the direction R(L) e3."""

    model_config = ConfigDict(extra="forbid")
    position: list[_Coordinate] = Field(min_length=3, max_length=3, description="tip position, base frame, m")
    direction: list[Annotated[float, Field(strict=True)]] = Field(  # type: ignore[assignment]
        None, min_length=3, max_length=3, description="tip tangent R(L) e3, any non-zero length (optional)",
        json_schema_extra={"contains": {"not": {"const": 0}}})


InverseDesign = _model("InverseDesign", _Loads, """A design for inverse kinematics (its tensions are the first start);
    gravity and a tip wrench only with a loaded operator.""",
                       _design_fields(InverseTendon, optional=True, inverse=True), schema_extra=_GRAVITY_NEEDS_DENSITY)


class InverseRequest(BaseModel):
    """One design and the targets of a path, in order (an operator takes 4 tendons)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"allOf": [
        {"if": {"properties": {"model": {"not": {"const": EXACT_MODEL}}}, "required": ["model"]},
         "then": {"properties": {"design": {"properties": {
             "poisson": {"type": "null"},
             "tendons": {"minItems": N_TENDONS, "maxItems": N_TENDONS, "items": {"properties": {
                 "angle": {"type": "null"}, "end": {"type": "null"}}}}}}}}},
        # a design with loads: an operator (the exact inverse covers tendon loads only), no polish
        {"if": {"properties": {"design": {"anyOf": [{"properties": {k: {"type": "array"}}, "required": [k]}
                                                    for k in ("gravity", "tip_force", "tip_moment")]}},
                "required": ["design"]},
         "then": {"properties": {"model": {"not": {"const": EXACT_MODEL}}, "polish": {"const": False}},
                  "required": ["model"]}}]})
    design: InverseDesign
    targets: list[TipTarget] = Field(min_length=1, max_length=MAX_TARGETS)
    tension_max: float = Field(5.0, gt=0.0, le=TABLE_I["tension"].admissible[1], description="upper bound of "
                               "every tension, N (the lower bound is 0)")
    model: str = Field(EXACT_MODEL, min_length=1, max_length=MAX_MODEL_NAME,
                       description="exact (the solver and its exact Jacobian) or an operator")
    polish: bool = Field(False, description="with an operator: finish each target with exact steps")
    tolerance: float = Field(1e-4, ge=1e-9, le=0.1, description="a target is reached within tolerance x L "
                             "(and tolerance in direction), in exact physics: an operator's answers are checked by "
                             "the exact solver and a target they miss is finished by exact steps (tendon loads only)")


class InverseResult(BaseModel):
    tensions: list[float] = Field(description="(N_t,) tensions, N")
    position: list[float] = Field(description="the tip they give, base frame, m")
    direction: list[float] | None = Field(None, description="its direction R(L) e3 (when the target had one)")
    error: float = Field(description="distance from the target position, m")
    status: str = Field(description="reached, closest (unreachable within the bounds: the closest tip) or failed")
    iterations: int = Field(description="forward-model evaluations")
    source: Literal["surrogate", "exact"] = Field("exact", description=(
        "whose tensions: the operator's (checked in exact physics: position, direction, error and status are the "
        "exact solver's), or exact steps' (the exact model, polish, or a target the operator's answer missed)"))


class InverseResponse(BaseModel):
    model: str
    results: list[InverseResult]


class ErrorItem(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class ErrorResponse(BaseModel):
    """Every 4xx/5xx body: a one-line ``message`` and, for 422, the items naming each bad field."""

    message: str
    detail: list[ErrorItem] | str


# -- design search (tdcr design) -----------------------------------------------------------------

#: The design parameters a search varies (tensions are each target's own), and the objectives.
SEARCH_PARAMETERS = ("E", "r", "L", "offset", "pitch")
OBJECTIVES = ("max_tension", "total_tension", "length")


class DesignTask(BaseModel):
    """A design search: the targets the robot must reach (base frame, m), the bounds of the
    parameters searched (default Table I), parameters held fixed, the tension bound (N), the
    tolerance (m, checked by the exact solver), the objective, the seed and the time budget (s)."""

    model_config = ConfigDict(extra="forbid")
    targets: list[TipTarget] = Field(min_length=1, max_length=50)
    bounds: dict[Literal["E", "r", "L", "offset", "pitch"], Annotated[list[float], Field(
        min_length=2, max_length=2)]] = Field(default_factory=dict, description="[low, high] per parameter, SI; "
                                              "default Table I")
    fixed: dict[Literal["E", "r", "L", "offset", "pitch"], float] = Field(default_factory=dict,
                                                                          description="parameters held fixed, SI")
    tension_max: float = Field(5.0, gt=0.0, le=TABLE_I["tension"].admissible[1], description="N")
    tolerance: float = Field(1e-3, gt=0.0, le=0.1, description="a target is reached within this distance, m")
    objective: Literal["max_tension", "total_tension", "length"] = Field(
        "max_tension", description="minimised among designs that reach every target: the largest tension over the "
        "targets (default), the sum of all tensions, or the length L")
    seed: int = Field(0, ge=0)
    budget_s: float = Field(120.0, gt=0.0, le=3600.0, description="wall-clock budget of the search, s")
