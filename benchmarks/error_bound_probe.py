"""Which difficulty score bounds an operator's error best: the measurement behind
``training.operators.calibrate.SCORES`` (issue #25).

    python benchmarks/error_bound_probe.py [--calibration 20000] [--test 5000] [--models fno_pose,...]

For every operator and every candidate score (the disagreement with each other shipped operator,
and ``bins``: no score, the bending-angle bin's quantile alone), the Mondrian split-conformal 99 %
bound of ``training.operators.calibrate.fit`` on calibration designs (seed 25), applied to test
designs (seed 26; the shipped models trained on seeds 0 and 24); loaded operators in their trained
load space.  Columns: log-log correlation of score and error (calibration set), coverage overall
and in the worst bending decile, and at tolerances 0.01 and 0.001 the share that would fall back
to the exact solver, the share of served designs within the tolerance, and the worst served error.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from service.process import ROOT
from tdcr import design_space
from tdcr.surrogates.bounds import Calibration, bending_angle
from tdcr.surrogates.runtime import load_manifest, takes_loads
from training.operators.calibrate import SCORE_FLOOR, Score, fit, measure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--calibration", type=int, default=20_000)
    parser.add_argument("--test", type=int, default=5_000)
    parser.add_argument("--models", default="", help="comma-separated (default: all)")
    parser.add_argument("--models-dir", default=str(ROOT / "models"))
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores\n")
    manifest = load_manifest(args.models_dir)
    names = sorted(manifest["models"])
    wanted = args.models.split(",") if args.models else names
    print("| operator | score | log-log corr. | coverage | worst decile | fallback @0.01 | within 0.01 | "
          "worst served | fallback @0.001 | within 0.001 | worst served |\n|---|---|" + "---:|" * 9)
    for loaded in (False, True):
        group = [n for n in wanted if takes_loads(manifest["models"][n]) == loaded]
        if not group:
            continue
        space = design_space.TRAINING_LOADS if loaded else None

        def sample(n, seed, space=space):
            return measure(args.models_dir, names, design_space.sample_designs(n, seed=seed),
                           None if space is None else space.sample(n, seed=seed))

        cal, test = sample(args.calibration, 25), sample(args.test, 26)
        theta = bending_angle(cal.features)
        for name in group:
            err_cal, err = cal.error(name), test.error(name)
            for score in [Score("disagreement", c) for c in names if c != name] + [Score("bins")]:
                s_cal, s_test = cal.score(name, score), test.score(name, score)
                edges, quantiles = fit(err_cal, s_cal, theta)
                calibration = Calibration({"score": score.kind, "floor": SCORE_FLOOR, "edges": edges.tolist(),
                                           "quantiles": quantiles.tolist()})
                bound = calibration.bound(test.features, s_test)  # the load ranges: the trained space itself
                bins = calibration.bins(test.features)
                covered = err <= bound
                worst = min(covered[bins == k].mean() for k in range(len(quantiles)) if (bins == k).any())
                corr = (np.nan if s_cal is None else
                        np.corrcoef(np.log(s_cal + SCORE_FLOOR), np.log(err_cal + SCORE_FLOOR))[0, 1])
                cells = [f"{corr:.3f}", f"{covered.mean():.4f}", f"{worst:.4f}"]
                for tolerance in (0.01, 0.001):
                    fallback = ~(bound <= tolerance)
                    served = np.where(fallback, 0.0, err)  # the exact answers' error is ~1e-7
                    cells += [f"{fallback.mean():.3f}", f"{np.mean(served <= tolerance):.4f}", f"{served.max():.3g}"]
                label = score.companion or score.kind
                print(f"| {name} | {label} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
