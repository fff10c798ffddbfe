"""Held-out accuracy of the exported (ONNX) models, next to physics baselines without a network:
the undeformed robot, the linearised reference robot the tuned operators correct, and on a dataset
with loads the loaded reference robot of the loaded operators and the exact solver with the loads
ignored.  On such a dataset an operator that takes no loads answers as if there were none (the
error of ignoring them), a loaded operator with them.

Error per design: relative l2 of tendon positions over all points and tendons (paper eq. l2Error),
||y_hat - y|| / ||y||, and the tip error in mm (mean over the tendons of |tip_hat - tip|).
Summaries: mean, median, p95, p99 and max, and the tip error's median, p90 and max.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, solve
from tdcr.physics.geometry import tendon_offsets
from tdcr.robot.designs import L_COLUMN, DesignBatch, ExternalLoads
from tdcr.surrogates.runtime import Surrogate, load_manifest, takes_loads
from training import dataset


def summary(errors: np.ndarray, tip_mm: np.ndarray | None = None) -> dict:
    """Relative l2 ``errors`` ``(B,)`` and optional tip errors ``(B,)`` mm, summarised."""
    out = {"mean": float(errors.mean()), "median": float(np.median(errors)),
           "p95": float(np.percentile(errors, 95)), "p99": float(np.percentile(errors, 99)),
           "max": float(errors.max()), "n": int(errors.size)}
    if tip_mm is not None:
        out |= {"tip_mm_median": float(np.median(tip_mm)), "tip_mm_p90": float(np.percentile(tip_mm, 90)),
                "tip_mm_max": float(tip_mm.max())}
    return out


def tip_error_mm(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Tip error per design, mm: the mean over the tendons of the distance between predicted and
    true tendon ends, for tendons ``(B, n, N_t, 3)`` m (the last point is the tip)."""
    return 1e3 * np.linalg.norm(pred[:, -1] - truth[:, -1], axis=-1).mean(axis=-1)


def scored(pred: np.ndarray, truth: np.ndarray) -> dict:
    """:func:`summary` of tendons ``pred`` against ``truth``, ``(B, n, N_t, 3)`` m each."""
    return summary(relative_l2(pred, truth), tip_error_mm(pred, truth))


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
#: The exact solver at a 10x finer step (both the tendon-only Magnus and the loaded RK4 steps).
FINER_SOLVER = SolverOptions(max_step=SolverOptions().max_step / 10, max_step_loads=SolverOptions().max_step_loads / 10)
#: Labels of the rows that only a dataset with loads has.
LOADED_REFERENCE, LOADS_IGNORED = "loaded reference", "loads ignored"


def loaded_reference_tendons(features: np.ndarray, fractions: np.ndarray, loads: np.ndarray) -> np.ndarray:
    """The loaded operators' reference robot (tendon strains plus the small-deflection response to
    the loads, :func:`training.operators.kinematics.loaded_reference`; no network), float64, m,
    ``(B, n, 4, 3)``, on the uniform grid of ``len(fractions)`` points."""
    import torch

    from training.operators import kinematics

    grid = torch.linspace(0.0, 1.0, len(fractions), dtype=torch.float64)
    base_angle = 2.0 * np.pi * torch.arange(design_space.N_TENDONS, dtype=torch.float64) / design_space.N_TENDONS
    ref = kinematics.loaded_reference(torch.as_tensor(features, dtype=torch.float64),
                                      torch.as_tensor(loads, dtype=torch.float64), grid, base_angle)
    return kinematics.batch_first(ref.tendons()).numpy()


def row_label(name: str, entry: dict, loaded_data: bool) -> str:
    """A model's row: its name, with ``(loads ignored)`` for an operator that takes none on data with loads."""
    return f"{name} ({LOADS_IGNORED})" if loaded_data and not takes_loads(entry) else name


def metrics_key(entry: dict, loaded_data: bool) -> str:
    """Where a model's metrics of a dataset go in its manifest entry: ``test_relative_l2`` on data
    like its training data, ``load_free_relative_l2`` for a loaded operator on data without loads,
    ``loads_ignored_relative_l2`` for another operator on data with loads."""
    if takes_loads(entry) == loaded_data:
        return "test_relative_l2"
    return "load_free_relative_l2" if takes_loads(entry) else "loads_ignored_relative_l2"

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
             keep: np.ndarray | None = None, exact_designs: int = 200) -> dict:
    """Metrics of each named model on the test split (the rows ``keep``, default all), plus the
    baselines; returns row label (:func:`row_label`) -> summary (:func:`summary`).

    On a dataset with loads, also: the loaded reference robot, the exact solver with the loads
    ignored, and the exact loaded solver at the dataset's settings against a 10x finer step on the
    first ``exact_designs`` test designs (the labels' own error).
    """
    test = dataset.load(data, "test")
    feats, truth, loads = test["features"], test["tendons"], dataset.load_matrix(test)
    if keep is not None:
        feats, truth, loads = feats[keep], truth[keep], loads[keep]
    return compare(models_dir, names, feats, truth, loads, batch=batch, exact_designs=exact_designs)


def compare(models_dir: str | Path, names: list[str], feats: np.ndarray, truth: np.ndarray, loads: np.ndarray, *,
            batch: int = 5000, exact_designs: int = 200) -> dict:
    """:func:`evaluate` on arrays: designs ``(B, 15)``, true tendons ``(B, n, 4, 3)`` m on the
    uniform grid of n points, and loads ``(B, 10)`` (zeros: none)."""
    loaded_data = bool(np.any(loads))
    fractions = np.linspace(0.0, 1.0, truth.shape[1])

    def batched(fn) -> np.ndarray:
        return np.concatenate([fn(slice(i, i + batch)) for i in range(0, len(feats), batch)])

    suffix = f" ({LOADS_IGNORED})" if loaded_data else ""
    results = {label + suffix: scored(batched(lambda rows, fn=fn: fn(feats[rows], fractions)), truth)
               for label, fn in BASELINES.items()}
    if loaded_data:
        results[LOADED_REFERENCE] = scored(batched(lambda rows: loaded_reference_tendons(feats[rows], fractions,
                                                                                         loads[rows])), truth)
        results[f"exact solver ({LOADS_IGNORED})"] = scored(batched(
            lambda rows: solve(DesignBatch.from_features(feats[rows]), fractions, workers=0).tendons), truth)
        k = min(exact_designs, len(feats))
        if k:
            fine = FINER_SOLVER
            exact = ExternalLoads.from_matrix(loads[:k])
            results["exact loaded solver (against a 10x finer step)"] = scored(
                truth[:k], solve(DesignBatch.from_features(feats[:k]), fractions, loads=exact, options=fine,
                                 workers=0).tendons)
    manifest = load_manifest(models_dir)
    for name in names:
        model = Surrogate.load(models_dir, name, manifest=manifest)
        given = loads if model.takes_loads else None
        pred = batched(lambda rows, model=model, given=given: model.predict(
            feats[rows], fractions, loads=None if given is None else given[rows], pose=False)["tendons"])
        results[row_label(name, model.entry, loaded_data)] = scored(pred, truth)
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
    lines = ["| model | mean rel. l2 | median | p95 | p99 | max | tip mm: median | p90 | max | test designs |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        tip = " | ".join(f"{r[k]:.3g}" if k in r else "-" for k in ("tip_mm_median", "tip_mm_p90", "tip_mm_max"))
        lines.append(f"| {name} | {r['mean']:.3g} | {r['median']:.3g} | {r['p95']:.3g} | {r['p99']:.3g} "
                     f"| {r['max']:.3g} | {tip} | {r['n']} |")
    return "\n".join(lines)
