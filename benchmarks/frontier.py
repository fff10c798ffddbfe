"""The accuracy-speed frontier, measured in one run on one machine.

    python benchmarks/frontier.py [--designs 2000] [--big 80000]

Methods: the exact solver (as shipped: the compiled kernel, tendon loads, step control), the
linearized reference (the strains of the undeformed tendon tangents, the operators' reference
robot), and each of the four operators in onnxruntime.  Accuracy on ``--designs`` unseen Table I
designs (seed 4242; the training sets used other seeds): relative l2 of the tendon paths
(``tdcr.metrics.relative_l2``) against the exact solver at a 10x finer step (so the exact solver's
own discretisation error is shown too): mean, p99 and max.  Speed: designs/s at batches of 1,
1,000 and ``--big`` (all cores: the solvers through ``solve(..., workers=0)``, onnxruntime with
one chunk per core), 42 points.  Router rows: ``tdcr.surrogates.router.Router`` (what ``/predict`` without a model
answers with: per batch the cheaper of the solver and the most accurate operator, by costs timed on
this machine), plain and keeping the tolerances.  Guarded rows: an operator keeping a ``tolerance`` of 0.01 or
0.001 (its calibrated error bound computed for every design, and the designs whose bound exceeds
the tolerance answered by the exact solver in the same call: ``Surrogate.predict(...,
tolerance=...)``).

A second table does the same in gravity and under tip loads (``tdcr.robot.design_space.BENCHMARK_LOADS``):
the exact loaded solver, the operators that take no loads (the error of ignoring them) and the
loaded operators, at batches of 1 and 1,000.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from service.process import ROOT
from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, solve
from tdcr.surrogates.router import Router
from tdcr.surrogates.runtime import Surrogate

S42 = np.linspace(0.0, 1.0, 42)
OPERATORS = ("deeponet", "deeponet_pose", "fno", "fno_pose", "deeponet_pose_loaded")
#: The tolerances of the guarded rows (relative l2).
TOLERANCES = (0.01, 0.001)
FINE = SolverOptions(max_step=SolverOptions().max_step / 10)
FINE_LOADS = SolverOptions(max_step_loads=SolverOptions().max_step_loads / 10)
LINEARIZED = SolverOptions(linearized=True)


def rate(run, designs, reps: int) -> float:
    """Designs per second of ``run(designs)`` (features, or rows of them; after one warm-up call)."""
    run(designs)
    started = time.perf_counter()
    for _ in range(reps):
        run(designs)
    return reps * len(designs) / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--designs", type=int, default=2000)
    parser.add_argument("--big", type=int, default=80_000)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores\n")
    held_out = design_space.sample_designs(args.designs, seed=4242)
    truth = solve(held_out, S42, options=FINE, workers=0)
    ok = truth.converged
    print(f"reference: exact solver at a 10x finer step, {ok.sum()} of {ok.size} designs converged (others left out)")

    def solver(options):
        def run(features):
            from tdcr.robot.designs import DesignBatch

            return solve(DesignBatch.from_features(features), S42, options=options, workers=0).tendons
        return run

    methods = {"exact solver": solver(None), "linearized reference": solver(LINEARIZED)}
    for name in OPERATORS:
        model = Surrogate.load(ROOT / "models", name)
        methods[name] = lambda features, model=model: model.predict(features, S42, pose=False)["tendons"]
        for tolerance in TOLERANCES:
            methods[f"{name}, tolerance {tolerance:g}"] = lambda features, model=model, tolerance=tolerance: (
                model.predict(features, S42, pose=False, tolerance=tolerance)["tendons"])

    router = Router.shipped()  # the cheaper of the solver and its operator, by costs timed here
    methods["router (no model)"] = lambda features: router.predict(features, S42, pose=False)["tendons"]
    for tolerance in TOLERANCES:
        methods[f"router, tolerance {tolerance:g}"] = lambda features, tolerance=tolerance: router.predict(
            features, S42, pose=False, tolerance=tolerance)["tendons"]

    features = held_out.features()
    batches = {1: features[:1], 1000: features[:1000]}
    big = design_space.sample_designs(args.big, seed=4243).features()
    rows = []
    for name, run in methods.items():
        tendons = run(features)
        err = relative_l2(tendons[ok], truth.tendons[ok])
        speeds = [rate(run, batches[1], 200 if "exact" in name or "linear" in name else 500),
                  rate(run, batches[1000], 3), rate(run, big, 1)]
        rows.append((name, err.mean(), np.percentile(err, 99), err.max(), *speeds))
        print(f"  {name}: done", flush=True)
    print("\n| method | mean rel. l2 | p99 | max | designs/s, batch 1 | batch 1,000 | batch "
          f"{args.big:,} |\n|---|---:|---:|---:|---:|---:|---:|")
    for name, mean, p99, worst, s1, s1000, sbig in rows:
        print(f"| {name} | {mean:.2e} | {p99:.2e} | {worst:.2e} | {s1:,.0f} | {s1000:,.0f} | {sbig:,.0f} |")
    loaded_frontier(args.designs)


def loaded_frontier(n: int) -> None:
    """The frontier in gravity and under tip loads: ``n`` held-out designs (seed 4242) with
    :data:`~tdcr.robot.design_space.BENCHMARK_LOADS`, truth at a 10x finer step; designs/s at batches
    of 1 and 1,000."""
    from tdcr.robot.designs import DesignBatch, ExternalLoads
    from tdcr.surrogates.runtime import load_manifest

    designs = design_space.sample_designs(n, seed=4242)
    loads = design_space.BENCHMARK_LOADS.sample(n, seed=4242)
    truth = solve(designs, S42, loads=loads, options=FINE_LOADS, workers=0)
    ok = truth.converged
    features, matrix = designs.features(), loads.matrix(n)
    manifest = load_manifest(ROOT / "models")
    methods = {"exact loaded solver": lambda rows: solve(DesignBatch.from_features(features[rows]), S42,
                                                         loads=ExternalLoads.from_matrix(matrix[rows]),
                                                         workers=0).tendons}
    for name, entry in sorted(manifest["models"].items()):
        model = Surrogate.load(ROOT / "models", name, manifest=manifest)
        if "loads" in entry["inputs"]:
            methods[name] = lambda rows, model=model: model.predict(features[rows], S42, loads=matrix[rows],
                                                                    pose=False)["tendons"]
            for tolerance in TOLERANCES:
                methods[f"{name}, tolerance {tolerance:g}"] = lambda rows, model=model, tolerance=tolerance: (
                    model.predict(features[rows], S42, loads=matrix[rows], pose=False, tolerance=tolerance)["tendons"])
        else:
            methods[f"{name} (loads ignored)"] = lambda rows, model=model: model.predict(
                features[rows], S42, pose=False)["tendons"]
    router = Router.shipped()
    methods["router (no model)"] = lambda rows: router.predict(features[rows], S42, loads=matrix[rows],
                                                               pose=False)["tendons"]
    print(f"\nin gravity and under tip loads: {ok.sum()} of {n} held-out designs, truth the exact loaded solver at a "
          "10x finer step\n\n| method | mean rel. l2 | p99 | max | designs/s, batch 1 | batch 1,000 |\n"
          "|---|---:|---:|---:|---:|---:|")
    every, one, thousand = np.arange(n), np.arange(1), np.arange(min(n, 1000))
    for name, run in methods.items():
        err = relative_l2(run(every)[ok], truth.tendons[ok])
        s1 = rate(run, one, 50 if "exact" in name else 500)
        s1000 = rate(run, thousand, 1 if "exact" in name else 3)
        print(f"| {name} | {err.mean():.2e} | {np.percentile(err, 99):.2e} | {err.max():.2e} | {s1:,.0f} | "
              f"{s1000:,.0f} |", flush=True)


if __name__ == "__main__":
    main()
