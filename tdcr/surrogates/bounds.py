"""Calibrated error bounds of the surrogates, and the tolerance that sends doubtful designs to the
exact solver.

A calibrated operator's manifest entry carries a ``calibration`` (:class:`Calibration`): a split
conformal, Mondrian (per-bin) upper bound on the relative l2 error of a design's tendon positions
``(n, 4, 3)`` on :data:`CALIBRATION_POINTS` equispaced arclengths, at confidence ``level`` (0.99):

    bound(x) = q_k(x) * (score(x) + floor)

* ``score``: ``"disagreement"``: the relative l2 distance between this operator's tendon paths and
  a ``companion`` operator's (both on the grid); or ``"bins"``: 1 (the bound is the bin's quantile);
* bins ``k``: intervals of the linearised bending angle :func:`bending_angle` between the
  calibration set's deciles (``edges`` ``(K + 1,)``, outermost: its min and max);
* ``q_k``: in bin k, the k-th smallest error / (score + floor) ratio of the n_k calibration
  designs (exact solutions held out from training and testing), by ``crepes``
  (training/operators/calibrate.py), at the least rank k whose coverage Beta(k, n_k + 1 - k) is at
  least ``level`` with probability 1 - ``delta`` (training-conditional split conformal; plain
  split conformal takes k = ceil((n_k + 1) level), ``level`` on average over calibration sets).

A design outside the calibrated region (a range warning of the design or its loads, or a bending
angle outside ``edges``) gets no finite bound (``inf``).  The calibration record is covered by its
own ``sha256`` (:meth:`Calibration.from_record` checks it) and names the companion's ``sha256``.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tdcr.metrics import relative_l2
from tdcr.robot.design_space import LAYOUT, in_trained_ranges

#: Calibration record format this runtime reads.
CALIBRATION_FORMAT = 1
#: Arclength fractions of the calibrated error, equispaced on [0, 1] (the paper's grid).
CALIBRATION_POINTS = 42
#: Calibration designs per group (load-free, loaded) and their seed (training used seeds 0 and 24).
CALIBRATION_DESIGNS, CALIBRATION_SEED = 40_000, 25
#: The least tolerance a request may ask for: what the exact solver itself guarantees (relative l2).
EXACT_TOLERANCE = 1e-6
#: Where each design's answer came from (``source``; OIP output INT32 codes in this order).
SOURCES = ("surrogate", "exact")
SURROGATE, EXACT = 0, 1


def calibration_grid() -> np.ndarray:
    """The arclength fractions of the calibrated error, ``(CALIBRATION_POINTS,)``."""
    return np.linspace(0.0, 1.0, CALIBRATION_POINTS)


def bending_angle(features: np.ndarray) -> np.ndarray:
    """Linearised bending angle theta = max_i tau_i |rho_i| L / (E I), rad, ``(B,)``, I = pi r^4 / 4:
    the arc one tendon alone would bend a straight rod into (Rucker & Webster 2011, small strains);
    features ``(B, 15)``."""
    e, r, length = features[:, 0], features[:, 1], features[:, 2]
    offsets, tensions = features[:, LAYOUT.group("offset")], features[:, LAYOUT.group("tension")]
    return (tensions * offsets).max(axis=1) * length / (e * math.pi * r**4 / 4.0)


class CalibrationError(ValueError):
    """A calibration record of another format, or whose sha256 does not match its content."""


def _digest(record: dict) -> str:
    """sha256 of a calibration record without its ``sha256`` (canonical JSON)."""
    body = {k: v for k, v in record.items() if k != "sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(frozen=True)
class Calibration:
    """A model's calibrated error bound (see the module docstring); ``record``: the manifest's dict
    (``format``, ``level``, ``delta``, ``score``, ``companion``, ``companion_sha256``, ``floor``, ``edges``,
    ``quantiles``, ``points``, ``calibration_set`` {``designs``, ``seed``, ``loads``}, ``sha256``).
    ``load_ranges``: the model's trained loads (None: it takes none)."""

    record: dict
    load_ranges: dict | None = None

    @classmethod
    def from_record(cls, record: dict, *, load_ranges: dict | None = None) -> Calibration:
        """A manifest ``calibration``, checked for its format and its sha256."""
        if record.get("format") != CALIBRATION_FORMAT:
            raise CalibrationError(f"calibration format {record.get('format')!r} is not the supported "
                                   f"{CALIBRATION_FORMAT}; recalibrate the model")
        if record.get("sha256") != _digest(record):
            raise CalibrationError("calibration: sha256 does not match its content")
        return cls(record, load_ranges)

    @staticmethod
    def sealed(record: dict) -> dict:
        """``record`` with its ``sha256`` (what the manifest stores)."""
        body = {k: v for k, v in record.items() if k != "sha256"}
        return body | {"sha256": _digest(body)}

    @property
    def level(self) -> float:
        return float(self.record["level"])

    @property
    def companion(self) -> str | None:
        """The operator whose disagreement is the score (None: score ``"bins"``)."""
        return self.record.get("companion") if self.record["score"] == "disagreement" else None

    @property
    def edges(self) -> np.ndarray:
        return np.asarray(self.record["edges"], dtype=np.float64)

    @property
    def quantiles(self) -> np.ndarray:
        return np.asarray(self.record["quantiles"], dtype=np.float64)

    def bins(self, features: np.ndarray) -> np.ndarray:
        """The bin of each design ``(B,)`` (-1: bending angle outside the calibrated edges)."""
        theta, edges = bending_angle(features), self.edges
        k = np.clip(np.searchsorted(edges, theta, side="right") - 1, 0, len(edges) - 2)
        return np.where((theta >= edges[0]) & (theta <= edges[-1]), k, -1)

    def in_region(self, features: np.ndarray, loads: np.ndarray | None = None, *,
                  bins: np.ndarray | None = None) -> np.ndarray:
        """Whether each design ``(B,)`` lies in the calibrated region: its parameters and loads
        ``(B, 10)`` in the trained ranges, its bending angle inside the calibrated edges (``bins``:
        :meth:`bins` if already computed)."""
        inside = in_trained_ranges(features, loads, self.load_ranges)
        return inside & ((self.bins(features) if bins is None else bins) >= 0)

    def bound(self, features: np.ndarray, score: np.ndarray | None, loads: np.ndarray | None = None) -> np.ndarray:
        """The error bound of each design ``(B,)`` (relative l2, ``inf`` outside the calibrated
        region); ``score`` ``(B,)``: the disagreement with the companion (None for ``"bins"``)."""
        k = self.bins(features)
        scale = np.ones(len(features)) if score is None else np.asarray(score, dtype=np.float64)
        with np.errstate(invalid="ignore", over="ignore"):
            bound = self.quantiles[np.maximum(k, 0)] * (scale + float(self.record["floor"]))
        return np.where(self.in_region(features, loads, bins=k) & np.isfinite(bound), bound, np.inf)


