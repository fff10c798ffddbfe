"""Batches of TDCR designs as float64 arrays (no torch, no pydantic).

A design is (E, r, L) plus, for each of ``N_t`` tendons, an offset, a helical
pitch and a tension.  Tendon ``i`` runs in the body frame at
``offset_i * [cos(angle_i + pitch_i s), sin(angle_i + pitch_i s), 0]`` for ``s <= end_i``, with
the defaults ``angle_i = 2 pi i / N_t`` and ``end_i = L``; the material's Poisson ratio defaults to
:data:`DEFAULT_POISSON`.  A tendon may be driven by a ``displacement`` (the length pulled in, m)
instead of its tension.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from tdcr.robot.fields import (  # noqa: F401 - re-exported: the designs' vocabulary
    BY_NAME,
    DEFAULT_POISSON,
    DESIGN_FEATURES,
    FIELDS,
    OPTIONAL,
    TENDON_FEATURES,
    default_angles,
)

#: Columns of E, r and L in a feature matrix (the per-tendon groups follow, see :class:`FeatureLayout`).
E_COLUMN, R_COLUMN, L_COLUMN = (DESIGN_FEATURES.index(name) for name in ("E", "r", "L"))
#: The per-tendon feature groups, in column order (:data:`tdcr.robot.fields.TENDON_FEATURES`).
TENDON_GROUPS = TENDON_FEATURES
#: Columns of the loads matrix ``(B, 10)`` of the loaded operators (the ONNX input ``loads``):
#: gravity (3, m/s^2), density (kg/m^3), tip force (3, N), tip moment (3, N m), base frame.
LOAD_COLUMNS: dict[str, slice] = {"gravity": slice(0, 3), "density": slice(3, 4), "tip_force": slice(4, 7),
                                  "tip_moment": slice(7, 10)}
N_LOAD_COLUMNS = 10


@dataclass(frozen=True)
class FeatureLayout:
    """Column layout of the raw SI feature matrix ``(B, 3 + 3 N_t)``:
    ``[E, r, L, offset_0..offset_{N_t-1}, pitch_0.., tension_0..]``.

    The one place that knows where each quantity sits; the dataset, the networks, the ONNX models
    and the service all use this order.
    """

    n_tendons: int

    @property
    def width(self) -> int:
        """Number of feature columns, ``3 + 3 N_t``."""
        return len(DESIGN_FEATURES) + len(TENDON_GROUPS) * self.n_tendons

    def group(self, name: str) -> slice:
        """Columns of one per-tendon group (``offset``, ``pitch`` or ``tension``)."""
        start = len(DESIGN_FEATURES) + TENDON_GROUPS.index(name) * self.n_tendons
        return slice(start, start + self.n_tendons)

    @cached_property
    def names(self) -> tuple[str, ...]:
        """Column names, e.g. ``('E', 'r', 'L', 'offset_0', ...)``."""
        return DESIGN_FEATURES + tuple(f"{g}_{i}" for g in TENDON_GROUPS for i in range(self.n_tendons))

    @cached_property
    def parameters(self) -> tuple[str, ...]:
        """The design parameter (a key of Table I) of every column, e.g. ``('E', 'r', 'L', 'offset', ...)``."""
        return DESIGN_FEATURES + tuple(g for g in TENDON_GROUPS for _ in range(self.n_tendons))

    @cached_property
    def tendon_index(self) -> tuple[int | None, ...]:
        """The tendon of every column (``None`` for E, r and L)."""
        return (None,) * len(DESIGN_FEATURES) + tuple(i for _ in TENDON_GROUPS for i in range(self.n_tendons))

    @classmethod
    def of(cls, features: np.ndarray) -> FeatureLayout:
        """The layout of a feature matrix ``(B, 3 + 3 N_t)`` (``ValueError`` if no layout fits)."""
        features = np.asarray(features)
        d, g = len(DESIGN_FEATURES), len(TENDON_GROUPS)
        n_t = (features.shape[-1] - d) // g if features.ndim == 2 else 0
        if n_t < 1 or features.shape[-1] != d + g * n_t:
            raise ValueError(f"features must have shape (B, 3 + 3 N_t) with N_t >= 1, got {features.shape}")
        return cls(n_t)


@dataclass(frozen=True)
class DesignBatch:
    """A batch of ``B`` designs with ``N_t`` tendons each (SI units).

    Attributes:
        E: Young's modulus, Pa, ``(B,)``.
        r: backbone radius, m, ``(B,)``.
        L: backbone length, m, ``(B,)``.
        offset: tendon offsets from the backbone axis, m, ``(B, N_t)``.
        pitch: helical pitch of each tendon, rad/m, ``(B, N_t)``.
        tension: tendon tensions, N, ``(B, N_t)`` (of a displacement-driven tendon: the solver's
            start, usually 0).
        angle: body-frame angle of each tendon at s = 0, rad, ``(B, N_t)``; ``None``: 2 pi i / N_t.
        end: arclength where each tendon terminates, m, ``(B, N_t)``, 0 < end <= L; ``None``: L.
        poisson: Poisson ratio nu of the backbone, ``(B,)``, G = E / (2 (1 + nu)); ``None``:
            :data:`DEFAULT_POISSON`.
        displacement: length pulled in of each displacement-driven tendon, m, ``(B, N_t)``, NaN
            where the tendon is driven by its tension; ``None``: every tendon by its tension.
        stiffness: series stiffness of each tendon and its drive, N/m, ``(B, N_t)`` (inf: rigid);
            ``None``: rigid.
        zero: the drive's reading where each tendon is just taut, m, ``(B, N_t)``; ``None``: 0.
        friction: Capstan coefficient of each tendon in its guides, ``(B, N_t)``; ``None``: 0.
        motion: each tendon's motion, 1 pulling or -1 releasing (:data:`tdcr.robot.fields.MOTIONS`),
            ``(B, N_t)``; ``None``: pulling.
    """

    E: np.ndarray
    r: np.ndarray
    L: np.ndarray
    offset: np.ndarray
    pitch: np.ndarray
    tension: np.ndarray
    angle: np.ndarray | None = None
    end: np.ndarray | None = None
    poisson: np.ndarray | None = None
    displacement: np.ndarray | None = None
    stiffness: np.ndarray | None = None
    zero: np.ndarray | None = None
    friction: np.ndarray | None = None
    motion: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in FIELDS:  # the registry's fields (a test checks that they are this class's)
            if getattr(self, f.name) is not None:
                object.__setattr__(self, f.name, np.asarray(getattr(self, f.name), dtype=np.float64))
        b = self.E.shape[0]
        if self.E.ndim != 1 or any(getattr(self, name).shape != (b,) for name in DESIGN_FEATURES):
            raise ValueError(f"{', '.join(DESIGN_FEATURES)} must all have shape (B,)")
        first = TENDON_GROUPS[0]
        if getattr(self, first).ndim != 2 or getattr(self, first).shape[0] != b:
            raise ValueError(f"{first} must have shape (B, N_t)")
        if any(getattr(self, name).shape != self.offset.shape for name in TENDON_GROUPS):
            raise ValueError(f"{', '.join(TENDON_GROUPS)} must share the shape (B, N_t)")
        for f in OPTIONAL:
            value = getattr(self, f.name)
            shape = (b,) if f.per == "design" else self.offset.shape
            if value is not None and value.shape != shape:
                raise ValueError(f"{f.name} must have shape {'(B,)' if f.per == 'design' else '(B, N_t) of offset'}")

    def resolved(self, name: str) -> np.ndarray:
        """Field ``name`` with its default filled in, ``(B,)`` or ``(B, N_t)`` (a field that is an
        alternative to another: NaN where the tendon is driven by the other)."""
        value = getattr(self, name)
        return BY_NAME[name].fill(self.L, self.n_tendons) if value is None else value

    def departs(self, name: str) -> np.ndarray:
        """Where field ``name`` is set to other than its default, ``(B,)`` or ``(B, N_t)`` bool (an
        arclength within rounding above L counts as L; a field that is an alternative: where given)."""
        f = BY_NAME[name]
        value = getattr(self, name)
        shape = (self.n_designs,) if f.per == "design" else self.offset.shape
        if value is None:
            return np.zeros(shape, dtype=bool)
        if f.alternative_to is not None:
            return ~np.isnan(value)
        if f.within_length:
            value = np.minimum(value, self.L[:, None] if f.per == "tendon" else self.L)
        return ~np.isclose(value, f.fill(self.L, self.n_tendons), rtol=0.0, atol=1e-12)

    @property
    def angles(self) -> np.ndarray:
        """The tendons' angles at s = 0, rad, ``(B, N_t)`` (defaults filled in)."""
        return self.resolved("angle")

    @property
    def ends(self) -> np.ndarray:
        """The tendons' ends, m, ``(B, N_t)`` (default L)."""
        return self.resolved("end")

    @property
    def end_fractions(self) -> np.ndarray:
        """The tendons' ends as fractions of L, ``(B, N_t)``, in (0, 1] (1 exactly for a tendon that
        ends at the tip)."""
        if self.end is None:
            return np.ones(self.offset.shape)
        return np.minimum(self.end / self.L[:, None], 1.0)

    @property
    def poissons(self) -> np.ndarray:
        """The Poisson ratio of every design, ``(B,)``."""
        return self.resolved("poisson")

    @property
    def displacement_driven(self) -> np.ndarray:
        """Per tendon ``(B, N_t)``: driven by a displacement (rather than its tension)."""
        return self.departs("displacement")

    @property
    def compliance(self) -> np.ndarray:
        """Each tendon's series compliance 1 / stiffness, m/N, ``(B, N_t)`` (0: rigid)."""
        if self.stiffness is None:  # rigid: the default's 1 / inf without filling it in
            return np.zeros(self.offset.shape)
        return 1.0 / self.stiffness

    @property
    def capstan(self) -> np.ndarray:
        """Each tendon's signed Capstan coefficient, ``(B, N_t)``: tau(s) = tau(0) exp(capstan
        theta(s)) with theta the wrap angle, -friction pulling, +friction releasing (eq. CAP)."""
        if self.friction is None:  # frictionless: 0 whatever the motion
            return np.zeros(self.offset.shape)
        return -self.friction * self.resolved("motion")

    @property
    def segmented(self) -> np.ndarray:
        """Per design ``(B,)``: some tendon ends before the tip (the rod has several segments)."""
        return (self.end_fractions < 1.0).any(axis=1)

    def first_departure(self) -> list[tuple | None]:
        """Per design, where it first leaves the surrogates' layout (every optional field at its
        default): ``("tendons", i, name)`` for the first tendon ``i`` with a field ``name`` set,
        else ``(name,)`` for a design field, or ``None`` (the surrogates' layout)."""
        if all(getattr(self, f.name) is None for f in OPTIONAL):  # none given (features alone): every default
            return [None] * self.n_designs
        tendon = [f.name for f in OPTIONAL if f.per == "tendon"]
        design = [f.name for f in OPTIONAL if f.per == "design"]
        per_tendon = [self.departs(n) for n in tendon]  # each (B, N_t)
        per_design = [self.departs(n) for n in design]  # each (B,)
        out: list[tuple | None] = []
        for b in range(self.n_designs):
            where = next((("tendons", i, n) for i in range(self.n_tendons) for n, d in zip(tendon, per_tendon,
                                                                                         strict=True) if d[b, i]),
                         None)
            out.append(where or next(((n,) for n, d in zip(design, per_design, strict=True) if d[b]), None))
        return out

    def is_standard(self) -> np.ndarray:
        """Per design ``(B,)``: the surrogates' layout, i.e. every optional field of
        :data:`tdcr.robot.fields.OPTIONAL` at its default (default angles, every tendon ending at the
        tip, the default Poisson ratio and tension actuation)."""
        out = np.ones(self.n_designs, dtype=bool)
        for f in OPTIONAL:
            departs = self.departs(f.name)
            out &= ~(departs.any(axis=1) if departs.ndim == 2 else departs)
        return out

    def replace(self, **fields) -> DesignBatch:
        """A copy with some fields replaced (e.g. ``tension=...``)."""
        return DesignBatch(**{f.name: fields.get(f.name, getattr(self, f.name)) for f in FIELDS})

    @property
    def n_designs(self) -> int:
        return int(self.E.shape[0])

    @property
    def n_tendons(self) -> int:
        return int(self.offset.shape[1])

    def __len__(self) -> int:
        return self.n_designs

    def take(self, index) -> DesignBatch:
        """Sub-batch selected by an integer index array or slice."""
        return DesignBatch(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[index]
                              for f in FIELDS})

    def features(self) -> np.ndarray:
        """Raw SI feature matrix ``(B, 3 + 3 N_t)``: [E, r, L, offsets, pitches, tensions]."""
        return np.concatenate([getattr(self, n)[:, None] for n in DESIGN_FEATURES]
                              + [getattr(self, n) for n in TENDON_GROUPS], axis=1)

    @classmethod
    def from_features(cls, features: np.ndarray) -> DesignBatch:
        """Inverse of :meth:`features` for ``(B, 3 + 3 N_t)`` arrays."""
        features = np.asarray(features, dtype=np.float64)
        layout = FeatureLayout.of(features)
        return cls(**{n: features[:, j] for j, n in enumerate(DESIGN_FEATURES)},
                   **{n: features[:, layout.group(n)] for n in TENDON_GROUPS})

    def to_dicts(self) -> list[dict]:
        """The designs as JSON-ready dicts of the request format (``tdcr.api.schemas.Design``), SI units;
        the optional fields only where given (a tendon driven by an alternative field gives it
        instead of the field it replaces)."""
        given = {f.name: getattr(self, f.name) for f in OPTIONAL if getattr(self, f.name) is not None}
        alternatives = [f for f in OPTIONAL if f.alternative_to is not None and f.name in given]
        out = []
        for b in range(self.n_designs):
            tendons = []
            for i in range(self.n_tendons):
                replaced = {f.alternative_to for f in alternatives if not np.isnan(given[f.name][b, i])}
                t = {n: float(getattr(self, n)[b, i]) for n in TENDON_GROUPS if n not in replaced}
                t |= {n: _json_value(BY_NAME[n], v[b, i]) for n, v in given.items() if BY_NAME[n].per == "tendon"
                      and np.isfinite(v[b, i])}  # NaN: the alternative drives it; inf: rigid (the default)
                tendons.append(t)
            design = {n: float(getattr(self, n)[b]) for n in DESIGN_FEATURES} | {"tendons": tendons}
            design |= {n: float(v[b]) for n, v in given.items() if BY_NAME[n].per == "design"}
            out.append(design)
        return out

    @classmethod
    def concatenate(cls, batches: list[DesignBatch]) -> DesignBatch:
        """One batch of ``batches`` with one tendon count (optional fields filled with defaults
        where some batches give them and others not)."""
        fields = {}
        for f in FIELDS:
            if not f.feature and all(getattr(b, f.name) is None for b in batches):
                fields[f.name] = None
                continue
            fields[f.name] = np.concatenate([np.array(b.resolved(f.name)) for b in batches], axis=0)
        return cls(**fields)


