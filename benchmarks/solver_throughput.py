"""Solver throughput: Table I designs per second at 42 points (prints a Markdown table).

    python benchmarks/solver_throughput.py [--n 2000] [--repeats 3]

Each row is the best of ``--repeats`` runs.  'workers' are real processes, each solving
chunks of ``--chunk`` designs.  The accuracy column is the worst relative l2 error of tendon
positions over the independent C++ reference cases, at the same solver settings.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.designs import DesignBatch
from tdcr.physics import solve

ROOT = Path(__file__).resolve().parents[1]


def _solve_chunk(features: np.ndarray) -> tuple[int, float]:
    sol = solve(DesignBatch.from_features(features), np.linspace(0.0, 1.0, 42))
    return int(sol.converged.sum()), float(sol.residual.max())


def run(features: np.ndarray, workers: int, chunk: int) -> tuple[float, int, float]:
    chunks = [features[i:i + chunk] for i in range(0, len(features), chunk)]
    start = time.perf_counter()
    if workers == 1:
        results = [_solve_chunk(c) for c in chunks]
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            results = list(pool.map(_solve_chunk, chunks))
    elapsed = time.perf_counter() - start
    return elapsed, sum(r[0] for r in results), max(r[1] for r in results)


def reference_error() -> float:
    path = ROOT.parent / "shared" / "reference" / "cosserat_cases.json"
    if not path.exists():
        return float("nan")
    worst = 0.0
    for case in json.loads(path.read_text())["cases"]:
        d = case["design"]
        batch = DesignBatch(E=[d["E"]], r=[d["r"]], L=[d["L"]], offset=[[t["offset"] for t in d["tendons"]]],
                            pitch=[[t["pitch"] for t in d["tendons"]]], tension=[[t["tension"] for t in d["tendons"]]])
        sol = solve(batch, np.asarray(case["s"]) / d["L"])
        ref = np.asarray(case["tendons"])
        worst = max(worst, np.linalg.norm(sol.tendons[0] - ref) / np.linalg.norm(ref))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--chunk", type=int, default=250)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    features = design_space.sample_designs(args.n, seed=args.seed).features()
    cores = os.cpu_count() or 1
    print(f"machine: {platform.machine()}, {cores} cores, {platform.python_implementation()} "
          f"{platform.python_version()}, numpy {np.__version__}")
    print(f"reference accuracy (max relative l2 of tendon positions, 22 C++ cases): {reference_error():.2e}\n")
    print("| workers | designs | points | best time (s) | designs/s | converged | max residual (N) |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for workers in sorted({1, cores}):
        best = min((run(features, workers, args.chunk) for _ in range(args.repeats)), key=lambda r: r[0])
        elapsed, ok, res = best
        print(f"| {workers} | {args.n} | 42 | {elapsed:.3f} | {args.n / elapsed:,.0f} | {ok}/{args.n} | {res:.1e} |")


if __name__ == "__main__":
    main()
