"""Split-conformal calibration of the exported operators' error bounds (:mod:`tdcr.surrogates.bounds`).

    tdcr calibrate --models-dir models [--designs 20000] [--seed 25]

For each operator: ``designs`` fresh Table I designs (seed ``seed``; the training data used seeds 0
and 24, the benchmarks 26 and up), in the loaded operators' trained load space
(:data:`tdcr.robot.design_space.TRAINING_LOADS`) for a loaded operator; the exact solver's tendon paths
on the calibration grid as the truth; the operator's relative l2 error, its score and its bending
angle bin; per bin, ``crepes``' normalised conformal regressor (residual = error, sigma = score +
floor) gives the ``level`` quantile.  The record goes into the manifest entry
(:meth:`tdcr.surrogates.bounds.Calibration.sealed`).

The score of each operator is chosen by measurement (``benchmarks/error_bound_probe.py``, and
docs/results.md, "Error bounds"): :data:`SCORES`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.surrogates.bounds import (
    CALIBRATION_DESIGNS,
    CALIBRATION_FORMAT,
    CALIBRATION_POINTS,
    CALIBRATION_SEED,
    Calibration,
    bending_angle,
    calibration_grid,
    disagreement,
)
from tdcr.surrogates.runtime import Surrogate, takes_loads

#: Confidence of the bounds.
LEVEL = 0.99
#: The chance that a calibration set leaves its bounds' coverage below LEVEL (training-conditional,
#: "PAC" split conformal: Vovk 2012): each bin's quantile rank is raised until the coverage of that
#: order statistic, Beta(k, n + 1 - k), is at least LEVEL with probability 1 - DELTA.
DELTA = 0.1
#: Mondrian bins: quantiles of the calibration set's bending angle.
N_BINS = 10
#: Added to every score: a bound is never zero.
SCORE_FLOOR = 1e-6


@dataclass(frozen=True)
class Score:
    """How an operator's difficulty score is computed: ``kind`` ``"disagreement"`` with the
    operator ``companion``, or ``"bins"`` (no score: the bin's quantile)."""

    kind: str
    companion: str | None = None


#: The choice per shipped operator: the bending-angle bins alone, for every operator (issue #34).  The
#: disagreement with the loaded DeepONet bounds the tendon-only operators more tightly (log-log
#: correlation 1.000; fallback at tolerance 0.01 3.6-4.7 % against 9.7-20 %, benchmarks/error_bound_probe.py),
#: but it runs a second graph that costs 4-8x a DeepONet's own (one design: 4.5 ms against a 0.6 ms
#: exact solve), so the bound cost more than the fallbacks it saves; the bins cost a lookup.
SCORES: dict[str, Score] = {name: Score("bins") for name in (
    "deeponet", "deeponet_pose", "fno", "fno_pose", "deeponet_pose_loaded", "fno_pose_loaded")}


@dataclass(frozen=True)
class Measured:
    """Held-out designs and their truth: ``features`` ``(B, 15)``, ``loads`` ``(B, 10)`` (zeros:
    none), ``truth`` tendon paths ``(B, 42, 4, 3)`` m (converged designs only), and each operator's
    tendon paths on the grid, ``paths[name]`` ``(B, 42, 4, 3)``."""

    features: np.ndarray
    loads: np.ndarray
    truth: np.ndarray
    paths: dict[str, np.ndarray]

    def error(self, name: str) -> np.ndarray:
        return relative_l2(self.paths[name], self.truth)

    def score(self, name: str, score: Score) -> np.ndarray | None:
        if score.kind == "bins":
            return None
        return disagreement(self.paths[name], self.paths[score.companion])


def measure(models_dir: str | Path, names: list[str], designs: DesignBatch, loads: ExternalLoads | None) -> Measured:
    """The exact solver's and the operators ``names``' tendon paths of ``designs`` under ``loads``
    on the calibration grid (designs the solver does not converge on are left out)."""
    grid = calibration_grid()
    truth = solve(designs, grid, loads=loads, workers=0)
    ok = np.nonzero(truth.converged)[0]
    features = designs.features()[ok]
    matrix = np.zeros((len(ok), 10)) if loads is None else np.nan_to_num(loads.matrix(len(designs))[ok])
    paths = {}
    for name in names:
        op = Surrogate.load(models_dir, name, verify=False)
        paths[name] = op.predict(features, grid, loads=matrix if op.takes_loads else None, pose=False,
                                 check=False)["tendons"]
    return Measured(features=features, loads=matrix, truth=truth.tendons[ok], paths=paths)


def conformal_rank(n: int, level: float, delta: float | None) -> int:
    """The rank k (1-based, of n ascending calibration ratios) of a bin's quantile: the split
    conformal ceil((n + 1) level) (``delta`` None: coverage >= level on average over calibration
    sets), or the least k whose coverage Beta(k, n + 1 - k) is >= level with probability
    1 - ``delta``; n + 1 (no finite bound) when the bin is too small."""
    from scipy.stats import beta

    k = int(np.ceil((n + 1) * level))
    if delta is not None:
        while k <= n and beta.sf(level, k, n + 1 - k) < 1.0 - delta:
            k += 1
    return k


class TooFewDesigns(ValueError):
    """A bin holds too few calibration designs for a finite bound at the level and delta."""


def least_bin(level: float = LEVEL, delta: float | None = DELTA) -> int:
    """The fewest calibration ratios n of a bin whose :func:`conformal_rank` is finite (at most n)."""
    n = 1
    while conformal_rank(n, level, delta) > n:
        n += 1
    return n


def fit(error: np.ndarray, score: np.ndarray | None, theta: np.ndarray, *, level: float = LEVEL,
        delta: float | None = DELTA, n_bins: int = N_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Mondrian split-conformal quantiles: bin ``edges`` ``(n_bins + 1,)`` of the bending angles
    ``theta`` ``(B,)`` (their quantiles, outermost min and max) and per bin the quantile
    ``(n_bins,)`` of error / (score + floor) at the rank of :func:`conformal_rank`, by
    ``crepes.ConformalRegressor`` (residuals >= 0, so its interval's upper end is the bound; its
    confidence (k - 1/2) / (n + 1) selects the k-th smallest ratio).  Raises :class:`TooFewDesigns`
    when a bin holds fewer than :func:`least_bin` designs (its bound would be infinite)."""
    from crepes import ConformalRegressor

    edges = np.quantile(theta, np.linspace(0.0, 1.0, n_bins + 1))
    bins = np.clip(np.searchsorted(edges, theta, side="right") - 1, 0, n_bins - 1)
    counts, least = np.bincount(bins, minlength=n_bins), least_bin(level, delta)
    if counts.min() < least:
        raise TooFewDesigns(f"a bending-angle bin holds {counts.min()} converged designs of {len(theta)}; "
                            f"a {level:g} bound (delta {delta}) needs at least {least} in each of the {n_bins} bins")
    sigmas = np.ones_like(error) if score is None else score + SCORE_FLOOR
    regressor = ConformalRegressor().fit(residuals=error, sigmas=sigmas, bins=bins)
    upper = np.empty(n_bins)
    for k in range(n_bins):
        n = int((bins == k).sum())
        confidence = min((conformal_rank(n, level, delta) - 0.5) / (n + 1), 1.0)
        upper[k] = regressor.predict_int(np.zeros(1), sigmas=np.ones(1), bins=np.array([k]),
                                         confidence=confidence)[0, 1]
    return edges, upper


def calibrate(models_dir: str | Path, manifest: dict, names: list[str], *, designs: int = CALIBRATION_DESIGNS,
              seed: int = CALIBRATION_SEED,
              scores: dict[str, Score] | None = None) -> dict[str, dict]:
    """The calibration record (:class:`tdcr.surrogates.bounds.Calibration`, sealed) of each operator of
    ``names``; the load-free operators share one calibration set, the loaded ones another."""
    scores = SCORES if scores is None else scores
    records = {}
    for loaded in (False, True):
        group = [n for n in names if takes_loads(manifest["models"][n]) == loaded]
        if not group:
            continue
        companions = sorted({s.companion for n in group if (s := scores[n]).companion})
        space = design_space.TRAINING_LOADS if loaded else None
        sample = design_space.sample_designs(designs, seed=seed)
        loads = None if space is None else space.sample(designs, seed=seed)
        measured = measure(models_dir, sorted(set(group) | set(companions)), sample, loads)
        theta = bending_angle(measured.features)
        for name in group:
            score = scores[name]
            edges, quantiles = fit(measured.error(name), measured.score(name, score), theta)
            companion = score.companion
            records[name] = Calibration.sealed({
                "format": CALIBRATION_FORMAT, "level": LEVEL, "delta": DELTA, "score": score.kind,
                "companion": companion,
                "companion_sha256": None if companion is None else manifest["models"][companion]["sha256"],
                "floor": SCORE_FLOOR, "bins": "bending_angle", "edges": edges.tolist(), "quantiles": quantiles.tolist(),
                "points": CALIBRATION_POINTS,
                "calibration_set": {"designs": int(designs), "converged": int(len(theta)), "seed": int(seed),
                                    "design_space": "table_i",
                                    "loads": None if space is None else asdict(space)}})
    return records
