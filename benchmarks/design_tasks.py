"""The design-search benchmark: tasks with a known solution, solved by `tdcr design` with an
operator in the inner loop and, on the same budget, with exact physics only (prints a table).

    python benchmarks/design_tasks.py [--tasks benchmarks/design_tasks.json] [--write] [--budget-s 60]

The task set (``benchmarks/design_tasks.json``, written by ``--write``): 10 tasks, each built from a
random Table I design (seed 2600 + k) and 3-5 targets taken from its equilibria at random tensions
in [0, 5] N (seeded), so that a solution exists; tasks 1, 4 and 7 fix L at the design's, tasks 2
and 5 fix E and r, tasks 3 and 7 also ask for the tip directions.  Tolerance 1 mm, objective the
least largest tension.  Every reported error is the exact solver's on the returned design and
tensions.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch
from tdcr.search.design import search, validate_task

HERE = Path(__file__).resolve().parent
N_TASKS = 10


def build_tasks(budget_s: float) -> list[dict]:
    """The published task set (deterministic)."""
    tasks = []
    for k in range(N_TASKS):
        design = design_space.sample_designs(1, seed=2600 + k)
        rng = np.random.default_rng(2600 + k)
        n_targets = 3 + k % 3
        tensions = rng.uniform(0.0, 5.0, size=(n_targets, 4))
        rows = np.repeat(design.features(), n_targets, axis=0)
        rows[:, 11:15] = tensions
        tip = solve(DesignBatch.from_features(rows), np.ones(1))
        directions = k in (3, 7)
        targets = [{"position": tip.backbone[j, -1].tolist()}
                   | ({"direction": tip.rotation[j, -1][:, 2].tolist()} if directions else {})
                   for j in range(n_targets)]
        fixed = {"L": float(design.L[0])} if k in (1, 4, 7) else (
            {"E": float(design.E[0]), "r": float(design.r[0])} if k in (2, 5) else {})
        tasks.append({"name": f"task-{k}", "targets": targets, "fixed": fixed, "tolerance": 1e-3, "seed": k,
                      "budget_s": budget_s, "source_design": design.to_dicts()[0]})
    return tasks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", default=str(HERE / "design_tasks.json"))
    parser.add_argument("--write", action="store_true", help="(re)build the task set file first")
    parser.add_argument("--budget-s", type=float, default=60.0)
    parser.add_argument("--inner", default="operator,exact", help="comma-separated: operator, exact")
    parser.add_argument("--select", default=None, help="comma-separated task indices (default: all)")
    args = parser.parse_args()
    if args.write:
        Path(args.tasks).write_text(json.dumps(build_tasks(args.budget_s), indent=1) + "\n")
    tasks = json.loads(Path(args.tasks).read_text())
    if args.select:
        tasks = [tasks[int(k)] for k in args.select.split(",")]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; {len(tasks)} tasks, budget {args.budget_s:g} s\n")
    summary = {}
    for inner in args.inner.split(","):
        print(f"inner loop: {inner}\n\n| task | targets | fixed | status | seconds | worst error (mm) | "
              "objective (N) | surrogate evaluations | exact evaluations | overturned |\n"
              "|---|---:|---|---|---:|---:|---:|---:|---:|---:|")
        times, solved = [], 0
        for spec in tasks:
            body = {k: v for k, v in spec.items() if k not in ("name", "source_design")} | {"budget_s": args.budget_s}
            result = search(validate_task(body), inner=inner).as_json()
            worst = max(t["error"] for t in result["targets"])
            solved += result["status"] == "solved" and worst <= 1e-3
            times.append(result["seconds"])
            print(f"| {spec['name']} | {len(spec['targets'])}{' + dir.' if 'direction' in spec['targets'][0] else ''} "
                  f"| {','.join(spec['fixed']) or '-'} | {result['status']} | {result['seconds']:.1f} | "
                  f"{1e3 * worst:.3f} | {result['objective']:.3g} | {result['evaluations']['surrogate']:,} | "
                  f"{result['evaluations']['exact']:,} | {result['overturned']} |", flush=True)
        summary[inner] = (solved, np.median(times), np.percentile(times, 90))
        print()
    print("| inner loop | solved (every target within 1 mm, exact) | median s | p90 s |\n|---|---:|---:|---:|")
    for inner, (solved, median, p90) in summary.items():
        print(f"| {inner} | {solved} / {len(tasks)} | {median:.1f} | {p90:.1f} |")


if __name__ == "__main__":
    main()
