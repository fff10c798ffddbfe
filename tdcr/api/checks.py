"""The value checks of the one validation path, numpy only: what every entry point runs, the
service's (through :mod:`tdcr.api.validation`) and the Python API's (:func:`tdcr.solve`,
:meth:`tdcr.Surrogate.predict`, :class:`tdcr.clients.client.Client`), so that the same mistake gets the
same words everywhere: ``designs[0].tendons[1].tension: must be in [0, 1000] N, got -2``.

:class:`InvalidRequest` is a ``ValueError``; the service answers it with a 422 naming the fields.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from tdcr.robot.design_space import FRACTION_ROUNDING, LOADS, N_TENDONS, TABLE_I, admissible_bounds
from tdcr.robot.designs import LOAD_COLUMNS, DesignBatch, ExternalLoads, FeatureLayout
from tdcr.robot.fields import OPTIONAL, interval, refusal
from tdcr.surrogates.bounds import EXACT_TOLERANCE

#: Problems quoted in one message (the rest are counted).
MAX_LISTED_PROBLEMS = 20
#: Characters of user input quoted in a message.
MAX_QUOTED = 40
#: What a design a surrogate cannot take should use instead.
EXACT_ROUTES = "the exact solver takes it: tdcr solve, POST /exact or tdcr.solve"
#: A loaded operator, named where a model that takes no loads is given some.
LOADED_EXAMPLE = "fno_pose_loaded"


class Problem(NamedTuple):
    """One bad field: its location (e.g. ``("designs", 3, "E")``), the reason and a short type."""

    loc: tuple[str | int, ...]
    msg: str
    type: str


def format_location(loc: Sequence[str | int]) -> str:
    """``("designs", 3, "tendons", 1, "tension")`` -> ``designs[3].tendons[1].tension``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else ("." if out else "") + str(part)
    return out


def quote(text: object) -> str:
    """``repr`` of user input, cut to :data:`MAX_QUOTED` characters."""
    text = repr(text)
    return text if len(text) <= MAX_QUOTED else text[:MAX_QUOTED] + "...'"


def _short(part: str | int) -> str | int:
    """A location part as given by the user (e.g. an unknown key), cut to :data:`MAX_QUOTED` characters."""
    return part if isinstance(part, int) or len(part) <= MAX_QUOTED else part[:MAX_QUOTED] + "..."


class InvalidRequest(ValueError):
    """Bad input: ``problems`` name each field and reason.  ``too_large`` marks size limits (413)."""

    def __init__(self, problems: Iterable[Problem], *, too_large: bool = False):
        self.problems = list(problems)
        self.too_large = too_large
        super().__init__(self.message)

    def __reduce__(self):  # picklable with its problems (it crosses process boundaries)
        return (_invalid_request, (self.problems, self.too_large))

    @property
    def message(self) -> str:
        """One line per problem (the first :data:`MAX_LISTED_PROBLEMS`): ``location: reason``."""
        lines = [f"{format_location(p.loc) or 'request'}: {p.msg}" for p in self.problems[:MAX_LISTED_PROBLEMS]]
        more = len(self.problems) - MAX_LISTED_PROBLEMS
        return "; ".join(lines) + (f"; and {more} more" if more > 0 else "")


def _invalid_request(problems: list[Problem], too_large: bool) -> InvalidRequest:
    return InvalidRequest(problems, too_large=too_large)


def check_features(features: np.ndarray, rows: np.ndarray | None = None) -> list[Problem]:
    """Problems with raw SI designs ``(B, 3 + 3 N_t)``: not finite, or outside the admissible
    bounds; ``rows`` ``(B,)`` are the designs' indices in the request (default ``0..B-1``)."""
    layout = FeatureLayout.of(features)
    low, high, exclusive = admissible_bounds(layout.n_tendons)
    finite = np.isfinite(features)
    with np.errstate(invalid="ignore"):
        bad = ~finite | (features > high) | np.where(exclusive, features <= low, features < low)
    rows = np.arange(len(features)) if rows is None else rows
    problems = []
    for b, j in zip(*np.nonzero(bad), strict=True):  # the offending entries only, by design then column
        name = layout.parameters[j]
        tendon = layout.tendon_index[j]
        loc = ("designs", int(rows[b])) + ((name,) if tendon is None else ("tendons", tendon, name))
        value = features[b, j]
        if not finite[b, j]:
            problems.append(Problem(loc, f"must be a finite number, got {value}", "finite_number"))
        else:
            problems.append(Problem(loc, f"must be in {interval(TABLE_I[name])}, got {value:.6g}", "out_of_range"))
    return problems


def _outside(values: np.ndarray, field) -> np.ndarray:
    """Where ``values`` (any shape) are not finite or outside ``field``'s admissible bounds (its
    ``admissible``, ``exclusive_min`` and ``exclusive_max``), as a bool array of the same shape."""
    low, high = field.admissible
    with np.errstate(invalid="ignore"):
        return (~np.isfinite(values) | ((values >= high) if field.exclusive_max else (values > high))
                | ((values <= low) if field.exclusive_min else (values < low)))


