"""The accuracy-speed frontier, measured in one run on one machine.

    python benchmarks/frontier.py [--designs 2000] [--big 80000]

Methods: the exact solver (as shipped: the compiled kernel, tendon loads, step control), the linearized reference (the
strains of the undeformed tendon tangents, the operators' reference robot), and each of the four
operators in onnxruntime.  Accuracy on ``--designs`` unseen Table I designs (seed 4242; the training
sets used other seeds): relative l2 of the tendon paths (``tdcr.metrics.relative_l2``) against the
exact solver at a 10x finer step (so the exact solver's own discretisation error is shown too):
mean, p99 and max.  Speed: designs/s at batches of 1, 1,000 and ``--big`` (all cores: the solvers
through ``solve(..., workers=0)``, onnxruntime with one chunk per core), 42 points.
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
from tdcr.runtime import Surrogate

S42 = np.linspace(0.0, 1.0, 42)
OPERATORS = ("deeponet", "deeponet_pose", "fno", "fno_pose")
FINE = SolverOptions(max_step=SolverOptions().max_step / 10)
LINEARIZED = SolverOptions(linearized=True)


def rate(run, designs, reps: int) -> float:
    """Designs per second of ``run(features)`` (after one warm-up call)."""
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
            from tdcr.designs import DesignBatch

            return solve(DesignBatch.from_features(features), S42, options=options, workers=0).tendons
        return run

    methods = {"exact solver": solver(None), "linearized reference": solver(LINEARIZED)}
    for name in OPERATORS:
        model = Surrogate.load(ROOT / "models", name)
        methods[name] = lambda features, model=model: model.predict(features, S42, pose=False)["tendons"]

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


if __name__ == "__main__":
    main()
