"""How low the validation error can go with this model: the floor under the real robot's targets.

    python benchmarks/real_robot_floor.py                      # the shared FTDCR v4 recording
    python benchmarks/real_robot_floor.py --robot R.json --train T.csv --validate V.csv
    python benchmarks/real_robot_floor.py --gravity=GX,GY,GZ --density RHO   # the robot in gravity (base frame)

A fit on train can do no better on val than the best parameters for val itself.  This script fits
the robot file with the default groups (:func:`tdcr.search.fit.fit`, ``--iterations`` least-squares
iterations, default 40, against :func:`~tdcr.search.fit.fit`'s 15):
- on the validation file alone, and scores it there (in-sample: the model's floor on val, up to the
  search's local minimum);
- on train and val together (val's rows after train's, its times shifted to follow them), and
  scores each part: the best one robot does on both files;
- on train alone (:func:`~tdcr.search.fit.fit` as ``tdcr fit`` runs it, without the time budget),
  and then puts each group of the train fit's values into the joint fit (and each of the joint fit's
  into the train fit's), every robot replayed from train's start over train and val in time order
  (:func:`tdcr.search.fit.at_start`): which of the train fit's values cost val the most.

It then lists the pairs of rows of each file whose commands agree (every drive within ``--same``
mm) but that lie more than 3 rows apart, with the distance between their measured tips and between
the joint fit's predicted tips.  Where the measured tips are far apart but the model's are not, the
robot remembers something the model does not (its state differs for one command and the same
motions).  Then the loops of the single-drive sweeps (:func:`sweep_loops`): how much more bent the
release branch is than the pull branch at the same command, measured and predicted.  Last, the turn
of each pattern's bend about the base's axis (:func:`bend_turns`) that the train fit leaves, before
and after train's longest pause and on val: a robot that turns on its mount during the session
shows as a turn that changes in time.  Figures depend on the machine: it is printed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from real_robot import add_load_arguments, add_recording_arguments, robot_under  # noqa: E402  (this folder's)

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import Recording, read_recording, rotation_matrix  # noqa: E402
from tdcr.search.fit import FitResult, Parameter, at_start, errors, fit  # noqa: E402

GAP = 1.0  # s between train's last row and val's first in the joint recording


def joined(first: Recording, second: Recording) -> Recording:
    """``second``'s rows after ``first``'s, its times shifted to start ``GAP`` s after ``first``'s last."""
    shift = first.time[-1] + GAP - second.time[0]
    return Recording(time=np.concatenate([first.time, second.time + shift]),
                     labels=np.concatenate([first.labels, second.labels]),
                     commands=np.concatenate([first.commands, second.commands]),
                     measured=np.concatenate([first.measured, second.measured]),
                     rows=np.concatenate([first.rows, second.rows]), header=first.header)


#: Groups traded together: E and the tendons' compliance lie on one ridge (without loads only their
#: product sets the shapes), so one of them alone from another fit is off it.
TRADED_TOGETHER = ({"E", "elasticity", "stiffness"},)


def trading(on_train: FitResult, joint: FitResult) -> list[tuple[str, list[Parameter]]]:
    """The joint fit's parameters, the train fit's, and for each group (:data:`TRADED_TOGETHER` as
    one) the one with that group's values taken from the other (two fits of the same groups):
    (name, parameters)."""
    pairs = list(zip(on_train.parameters, joint.parameters, strict=True))
    units = []
    for group in joint.groups:
        unit = next((set(joint.groups) & together for together in TRADED_TOGETHER if group in together), {group})
        if unit not in units:
            units.append(unit)
    out = [("the joint fit", list(joint.parameters)), ("the train fit", list(on_train.parameters))]
    for unit in units:
        name = " and ".join(g for g in joint.groups if g in unit)
        out.append((f"the joint fit, train's {name}", [t if j.group in unit else j for t, j in pairs]))
    for unit in units:
        name = " and ".join(g for g in joint.groups if g in unit)
        out.append((f"the train fit, the joint's {name}", [j if j.group in unit else t for t, j in pairs]))
    return out


