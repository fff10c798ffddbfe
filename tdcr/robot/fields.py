"""The one registry of design and tendon fields.

Every input of a design is one :class:`DesignField` here: its name, whether it is given per design
or per tendon, its SI unit, its admissible bounds (refused outside), its Table I range where the
surrogates take it as a feature (warned outside), its default, why an operator refuses it where
it is not a feature, and where it travels in the Open Inference Protocol's tensors.  What knows
about fields derives from :data:`FIELDS`: :class:`tdcr.robot.designs.DesignBatch` and its
:class:`~tdcr.robot.designs.FeatureLayout`, the value checks (:mod:`tdcr.api.checks`), the JSON
schemas (:mod:`tdcr.api.schemas`), the OIP ``layout`` tensor (``service/oip.py``),
:func:`tdcr.robot.design_space.describe` and the dataset's arrays (``training/dataset.py``).

A new field is one entry of :data:`FIELDS` (and the physics that reads it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Literal, NamedTuple

import numpy as np

#: The Poisson ratio of a design that gives none (G = E / (2 (1 + nu))): the surrogates' material.
DEFAULT_POISSON = 0.3
#: Longest admissible backbone, m (also the bound of a tendon's end and of arclengths in metres).
MAX_LENGTH = 5.0
#: A tendon's motion through its guides (the sign of its friction, eq. CAP): its word and number.
MOTIONS: dict[str, float] = {"pull": 1.0, "release": -1.0}


@cache
def default_angles(n_tendons: int) -> np.ndarray:
    """The body-frame angles at s = 0 of evenly spaced tendons, 2 pi i / N_t, rad, ``(N_t,)``,
    read-only (built once per tendon count)."""
    angles = 2.0 * np.pi * np.arange(n_tendons) / n_tendons
    angles.flags.writeable = False
    return angles


class Default(NamedTuple):
    """The default of a field that depends on the design: in words (schemas, docs), and its values
    ``(B,)`` or ``(B, N_t)`` from the designs' lengths ``L`` ``(B,)`` and tendon count."""

    words: str
    values: Callable[[np.ndarray, int], np.ndarray]


@dataclass(frozen=True)
class DesignField:
    """One input of a design.

    Attributes:
        name: the key in a request, e.g. ``"offset"``; the attribute of :class:`DesignBatch`.
        per: ``"design"`` (shape ``(B,)``) or ``"tendon"`` (``(B, N_t)``).
        unit: SI unit (``""``: dimensionless).
        description: what it is, in a phrase (the JSON schema's description, with the unit).
        admissible: the physically sane range ``(low, high)``; values outside are refused.
        exclusive_min / exclusive_max: the bound itself is outside.
        trained: the Table I range ``(low, high)`` of a field the surrogates take as a feature
            column (values outside get a range warning); ``None``: not a feature.
        default: the value of a design that gives none (a number, a :class:`Default`, or ``None``:
            required, or for ``alternative_to`` absent: the other field drives the tendon).
        refusal: why an operator refuses a design that sets this non-feature field.
        alternative_to: a field this one replaces where given (a tendon gives one of the two).
        within_length: the value is an arclength, at most the design's L.
        oip: how it travels in the OIP tensors: ``"design"`` (a column of the ``design`` matrix),
            ``"layout"`` (a column of the ``layout`` tensor ``[B, N_t, k]``) or ``"own"`` (a tensor
            of its name, ``[B]``).
        inverse: an inverse-kinematics design may give it (not a quantity the inverse finds).
        choices: a field given in words: each word and the number it stands for (e.g. ``motion``:
            ``{"pull": 1, "release": -1}``); ``None``: a number.
    """

    name: str
    per: Literal["design", "tendon"]
    unit: str
    description: str
    admissible: tuple[float, float]
    exclusive_min: bool = False
    exclusive_max: bool = False
    trained: tuple[float, float] | None = None
    default: float | Default | None = None
    refusal: str | None = None
    alternative_to: str | None = None
    within_length: bool = False
    oip: Literal["design", "layout", "own"] = "design"
    inverse: bool = True
    choices: dict[str, float] | None = None

    @property
    def feature(self) -> bool:
        """A column of the surrogates' feature matrix (it has a Table I range)."""
        return self.trained is not None

    @property
    def low(self) -> float:
        """Table I lower bound (features only)."""
        return self.trained[0]

    @property
    def high(self) -> float:
        """Table I upper bound (features only)."""
        return self.trained[1]

    @property
    def required(self) -> bool:
        """A design must give it (a feature without a default)."""
        return self.feature and self.default is None

    def fill(self, L: np.ndarray, n_tendons: int) -> np.ndarray:
        """The default values of ``B`` designs of lengths ``L`` ``(B,)``: ``(B,)`` or ``(B, N_t)``
        (NaN: absent, for a field that is an alternative to another)."""
        shape = (L.shape[0],) if self.per == "design" else (L.shape[0], n_tendons)
        if isinstance(self.default, Default):
            return np.array(np.broadcast_to(self.default.values(L, n_tendons), shape), dtype=np.float64)
        return np.full(shape, np.nan if self.default is None else float(self.default))

    @property
    def default_words(self) -> str | float | None:
        """The default as the schemas and :func:`~tdcr.robot.design_space.describe` show it."""
        if self.choices:
            return next(word for word, number in self.choices.items() if number == self.default)
        return self.default.words if isinstance(self.default, Default) else self.default