def _json_value(field, value: float) -> float | str:
    """A field's value as a request gives it: its word for a field in words (``motion``), else the number."""
    if field.choices:
        return next(word for word, number in field.choices.items() if number == value)
    return float(value)


@dataclass(frozen=True)
class ExternalLoads:
    """Optional external loads, per design; each ``None`` means zero.

    Attributes:
        gravity: gravitational acceleration in the base frame, m/s^2, ``(B, 3)``.
        density: backbone density, kg/m^3, ``(B,)`` (needed with ``gravity``).
        tip_force: force applied at the tip, base frame, N, ``(B, 3)``.
        tip_moment: moment applied at the tip, base frame, N m, ``(B, 3)``.
    """

    gravity: np.ndarray | None = None
    density: np.ndarray | None = None
    tip_force: np.ndarray | None = None
    tip_moment: np.ndarray | None = None

    def resolved(self, n_designs: int, area: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(f_g, F, M)``: weight per unit length (N/m), tip force (N), tip moment (N m), each ``(B, 3)``."""
        zeros = np.zeros((n_designs, 3))
        f_g = zeros
        if self.gravity is not None:
            if self.density is None:
                raise ValueError("gravity needs a density")
            f_g = np.asarray(self.density, float)[:, None] * area[:, None] * np.asarray(self.gravity, float)
        F = zeros if self.tip_force is None else np.asarray(self.tip_force, float).reshape(n_designs, 3)
        M = zeros if self.tip_moment is None else np.asarray(self.tip_moment, float).reshape(n_designs, 3)
        return f_g, F, M

    def matrix(self, n_designs: int) -> np.ndarray:
        """The loads as the loaded operators take them, ``(B, 10)`` (:data:`LOAD_COLUMNS`); absent
        loads are zeros, and a design without gravity has density 0."""
        out = np.zeros((n_designs, N_LOAD_COLUMNS))
        for name, columns in LOAD_COLUMNS.items():
            value = getattr(self, name)
            if value is not None:
                out[:, columns] = np.asarray(value, dtype=np.float64).reshape(n_designs, -1)
        if self.gravity is None:
            out[:, LOAD_COLUMNS["density"]] = 0.0
        return out

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> ExternalLoads:
        """Inverse of :meth:`matrix` for ``(B, 10)`` arrays."""
        matrix = np.asarray(matrix, dtype=np.float64)
        return cls(**{name: matrix[:, columns].reshape(len(matrix), -1).squeeze(-1) if name == "density"
                      else matrix[:, columns] for name, columns in LOAD_COLUMNS.items()})

    def take(self, index) -> ExternalLoads:
        """The loads of the designs selected by an integer index array or slice."""
        def rows(a):
            return None if a is None else np.asarray(a)[index]
        return ExternalLoads(gravity=rows(self.gravity), density=rows(self.density),
                             tip_force=rows(self.tip_force), tip_moment=rows(self.tip_moment))

    def is_zero(self) -> bool:
        def zero(a):
            return a is None or not np.any(np.asarray(a))
        return (zero(self.gravity) or zero(self.density)) and zero(self.tip_force) and zero(self.tip_moment)