def check_layout(designs: DesignBatch, rows: np.ndarray | None = None) -> list[Problem]:
    """Problems with the general design's optional fields (:data:`tdcr.robot.fields.OPTIONAL`): a value
    that is not finite or outside its admissible bounds, or an arclength (``end``) beyond the
    design's L (within rounding: clamped; not judged where L itself is refused, which
    :func:`check_features` names)."""
    rows = np.arange(designs.n_designs) if rows is None else rows
    length_admissible = ~_outside(designs.L, TABLE_I["L"])  # (B,): an end is judged against these Ls only
    problems = []
    for field in OPTIONAL:
        values = getattr(designs, field.name)
        if values is None:
            continue
        values = values.reshape(designs.n_designs, -1)
        low = field.admissible[0]
        given = ~np.isnan(values) if field.alternative_to else np.ones(values.shape, dtype=bool)
        given &= ~((values == np.inf) & np.isinf(field.fill(designs.L[:1], 1)).all())  # inf: the default (rigid)
        bad = given & _outside(values, field)
        if field.choices:
            bad |= given & ~np.isin(values, list(field.choices.values()))
        if field.within_length:
            bad |= length_admissible[:, None] & (values > designs.L[:, None] * (1.0 + FRACTION_ROUNDING))
        for b, i in zip(*np.nonzero(bad), strict=True):
            loc = ("designs", int(rows[b])) + ((field.name,) if field.per == "design" else ("tendons", int(i),
                                                                                            field.name))
            value = values[b, i]
            if not np.isfinite(value):
                msg, kind = f"must be a finite number, got {value}", "finite_number"
            elif field.choices:
                words = " or ".join(f"{w!r} ({n:g})" for w, n in field.choices.items())
                msg, kind = f"must be {words}, got {value:.6g}", "not_a_choice"
            elif field.within_length and value > low and length_admissible[b]:
                msg, kind = (f"must be in (0, L] = {interval(field, high=designs.L[b])}, got {value:.6g}",
                             "end_beyond_length")
            else:
                msg, kind = f"must be in {interval(field)}, got {value:.6g}", "out_of_range"
            problems.append(Problem(loc, msg, kind))
    return problems


#: Why a surrogate refuses a general design's field (it was trained on one layout): field -> reason
#: (:attr:`tdcr.robot.fields.DesignField.refusal`), and the request option ``termination``.
LAYOUT_REASONS = {f.name: refusal(f.name, N_TENDONS) for f in OPTIONAL} | {
    "termination": "the operators' tendons all end at the tip"}


def check_standard_layout(designs: DesignBatch, rows: np.ndarray | None = None) -> list[Problem]:
    """Problems of designs for a surrogate, which takes only the layout it was trained on
    (:meth:`DesignBatch.is_standard`): one per design, naming its first other field
    (:meth:`DesignBatch.first_departure`)."""
    rows = np.arange(designs.n_designs) if rows is None else rows
    return [Problem(("designs", int(rows[b])) + where, f"{LAYOUT_REASONS[where[-1]]}; {EXACT_ROUTES}", "layout")
            for b, where in enumerate(designs.first_departure()) if where is not None]


