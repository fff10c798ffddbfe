"""The design space of Table I: names, units, ranges, sampling, OOD bins, normalisation.

Feature order (shared by the dataset, the networks and the ONNX models), for N_t tendons:
``[E, r, L, offset_0..offset_{N_t-1}, pitch_0.., tension_0..]``, shape ``(B, 3 + 3 N_t)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training.designs import DesignBatch


@dataclass(frozen=True)
class Parameter:
    """One design parameter: name, SI unit and Table I range [low, high]."""

    name: str
    unit: str
    low: float
    high: float


#: Table I of the paper (SI units).
TABLE_I: dict[str, Parameter] = {
    "E": Parameter("E", "Pa", 15.5e9, 45.5e9),
    "r": Parameter("r", "m", 0.0005, 0.0015),
    "L": Parameter("L", "m", 0.1, 0.35),
    "offset": Parameter("offset", "m", 0.005, 0.01),
    "pitch": Parameter("pitch", "rad/m", -20.0, 20.0),
    "tension": Parameter("tension", "N", 0.0, 5.0),
}

#: The paper's out-of-distribution bins, as fractions p of the upper bound (x = high * (1 + p)).
OOD_BINS: tuple[tuple[float, float], ...] = ((-0.05, 0.0), (0.0, 0.05), (0.05, 0.10), (0.10, 0.15), (0.15, 0.20))

N_TENDONS = 4


def feature_names(n_tendons: int = N_TENDONS) -> list[str]:
    """Names of the feature columns, e.g. ``['E', 'r', 'L', 'offset_0', ...]``."""
    names = ["E", "r", "L"]
    for group in ("offset", "pitch", "tension"):
        names += [f"{group}_{i}" for i in range(n_tendons)]
    return names


def feature_bounds(n_tendons: int = N_TENDONS) -> tuple[np.ndarray, np.ndarray]:
    """Table I lower and upper bounds per feature column, each ``(3 + 3 N_t,)``."""
    groups = ["E", "r", "L"] + [g for g in ("offset", "pitch", "tension") for _ in range(n_tendons)]
    low = np.array([TABLE_I[g].low for g in groups])
    high = np.array([TABLE_I[g].high for g in groups])
    return low, high


def sample_designs(n: int, *, seed: int, n_tendons: int = N_TENDONS) -> DesignBatch:
    """``n`` designs with every parameter uniform in its Table I range (seeded)."""
    rng = np.random.default_rng(seed)
    low, high = feature_bounds(n_tendons)
    return DesignBatch.from_features(rng.uniform(low, high, size=(n, low.size)))


def sample_ood_designs(n: int, bin_range: tuple[float, float], *, seed: int, n_tendons: int = N_TENDONS) -> DesignBatch:
    """The paper's OOD test: every parameter set to ``high * (1 + p)``, p uniform in ``bin_range``.

    For tensions and offsets/lengths this extrapolates beyond the trained upper bound; pitches
    move past +20 rad/m.
    """
    rng = np.random.default_rng(seed)
    _, high = feature_bounds(n_tendons)
    p = rng.uniform(bin_range[0], bin_range[1], size=(n, high.size))
    return DesignBatch.from_features(high * (1.0 + p))


def normalize(features: np.ndarray, n_tendons: int = N_TENDONS) -> np.ndarray:
    """Map raw SI features ``(B, 3 + 3 N_t)`` affinely to [-1, 1] over the Table I ranges.

    x_norm = 2 (x - low) / (high - low) - 1.  Values outside Table I map outside [-1, 1].
    """
    low, high = feature_bounds(n_tendons)
    return 2.0 * (np.asarray(features) - low) / (high - low) - 1.0


def out_of_range(features: np.ndarray, n_tendons: int = N_TENDONS) -> list[list[str]]:
    """Per design, the names of features outside Table I, for ``(B, 3 + 3 N_t)`` features."""
    low, high = feature_bounds(n_tendons)
    names = feature_names(n_tendons)
    bad = (features < low) | (features > high)
    out: list[list[str]] = [[] for _ in range(len(features))]
    for b, j in zip(*np.nonzero(bad), strict=True):  # only the offending entries are visited
        out[b].append(names[j])
    return out


def validate_design(design: DesignBatch) -> list[str]:
    """Human-readable problems with every design of a batch (empty when all are valid).

    Checks: all values finite; E, r, L and offsets positive; tensions non-negative.
    Each message names the design index and the field.
    """
    feats = design.features()
    n_t = design.n_tendons
    names = feature_names(n_t)
    positive = np.zeros(feats.shape[1], dtype=bool)
    positive[:3 + n_t] = True  # E, r, L, offsets
    tension = np.zeros(feats.shape[1], dtype=bool)
    tension[3 + 2 * n_t:] = True
    finite = np.isfinite(feats)
    bad = ~finite | (positive & (feats <= 0)) | (tension & (feats < 0))
    problems = []
    for b, j in zip(*np.nonzero(bad), strict=True):  # row-major: by design, then field
        value = feats[b, j]
        if not finite[b, j]:
            problems.append(f"design {b}: {names[j]} must be finite, got {value}")
        elif positive[j]:
            problems.append(f"design {b}: {names[j]} must be positive, got {value}")
        else:
            problems.append(f"design {b}: {names[j]} must be non-negative, got {value}")
    return problems
