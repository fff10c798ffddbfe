"""A probe for calibrated error bounds (issue #25): which difficulty score predicts an operator's error.

    python benchmarks/error_bound_probe.py [--model fno_pose] [--calibration 20000] [--test 5000]

Not the feature itself: it measures candidate scores for the held-out relative l2 error of one
tendon-only operator's tendon paths, with a plain Mondrian split-conformal bound in numpy (bins:
deciles of the linearised bending angle max_i tau_i o_i L / (E I) on the calibration set; per bin
the ceil((n + 1) 0.99)-th smallest error / score ratio).  Candidates: the disagreement with a
second tendon-only operator (``deeponet_pose``), the disagreement with the loaded DeepONet (whose
iterated reference makes it near-exact on load-free designs too), and the bending angle itself.
Calibration designs: seed 25; test designs: seed 26 (the shipped models trained on seeds 0 and 24).
For each score: log-log correlation with the error, coverage of the 99 % bound (overall and in
the worst bending decile), and at tolerances 0.01 and 0.001 the share of designs that would fall
back to the exact solver, the share served within the tolerance and the worst served error.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.runtime import Surrogate

S42 = np.linspace(0.0, 1.0, 42)
LEVEL = 0.99
DECILES = 10
#: added to every score: a bound is never zero
SCORE_FLOOR = 1e-6


def bending_angle(features: np.ndarray) -> np.ndarray:
    """The largest linearised bending angle of one tendon, tau_i o_i L / (E I), rad, ``(B,)``."""
    ei = features[:, 0] * np.pi / 4 * features[:, 1] ** 4
    return (features[:, 11:15] * features[:, 3:7]).max(axis=1) * features[:, 2] / ei


def measure(designs, model: str) -> dict[str, np.ndarray]:
    """Per converged design: the operator's error, each candidate score and the bending angle."""
    truth = solve(designs, S42, workers=0)
    ok = truth.converged
    features = designs.features()

    def tendons(name: str) -> np.ndarray:
        return Surrogate.shipped(name).predict(features, S42, pose=False)["tendons"]

    mine = tendons(model)
    return {"error": relative_l2(mine, truth.tendons)[ok],
            "disagreement with deeponet_pose": relative_l2(mine, tendons("deeponet_pose"))[ok],
            "disagreement with deeponet_pose_loaded": relative_l2(mine, tendons("deeponet_pose_loaded"))[ok],
            "bending angle": bending_angle(features)[ok]}


def mondrian_bounds(cal: dict, test: dict, score: str) -> tuple[np.ndarray, np.ndarray]:
    """99 % upper bounds of the test errors and the test designs' bins."""
    edges = np.percentile(cal["bending angle"], np.linspace(0, 100, DECILES + 1))[1:-1]
    bin_cal, bin_test = np.digitize(cal["bending angle"], edges), np.digitize(test["bending angle"], edges)
    bounds = np.empty(len(bin_test))
    for k in range(DECILES):
        ratios = np.sort(cal["error"][bin_cal == k] / (cal[score][bin_cal == k] + SCORE_FLOOR))
        rank = min(len(ratios), int(np.ceil((len(ratios) + 1) * LEVEL))) - 1
        bounds[bin_test == k] = ratios[rank] * (test[score][bin_test == k] + SCORE_FLOOR)
    return bounds, bin_test


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="fno_pose")
    parser.add_argument("--calibration", type=int, default=20_000)
    parser.add_argument("--test", type=int, default=5_000)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; operator {args.model}\n")
    cal = measure(design_space.sample_designs(args.calibration, seed=25), args.model)
    test = measure(design_space.sample_designs(args.test, seed=26), args.model)
    err = test["error"]
    print(f"test error: mean {err.mean():.3g}, p99 {np.percentile(err, 99):.3g}, max {err.max():.3g} "
          f"({len(err)} designs)\n")
    print("| score | log-log corr. | coverage | worst decile | fallback @0.01 | within 0.01 | worst served "
          "| fallback @0.001 | within 0.001 | worst served |\n|---|" + "---:|" * 9)
    for score in [k for k in cal if k != "error"]:
        corr = np.corrcoef(np.log(cal[score] + SCORE_FLOOR), np.log(cal["error"] + SCORE_FLOOR))[0, 1]
        bounds, bins = mondrian_bounds(cal, test, score)
        covered = err <= bounds
        worst_bin = min(covered[bins == k].mean() for k in range(DECILES))
        cells = [f"{corr:.3f}", f"{covered.mean():.4f}", f"{worst_bin:.4f}"]
        for tolerance in (0.01, 0.001):
            fallback = bounds > tolerance
            served = np.where(fallback, 0.0, err)  # the exact answers' error is ~1e-8
            cells += [f"{fallback.mean():.3f}", f"{np.mean(served <= tolerance):.4f}", f"{served.max():.3g}"]
        print(f"| {score} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
