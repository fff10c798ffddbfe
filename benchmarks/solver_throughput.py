"""Tendon-only solver throughput and accuracy: Table I designs per second at 42 points (prints a
Markdown table).

    python benchmarks/solver_throughput.py [--n 2000] [--repeats 3] [--seed 1] [--against REV]

Rows: the compiled kernel (numba) on 1 thread and on every core, and the same kernel computing
the exact Jacobian to the tensions too (``solve(..., jacobian=True)``) on 1 core and every core.
Each row is the best of ``--repeats`` runs of the whole batch, after one warm-up call.  Accuracy
columns: the worst relative l2 of tendon positions against the same method at a 20x finer fixed
step (``max_step = 1/820``), how many designs exceed 1e-6, and the distribution of the step the
step control chose; the line above the table gives the worst error over the 22 independent C++
reference cases.  A second table: the throughput targets of issue #34 on every core (Table I, two
segments, gravity and tip loads); ``--against REV`` measures a git revision's solver beside it, in
alternating rounds (e.g. ``--against c3f0ad9``, the solver before issue #34).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, solve
from tdcr.robot.designs import DesignBatch

ROOT = Path(__file__).resolve().parents[1]
SIGMA = np.linspace(0.0, 1.0, 42)


def reference_error(options: SolverOptions) -> float:
    path = ROOT / "tests" / "data" / "cosserat_cases.json"
    if not path.exists():
        return float("nan")
    worst = 0.0
    for case in json.loads(path.read_text())["cases"]:
        d = case["design"]
        batch = DesignBatch(E=[d["E"]], r=[d["r"]], L=[d["L"]], offset=[[t["offset"] for t in d["tendons"]]],
                            pitch=[[t["pitch"] for t in d["tendons"]]], tension=[[t["tension"] for t in d["tendons"]]])
        sol = solve(batch, np.asarray(case["s"]) / d["L"], options=options)
        ref = np.asarray(case["tendons"])
        worst = max(worst, np.linalg.norm(sol.tendons[0] - ref) / np.linalg.norm(ref))
    return worst


def timed(designs: DesignBatch, workers: int, repeats: int, jacobian: bool):
    solve(designs.take(np.arange(min(10, designs.n_designs))), SIGMA, workers=1, jacobian=jacobian)  # warm-up
    best, sol = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        sol = solve(designs, SIGMA, workers=workers, jacobian=jacobian)
        best = min(best, time.perf_counter() - start)
    return best, sol


#: The throughput targets of issue #34 (designs/s on 2 cores): label -> target.
TARGETS = {"Table I, tendon loads": 25_000, "two segments of 3 tendons": 20_000,
           "Table I in gravity and under tip loads (TRAINING_LOADS)": 500}


def rates(n: int, seed: int, repeats: int) -> dict[str, float]:
    """Designs/s of the :data:`TARGETS` cases on every core (``workers=0``), best of ``repeats``:
    Table I designs, two segments of 3 tendons (``sample_segmented_designs``), and designs in gravity
    and under tip loads (``TRAINING_LOADS``; a fifth of ``n``: each costs about 50 tendon-only solves).
    Uses whichever ``tdcr`` is imported (``--against`` runs an older tree's)."""
    from tdcr.robot.design_space import TRAINING_LOADS, sample_segmented_designs

    n_loaded = max(n // 5, 1)
    cases = dict(zip(TARGETS, ((design_space.sample_designs(n, seed=seed), None),
                               (sample_segmented_designs(n, seed=seed), None),
                               (design_space.sample_designs(n_loaded, seed=seed), TRAINING_LOADS.sample(n_loaded,
                                                                                                        seed=seed))),
                     strict=True))
    out = {}
    for label, (batch, external) in cases.items():
        solve(batch, SIGMA, loads=external, workers=0)  # warm-up (compiles on a first run)
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            solve(batch, SIGMA, loads=external, workers=0)
            best = min(best, time.perf_counter() - start)
        out[label] = batch.n_designs / best
    return out


def targets(n: int, seed: int, repeats: int, against: str | None) -> None:
    """The :data:`TARGETS` table; with ``against`` (a git revision) that tree's rates too, measured
    in alternating rounds in processes of their own (ratios within one run: the VM's speed drifts)."""
    from against import run_in, worktree  # benchmarks/ is the script's folder

    if against is None:
        ours, theirs = rates(n, seed, repeats), None
    else:
        tree, call = worktree(against), f"b.rates({n}, {seed}, {repeats})"
        runs = [(run_in(tree, "solver_throughput", call), run_in(ROOT, "solver_throughput", call))
                for _ in range(3)]  # alternating rounds
        theirs = {k: max(r[0][k] for r in runs) for k in TARGETS}
        ours = {k: max(r[1][k] for r in runs) for k in TARGETS}
    head = f" | {against} | ratio" if against else ""
    print(f"\n| on every core ({os.cpu_count()}), best of {repeats} | designs/s{head} | target | |\n"
          f"|---|---:{'|---:|---:' if against else ''}|---:|---|")
    for label, target in TARGETS.items():
        old = f" | {theirs[label]:,.0f} | {ours[label] / theirs[label]:.2f}x" if theirs else ""
        verdict = "met" if ours[label] >= target else "NOT met"
        print(f"| {label} | {ours[label]:,.0f}{old} | >= {target:,} | {verdict} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--against", help="a git revision whose solver's rates are measured beside (alternating)")
    args = parser.parse_args()
    designs = design_space.sample_designs(args.n, seed=args.seed)
    cores = os.cpu_count() or 1
    print(f"machine: {platform.machine()}, {cores} cores, {platform.python_implementation()} "
          f"{platform.python_version()}, numpy {np.__version__}")
    print(f"22 C++ reference cases, max relative l2 of tendon positions: {reference_error(SolverOptions()):.2e}")
    fine = solve(designs, SIGMA, options=SolverOptions(max_step=1 / 820, max_level=0, step_tol=np.inf), workers=0)
    print(f"{args.n} Table I designs (seed {args.seed}), 42 points, best of {args.repeats}\n")
    print("| path | cores | best time (s) | designs/s | converged | max rel. l2 vs 20x finer | > 1e-6 "
          "| max error estimate | steps chosen (41 / 82 / 164 / more) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = [("compiled kernel (numba)", 1, False), ("compiled kernel (numba)", cores, False),
            ("compiled kernel, with the tension Jacobian", 1, True),
            ("compiled kernel, with the tension Jacobian", cores, True)]
    for label, workers, jacobian in rows:
        if workers > 1 and cores == 1:
            continue
        elapsed, sol = timed(designs, workers, args.repeats, jacobian)
        error = relative_l2(sol.tendons, fine.tendons)
        counts = [int((sol.steps == k).sum()) for k in (41, 82, 164)]
        counts.append(args.n - sum(counts))
        print(f"| {label} | {workers} | {elapsed:.3f} | {args.n / elapsed:,.0f} | {int(sol.converged.sum())}/{args.n} "
              f"| {error.max():.1e} | {int((error > 1e-6).sum())} | {sol.error_estimate.max():.1e} "
              f"| {' / '.join(map(str, counts))} |")
    targets(args.n, args.seed, max(args.repeats, 5), args.against)
    base = solve(designs, SIGMA, options=SolverOptions(max_level=0, step_tol=np.inf))
    error = relative_l2(base.tendons, fine.tendons)
    print(f"\nwithout step control (one step per output interval): max {error.max():.1e}, "
          f"{int((error > 1e-6).sum())} of {args.n} designs above 1e-6")


if __name__ == "__main__":
    main()
