"""What a second, slow lag would buy on the shared recording, and who asks for it (prints a table).

    python benchmarks/real_robot_lags.py [--robot examples/ftdcr_v4_fitted.json]

The fitted robot's static tips (each row's equilibrium, :func:`tdcr.physics.replay.replay` without
times) seen through a mix of two first-order lags (eq. LAG, :func:`tdcr.robot.real.settle`),
y = (1 - w) lag(q, T1) + w lag(q, T2), over a grid of T1, T2 and w; aligned RMSE, mm, on train and
val.  The model is only worth building if train (the file that is fitted) chooses it.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from real_robot import add_recording_arguments  # noqa: E402  (this folder's)

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import load_robot, read_recording, settle  # noqa: E402
from tdcr.search.fit import errors  # noqa: E402

FAST, SLOW, WEIGHTS = (0.25, 0.29, 0.35), (1.0, 3.0, 10.0), (0.0, 0.1, 0.2, 0.3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4_fitted.json")
    args = parser.parse_args()
    robot = load_robot(args.robot)
    scores = {}
    for name, path in (("train", args.train), ("val", args.validate)):
        rec = read_recording(path, robot)
        answer = replay(robot, rec.commands)  # each row's equilibrium, no lag
        for fast, slow, w in itertools.product(FAST, SLOW, WEIGHTS):
            seen = (1 - w) * settle(answer.points, rec.time, fast) + w * settle(answer.points, rec.time, slow)
            scores.setdefault((fast, slow, w), {})[name] = errors(replace(answer, points=seen), rec).aligned
    by_train = min(scores, key=lambda k: scores[k]["train"])
    by_val = min(scores, key=lambda k: scores[k]["val"])
    print(f"robot {args.robot}; the file's own lag: {robot.measurement.time_constant:.3f} s\n")
    print("| T1 (s) | T2 (s) | w | train aligned (mm) | val aligned (mm) | chosen by |\n|---:|---:|---:|---:|---:|---|")
    for key in sorted(scores, key=lambda k: scores[k]["train"])[:8] + [by_val]:
        chosen = " and ".join(n for n, k in (("train", by_train), ("val", by_val)) if k == key)
        print(f"| {key[0]:g} | {key[1]:g} | {key[2]:g} | {scores[key]['train']:.2f} | {scores[key]['val']:.2f} | "
              f"{chosen} |")


if __name__ == "__main__":
    main()