def check_loads(loads: ExternalLoads, rows: np.ndarray) -> list[Problem]:
    """Problems with external loads (arrays as in :class:`ExternalLoads`, NaN where absent):
    not finite, outside the admissible bounds, or gravity without a density."""
    problems = []
    for name in ("gravity", "density", "tip_force", "tip_moment"):
        values = getattr(loads, name)
        if values is None:
            continue
        values = values.reshape(len(rows), -1)
        bound = LOADS[name]
        low, high = bound.admissible
        given = ~np.isnan(values) if name in ("gravity", "density") else np.ones(values.shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            bad = given & (~np.isfinite(values) | (values > high) | ((values <= low) if bound.exclusive_min
                                                                     else (values < low)))
        for b, k in zip(*np.nonzero(bad), strict=True):
            loc = ("designs", int(rows[b]), name) + ((int(k),) if values.shape[1] > 1 else ())
            value = values[b, k]
            msg = (f"must be a finite number, got {value}" if not np.isfinite(value) else
                   f"must be in {interval(bound)}, got {value:.6g}")
            problems.append(Problem(loc, msg, "finite_number" if not np.isfinite(value) else "out_of_range"))
    if loads.gravity is not None:
        no_density = np.isnan(loads.density) & ~np.isnan(loads.gravity).any(axis=1)
        problems += [Problem(("designs", int(rows[b]), "density"), "gravity needs a density (kg/m^3)",
                             "missing_density") for b in np.nonzero(no_density)[0]]
    return problems


def checkable_loads(loads: ExternalLoads, n: int) -> ExternalLoads:
    """Loads as the checks read them: arrays of ``n`` rows; a design without gravity (zero or
    absent) has no weight, so its gravity and density count as absent (NaN)."""
    def rows(values, shape):
        return None if values is None else np.asarray(values, dtype=np.float64).reshape(n, *shape)

    gravity, density = rows(loads.gravity, (3,)), rows(loads.density, ())
    if gravity is not None and density is not None:
        weightless = ~np.any(gravity != 0, axis=1)
        gravity, density = gravity.copy(), density.copy()
        gravity[weightless], density[weightless] = np.nan, np.nan
    return ExternalLoads(gravity=gravity, density=density, tip_force=rows(loads.tip_force, (3,)),
                         tip_moment=rows(loads.tip_moment, (3,)))


def loaded_rows(matrix: np.ndarray) -> np.ndarray:
    """Per design of a loads matrix ``(B, 10)`` (:meth:`ExternalLoads.matrix`, NaN read as 0): a
    weight (gravity and a density), a tip force or a tip moment that is not zero, ``(B,)``."""
    matrix = np.nan_to_num(matrix)
    weight = matrix[:, LOAD_COLUMNS["gravity"]] * matrix[:, LOAD_COLUMNS["density"]]
    return np.any(weight != 0, axis=1) | np.any(matrix[:, LOAD_COLUMNS["tip_force"].start:] != 0, axis=1)


def check_model_loads(loads: ExternalLoads | None, rows: np.ndarray, *, model: str) -> list[Problem]:
    """Problems for an operator that takes no loads (``model``): one per design ``rows`` with a
    load, naming its first load field."""
    if loads is None:
        return []
    matrix = np.nan_to_num(loads.matrix(len(rows)))
    problems = []
    for b in np.nonzero(loaded_rows(matrix))[0]:
        field = next(name for name in ("gravity", "tip_force", "tip_moment") if np.any(matrix[b, LOAD_COLUMNS[name]]))
        problems.append(Problem(("designs", int(rows[b]), field), f"model {model!r} takes no external loads: name a "
                                f"loaded operator (model {LOADED_EXAMPLE!r}), or {EXACT_ROUTES}",
                                "model_takes_no_loads"))
    return problems


def check_tolerance(tolerance: float | None, *, name: str = "tolerance") -> list[Problem]:
    """The problem with a ``tolerance`` (relative l2; None: none): it must be a number of at least
    :data:`tdcr.surrogates.bounds.EXACT_TOLERANCE`, what the exact solver itself guarantees."""
    if tolerance is None:
        return []
    number = isinstance(tolerance, (int, float, np.floating)) and not isinstance(tolerance, bool)
    if not number or not np.isfinite(tolerance) or tolerance < EXACT_TOLERANCE:
        shown = tolerance if number else type(tolerance).__name__
        return [Problem((name,), f"must be a relative l2 error of at least {EXACT_TOLERANCE:g} (what the exact "
                        f"solver guarantees), got {shown}", "greater_than_equal")]
    return []


def check_fractions(fractions: Sequence[float] | np.ndarray, *, name: str = "s") -> tuple[np.ndarray | None,
                                                                                    list[Problem]]:
    """Arclength fractions ``(n,)`` clamped onto [0, 1] (within :data:`FRACTION_ROUNDING`), or
    None and the problems (not finite, outside [0, 1])."""
    values = np.asarray(fractions, dtype=np.float64).reshape(-1)
    with np.errstate(invalid="ignore"):
        bad = np.nonzero(~((values >= -FRACTION_ROUNDING) & (values <= 1.0 + FRACTION_ROUNDING)))[0]
    problems = [Problem((name, int(i)), f"must be a fraction of L in [0, 1], got {values[i]}", "fraction")
                for i in bad]
    if values.size == 0:
        problems.append(Problem((name,), "must hold at least one fraction of L", "points"))
    return (None if problems else np.clip(values, 0.0, 1.0)), problems


def check_surrogate_features(features: np.ndarray) -> list[Problem]:
    """Problems of raw SI designs for a surrogate, which takes ``(B, 15)``: 4 tendons and no loads."""
    features = np.asarray(features)
    if features.ndim != 2 or features.shape[0] < 1 or features.dtype.kind not in "fiu":
        return [Problem(("designs",), f"expected a numeric (B, {3 + 3 * N_TENDONS}) array [E, r, L, offsets, "
                                      f"pitches, tensions] with B >= 1, got {features.dtype} {features.shape}",
                        "array")]
    if features.shape[1] != 3 + 3 * N_TENDONS:
        tendons = (features.shape[1] - 3) / 3
        count = f"{tendons:g} tendons" if tendons == int(tendons) else f"{features.shape[1]} columns"
        return [Problem(("designs",), f"the operators take {N_TENDONS} tendons ({3 + 3 * N_TENDONS} columns), got "
                                      f"{count}; {EXACT_ROUTES}", "tendon_count")]
    return check_features(features)


def raise_problems(problems: Iterable[Problem]) -> None:
    """:class:`InvalidRequest` if there is any problem."""
    problems = list(problems)
    if problems:
        raise InvalidRequest(problems)
