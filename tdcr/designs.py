"""Batches of TDCR designs as float64 arrays (no torch, no pydantic).

A design is (E, r, L) plus, for each of ``N_t`` tendons, an offset, a helical
pitch and a tension.  Tendon ``i`` runs in the body frame at
``offset_i * [cos(2 pi i / N_t + pitch_i s), sin(2 pi i / N_t + pitch_i s), 0]``.
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
        tension: tendon tensions, N, ``(B, N_t)``.
    """

    E: np.ndarray
    r: np.ndarray
    L: np.ndarray
    offset: np.ndarray
    pitch: np.ndarray
    tension: np.ndarray

    def __post_init__(self) -> None:
        for name in ("E", "r", "L", "offset", "pitch", "tension"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        b = self.E.shape[0]
        if self.E.ndim != 1 or self.r.shape != (b,) or self.L.shape != (b,):
            raise ValueError("E, r and L must all have shape (B,)")
        if self.offset.ndim != 2 or self.offset.shape[0] != b:
            raise ValueError("offset must have shape (B, N_t)")
        if self.pitch.shape != self.offset.shape or self.tension.shape != self.offset.shape:
            raise ValueError("offset, pitch and tension must share the shape (B, N_t)")

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
        return DesignBatch(
            E=self.E[index], r=self.r[index], L=self.L[index],
            offset=self.offset[index], pitch=self.pitch[index], tension=self.tension[index],
        )

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
        """The designs as JSON-ready dicts of the request format (``tdcr.schemas.Design``), SI units."""
        return [{"E": E, "r": r, "L": L, "tendons": [{"offset": o, "pitch": p, "tension": t}
                                                     for o, p, t in zip(offset, pitch, tension, strict=True)]}
                for E, r, L, offset, pitch, tension in zip(self.E.tolist(), self.r.tolist(), self.L.tolist(),
                                                           self.offset.tolist(), self.pitch.tolist(),
                                                           self.tension.tolist(), strict=True)]

    @classmethod
    def concatenate(cls, batches: list[DesignBatch]) -> DesignBatch:
        return cls.from_features(np.concatenate([b.features() for b in batches], axis=0))


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