def repeated_commands(recording: Recording, tolerance: float, min_apart: int = 3) -> list[tuple[int, int]]:
    """Pairs (i, j), j > i + ``min_apart``, of measured rows whose commands ``(T, N_t)`` agree within
    ``tolerance`` (SI) in every drive."""
    from scipy.spatial import cKDTree

    scored = recording.has_measurement
    pairs = cKDTree(recording.commands).query_pairs(tolerance, p=np.inf)
    return sorted((i, j) for i, j in pairs if abs(j - i) > min_apart and scored[i] and scored[j])


def sweep_loops(recording: Recording, points: np.ndarray, *, span: float = 3e-3,
                others: float = 0.25) -> np.ndarray:
    """The loops of the recording's single-drive sweeps: in each pattern (a run of one label) where one
    drive's command spans at least ``span`` m and every other drive's at most ``others`` times that,
    the tip's deflection |p - p_0| (p_0 the tip at the sweep's first row, ``points`` ``(T, 3)`` m,
    measured or predicted) on each release row (after the largest command) minus the deflection
    the pull branch (up to it) reaches at the same command, interpolated linearly.  Returns the
    differences ``(K,)`` m over all sweeps: positive where the release branch is the more bent one
    (lagging behind, as friction and the settling lag make it)."""
    out = []
    labels, scored = recording.labels, recording.has_measurement
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], len(labels)], strict=True):
        commands = recording.commands[a:b]
        ranges = np.ptp(commands, axis=0) if b - a > 2 else np.zeros(commands.shape[1])
        drive = int(np.argmax(ranges))
        if ranges[drive] < span or np.delete(ranges, drive).max(initial=0.0) > others * ranges[drive]:
            continue
        u = commands[:, drive]
        peak = int(np.argmax(u))
        ok = scored[a:b] & np.isfinite(points[a:b]).all(axis=1)
        pull = np.flatnonzero(ok[:peak + 1])
        pull = pull[u[pull] >= np.maximum.accumulate(u[pull])]  # the pull branch's rising rows
        release = np.flatnonzero(ok[peak + 1:]) + peak + 1
        if pull.size < 2 or not release.size:
            continue
        deflection = np.linalg.norm(points[a:b] - points[a + pull[0]], axis=1)
        inside = release[(u[release] >= u[pull[0]]) & (u[release] <= u[pull[-1]])]
        out.extend(deflection[inside] - np.interp(u[inside], u[pull], deflection[pull]))
    return np.array(out)


