"""The design space: Table I (names, units, trained ranges), the admissible physical bounds of
every input, sampling, OOD bins, normalisation, and range warnings.

Feature order (shared by the dataset, the networks and the ONNX models), for N_t tendons:
``[E, r, L, offset_0..offset_{N_t-1}, pitch_0.., tension_0..]``, shape ``(B, 3 + 3 N_t)``
(:class:`tdcr.robot.designs.FeatureLayout`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from tdcr.robot.designs import LOAD_COLUMNS, DesignBatch, ExternalLoads, FeatureLayout
from tdcr.robot.fields import FEATURES, OPTIONAL, DesignField

#: Tendons of the trained surrogates (the solver takes any number >= 1).
N_TENDONS = 4
#: The surrogates' feature layout and width, 3 + 3 N_TENDONS = 15.
LAYOUT = FeatureLayout(N_TENDONS)
N_FEATURES = LAYOUT.width
#: Equispaced arclengths on [0, L] when a request gives neither ``points`` nor ``s`` (the paper's grid).
DEFAULT_POINTS = 42
#: Hard upper limit of arclengths per request (a service may set a lower one).
MAX_POINTS = 1000
#: Arclength fractions within this of [0, 1] are rounding (a client's s / L at the tip can be
#: 1.000000000001): every entry point clamps them onto [0, 1] and refuses farther ones.
FRACTION_ROUNDING = 1e-9
#: Most tendons per design a request may carry.
MAX_TENDONS = 64


#: Table I of the paper (SI units): the surrogates' features (:data:`tdcr.robot.fields.FEATURES`), each
#: with its trained range (``low``, ``high``: warned outside) and its admissible bounds (refused outside).
TABLE_I: dict[str, DesignField] = {f.name: f for f in FEATURES}


@dataclass(frozen=True)
class LoadBound:
    """Admissible range of an external load (each component of a vector load)."""

    name: str
    unit: str
    admissible: tuple[float, float]
    exclusive_min: bool = False


#: Admissible external loads (physics solver only).
LOADS: dict[str, LoadBound] = {
    "gravity": LoadBound("gravity", "m/s^2", (-100.0, 100.0)),  # 10 g per component
    # Effective density: the rod's mass per length (disks and tendons it carries included) over its
    # cross-section, so above any metal's (osmium: 22,600); opencr-mujoco's FTDCR files use 37,708.
    "density": LoadBound("density", "kg/m^3", (0.0, 100_000.0), exclusive_min=True),
    "tip_force": LoadBound("tip_force", "N", (-100.0, 100.0)),
    "tip_moment": LoadBound("tip_moment", "N m", (-10.0, 10.0)),
}

#: The general design's optional fields (:data:`tdcr.robot.fields.OPTIONAL`; the surrogates take only the
#: defaults: angles 2 pi i / N_t, every tendon ending at the tip, nu = 0.3, tensions).
LAYOUT_FIELDS: dict[str, DesignField] = {f.name: f for f in OPTIONAL}


#: The paper's out-of-distribution bins, as fractions p of the upper bound (x = high * (1 + p)).
OOD_BINS: tuple[tuple[float, float], ...] = ((-0.05, 0.0), (0.0, 0.05), (0.05, 0.10), (0.10, 0.15), (0.15, 0.20))


def describe() -> dict:
    """The design space as JSON-ready data: per parameter its unit, Table I range and admissible
    bounds; the loads' admissible bounds and the loaded operators' trained range (``trained``:
    |gravity|, density, |tip_force|, |tip_moment|); the number of tendons and the feature order."""
    def bounds(b) -> dict:
        return {"admissible": list(b.admissible), "exclusive_min": b.exclusive_min, "unit": b.unit}

    trained = TRAINING_LOADS.ranges()
    return {"parameters": {k: bounds(p) | {"table_i": [p.low, p.high]} for k, p in TABLE_I.items()},
            "loads": {k: bounds(b) | {"trained": trained[k]} for k, b in LOADS.items()},
            "layout": {k: bounds(b) | {"exclusive_max": b.exclusive_max, "default": b.default_words}
                       for k, b in LAYOUT_FIELDS.items()},
            "n_tendons": N_TENDONS, "max_tendons": MAX_TENDONS, "feature_order": feature_names(),
            "default_points": DEFAULT_POINTS}



def feature_names(n_tendons: int = N_TENDONS) -> list[str]:
    """Names of the feature columns, e.g. ``['E', 'r', 'L', 'offset_0', ...]``."""
    return list(FeatureLayout(n_tendons).names)


def feature_bounds(n_tendons: int = N_TENDONS) -> tuple[np.ndarray, np.ndarray]:
    """Table I lower and upper bounds per feature column, each ``(3 + 3 N_t,)``."""
    groups = FeatureLayout(n_tendons).parameters
    return np.array([TABLE_I[g].low for g in groups]), np.array([TABLE_I[g].high for g in groups])


@cache
def admissible_bounds(n_tendons: int = N_TENDONS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Admissible ``(low, high, exclusive_low)`` per feature column, each ``(3 + 3 N_t,)``, read-only
    (built once per tendon count: every request's check reads them)."""
    groups = FeatureLayout(n_tendons).parameters
    return _read_only(np.array([TABLE_I[g].admissible[0] for g in groups]),
                      np.array([TABLE_I[g].admissible[1] for g in groups]),
                      np.array([TABLE_I[g].exclusive_min for g in groups]))


