"""Tip Jacobians and inverse kinematics: cost and accuracy (in-process, this machine).

    python benchmarks/inverse.py [--targets 200]

Prints:
1. the exact Jacobian's cost against a forward solve (42 points, batches of 1 and 1,000 designs);
2. inverse kinematics with the exact model on ``--targets`` reachable targets: the tips of random
   Table I equilibria (tensions uniform in [0, 5] N), each solved cold from zero tensions: share
   reached within 1e-4 L, time per target (p50, p90) and forward evaluations;
3. the same targets as a path (each design's tips at 10 tensions along a line, warm starts);
4. each operator: its Jacobian's error against the exact one (relative Frobenius, median over
   designs), its inverse answers' true tip error (the exact forward solve at its tensions), time
   per target, and what ``polish`` (exact steps from its answer) costs and gives.
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
from tdcr.robot.designs import DesignBatch
from tdcr.search.inverse import exact_forward, inverse, model_forward, model_tip_pose, tip_by_differences
from tdcr.surrogates.runtime import Surrogate

S42 = np.linspace(0.0, 1.0, 42)
TIP = np.array([1.0])
OPERATORS = ("deeponet", "deeponet_pose", "fno", "fno_pose")


def timed(fn, reps: int) -> float:
    fn()
    started = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - started) / reps


def jacobian_cost() -> None:
    print("1. exact Jacobian vs forward solve (42 points)")
    for n, reps in ((1, 100), (1000, 3)):
        d = design_space.sample_designs(n, seed=5)
        forward = timed(lambda d=d: solve(d, S42), reps)
        with_jacobian = timed(lambda d=d: solve(d, S42, jacobian=True), reps)
        print(f"   batch {n:>5}: forward {forward * 1e3:8.2f} ms, with Jacobian {with_jacobian * 1e3:8.2f} ms "
              f"({with_jacobian / forward:.2f}x)")


def _tips(designs: DesignBatch) -> np.ndarray:
    return solve(designs, TIP).backbone[:, -1]


def _with(d: DesignBatch, tension: np.ndarray) -> DesignBatch:
    return DesignBatch(E=d.E, r=d.r, L=d.L, offset=d.offset, pitch=d.pitch, tension=tension[None])


def exact_targets(designs: DesignBatch) -> None:
    tips = _tips(designs)
    times, evaluations, reached = [], [], 0
    for j in range(designs.n_designs):
        d = designs.take(np.array([j]))
        started = time.perf_counter()
        (res,) = inverse(exact_forward(d), float(d.L[0]), tips[j:j + 1], None, start=np.zeros(4), tension_max=5.0)
        times.append(time.perf_counter() - started)
        evaluations.append(res.iterations)
        back = _tips(_with(d, res.tensions))[0]
        reached += res.status == "reached" and np.linalg.norm(back - tips[j]) <= 1e-4 * d.L[0]
    ms = np.array(times) * 1e3
    n = designs.n_designs
    print(f"2. exact, {n} cold targets: reached within 1e-4 L {100 * reached / n:.1f} %, "
          f"per target p50 {np.median(ms):.1f} ms, p90 {np.percentile(ms, 90):.1f} ms, "
          f"evaluations p50 {np.median(evaluations):.0f}, max {max(evaluations)}")


def exact_paths(designs: DesignBatch, steps: int = 10) -> None:
    times, reached, total = [], 0, 0
    rng = np.random.default_rng(1)
    for j in range(designs.n_designs):
        d = designs.take(np.array([j]))
        line = np.linspace(rng.uniform(0, 5, 4), rng.uniform(0, 5, 4), steps)
        path = DesignBatch(E=np.repeat(d.E, steps), r=np.repeat(d.r, steps), L=np.repeat(d.L, steps),
                           offset=np.repeat(d.offset, steps, axis=0), pitch=np.repeat(d.pitch, steps, axis=0),
                           tension=line)
        tips = _tips(path)
        started = time.perf_counter()
        results = inverse(exact_forward(d), float(d.L[0]), tips, None, start=np.zeros(4), tension_max=5.0)
        times.append((time.perf_counter() - started) / steps)
        reached += sum(r.status == "reached" for r in results)
        total += steps
    ms = np.array(times) * 1e3
    share = 100 * reached / total
    print(f"3. exact, {designs.n_designs} paths of {steps} targets (warm starts): reached {share:.1f} %, "
          f"per target p50 {np.median(ms):.1f} ms")


def operators(designs: DesignBatch) -> None:
    tips = _tips(designs)
    exact_jacobian = solve(designs, TIP, jacobian=True).jacobian[:, -1]
    print("4. operators (onnxruntime, central differences; true errors from the exact solver)")
    print("   | model | Jacobian error (median rel.) | tip error after inverse, median / p90 (mm) | ms/target "
          "| polished: reached % | polish ms/target |")
    for name in OPERATORS:
        model = Surrogate.load(ROOT / "models", name)

        tip_pose = model_tip_pose(model.predict)

        _, _, jac = tip_by_differences(designs.features(), tip_pose)
        jac_error = np.linalg.norm(jac - exact_jacobian, axis=(1, 2)) / np.linalg.norm(exact_jacobian, axis=(1, 2))
        errors, times, polish_times, polished = [], [], [], 0
        for j in range(designs.n_designs):
            d = designs.take(np.array([j]))
            started = time.perf_counter()
            (res,) = inverse(model_forward(d, tip_pose), float(d.L[0]), tips[j:j + 1], None, start=np.zeros(4),
                             tension_max=5.0)
            times.append(time.perf_counter() - started)
            errors.append(np.linalg.norm(_tips(_with(d, res.tensions))[0] - tips[j]))
            started = time.perf_counter()
            (fine,) = inverse(exact_forward(d), float(d.L[0]), tips[j:j + 1], None, start=res.tensions,
                              tension_max=5.0)
            polish_times.append(time.perf_counter() - started)
            polished += fine.status == "reached"
        mm = np.array(errors) * 1e3
        print(f"   | {name} | {np.median(jac_error):.3g} | {np.median(mm):.3f} / {np.percentile(mm, 90):.3f} | "
              f"{np.median(times) * 1e3:.1f} | {100 * polished / designs.n_designs:.1f} | "
              f"{np.median(polish_times) * 1e3:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--targets", type=int, default=200)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; one process\n")
    designs = design_space.sample_designs(args.targets, seed=2026)
    jacobian_cost()
    exact_targets(designs)
    exact_paths(designs.take(np.arange(min(50, args.targets))))
    operators(designs.take(np.arange(min(100, args.targets))))


if __name__ == "__main__":
    main()