def bend_turns(recording: Recording, predicted: np.ndarray, axis: np.ndarray, *, rest: float = 2.5e-4,
               least: float = 0.02) -> list[tuple[str, float, float]]:
    """Per pattern (a run of one label with 5 or more scored rows whose predicted tip moves at least
    ``least`` m across ``axis``): the turn about ``axis`` ``(3,)`` (a unit vector, the base's axis in the
    measurement frame) that best maps the ``predicted`` ``(T, 3)`` m deflections onto the measured
    ones, each taken across the axis from its own median at rest (the rows whose every command is
    within ``rest`` m of 0).  Returns ``(label, its first row's time s, turn rad)``, the turn
    counterclockwise about the axis: atan2(sum a . (q x m), sum q . m) over the pattern's rows."""
    scored = recording.has_measurement & np.isfinite(predicted).all(axis=1)
    at_rest = scored & (np.abs(recording.commands).max(axis=1) <= rest)
    if not at_rest.any():
        return []
    across = np.eye(3) - np.outer(axis, axis)
    measured = (recording.measured - np.median(recording.measured[at_rest], axis=0)) @ across
    model = (predicted - np.median(predicted[at_rest], axis=0)) @ across
    labels = recording.labels
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    out = []
    for a, b in zip(starts, np.r_[starts[1:], len(labels)], strict=True):
        rows = np.flatnonzero(scored[a:b]) + a
        if rows.size < 5 or np.linalg.norm(model[rows], axis=1).max() < least:
            continue
        q, m = model[rows], measured[rows]
        turn = np.arctan2(np.sum(np.cross(q, m) @ axis), np.sum(q * m))
        out.append((str(labels[a]), float(recording.time[a]), float(turn)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4.json")
    parser.add_argument("--iterations", type=int, default=40, help="least-squares iterations of each fit")
    parser.add_argument("--same", type=float, default=0.05, help="commands agree within this, mm (every drive)")
    add_load_arguments(parser)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    robot = robot_under(args.robot, args)
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
    joint_train = errors(part.take(in_train), both.take(in_train))
    joint_val = errors(part.take(in_val), both.take(in_val))

    print("\n| fitted on | scored on | aligned RMSE, mm | plain RMSE, mm | max, mm | rows failed | fit, s |")
    print("|---|---|---|---|---|---|---|")
    print(f"| val | val | {on_val.train.aligned:.2f} | {on_val.train.rmse:.2f} | {on_val.train.max:.2f} | "
          f"{on_val.train.failed} | {val_seconds:.0f} |")
    for name, e in (("train", joint_train), ("val", joint_val)):
        print(f"| train + val | {name} | {e.aligned:.2f} | {e.rmse:.2f} | {e.max:.2f} | {e.failed} | "
              f"{both_seconds:.0f} |")

    start = time.perf_counter()
    on_train = fit(robot, train, budget=budget)
    train_seconds = time.perf_counter() - start
    print(f"\nthe train fit ({train_seconds:.0f} s) and the joint fit with one group of the other's values, "
          "replayed from train's start over train and val; aligned / plain RMSE, mm:")
    print("\n| robot | train | val |\n|---|---|---|")
    for name, parameters in trading(on_train, on_both):
        answer = replay(at_start(robot, on_both, parameters), both.commands, time=both.time)
        scores = [errors(answer.take(mask), both.take(mask)) for mask in (in_train, in_val)]
        print(f"| {name} | " + " | ".join(f"{e.aligned:.2f} / {e.rmse:.2f}" for e in scores) + " |", flush=True)

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

    print("\nthe single-drive sweeps' loops: the release branch's deflection minus the pull branch's at the same "
          "command (positive: the release branch lags, more bent), mm, measured and predicted by the joint fit:")
    for name, mask in (("train", in_train), ("val", in_val)):
        recording = both.take(mask)
        measured = sweep_loops(recording, recording.measured) * 1e3
        predicted = sweep_loops(recording, part.points[mask]) * 1e3
        if measured.size:
            print(f"  {name}: {measured.size} release rows; measured mean {measured.mean():+.2f}, median "
                  f"{np.median(measured):+.2f}; predicted mean {predicted.mean():+.2f}, median "
                  f"{np.median(predicted):+.2f}")
        else:
            print(f"  {name}: no single-drive sweep")

    fitted = at_start(robot, on_train)
    axis = rotation_matrix(fitted.measurement.base_rotation) @ np.array([0.0, 0.0, 1.0])
    turns = bend_turns(both, replay(fitted, both.commands, time=both.time).points, axis)
    gaps = np.diff(train.time)
    pause = int(np.argmax(gaps))
    print(f"\nthe turn of each pattern's bend about the base's axis that the train fit leaves (measured against "
          f"predicted, counterclockwise), degrees; train's longest pause: {gaps[pause]:.1f} s after "
          f"{train.time[pause] - train.time[0]:.0f} s:")
    parts = (("train, before the pause", lambda t: t <= train.time[pause]),
             ("train, after it", lambda t: train.time[pause] < t <= train.time[-1]),
             ("val", lambda t: t > train.time[-1]))
    for name, inside in parts:
        chosen = [(label, turn) for label, t, turn in turns if inside(t)]
        if chosen:
            degrees = np.degrees([turn for _, turn in chosen])
            print(f"  {name}: {len(chosen)} patterns, mean {degrees.mean():+.2f}, from {degrees.min():+.1f} to "
                  f"{degrees.max():+.1f}: " + ", ".join(f"{label} {d:+.1f}" for (label, _), d in zip(chosen, degrees,
                                                                                                      strict=True)))
        else:
            print(f"  {name}: no pattern")


if __name__ == "__main__":
    main()