def _read_only(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.flags.writeable = False
    return arrays


def sample_designs(n: int, *, seed: int, n_tendons: int = N_TENDONS) -> DesignBatch:
    """``n`` designs with every parameter uniform in its Table I range (seeded)."""
    rng = np.random.default_rng(seed)
    low, high = feature_bounds(n_tendons)
    return DesignBatch.from_features(rng.uniform(low, high, size=(n, low.size)))


def sample_segmented_designs(n: int, *, seed: int, segments: int = 2, tendons_per_segment: int = 3) -> DesignBatch:
    """``n`` robots of ``segments`` equal segments with ``tendons_per_segment`` tendons each, every
    other parameter uniform in its Table I range (seeded): segment k's tendons end at (k + 1) L /
    segments, evenly spaced around the axis and turned by pi k / tendons_per_segment against the
    segment before (staggered, as multi-segment robots route them)."""
    if segments < 1 or tendons_per_segment < 1 or segments * tendons_per_segment > MAX_TENDONS:
        raise ValueError(f"segments and tendons per segment must be >= 1 with at most {MAX_TENDONS} tendons in all")
    n_t = segments * tendons_per_segment
    designs = sample_designs(n, seed=seed, n_tendons=n_t)
    k = np.repeat(np.arange(segments), tendons_per_segment)
    j = np.tile(np.arange(tendons_per_segment), segments)
    angles = 2.0 * np.pi * j / tendons_per_segment + np.pi * k / tendons_per_segment
    ends = designs.L[:, None] * ((k + 1) / segments)[None, :]
    return designs.replace(angle=np.tile(angles, (n, 1)), end=np.where(k[None, :] == segments - 1,
                                                                       designs.L[:, None], ends))


def sample_ood_designs(n: int, bin_range: tuple[float, float], *, seed: int, n_tendons: int = N_TENDONS) -> DesignBatch:
    """The paper's OOD test: every parameter set to ``high * (1 + p)``, p uniform in ``bin_range``.

    For tensions and offsets/lengths this extrapolates beyond the trained upper bound; pitches
    move past +20 rad/m.
    """
    rng = np.random.default_rng(seed)
    _, high = feature_bounds(n_tendons)
    p = rng.uniform(bin_range[0], bin_range[1], size=(n, high.size))
    return DesignBatch.from_features(high * (1.0 + p))


def sample_outside_designs(n: int, *, widen: float = 0.2, seed: int, n_tendons: int = N_TENDONS) -> DesignBatch:
    """Designs with every parameter outside Table I in a random direction: below ``low`` or above
    ``high`` by a fraction uniform in (0, ``widen``] of the range's width (above where below would
    leave the admissible bounds, e.g. a negative tension)."""
    rng = np.random.default_rng([seed, 0x0D])
    low, high = feature_bounds(n_tendons)
    admissible_low = admissible_bounds(n_tendons)[0]
    step = (high - low) * rng.uniform(0.0, widen, size=(n, low.size))
    step = np.where(step > 0, step, widen * (high - low))  # uniform in (0, widen]
    below = (rng.random((n, low.size)) < 0.5) & (low - step > admissible_low)
    return DesignBatch.from_features(np.where(below, low - step, high + step))


@dataclass(frozen=True)
class LoadSpace:
    """A space of external loads to sample (all off by default; SI units).

    Attributes:
        gravity: ``'none'``, ``'sphere'`` (|g| = ``gravity_magnitude`` in a direction uniform on the
            sphere) or a fixed vector ``'X,Y,Z'`` in m/s^2.
        gravity_magnitude: |g| for ``'sphere'``, m/s^2.
        density: ``(low, high)`` backbone density range, kg/m^3 (needed with gravity).
        tip_force: largest tip force, N: |F| uniform in [0, tip_force], direction uniform on the sphere.
        tip_moment: largest tip moment, N m, likewise.
        tip_fraction: share of the designs that carry the tip loads (the others carry none).
        unloaded_fraction: share of the designs with no load at all (no gravity, no tip load), so
            that one dataset teaches a loaded operator both cases.
    """

    gravity: str = "none"
    gravity_magnitude: float = 9.81
    density: tuple[float, float] | None = None
    tip_force: float = 0.0
    tip_moment: float = 0.0
    tip_fraction: float = 1.0
    unloaded_fraction: float = 0.0

    def __post_init__(self):
        fixed = self._fixed_gravity()
        if fixed is not None and np.abs(fixed).max() > LOADS["gravity"].admissible[1]:
            raise ValueError(f"gravity: each component must be in {list(LOADS['gravity'].admissible)} m/s^2")
        if not 0.0 <= self.gravity_magnitude <= LOADS["gravity"].admissible[1]:
            raise ValueError(f"gravity magnitude: must be in [0, {LOADS['gravity'].admissible[1]:g}] m/s^2")
        if self.density is not None:
            low, high = self.density
            if not 0.0 < low <= high <= LOADS["density"].admissible[1]:
                raise ValueError(f"density: need 0 < low <= high <= {LOADS['density'].admissible[1]:g} kg/m^3")
        if self.gravity != "none" and self.density is None:
            raise ValueError("gravity needs a density range")
        if not 0.0 <= self.tip_force <= LOADS["tip_force"].admissible[1]:
            raise ValueError(f"tip force: must be in [0, {LOADS['tip_force'].admissible[1]:g}] N")
        if not 0.0 <= self.tip_moment <= LOADS["tip_moment"].admissible[1]:
            raise ValueError(f"tip moment: must be in [0, {LOADS['tip_moment'].admissible[1]:g}] N m")
        for name in ("tip_fraction", "unloaded_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name.replace('_', ' ')}: must be in [0, 1]")

    def _fixed_gravity(self) -> np.ndarray | None:
        if self.gravity in ("none", "sphere"):
            return None
        try:
            vector = np.array([float(v) for v in self.gravity.split(",")])
        except ValueError:
            vector = np.zeros(0)
        if vector.shape != (3,) or not np.isfinite(vector).all():
            raise ValueError(f"gravity: 'none', 'sphere' or 'X,Y,Z' in m/s^2, got {self.gravity!r}")
        return vector

    @classmethod
    def from_record(cls, record: dict) -> LoadSpace:
        """The space a dataset's ``metadata.json`` records (its ``loads``: JSON lists for tuples)."""
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in record.items()})

    def is_zero(self) -> bool:
        return self.gravity == "none" and self.tip_force == 0.0 and self.tip_moment == 0.0

    def sample(self, n: int, *, seed: int) -> ExternalLoads | None:
        """``n`` loads (seeded), or ``None`` when the space holds no load."""
        if self.is_zero():
            return None
        rng = np.random.default_rng([seed, 0x10AD])

        def directions() -> np.ndarray:
            v = rng.normal(size=(n, 3))
            return v / np.linalg.norm(v, axis=1, keepdims=True)

        gravity = density = None
        if self.gravity == "sphere":
            gravity = self.gravity_magnitude * directions()
        elif self.gravity != "none":
            gravity = np.tile(self._fixed_gravity(), (n, 1))
        if gravity is not None:
            density = rng.uniform(*self.density, size=n)
        force = directions() * rng.uniform(0.0, self.tip_force, size=(n, 1))
        moment = directions() * rng.uniform(0.0, self.tip_moment, size=(n, 1))
        if self.tip_fraction < 1.0 or self.unloaded_fraction > 0.0:  # a stream of its own: the draws above keep
            shares = np.random.default_rng([seed, 0x5A4E]).uniform(size=(2, n))
            untipped = shares[0] >= self.tip_fraction
            force[untipped], moment[untipped] = 0.0, 0.0
            unloaded = shares[1] < self.unloaded_fraction
            force[unloaded], moment[unloaded] = 0.0, 0.0
            if gravity is not None:
                gravity[unloaded] = 0.0
        return ExternalLoads(gravity=gravity, density=density, tip_force=force, tip_moment=moment)

    def ranges(self) -> dict[str, list[float]]:
        """The loads this space holds, as the manifest records them: ``|gravity|`` in m/s^2, density
        in kg/m^3 (of designs in gravity), ``|tip_force|`` in N and ``|tip_moment|`` in N m, each
        ``[low, high]``."""
        fixed = self._fixed_gravity()
        g_high = 0.0 if self.gravity == "none" else (
            self.gravity_magnitude if fixed is None else float(np.linalg.norm(fixed)))
        return {"gravity": [0.0, g_high], "density": list(self.density) if self.density else [0.0, 0.0],
                "tip_force": [0.0, self.tip_force], "tip_moment": [0.0, self.tip_moment]}


