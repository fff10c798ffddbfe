"""The one validation path: every entry point turns its input into a :class:`ShapeRequest` here.

JSON ``/predict`` and ``/exact`` bodies, ``.npy`` bodies with query parameters, ``tdcr solve`` and
``tdcr predict`` all end in :func:`_checked`, so the same mistake gets the same message
everywhere.  Order of the checks, so that nothing large is allocated for a bad request:

1. structure and types (pydantic, for JSON; shape and dtype for arrays);
2. sizes from the declared counts: designs, points, designs x points (:class:`Limits`);
3. values, vectorised over the batch: finite, inside the admissible physical bounds of
   :mod:`tdcr.robot.design_space`, arclength fractions in [0, 1], density with gravity, and for the
   surrogates 4 tendons and no external loads.

Problems name the field as ``designs[3].tendons[1].tension`` and say why.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
from typing import Literal

import numpy as np
from pydantic import ValidationError

from tdcr.api.checks import (  # noqa: F401 - re-exported: the validation path's vocabulary
    EXACT_ROUTES,
    LAYOUT_REASONS,
    LOADED_EXAMPLE,
    MAX_QUOTED,
    InvalidRequest,
    Problem,
    _short,
    check_features,
    check_fractions,
    check_layout,
    check_loads,
    check_standard_layout,
    check_tolerance,
    checkable_loads,
    format_location,
    loaded_rows,
    quote,
)
from tdcr.api.schemas import EXACT_MODEL, MAX_MODEL_NAME, MAX_TARGETS, InverseRequest, PredictRequest, SolveRequest
from tdcr.robot.design_space import (
    DEFAULT_POINTS,
    FRACTION_ROUNDING,
    MAX_POINTS,
    N_FEATURES,
    N_TENDONS,
    TABLE_I,
)
from tdcr.robot.designs import DesignBatch, ExternalLoads, FeatureLayout
from tdcr.robot.fields import BY_NAME, FIELDS, OPTIONAL

#: What a request is for: the surrogates (4 tendons, no loads) or the physics solver.
Target = Literal["surrogate", "solver"]
#: Arrays a surrogate can answer with; a request may ask for a subset.
OUTPUTS = ("backbone", "rotation", "tendons")


@dataclass(frozen=True)
class Limits:
    """Size limits of one request, checked before anything is allocated.

    ``max_design_points`` bounds designs x points together: the memory of the answer (the
    surrogates' float32 outputs take 96 bytes per design-point, their JSON text about 330).
    """

    max_designs: int = 100_000
    max_points: int = MAX_POINTS
    max_design_points: int = 1_000_000


@dataclass(frozen=True)
class DesignGroup:
    """Designs of a request that share one tendon count: request rows ``(b,)``, arrays, loads."""

    rows: np.ndarray
    designs: DesignBatch
    loads: ExternalLoads | None


@dataclass(frozen=True)
class ShapeRequest:
    """A validated request, whatever its transport.

    ``groups``: the designs by tendon count (one group for surrogate requests); ``fractions``:
    arclengths ``(n,)`` as fractions of L; ``model``: the surrogate named (None: the default);
    ``outputs``: the arrays wanted; ``jacobian``: add each tip's Jacobian to the tensions;
    ``tolerance``: the relative l2 error a surrogate answer may have (the exact solver answers the
    designs whose calibrated bound exceeds it; None: every design from the surrogate).
    """

    groups: tuple[DesignGroup, ...]
    fractions: np.ndarray
    model: str | None = None
    outputs: tuple[str, ...] = OUTPUTS
    jacobian: bool = False
    tolerance: float | None = None  #: relative l2: designs whose error bound exceeds it are solved exactly
    termination: str = "exact"  #: how a tendon that ends before the tip loads the rod (tdcr.solve)

    @property
    def n_designs(self) -> int:
        return sum(len(g.rows) for g in self.groups)

    @property
    def features(self) -> np.ndarray:
        """Raw SI features ``(B, 3 + 3 N_t)`` of a request whose designs share one tendon count."""
        if len(self.groups) != 1:
            raise ValueError("the designs have different tendon counts")
        return self.groups[0].designs.features()

    @property
    def loads(self) -> ExternalLoads | None:
        """The loads of a request whose designs share one tendon count (None: no design has any),
        arrays of every design, zeros where absent."""
        if len(self.groups) != 1:
            raise ValueError("the designs have different tendon counts")
        return self.groups[0].loads

    @cached_property  # the request is immutable; routing and admission each ask
    def n_loaded(self) -> int:
        """Designs the solver shoots for: non-zero gravity, tip force or tip moment, or segments
        under Rucker & Webster's rule."""
        count = 0
        for g in self.groups:
            if g.loads is None and self.termination != "rucker_webster":
                continue  # (the checks below cost as much as a small request's solve)
            shooting = np.zeros(len(g.rows), dtype=bool) if g.loads is None else _loaded(g.loads)
            if self.termination == "rucker_webster":
                shooting |= g.designs.segmented
            count += int(shooting.sum())
        return count

    @cached_property
    def n_displacement(self) -> int:
        """Designs with a displacement-driven tendon (the solver first finds their tensions)."""
        return sum(int(g.designs.displacement_driven.any(axis=1).sum()) for g in self.groups
                   if g.designs.displacement is not None)

    @cached_property
    def n_loaded_displacement(self) -> int:
        """Designs with a displacement-driven tendon under loads (the solver finds their tensions on
        the loaded solver)."""
        return sum(int((g.designs.displacement_driven.any(axis=1) & _loaded(g.loads)).sum()) for g in self.groups
                   if g.designs.displacement is not None and g.loads is not None)

    @property
    def pose(self) -> bool:
        """Whether backbone or rotation are wanted (tendon models then fit a pose)."""
        return self.outputs != ("tendons",)

    def take(self, rows: np.ndarray) -> ShapeRequest:
        """The designs ``rows`` ``(m,)`` of a request whose designs share one tendon count, as a
        request of their own (the same arclengths and outputs; no Jacobian, no tolerance): what the
        exact solver answers when a tolerance sends them to it."""
        if len(self.groups) != 1:
            raise ValueError("the designs have different tendon counts")
        group = self.groups[0]
        loads = None if group.loads is None else group.loads.take(rows)
        if loads is not None and not _loaded(loads).any():
            loads = None  # tendon loads only: the solver needs no shooting
        return ShapeRequest(groups=(DesignGroup(rows=np.arange(len(rows)), designs=group.designs.take(rows),
                                                loads=loads),), fractions=self.fractions, outputs=self.outputs,
                            termination=self.termination)


# -- value checks ------------------------------------------------------------------------------


def check_outputs(outputs: Iterable[str] | None) -> tuple[tuple[str, ...], list[Problem]]:
    """The arrays wanted (sorted, a subset of :data:`OUTPUTS`; all when ``None``) and any problem."""
    if outputs is None:
        return OUTPUTS, []
    wanted = tuple(sorted({w.strip() for w in outputs if w.strip()}))
    if not wanted or any(w not in OUTPUTS for w in wanted):
        return OUTPUTS, [Problem(("outputs",), f"must be a comma-separated subset of {list(OUTPUTS)}, got "
                                 f"{quote(','.join(outputs))}", "value_error")]
    return wanted, []


def _check_model(model: str | None) -> list[Problem]:
    if model is not None and not 1 <= len(model) <= MAX_MODEL_NAME:
        return [Problem(("model",), f"must be 1 to {MAX_MODEL_NAME} characters", "string_length")]
    return []


@lru_cache(maxsize=64)
def _even_fractions(n: int) -> np.ndarray:
    """``n`` evenly spaced fractions of L from 0 to 1, ``(n,)`` (kept: a service asks for the same few
    counts again and again, and np.linspace costs more than a small request's other checks)."""
    return np.linspace(0.0, 1.0, n)


def _fractions(points: int | None, s: Sequence[float] | np.ndarray | None, limits: Limits, *,
               arclength: Sequence[float] | np.ndarray | None = None,
               lengths: np.ndarray | None = None) -> tuple[np.ndarray | None, list[Problem]]:
    """Arclength fractions ``(n,)`` from ``points``, ``s`` (fractions of L) or ``arclength`` (m, for
    designs of one length: ``lengths`` ``(B,)``); nothing is allocated for a bad count."""
    if points is not None and s is not None:
        return None, [Problem(("s",), "give either 'points' or 's', not both", "points_or_s")]
    if arclength is not None:
        if points is not None or s is not None:
            return None, [Problem(("arclength",), "give one of 'points', 's' and 'arclength'", "points_or_s")]
        if not 1 <= len(arclength) <= limits.max_points:
            return None, [Problem(("arclength",), f"must hold 1 to {limits.max_points} arclengths, got "
                                                  f"{len(arclength)}", "points")]
        length = float(lengths[0]) if lengths is not None and len(lengths) else float("nan")
        if lengths is None or not np.all(lengths == length):
            return None, [Problem(("arclength",), "metres need designs of one length L: give 's' (fractions of "
                                                  "each design's L) instead", "arclength")]
        metres = np.asarray(arclength, dtype=np.float64)
        fractions, problems = check_fractions(metres / length, name="arclength")
        return fractions, [p._replace(msg=f"must be in [0, L] = [0, {length:g}] m, got {metres[p.loc[1]]:g}")
                           if len(p.loc) == 2 else p for p in problems]
    if s is None:
        n = DEFAULT_POINTS if points is None else points
        if not 2 <= n <= limits.max_points:
            return None, [Problem(("points",), f"must be an integer from 2 to {limits.max_points}, got {n}",
                                  "points")]
        return _even_fractions(n).copy(), []  # a copy: the request owns its fractions
    if not 1 <= len(s) <= limits.max_points:
        return None, [Problem(("s",), f"must hold 1 to {limits.max_points} fractions, got {len(s)}", "points")]
    return check_fractions(s)


def _check_sizes(n_designs: int, n_points: int, limits: Limits) -> None:
    """413 before any allocation: too many designs, or designs x points over the budget."""
    if n_designs > limits.max_designs:
        raise InvalidRequest([Problem(("designs",), f"{n_designs} designs exceed the limit of {limits.max_designs} "
                                      "per request", "too_many_designs")], too_large=True)
    if n_designs * n_points > limits.max_design_points:
        raise InvalidRequest([Problem(("designs",), f"{n_designs} designs x {n_points} points exceed the budget of "
                                      f"{limits.max_design_points} design-points per request", "too_many_values")],
                             too_large=True)


def _checked(groups: list[DesignGroup], fractions: np.ndarray | None, problems: list[Problem], *,
             model: str | None, outputs: tuple[str, ...], jacobian: bool = False,
             tolerance: float | None = None, target: Target = "solver",
             termination: str = "exact") -> ShapeRequest:
    """Every value check of every entry point; raises :class:`InvalidRequest` naming each field."""
    problems = problems + check_tolerance(tolerance)
    if tolerance is not None and jacobian:
        problems.append(Problem(("tolerance",), "the tip Jacobian is the operator's own: ask for it without a "
                                "tolerance, or from /exact", "tolerance_with_jacobian"))
    value_problems = []
    for g in groups:  # (the surrogates' 4 tendons and no loads are structure: checked by the schema or shape)
        value_problems += check_features(g.designs.features(), g.rows) + check_layout(g.designs, g.rows)
        if target == "surrogate":
            value_problems += check_standard_layout(g.designs, g.rows)
        value_problems += _check_actuation(g, jacobian=jacobian, termination=termination)
        if g.loads is not None:
            value_problems += check_loads(g.loads, g.rows)
            if jacobian:
                value_problems += [Problem(("designs", int(g.rows[b]), "jacobian"), "the tip Jacobian covers tendon "
                                           "loads only: remove gravity and tip loads", "jacobian_with_loads")
                                   for b in np.nonzero(_loaded(_zero_absent(g.loads)))[0]]
    value_problems.sort(key=lambda p: p.loc[1])  # by design, stable within a design (column order)
    problems = problems + value_problems
    if problems:
        raise InvalidRequest(problems)
    groups = [g if g.loads is None else replace(g, loads=_zero_absent(g.loads)) for g in groups]
    return ShapeRequest(groups=tuple(groups), fractions=fractions, model=model, outputs=outputs, jacobian=jacobian,
                        tolerance=None if tolerance is None else float(tolerance), termination=termination)


def _check_actuation(group: DesignGroup, *, jacobian: bool, termination: str) -> list[Problem]:
    """Problems of what the solver covers: displacement actuation and friction with consistent
    termination and no Jacobian (in gravity and under tip loads too); the Jacobian of segments under
    consistent termination."""
    designs, problems = group.designs, []
    for where, field, what, instead in [
            (designs.displacement_driven, "displacement", "displacement actuation", "give the tension"),
            (designs.capstan != 0.0, "friction", "friction", "the friction")]:
        for b, i in zip(*np.nonzero(where), strict=True):
            if jacobian or termination != "exact":
                why = "the tip Jacobian" if jacobian else f"termination {termination!r}"
                problems.append(Problem(("designs", int(group.rows[b]), "tendons", int(i), field),
                                        f"{what} covers termination 'exact' and no Jacobian: remove {why}, or "
                                        f"{instead}", f"{field}_unsupported"))
                break
    if jacobian and termination != "exact":
        problems += [Problem(("designs", int(group.rows[b]), "jacobian"), "the tip Jacobian of segments is the "
                             "consistent model's: use termination 'exact'", "jacobian_with_shortcut")
                     for b in np.nonzero(designs.segmented)[0]]
    return problems


def _zero_absent(loads: ExternalLoads) -> ExternalLoads:
    """Absent gravity and density (NaN from JSON) as zeros: no weight."""
    return replace(loads, gravity=np.nan_to_num(loads.gravity), density=np.nan_to_num(loads.density))


def _loaded(loads: ExternalLoads) -> np.ndarray:
    """Per design ``(b,)``: a load that is not zero (:func:`tdcr.api.checks.loaded_rows`; after the checks)."""
    return loaded_rows(loads.matrix(len(loads.tip_force)))


# -- entry points ------------------------------------------------------------------------------


def validate_json(body: bytes | str | dict, *, target: Target, limits: Limits = Limits(),
                  outputs: Iterable[str] | None = None) -> ShapeRequest:
    """A JSON request (``PredictRequest`` for the surrogates, ``SolveRequest`` for the solver).

    ``body``: the raw JSON text, or already-decoded JSON.  Raises :class:`InvalidRequest`.
    """
    schema = PredictRequest if target == "surrogate" else SolveRequest
    try:
        request = (schema.model_validate(body) if isinstance(body, dict) else schema.model_validate_json(body))
    except ValidationError as exc:
        robot = robot_file(body) if target == "solver" else None
        if robot is not None:
            return _robot_file_request(robot, limits=limits, outputs=outputs)
        raise InvalidRequest(_what_to_do(Problem(tuple(_short(part) for part in e["loc"]), e["msg"], e["type"]), target)
                             for e in exc.errors(include_input=False, include_url=False)) from None
    fractions, problems = _fractions(request.points, request.s, limits, arclength=request.arclength,
                                     lengths=np.array([d.L for d in request.designs]))
    _check_sizes(len(request.designs), 0 if fractions is None else fractions.size, limits)
    wanted, more = check_outputs(outputs)
    problems += more + _check_model(getattr(request, "model", None))
    by_count: dict[int, list[int]] = {}
    for i, d in enumerate(request.designs):
        by_count.setdefault(len(d.tendons), []).append(i)
    groups = [_group_from_json([request.designs[i] for i in rows], np.asarray(rows), problems)
              for rows in by_count.values()]
    return _checked(groups, fractions, problems, model=getattr(request, "model", None),
                    outputs=wanted, jacobian=request.jacobian, tolerance=getattr(request, "tolerance", None),
                    target=target, termination=getattr(request, "termination", "exact"))


def robot_file(body: bytes | str | dict) -> dict | None:
    """A robot file, parsed (``tdcr/robot/real.py``: an object with a ``design`` object and an
    ``actuation``; ``tdcr fit`` writes one), or None for any other body."""
    if not isinstance(body, dict):
        try:
            body = json.loads(body)
        except (ValueError, TypeError):  # not JSON (UnicodeDecodeError is a ValueError)
            return None
    if isinstance(body, dict) and isinstance(body.get("design"), dict) and "actuation" in body:
        return body
    return None


def _robot_file_request(robot: dict, *, limits: Limits, outputs: Iterable[str] | None) -> ShapeRequest:
    """A robot file asked of the solver: its design at the default arclengths (its actuation and
    measurement describe a recording: ``tdcr replay``).  Problems of the design are named under
    ``design``; the rest of the file passes the robot file's own checks
    (:func:`tdcr.robot.real.robot_from`, as ``tdcr replay`` and ``tdcr fit`` run them after the design
    passed this path once), so a file they refuse is refused here too, its problem named by its key
    (e.g. ``actuation.columns``)."""
    from tdcr.robot.real import RobotFileError, robot_from

    try:
        request = validate_json({"designs": [robot["design"]]}, target="solver", limits=limits, outputs=outputs)
    except InvalidRequest as exc:
        raise InvalidRequest((p._replace(loc=("design", *p.loc[2:])) if p.loc[:2] == ("designs", 0) else p
                              for p in exc.problems), too_large=exc.too_large) from None
    try:
        robot_from(robot, request.groups[0])
    except RobotFileError as exc:
        key, _, reason = str(exc).partition(": ")
        raise InvalidRequest([Problem(tuple(key.split(".")), reason, "robot_file") if reason
                              else Problem((), str(exc), "robot_file")]) from None
    return request


def _what_to_do(problem: Problem, target: Target) -> Problem:
    """A schema problem of a surrogate request that the exact solver would take says so: a design
    with another tendon count (``EXACT_ROUTES``)."""
    loc = problem.loc
    if target != "surrogate" or len(loc) < 3 or loc[0] != "designs":
        return problem
    if loc[2:] == ("tendons",) and problem.type in ("too_short", "too_long"):
        return problem._replace(msg=f"{problem.msg}: the operators take {N_TENDONS} tendons; {EXACT_ROUTES}")
    if problem.type == "extra_forbidden" and loc[-1] in LAYOUT_REASONS:
        return problem._replace(msg=f"{LAYOUT_REASONS[loc[-1]]}; {EXACT_ROUTES}")
    return problem



def _group_from_json(designs: list, rows: np.ndarray, problems: list[Problem] | None = None) -> DesignGroup:
    """Arrays of parsed designs that share a tendon count (loads: NaN gravity and density where
    absent; each optional field of the registry None when no design gives it, else its default
    where absent; a feature that a tendon replaces by an alternative field starts at 0).  A tendon
    with neither or both of a feature and its alternative (tension, displacement) is a problem
    (appended)."""
    n_t = len(designs[0].tendons)
    for f in OPTIONAL:
        if f.alternative_to is None or problems is None:
            continue
        other = BY_NAME[f.alternative_to]
        for j, d in enumerate(designs):
            for i, t in enumerate(d.tendons):
                given = (getattr(t, other.name, None) is not None) + (getattr(t, f.name, None) is not None)
                if given != 1:
                    what = f"give the tendon's {other.name} ({other.unit}) or its {f.name} ({f.unit})"
                    problems.append(Problem(("designs", int(rows[j]), "tendons", i, other.name),
                                            what + (", not both" if given else ""), f"{other.name}_or_{f.name}"))
    lengths = np.array([d.L for d in designs], dtype=np.float64)
    fields = {}
    per = {"design": [d.__dict__ for d in designs], "tendon": [t.__dict__ for d in designs for t in d.tendons]}
    for f in FIELDS:
        values = [row.get(f.name) for row in per[f.per]]  # flat: designs, or designs x tendons in order
        if not f.feature and all(v is None for v in values):
            continue  # None: no design gives it (found without the arrays below: most requests give few)
        if f.choices:  # a field in words (the schema admits only its words)
            values = [f.choices[v] if isinstance(v, str) else v for v in values]
        shape = (len(designs),) if f.per == "design" else (len(designs), n_t)
        given = np.array(values, dtype=np.float64).reshape(shape)  # numpy reads None as NaN
        absent = np.isnan(given)
        if absent.any():  # which are None (a NaN given stays, for the checks to refuse)
            absent = np.array([v is None for v in values], dtype=bool).reshape(shape)
            fields[f.name] = np.where(absent, 0.0 if f.feature else f.fill(lengths, n_t), given)
        else:
            fields[f.name] = given
        if f.within_length:  # an arclength within rounding of L is L (farther ones are refused by check_layout)
            limit = lengths[:, None] if f.per == "tendon" else lengths
            rounding = (given > limit) & (given <= limit * (1.0 + FRACTION_ROUNDING))
            fields[f.name] = np.where(rounding, limit, fields[f.name])
    batch = DesignBatch(**fields)
    loads = None
    takes_loads = "gravity" in type(designs[0]).model_fields  # surrogate designs have no load fields
    if takes_loads and any(d.gravity is not None or d.tip_force is not None or d.tip_moment is not None
                           for d in designs):
        zero, absent = (0.0, 0.0, 0.0), (np.nan, np.nan, np.nan)
        loads = ExternalLoads(
            gravity=np.array([absent if d.gravity is None else d.gravity for d in designs], dtype=np.float64),
            density=np.array([np.nan if d.density is None else d.density for d in designs]),
            tip_force=np.array([d.tip_force or zero for d in designs], dtype=np.float64),
            tip_moment=np.array([d.tip_moment or zero for d in designs], dtype=np.float64),
        )
    return DesignGroup(rows=rows, designs=batch, loads=loads)


def validate_features(features: np.ndarray, *, target: Target = "surrogate", points: int | None = None,
                      s: Sequence[float] | np.ndarray | None = None, model: str | None = None,
                      outputs: Iterable[str] | None = None, limits: Limits = Limits(),
                      loads: Mapping[str, np.ndarray] | None = None,
                      arclength: Sequence[float] | np.ndarray | None = None,
                      tolerance: float | None = None, layout: Mapping[str, np.ndarray] | None = None,
                      termination: str = "exact") -> ShapeRequest:
    """Raw SI designs ``(B, 3 + 3 N_t)`` (e.g. a ``.npy`` body or OIP tensors) with arclengths and
    options; ``loads``: any of ``gravity`` ``(B, 3)`` m/s^2, ``density`` ``(B,)`` kg/m^3,
    ``tip_force`` ``(B, 3)`` N, ``tip_moment`` ``(B, 3)`` N m (whether the model takes them is the
    model's check: :func:`tdcr.api.checks.check_model_loads`); ``tolerance``: as :class:`ShapeRequest`'s;
    ``layout``: any of the general design's ``angle``, ``end``, ``displacement`` (NaN: tension-driven)
    ``(B, N_t)`` and ``poisson`` ``(B,)`` (:class:`tdcr.robot.designs.DesignBatch`); ``termination``: as
    :func:`tdcr.solve`'s.

    Raises :class:`InvalidRequest`.
    """
    features = np.asarray(features)
    if features.dtype.kind not in "fiu" or features.ndim != 2 or features.shape[0] < 1 or (
            target == "surrogate" and features.shape[1] != N_FEATURES):
        expect = f"(B, {N_FEATURES})" if target == "surrogate" else "(B, 3 + 3 N_t)"
        raise InvalidRequest([Problem(("designs",), f"expected a numeric {expect} array [E, r, L, offsets, pitches, "
                                      f"tensions] with B >= 1, got {features.dtype} {features.shape}", "array")])
    try:
        FeatureLayout.of(features)
    except ValueError as exc:
        raise InvalidRequest([Problem(("designs",), str(exc), "array")]) from None
    fractions, problems = _fractions(points, s, limits, arclength=arclength,
                                     lengths=np.asarray(features[:, 2], dtype=np.float64))
    _check_sizes(len(features), 0 if fractions is None else fractions.size, limits)
    wanted, more = check_outputs(outputs)
    problems += more + _check_model(model)
    designs = _with_layout(DesignBatch.from_features(features), layout, problems)
    group = DesignGroup(rows=np.arange(len(features)), designs=designs,
                        loads=_loads_from_arrays(loads, len(features), problems))
    if tolerance is not None and target != "surrogate":
        problems.append(Problem(("tolerance",), "applies to surrogate answers only (the exact solver's error is "
                                "below 1e-6 already)", "tolerance_exact"))
        tolerance = None
    return _checked([group], fractions, problems, model=model, outputs=wanted, tolerance=tolerance, target=target,
                    termination=termination)


def _with_layout(designs: DesignBatch, layout: Mapping[str, np.ndarray] | None,
                 problems: list[Problem]) -> DesignBatch:
    """``designs`` with the general design's arrays of ``layout`` by name; a wrong name or shape is
    a problem (appended) and the field is left at its default."""
    if not layout:
        return designs
    fields = {}
    for name, values in layout.items():
        values = np.asarray(values, dtype=np.float64)
        field = BY_NAME.get(name)
        if field is None or field.feature:
            names = [f.name for f in OPTIONAL]
            problems.append(Problem((name,), f"not a layout field; they are {', '.join(names[:-1])} and {names[-1]}",
                                    "layout"))
            continue
        per_design = field.per == "design"
        shape = (designs.n_designs,) if per_design else (designs.n_designs, designs.n_tendons)
        if values.shape != shape:
            rows = "a row per design" + ("" if per_design else ", a column per tendon of design")
            problems.append(Problem(("layout" if field.oip == "layout" else name,), f"{name} must have shape "
                                    f"{list(shape)} ({rows}), got {list(values.shape)}", "shape"))
        else:
            fields[name] = values
    return designs.replace(**fields) if fields else designs


#: The external loads' arrays and their trailing shapes.
LOAD_SHAPES = {"gravity": (3,), "density": (), "tip_force": (3,), "tip_moment": (3,)}


def _loads_from_arrays(loads: Mapping[str, np.ndarray] | None, n_designs: int,
                       problems: list[Problem]) -> ExternalLoads | None:
    """:class:`ExternalLoads` from arrays by name (NaN gravity and density where absent, as from
    JSON), or None without loads; a wrong name, shape or row count is a problem."""
    if not loads:
        return None
    arrays = {}
    for name, values in loads.items():
        values = np.asarray(values, dtype=np.float64)
        if name not in LOAD_SHAPES:
            problems.append(Problem((name,), f"not a load; loads are {list(LOAD_SHAPES)}", "loads"))
        elif values.shape != (n_designs, *LOAD_SHAPES[name]):
            problems.append(Problem((name,), f"must have shape {[n_designs, *LOAD_SHAPES[name]]} (a row per design), "
                                             f"got {list(values.shape)}", "shape"))
        else:
            arrays[name] = values
    nan3, zero3 = np.full((n_designs, 3), np.nan), np.zeros((n_designs, 3))
    given = ExternalLoads(gravity=arrays.get("gravity", nan3),
                          density=arrays.get("density", np.full(n_designs, np.nan)),
                          tip_force=arrays.get("tip_force", zero3), tip_moment=arrays.get("tip_moment", zero3))
    return checkable_loads(given, n_designs)  # a row without gravity has no weight: its density is not checked


@dataclass(frozen=True)
class InverseProblem:
    """A validated inverse-kinematics request: one ``design`` (its tensions are the first start),
    target ``positions`` ``(T, 3)`` m and ``directions`` ``(T, 3)`` (NaN rows: none), and the options."""

    design: DesignBatch
    positions: np.ndarray
    directions: np.ndarray
    tension_max: float
    model: str
    polish: bool
    tolerance: float
    loads: ExternalLoads | None = None  #: gravity and tip wrench of the design (a loaded operator's)

    @property
    def n_targets(self) -> int:
        return len(self.positions)


def validate_inverse(body: bytes | str | dict) -> InverseProblem:
    """A JSON ``InverseRequest``: structure (pydantic), then :func:`check_inverse`.  Raises
    :class:`InvalidRequest`."""
    try:
        request = (InverseRequest.model_validate(body) if isinstance(body, dict)
                   else InverseRequest.model_validate_json(body))
    except ValidationError as exc:
        raise InvalidRequest(Problem(tuple(_short(part) for part in e["loc"]), e["msg"], e["type"])
                             for e in exc.errors(include_input=False, include_url=False)) from None
    group = _group_from_json([request.design], np.zeros(1, dtype=int))
    directions = np.array([np.full(3, np.nan) if t.direction is None else t.direction for t in request.targets],
                          dtype=np.float64)
    return check_inverse(group.designs, np.array([t.position for t in request.targets], dtype=np.float64), directions,
                         tension_max=request.tension_max, model=request.model, polish=request.polish,
                         tolerance=request.tolerance, loads=group.loads)


#: The defaults of an inverse request (``tdcr.api.schemas.InverseRequest``).
INVERSE_DEFAULTS = {name: InverseRequest.model_fields[name].default for name in ("tension_max", "tolerance")}


def check_inverse(design: DesignBatch, positions: np.ndarray, directions: np.ndarray, *, tension_max: float,
                  model: str = EXACT_MODEL, polish: bool = False,
                  tolerance: float = INVERSE_DEFAULTS["tolerance"],
                  loads: ExternalLoads | None = None) -> InverseProblem:
    """The value checks of every inverse request (JSON or tensors): the design's values through the
    same checks as every design, 4 tendons for an operator, ``positions`` ``(T, 3)`` m finite,
    ``directions`` ``(T, 3)`` (NaN rows: none) finite and non-zero, ``tension_max`` in (0, 1000] N;
    ``loads`` (one row, NaN gravity and density where absent; None: no load field) inside their
    bounds, and only for an operator (the exact model's Jacobian covers tendon loads) without
    ``polish``.
    Raises :class:`InvalidRequest`."""
    problems = [Problem(("design",) + p.loc[2:], p.msg, p.type) for p in check_features(design.features())
                + check_layout(design) + (check_standard_layout(design) if model != EXACT_MODEL else [])]
    if loads is not None:  # any load field given
        problems += [Problem(("design",) + p.loc[2:], p.msg, p.type) for p in check_loads(loads, np.zeros(1, int))]
        loads = _zero_absent(loads)
        if model == EXACT_MODEL or polish:
            field = "model" if model == EXACT_MODEL else "polish"
            problems.append(Problem((field,), "the exact inverse kinematics covers tendon loads only: for a design "
                                    f"with gravity or tip loads name a loaded operator (model {LOADED_EXAMPLE!r}) "
                                    "without polish", "inverse_with_loads"))
    if model != EXACT_MODEL and design.n_tendons != N_TENDONS:
        problems.append(Problem(("design", "tendons"), f"the operators take {N_TENDONS} tendons, got "
                                                       f"{design.n_tendons}", "tendon_count"))
    high = TABLE_I["tension"].admissible[1]
    if not 0.0 < tension_max <= high:
        problems.append(Problem(("tension_max",), f"must be in (0, {high:g}] N, got {tension_max:.6g}", "out_of_range"))
    if not 1 <= len(positions) <= MAX_TARGETS:
        problems.append(Problem(("targets",), f"must hold 1 to {MAX_TARGETS} targets, got {len(positions)}",
                                "targets"))
    directions = np.array(directions, dtype=np.float64)
    for k in range(len(positions)):
        if not np.isfinite(positions[k]).all():
            problems.append(Problem(("targets", k, "position"), "must be finite numbers", "finite_number"))
        d = directions[k]
        if np.isnan(d).all():
            continue
        if not np.isfinite(d).all() or not np.abs(d).max() > 0.0:
            problems.append(Problem(("targets", k, "direction"), "must be a finite, non-zero vector", "direction"))
        else:
            d = d / np.abs(d).max()  # scaled first: no overflow or underflow in the norm
            directions[k] = d / np.linalg.norm(d)
    if problems:
        raise InvalidRequest(problems)
    return InverseProblem(design=design, positions=positions, directions=directions, tension_max=float(tension_max),
                          model=model, polish=polish, tolerance=float(tolerance), loads=loads)
