"""Held-out accuracy of the exported (ONNX) models, next to two physics baselines without a network:
the undeformed robot, and the linearised reference robot the tuned operators correct.

Error per design: relative l2 of tendon positions over all points and tendons (paper eq. l2Error),
||y_hat - y|| / ||y||.  Summaries: mean, median and 95th percentile over the test designs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.designs import L_COLUMN, DesignBatch
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, solve
from tdcr.physics.geometry import tendon_offsets
from tdcr.runtime import Surrogate
from training import dataset


def summary(errors: np.ndarray) -> dict:
    return {"mean": float(errors.mean()), "median": float(np.median(errors)),
            "p95": float(np.percentile(errors, 95)), "n": int(errors.size)}


def undeformed_tendons(features: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """The straight robot with the design's routing, m, ``(B, n, 4, 3)``."""
    rho = tendon_offsets(features, fractions)
    rho[..., 2] += (features[:, L_COLUMN, None] * fractions[None, :])[..., None]
    return rho


def linearized_tendons(features: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """The operators' reference robot (first-order strains, no network), m, ``(B, n, 4, 3)``."""
    designs = DesignBatch.from_features(features)
    return solve(designs, fractions, options=SolverOptions(linearized=True)).tendons


BASELINES = {"undeformed baseline": undeformed_tendons, "linearized reference": linearized_tendons}


def held_out(features: np.ndarray, entries: dict[str, dict]) -> tuple[np.ndarray, dict[str, int], list[str]]:
    """Which test designs ``(B, 15)`` no model of ``entries`` (manifest entries) was trained on:
    ``(mask (B,), designs left out per model, models whose training set is not recorded)``.  A
    model's training designs are regenerated from its manifest's dataset record (seed, size,
    split) and compared exactly."""
    keep = np.ones(len(features), dtype=bool)
    left_out, unknown = {}, []
    rows = [f.tobytes() for f in np.ascontiguousarray(features, dtype=np.float64)]
    for name, entry in entries.items():
        record = entry.get("dataset")
        if not record or not {"n", "seed", "n_test"} <= set(record):
            unknown.append(name)
            continue
        trained = {f.tobytes() for f in np.ascontiguousarray(dataset.training_features(record), dtype=np.float64)}
        seen = np.array([row in trained for row in rows], dtype=bool)
        left_out[name] = int(seen.sum())
        keep &= ~seen
    return keep, left_out, unknown


def evaluate(models_dir: str | Path, data: str | Path, names: list[str], *, batch: int = 5000,
             keep: np.ndarray | None = None) -> dict:
    """Metrics of each named model on the test split (the rows ``keep``, default all), plus the
    baselines; returns name -> summary."""
    test = dataset.load(data, "test")
    feats, truth = test["features"], test["tendons"]
    if keep is not None:
        feats, truth = feats[keep], truth[keep]
    fractions = np.linspace(0.0, 1.0, truth.shape[1])
    results = {label: summary(relative_l2(np.concatenate([fn(feats[i:i + batch], fractions)
                                                         for i in range(0, len(feats), batch)]), truth))
               for label, fn in BASELINES.items()}
    for name in names:
        model = Surrogate.load(models_dir, name)
        pred = np.concatenate([model.predict(feats[i:i + batch], fractions)["tendons"]
                               for i in range(0, len(feats), batch)])
        results[name] = summary(relative_l2(pred, truth))
    return results


def evaluate_ood(models_dir: str | Path, names: list[str], *, n: int = 1000, seed: int = 0) -> dict:
    """The paper's out-of-distribution test: for each bin, ``n`` designs with every parameter at
    high * (1 + p), p uniform in the bin, solved exactly; mean relative l2 per model and bin."""
    fractions = np.linspace(0.0, 1.0, design_space.DEFAULT_POINTS)
    models = {name: Surrogate.load(models_dir, name) for name in names}
    table: dict[str, dict[str, float]] = {}
    for k, bin_range in enumerate(design_space.OOD_BINS):
        designs = design_space.sample_ood_designs(n, bin_range, seed=seed + k)
        sol = solve(designs, fractions)
        ok = sol.converged
        feats, truth = designs.features()[ok], sol.tendons[ok]
        label = f"{100 * bin_range[0]:+.0f}..{100 * bin_range[1]:+.0f} %"
        row = {label: float(relative_l2(fn(feats, fractions), truth).mean()) for label, fn in BASELINES.items()}
        for name, model in models.items():
            row[name] = float(relative_l2(model.predict(feats, fractions)["tendons"], truth).mean())
        table[label] = row
    return table


def format_ood(table: dict) -> str:
    names = list(next(iter(table.values())))
    lines = ["| bin (p of upper bound) | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for label, row in table.items():
        lines.append(f"| {label} | " + " | ".join(f"{row[n]:.3g}" for n in names) + " |")
    return "\n".join(lines)


def format_table(results: dict) -> str:
    lines = ["| model | mean rel. l2 | median | p95 | test designs |", "|---|---:|---:|---:|---:|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['mean']:.3g} | {r['median']:.3g} | {r['p95']:.3g} | {r['n']} |")
    return "\n".join(lines)