def disagreement(tendons: np.ndarray, companion_tendons: np.ndarray) -> np.ndarray:
    """The score of ``"disagreement"``: relative l2 distance ``(B,)`` between two operators'
    tendon positions ``(B, n, 4, 3)`` (the companion's as the reference): :func:`relative_l2`,
    differences in the graphs' float32 and sums in float64 (8x faster than converting first)."""
    mine, theirs = (np.asarray(a).reshape(len(a), -1) for a in (tendons, companion_tendons))
    if mine.dtype != theirs.dtype:
        return relative_l2(tendons, companion_tendons)
    difference = mine - theirs
    return np.sqrt(np.einsum("bi,bi->b", difference, difference, dtype=np.float64)
                   / np.einsum("bi,bi->b", theirs, theirs, dtype=np.float64))


@dataclass(frozen=True)
class Guarded:
    """What :func:`guard` adds to a surrogate answer: per design the ``error_bound`` ``(B,)`` and the
    ``source`` ``(B,)`` (:data:`SURROGATE` or :data:`EXACT`), and the ``exact`` rows ``(m,)``."""

    error_bound: np.ndarray
    source: np.ndarray
    exact: np.ndarray


def fallback_rows(error_bound: np.ndarray, tolerance: float | None) -> np.ndarray:
    """The designs ``(m,)`` the exact solver answers: bound above ``tolerance`` or not finite (none
    without a tolerance)."""
    if tolerance is None:
        return np.zeros(0, dtype=np.int64)
    return np.nonzero(~(error_bound <= tolerance))[0]


def guard(arrays: dict[str, np.ndarray], error_bound: np.ndarray, *, tolerance: float | None,
          exact: Callable[[np.ndarray], dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], Guarded]:
    """Keep ``tolerance``: the rows of ``arrays`` (each ``(B, ...)``) whose ``error_bound`` exceeds
    it, or is not finite, replaced by ``exact(rows)`` (the exact solver's arrays of those rows, the
    same keys, and ``converged`` ``(m,)``); float64 where any row is exact.  The bound of an exact
    row is :data:`EXACT_TOLERANCE` where the solver converged, ``inf`` where it did not."""
    rows = fallback_rows(error_bound, tolerance)
    source = np.full(len(error_bound), SURROGATE, dtype=np.int32)
    if rows.size:
        solved = exact(rows)
        arrays = {k: v.astype(np.float64) for k, v in arrays.items()}
        for k, v in arrays.items():
            v[rows] = solved[k]
        source[rows] = EXACT
        error_bound = np.asarray(error_bound, dtype=np.float64).copy()
        error_bound[rows] = np.where(solved["converged"], EXACT_TOLERANCE, np.inf)
    return arrays, Guarded(error_bound=error_bound, source=source, exact=rows)