#: The loads of the loaded operators' benchmark (issue 24): |g| = 9.81 m/s^2 in a uniform direction,
#: steel-like densities, and on 30 % of the designs a tip force up to 0.02 N and moment up to 0.002 N m.
BENCHMARK_LOADS = LoadSpace(gravity="sphere", gravity_magnitude=9.81, density=(6450.0, 8000.0),
                            tip_force=0.02, tip_moment=0.002, tip_fraction=0.3)
#: The loaded operators' training loads: the benchmark's, with tip loads on half the designs and a
#: fifth of the designs unloaded, so that one model answers both.
TRAINING_LOADS = LoadSpace(gravity="sphere", gravity_magnitude=9.81, density=(6450.0, 8000.0),
                           tip_force=0.02, tip_moment=0.002, tip_fraction=0.5, unloaded_fraction=0.2)


def normalize(features: np.ndarray, n_tendons: int = N_TENDONS) -> np.ndarray:
    """Map raw SI features ``(B, 3 + 3 N_t)`` affinely to [-1, 1] over the Table I ranges.

    x_norm = 2 (x - low) / (high - low) - 1.  Values outside Table I map outside [-1, 1].
    """
    low, high = feature_bounds(n_tendons)
    return 2.0 * (np.asarray(features) - low) / (high - low) - 1.0


