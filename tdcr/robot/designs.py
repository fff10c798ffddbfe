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

#: Columns of E, r and L in a feature matrix (the per-tendon groups follow, see :class:`FeatureLayout`).
E_COLUMN, R_COLUMN, L_COLUMN = 0, 1, 2
#: The per-tendon feature groups, in column order.
TENDON_GROUPS = ("offset", "pitch", "tension")
#: Columns of the loads matrix ``(B, 10)`` of the loaded operators (the ONNX input ``loads``):
#: gravity (3, m/s^2), density (kg/m^3), tip force (3, N), tip moment (3, N m), base frame.
LOAD_COLUMNS: dict[str, slice] = {"gravity": slice(0, 3), "density": slice(3, 4), "tip_force": slice(4, 7),
                                  "tip_moment": slice(7, 10)}
N_LOAD_COLUMNS = 10
#: The Poisson ratio of a design that gives none (G = E / (2 (1 + nu))): the surrogates' material.
DEFAULT_POISSON = 0.3


def default_angles(n_tendons: int) -> np.ndarray:
    """The body-frame angles at s = 0 of evenly spaced tendons, 2 pi i / N_t, rad, ``(N_t,)``."""
    return 2.0 * np.pi * np.arange(n_tendons) / n_tendons


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
        return 3 + 3 * self.n_tendons

    def group(self, name: str) -> slice:
        """Columns of one per-tendon group (``offset``, ``pitch`` or ``tension``)."""
        start = 3 + TENDON_GROUPS.index(name) * self.n_tendons
        return slice(start, start + self.n_tendons)

    @cached_property
    def names(self) -> tuple[str, ...]:
        """Column names, e.g. ``('E', 'r', 'L', 'offset_0', ...)``."""
        return ("E", "r", "L") + tuple(f"{g}_{i}" for g in TENDON_GROUPS for i in range(self.n_tendons))

    @cached_property
    def parameters(self) -> tuple[str, ...]:
        """The design parameter (a key of Table I) of every column, e.g. ``('E', 'r', 'L', 'offset', ...)``."""
        return ("E", "r", "L") + tuple(g for g in TENDON_GROUPS for _ in range(self.n_tendons))

    @cached_property
    def tendon_index(self) -> tuple[int | None, ...]:
        """The tendon of every column (``None`` for E, r and L)."""
        return (None, None, None) + tuple(i for _ in TENDON_GROUPS for i in range(self.n_tendons))

    @classmethod
    def of(cls, features: np.ndarray) -> FeatureLayout:
        """The layout of a feature matrix ``(B, 3 + 3 N_t)`` (``ValueError`` if no layout fits)."""
        features = np.asarray(features)
        n_t = (features.shape[-1] - 3) // 3 if features.ndim == 2 else 0
        if n_t < 1 or features.shape[-1] != 3 + 3 * n_t:
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

    def __post_init__(self) -> None:
        for name in ("E", "r", "L", "offset", "pitch", "tension"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        for name in _OPTIONAL:
            if getattr(self, name) is not None:
                object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        b = self.E.shape[0]
        if self.E.ndim != 1 or self.r.shape != (b,) or self.L.shape != (b,):
            raise ValueError("E, r and L must all have shape (B,)")
        if self.offset.ndim != 2 or self.offset.shape[0] != b:
            raise ValueError("offset must have shape (B, N_t)")
        if self.pitch.shape != self.offset.shape or self.tension.shape != self.offset.shape:
            raise ValueError("offset, pitch and tension must share the shape (B, N_t)")
        for name in ("angle", "end", "displacement"):
            if getattr(self, name) is not None and getattr(self, name).shape != self.offset.shape:
                raise ValueError(f"{name} must have the shape (B, N_t) of offset")
        if self.poisson is not None and self.poisson.shape != (b,):
            raise ValueError("poisson must have shape (B,)")

    @property
    def angles(self) -> np.ndarray:
        """The tendons' angles at s = 0, rad, ``(B, N_t)`` (defaults filled in)."""
        if self.angle is None:
            return np.broadcast_to(default_angles(self.n_tendons), self.offset.shape)
        return self.angle

    @property
    def ends(self) -> np.ndarray:
        """The tendons' ends, m, ``(B, N_t)`` (default L)."""
        return np.broadcast_to(self.L[:, None], self.offset.shape) if self.end is None else self.end

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
        return np.full(self.n_designs, DEFAULT_POISSON) if self.poisson is None else self.poisson

    @property
    def displacement_driven(self) -> np.ndarray:
        """Per tendon ``(B, N_t)``: driven by a displacement (rather than its tension)."""
        if self.displacement is None:
            return np.zeros(self.offset.shape, dtype=bool)
        return ~np.isnan(self.displacement)

    @property
    def segmented(self) -> np.ndarray:
        """Per design ``(B,)``: some tendon ends before the tip (the rod has several segments)."""
        return (self.end_fractions < 1.0).any(axis=1)

    def is_standard(self) -> np.ndarray:
        """Per design ``(B,)``: the surrogates' layout, i.e. default angles, every tendon ending at
        the tip, the default Poisson ratio and tension actuation."""
        out = ~self.segmented & ~self.displacement_driven.any(axis=1)
        if self.angle is not None:
            out &= np.isclose(self.angle, default_angles(self.n_tendons), rtol=0.0, atol=1e-12).all(axis=1)
        if self.poisson is not None:
            out &= self.poisson == DEFAULT_POISSON
        return out

    def replace(self, **fields) -> DesignBatch:
        """A copy with some fields replaced (e.g. ``tension=...``)."""
        return DesignBatch(**{name: fields.get(name, getattr(self, name)) for name in _FIELDS})

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
        return DesignBatch(**{name: None if getattr(self, name) is None else getattr(self, name)[index]
                              for name in _FIELDS})

    def features(self) -> np.ndarray:
        """Raw SI feature matrix ``(B, 3 + 3 N_t)``: [E, r, L, offsets, pitches, tensions]."""
        return np.concatenate(
            [self.E[:, None], self.r[:, None], self.L[:, None], self.offset, self.pitch, self.tension],
            axis=1,
        )

    @classmethod
    def from_features(cls, features: np.ndarray) -> DesignBatch:
        """Inverse of :meth:`features` for ``(B, 3 + 3 N_t)`` arrays."""
        features = np.asarray(features, dtype=np.float64)
        layout = FeatureLayout.of(features)
        return cls(
            E=features[:, E_COLUMN], r=features[:, R_COLUMN], L=features[:, L_COLUMN],
            offset=features[:, layout.group("offset")], pitch=features[:, layout.group("pitch")],
            tension=features[:, layout.group("tension")],
        )

    def to_dicts(self) -> list[dict]:
        """The designs as JSON-ready dicts of the request format (``tdcr.api.schemas.Design``), SI units;
        the optional fields only where given."""
        out = []
        for b in range(self.n_designs):
            tendons = []
            for i in range(self.n_tendons):
                t = {"offset": float(self.offset[b, i]), "pitch": float(self.pitch[b, i])}
                if self.displacement is not None and not np.isnan(self.displacement[b, i]):
                    t["displacement"] = float(self.displacement[b, i])
                else:
                    t["tension"] = float(self.tension[b, i])
                if self.angle is not None:
                    t["angle"] = float(self.angle[b, i])
                if self.end is not None:
                    t["end"] = float(self.end[b, i])
                tendons.append(t)
            design = {"E": float(self.E[b]), "r": float(self.r[b]), "L": float(self.L[b]), "tendons": tendons}
            if self.poisson is not None:
                design["poisson"] = float(self.poisson[b])
            out.append(design)
        return out

    @classmethod
    def concatenate(cls, batches: list[DesignBatch]) -> DesignBatch:
        """One batch of ``batches`` with one tendon count (optional fields filled with defaults
        where some batches give them and others not)."""
        fields = {}
        for name in _FIELDS:
            if name in _OPTIONAL and all(getattr(b, name) is None for b in batches):
                fields[name] = None
                continue
            fields[name] = np.concatenate([_resolved(b, name) for b in batches], axis=0)
        return cls(**fields)


#: The optional fields of :class:`DesignBatch` (``None``: the default), and all of them in order.
_OPTIONAL = ("angle", "end", "poisson", "displacement")
_FIELDS = ("E", "r", "L", "offset", "pitch", "tension") + _OPTIONAL


def _resolved(batch: DesignBatch, name: str) -> np.ndarray:
    """A field of ``batch`` with its default filled in (NaN displacements: tension-driven)."""
    if name == "angle":
        return np.array(batch.angles)
    if name == "end":
        return np.array(batch.ends)
    if name == "poisson":
        return batch.poissons
    if name == "displacement" and batch.displacement is None:
        return np.full(batch.offset.shape, np.nan)
    return getattr(batch, name)


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
