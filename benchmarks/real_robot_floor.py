"""How low the validation error can go with this model: the floor under the real robot's targets.

    python benchmarks/real_robot_floor.py                      # the shared FTDCR v4 recording
    python benchmarks/real_robot_floor.py --robot R.json --train T.csv --validate V.csv

A fit on train can do no better on val than the best parameters for val itself.  This script fits
the robot file with the default groups (:func:`tdcr.search.fit.fit`, ``--iterations`` least-squares
iterations, default 40, against :func:`~tdcr.search.fit.fit`'s 15):
- on the validation file alone, and scores it there (in-sample: the model's floor on val, up to the
  search's local minimum);
- on train and val together (val's rows after train's, its times shifted to follow them), and
  scores each part: the best one robot does on both files.

It then lists the pairs of rows of each file whose commands agree (every drive within ``--same``
mm) but that lie more than 3 rows apart, with the distance between their measured tips and between
the joint fit's predicted tips.  Where the measured tips are far apart but the model's are not, the
robot remembers something the model does not (its state differs for one command and the same
motions).  Figures depend on the machine: it is printed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tdcr.physics.replay import Replay  # noqa: E402
from tdcr.robot.real import Recording, load_robot, read_recording  # noqa: E402
from tdcr.search.fit import errors, fit  # noqa: E402

SHARED = ROOT.parent / "shared" / "real_robot" / "ftdcr_v4"
GAP = 1.0  # s between train's last row and val's first in the joint recording


def joined(first: Recording, second: Recording) -> Recording:
    """``second``'s rows after ``first``'s, its times shifted to start ``GAP`` s after ``first``'s last."""
    shift = first.time[-1] + GAP - second.time[0]
    return Recording(time=np.concatenate([first.time, second.time + shift]),
                     labels=np.concatenate([first.labels, second.labels]),
                     commands=np.concatenate([first.commands, second.commands]),
                     measured=np.concatenate([first.measured, second.measured]),
                     rows=np.concatenate([first.rows, second.rows]), header=first.header)


def repeated_commands(recording: Recording, tolerance: float, min_apart: int = 3) -> list[tuple[int, int]]:
    """Pairs (i, j), j > i + ``min_apart``, of measured rows whose commands ``(T, N_t)`` agree within
    ``tolerance`` (SI) in every drive."""
    from scipy.spatial import cKDTree

    scored = recording.has_measurement
    pairs = cKDTree(recording.commands).query_pairs(tolerance, p=np.inf)
    return sorted((i, j) for i, j in pairs if abs(j - i) > min_apart and scored[i] and scored[j])


def rows_of(answer: Replay, keep: np.ndarray) -> Replay:
    """The rows of a replay where ``keep`` ``(T,)`` is true."""
    return Replay(**{f.name: getattr(answer, f.name)[keep] for f in fields(answer)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default=str(ROOT / "examples" / "ftdcr_v4.json"))
    parser.add_argument("--train", default=str(SHARED / "train.csv"))
    parser.add_argument("--validate", default=str(SHARED / "val.csv"))
    parser.add_argument("--iterations", type=int, default=40, help="least-squares iterations of each fit")
    parser.add_argument("--same", type=float, default=0.05, help="commands agree within this, mm (every drive)")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    robot = load_robot(args.robot)
    train, val = read_recording(args.train, robot), read_recording(args.validate, robot)
    budget = 1e9  # the iterations bound each fit, not the clock

    start = time.perf_counter()
    on_val = fit(robot, val, max_iterations=args.iterations, budget=budget)
    val_seconds = time.perf_counter() - start
    start = time.perf_counter()
    both = joined(train, val)
    on_both = fit(robot, both, max_iterations=args.iterations, budget=budget)
    both_seconds = time.perf_counter() - start
    n = len(train.time)
    in_train, in_val = np.arange(len(both.time)) < n, np.arange(len(both.time)) >= n
    part = on_both.train_replay
    joint_train = errors(rows_of(part, in_train), both.take(in_train))
    joint_val = errors(rows_of(part, in_val), both.take(in_val))

    print("\n| fitted on | scored on | aligned RMSE, mm | plain RMSE, mm | max, mm | rows failed | fit, s |")
    print("|---|---|---|---|---|---|---|")
    print(f"| val | val | {on_val.train.aligned:.2f} | {on_val.train.rmse:.2f} | {on_val.train.max:.2f} | "
          f"{on_val.train.failed} | {val_seconds:.0f} |")
    for name, e in (("train", joint_train), ("val", joint_val)):
        print(f"| train + val | {name} | {e.aligned:.2f} | {e.rmse:.2f} | {e.max:.2f} | {e.failed} | "
              f"{both_seconds:.0f} |")

    print(f"\nrows with the same commands (every drive within {args.same} mm), more than 3 rows apart; tip "
          "distance, mm, measured and predicted by the joint fit:")
    for name, mask in (("train", in_train), ("val", in_val)):
        rows = np.flatnonzero(mask)
        recording = both.take(mask)
        pairs = repeated_commands(recording, args.same * 1e-3)
        measured, predicted = [], []
        for i, j in pairs:
            measured.append(np.linalg.norm(recording.measured[i] - recording.measured[j]) * 1e3)
            predicted.append(np.linalg.norm(part.points[rows[i]] - part.points[rows[j]]) * 1e3)
            print(f"  {name} rows {recording.rows[i]:4d} {recording.labels[i]:30s} {recording.rows[j]:4d} "
                  f"{recording.labels[j]:30s} largest command {np.abs(recording.commands[i]).max() * 1e3:5.2f} mm: "
                  f"measured {measured[-1]:5.2f}, predicted {predicted[-1]:5.2f}")
        if pairs:
            print(f"  {name}: {len(pairs)} pairs, measured median {np.median(measured):.2f} mm, predicted median "
                  f"{np.median(predicted):.2f} mm")
        else:
            print(f"  {name}: none")


if __name__ == "__main__":
    main()