def out_of_range(features: np.ndarray, n_tendons: int = N_TENDONS) -> list[list[str]]:
    """Per design, the names of features outside Table I, for ``(B, 3 + 3 N_t)`` features."""
    low, high = feature_bounds(n_tendons)
    names = FeatureLayout(n_tendons).names
    bad = (features < low) | (features > high)
    out: list[list[str]] = [[] for _ in range(len(features))]
    for b, j in zip(*np.nonzero(bad), strict=True):  # only the offending entries are visited
        out[b].append(names[j])
    return out


def _outside_features(features: np.ndarray) -> np.ndarray:
    """Which features ``(B, 3 + 3 N_t)`` lie outside Table I (the trained ranges), ``(B, 3 + 3 N_t)``."""
    low, high = feature_bounds(FeatureLayout.of(features).n_tendons)
    return (features < low) | (features > high)


def in_trained_ranges(features: np.ndarray, loads: np.ndarray | None = None,
                      ranges: dict[str, list[float]] | None = None) -> np.ndarray:
    """Per design ``(B,)``: no range warning (:func:`range_warnings`, and with ``loads`` ``(B, 10)``
    and ``ranges`` :func:`load_warnings`), without writing the warnings."""
    inside = ~_outside_features(features).any(axis=1)
    if loads is not None and ranges is not None:
        inside &= ~_outside_loads(loads, ranges)[1].any(axis=0)
    return inside