#: Every design field, in order: the features first, in the feature matrix's column order
#: (:class:`tdcr.robot.designs.FeatureLayout`), then the general design's optional fields.
FIELDS: tuple[DesignField, ...] = (
    DesignField("E", "design", "Pa", "Young's modulus", (1e6, 1e12), trained=(15.5e9, 45.5e9)),  # rubber .. diamond
    DesignField("r", "design", "m", "backbone radius", (1e-4, 0.05), trained=(0.0005, 0.0015)),
    DesignField("L", "design", "m", "backbone length", (0.01, MAX_LENGTH), trained=(0.1, 0.35)),
    DesignField("offset", "tendon", "m", "distance of the tendon from the backbone axis", (1e-4, 0.1),
                trained=(0.005, 0.01)),
    DesignField("pitch", "tendon", "rad/m", "helical pitch of the routing", (-200.0, 200.0), trained=(-20.0, 20.0),
                default=0.0),
    DesignField("tension", "tendon", "N", "tendon tension", (0.0, 1000.0), trained=(0.0, 5.0)),
    DesignField("angle", "tendon", "rad", "body-frame angle of the tendon at s = 0 (default 2 pi i / N_t)",
                (-50.0, 50.0), default=Default("2 pi i / N_t", lambda L, n: default_angles(n)),
                refusal="the operators take tendons at 2 pi i / {n_tendons}", oip="layout"),
    DesignField("end", "tendon", "m", "arclength where the tendon terminates, 0 < end <= L (default L): tendons "
                "with distinct ends make segments", (0.0, MAX_LENGTH), exclusive_min=True,
                default=Default("L", lambda L, n: L[:, None]), refusal="the operators take tendons that end at the tip",
                within_length=True, oip="layout"),
    DesignField("poisson", "design", "", "Poisson ratio nu of the backbone, G = E / (2 (1 + nu)) (default 0.3)",
                (0.0, 0.5), exclusive_min=True, exclusive_max=True, default=DEFAULT_POISSON,
                refusal=f"the operators were trained at nu = {DEFAULT_POISSON}", oip="own"),
    DesignField("displacement", "tendon", "m", "length pulled in (its path length on the straight rod minus its "
                "deformed path length), instead of a tension: the solver finds the tension (0 where the tendon would "
                "go slack)", (-1.0, 1.0), refusal="the operators take tensions", alternative_to="tension",
                oip="layout", inverse=False),
    DesignField("stiffness", "tendon", "N/m", "series stiffness k of the tendon and its drive (default rigid): a "
                "displacement u then pulls with tension k max(0, u - zero - d), d the length the path shortened "
                "(OIP layout: 0 for rigid)", (1e-3, 1e12), exclusive_min=True,
                default=Default("rigid", lambda L, n: np.inf), refusal="the operators take rigid tendons",
                oip="layout", inverse=False),
    DesignField("zero", "tendon", "m", "the drive's reading at which the tendon is just taut on the straight rod "
                "(subtracted from a displacement)", (-1.0, 1.0), default=0.0,
                refusal="the operators take tensions", oip="layout", inverse=False),
    DesignField("friction", "tendon", "", "Capstan friction coefficient mu between the tendon and its guides: the "
                "tension decays (pull) or grows (release) along the path as d tau / ds = -/+ mu tau |d t / ds|",
                (0.0, 2.0), default=0.0, refusal="the operators take frictionless tendons", oip="layout",
                inverse=False),
    DesignField("motion", "tendon", "", "how the tendon last moved through its guides, the sign of its friction: "
                "\"pull\" (tension falls from the drive) or \"release\" (it grows)", (-1.0, 1.0),
                default=MOTIONS["pull"], refusal="the operators take frictionless tendons", oip="layout",
                inverse=False, choices=MOTIONS),
)
#: The fields by name.
BY_NAME: dict[str, DesignField] = {f.name: f for f in FIELDS}
#: The features (the surrogates' inputs, Table I), in column order: per design, then per tendon.
FEATURES: tuple[DesignField, ...] = tuple(f for f in FIELDS if f.feature)
DESIGN_FEATURES: tuple[str, ...] = tuple(f.name for f in FEATURES if f.per == "design")
TENDON_FEATURES: tuple[str, ...] = tuple(f.name for f in FEATURES if f.per == "tendon")
#: The general design's optional fields (exact solver only; the surrogates take their defaults).
OPTIONAL: tuple[DesignField, ...] = tuple(f for f in FIELDS if not f.feature)
#: The OIP ``layout`` tensor's columns ``[B, N_t, k]``: each tendon field that travels there, and
#: after a field that is an alternative to another, a column ``driven`` (1: the tendon is driven by
#: that field, 0: by the other).
LAYOUT_COLUMNS: tuple[str, ...] = tuple(name for f in OPTIONAL if f.oip == "layout"
                                        for name in ((f.name, "driven") if f.alternative_to else (f.name,)))
#: The general design's fields that travel as tensors of their own (``[B]``).
OWN_TENSORS: tuple[str, ...] = tuple(f.name for f in OPTIONAL if f.oip == "own")


def refusal(name: str, n_tendons: int) -> str:
    """Why an operator of ``n_tendons`` tendons refuses a design that sets field ``name``."""
    return BY_NAME[name].refusal.format(n_tendons=n_tendons)


def interval(field, low: float | None = None, high: float | None = None) -> str:
    """A field's admissible interval in words, e.g. ``(0, 0.5)`` or ``[0, 1000] N``; ``low`` and
    ``high`` override its bounds (the bounds of a load or a parameter: anything with
    ``admissible``, ``exclusive_min`` and ``unit``)."""
    lo, hi = field.admissible
    lo, hi = lo if low is None else low, hi if high is None else high
    closing = ")" if getattr(field, "exclusive_max", False) else "]"
    return f"{'(' if field.exclusive_min else '['}{lo:g}, {hi:g}{closing}" + (f" {field.unit}" if field.unit else "")
