"""The loaded operators against the exact loaded solver, measured in one run on one machine.

    python benchmarks/loaded_operators.py [--designs 1000] [--free 1000]

Held-out designs: ``--designs`` Table I designs (seed 4242; the training data used seed 24) in the
load space of :data:`tdcr.robot.design_space.BENCHMARK_LOADS`: |g| = 9.81 m/s^2 in a uniform direction,
density 6,450-8,000 kg/m^3, and on 30 % of them a tip force up to 0.02 N and a tip moment up to
0.002 N m.  Truth: the exact loaded solver at a 10x finer step.  Rows: the exact solver with and
without the loads, the linearised and the loaded reference robots (no network), the operators that
take no loads (the error of ignoring them) and the loaded operators.  Errors: relative l2 of the
tendon paths (mean, median, p99, max) and the tip error in mm (median, p90, max).

Then ``--free`` load-free Table I designs (seed 4243) through every operator, and the speed at
1,000 designs, side by side: ``Surrogate.predict(..., loads=...)`` against
``solve(..., loads=..., workers=0)`` (both on all cores), 42 points.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from service.process import ROOT
from tdcr import design_space
from tdcr.physics import solve
from tdcr.surrogates.runtime import Surrogate, load_manifest
from training.operators.evaluate import FINER_SOLVER, compare, scored

S42 = np.linspace(0.0, 1.0, 42)
COLUMNS = ("mean", "median", "p99", "max", "tip_mm_median", "tip_mm_p90", "tip_mm_max")


def table(results: dict, columns=COLUMNS) -> str:
    head = "| method | mean rel. l2 | median | p99 | max | tip mm: median | p90 | max |"
    lines = [head, "|---|" + "---:|" * len(columns)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(f"{r[c]:.3g}" for c in columns) + " |")
    return "\n".join(lines)


def seconds(run, reps: int) -> float:
    """Best-of-``reps`` wall time of ``run()`` after one warm-up call."""
    run()
    best = float("inf")
    for _ in range(reps):
        started = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - started)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--designs", type=int, default=1000)
    parser.add_argument("--free", type=int, default=1000)
    parser.add_argument("--models-dir", default=str(ROOT / "models"))
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores\n")
    manifest = load_manifest(args.models_dir)
    names = sorted(manifest["models"])
    loaded = [n for n in names if "loads" in manifest["models"][n]["inputs"]]

    designs = design_space.sample_designs(args.designs, seed=4242)
    loads = design_space.BENCHMARK_LOADS.sample(args.designs, seed=4242)
    truth = solve(designs, S42, loads=loads, options=FINER_SOLVER, workers=0)
    ok = truth.converged
    print(f"held out: {args.designs} designs in gravity, {int(np.any(loads.tip_force != 0, axis=1).sum())} with tip "
          f"loads; truth: the exact loaded solver at a 10x finer step, {ok.sum()} converged (others left out)\n")
    features, matrix = designs.features()[ok], loads.matrix(args.designs)[ok]
    exact = solve(designs.take(np.nonzero(ok)[0]), S42, loads=loads.take(np.nonzero(ok)[0]), workers=0).tendons
    results = compare(args.models_dir, names, features, truth.tendons[ok], matrix, exact_designs=0)
    results = {"exact loaded solver": scored(exact, truth.tendons[ok])} | results
    print(table(results))

    free = design_space.sample_designs(args.free, seed=4243)
    free_truth = solve(free, S42, options=FINER_SOLVER, workers=0)
    keep = free_truth.converged
    print(f"\nload-free Table I designs ({keep.sum()} of {args.free} converged), relative l2 of the tendon paths:\n")
    print("| operator | mean | p99 | max |\n|---|---:|---:|---:|")
    for name in names:
        model = Surrogate.load(args.models_dir, name, manifest=manifest)
        pred = model.predict(free.features()[keep], S42, pose=False)["tendons"]
        r = scored(pred, free_truth.tendons[keep])
        print(f"| {name} | {r['mean']:.3g} | {r['p99']:.3g} | {r['max']:.3g} |")

    batch = design_space.sample_designs(1000, seed=4244)
    batch_loads = design_space.BENCHMARK_LOADS.sample(1000, seed=4244)
    solver_s = seconds(lambda: solve(batch, S42, loads=batch_loads, workers=0), 2)
    print(f"\nspeed at 1,000 loaded designs, 42 points (best of repeats, one run):\n\n"
          f"| method | ms | designs/s | speed-up over the exact loaded solver |\n|---|---:|---:|---:|\n"
          f"| exact loaded solver, solve(..., workers=0) | {1e3 * solver_s:.1f} | {1000 / solver_s:,.0f} | 1 |")
    for name in loaded:
        model = Surrogate.load(args.models_dir, name, manifest=manifest)
        t = seconds(lambda model=model: model.predict(batch.features(), S42, loads=batch_loads), 10)
        print(f"| {name}, Surrogate.predict | {1e3 * t:.2f} | {1000 / t:,.0f} | {solver_s / t:.0f} |")


if __name__ == "__main__":
    main()