def range_warnings(features: np.ndarray) -> list[list[str]]:
    """Per design, one line for each parameter outside Table I (the trained ranges), for
    features ``(B, 3 + 3 N_t)``; e.g. ``tension_2 = 6.5 N is outside the trained range [0, 5]``."""
    layout = FeatureLayout.of(features)
    low, high = feature_bounds(layout.n_tendons)
    out: list[list[str]] = [[] for _ in range(len(features))]
    for b, j in zip(*np.nonzero(_outside_features(features)), strict=True):  # offenders only
        unit = TABLE_I[layout.parameters[j]].unit
        out[b].append(f"{layout.names[j]} = {features[b, j]:.6g} {unit} is outside the trained range "
                      f"[{low[j]:.6g}, {high[j]:.6g}]")
    return out


#: The load ranges a manifest records (:meth:`LoadSpace.ranges`): name -> (unit, how a design's
#: value is read from its loads matrix ``(B, 10)``).
_LOAD_MAGNITUDES = {"gravity": "m/s^2", "density": "kg/m^3", "tip_force": "N", "tip_moment": "N m"}
#: Relative slack of the load-range checks (a |g| of 9.81 computed from its components).
_LOAD_SLACK = 1e-6


def load_warnings(loads: np.ndarray, ranges: dict[str, list[float]]) -> list[list[str]]:
    """Per design, one line for each load outside the trained ``ranges`` (a manifest's
    ``load_ranges``) of the loads matrix ``(B, 10)`` (:data:`tdcr.robot.designs.LOAD_COLUMNS`): the
    magnitudes |gravity|, |tip_force| and |tip_moment|, and the density of designs in gravity;
    e.g. ``|tip_force| = 0.05 N is outside the trained range [0, 0.02]``."""
    values, outside = _outside_loads(loads, ranges)
    out: list[list[str]] = [[] for _ in range(len(values["gravity"]))]
    for (name, unit), bad in zip(_LOAD_MAGNITUDES.items(), outside, strict=True):
        low, high = ranges[name]
        label = name if name == "density" else f"|{name}|"
        for b in np.nonzero(bad)[0]:
            out[b].append(f"{label} = {values[name][b]:.6g} {unit} is outside the trained range "
                          f"[{low:.6g}, {high:.6g}]")
    return out


def _outside_loads(loads: np.ndarray, ranges: dict[str, list[float]]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The loads' magnitudes (name -> ``(B,)``, density NaN outside gravity) and which lie outside
    the trained ``ranges``, ``(4, B)`` in the order of :data:`_LOAD_MAGNITUDES`."""
    loads = np.asarray(loads, dtype=np.float64)
    values = {name: np.linalg.norm(loads[:, LOAD_COLUMNS[name]], axis=1) for name in ("gravity", "tip_force",
                                                                                     "tip_moment")}
    values["density"] = np.where(values["gravity"] > 0, loads[:, LOAD_COLUMNS["density"]][:, 0], np.nan)
    outside = np.zeros((len(_LOAD_MAGNITUDES), len(loads)), dtype=bool)
    for k, name in enumerate(_LOAD_MAGNITUDES):
        low, high = ranges[name]
        slack = _LOAD_SLACK * max(abs(high), 1.0)
        with np.errstate(invalid="ignore"):
            outside[k] = (values[name] < low - slack) | (values[name] > high + slack)
    return values, outside
