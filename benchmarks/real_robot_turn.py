"""Does the robot turn on its mount during a session?  Registration-only models on a fitted robot.

    python benchmarks/real_robot_turn.py                      # the shipped FTDCR v4 fit, the shared recording
    python benchmarks/real_robot_turn.py --robot FITTED.json --train T.csv --validate V.csv

The fitted robot file (what ``tdcr fit`` writes; its drive zeros moved back by its report's
``crept_m``: the robot as train found it, :meth:`tdcr.robot.real.Robot.after`) replays train and then
val in time order (val's times shifted to follow train's, as ``real_robot_floor.joined`` does), and
its physics is held.  Least squares on train's
points then fits the registration again (base position and rotation, marker; the lag held) with
each model of a turn, and val is scored (aligned / plain RMSE, mm; :func:`tdcr.search.fit.errors`):

- none: the registration alone;
- a constant rate of turn about the base's axis (rad/s) from train's first row: the measured point
  b + Rot(r) Rz(w (t - t_0)) (p + R marker), seen through the file's lag (eq. LAG);
- a constant rate about all three of the base's axes, Rot(w (t - t_0));
- a drift of the base position instead, b + v (t - t_0);
- a step of the turn about the base's axis at train's longest pause, val going on from the part
  after it;
- forward within train: the constant rate about the axis fitted on train's first half and scored on
  its second half, against the registration alone there.

docs/real_robot.md ("The bend's plane turns during the session") gives the figures.  Figures depend
on the machine: it is printed.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from real_robot import add_recording_arguments  # noqa: E402  (this folder's)
from real_robot_floor import joined  # noqa: E402

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import load_robot, read_recording, rotation_matrix, settle  # noqa: E402
from tdcr.search.fit import errors  # noqa: E402

#: Each model's extra parameters: (count, their scale in the search: rad/s or m/s).
MODELS = {"none": (0, 1.0), "rate about the base's axis": (1, 1e-4), "rate about all three axes": (3, 1e-4),
          "drift of the base position": (3, 1e-6), "step at the longest pause": (1, 0.01)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4_fitted.json")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    fitted = load_robot(args.robot)
    robot = fitted.after(-np.asarray(fitted.extra.get("fitted", {}).get("crept_m", np.zeros(fitted.n_tendons))))
    train, val = read_recording(args.train, robot), read_recording(args.validate, robot)
    both = joined(train, val)
    answer = replay(robot, both.commands, time=both.time)
    n, m = len(train.time), robot.measurement
    elapsed = both.time - both.time[0]
    pause = int(np.argmax(np.diff(train.time)))
    later = (np.arange(len(both.time)) > pause).astype(float)  # 1 after train's longest pause (val too)
    tips = answer.tip_position  # (T, 3) m, base frame

    def points(x: np.ndarray, model: str) -> np.ndarray:
        """The measured points (T, 3) m of registration ``x`` (base position, rotation, marker, extras)."""
        local = tips + np.einsum("tij,j->ti", answer.tip_rotation, x[6:9])
        extra, shift = x[9:], 0.0
        turn = {"rate about the base's axis": lambda: np.outer(extra[0] * elapsed, [0.0, 0.0, 1.0]),
                "rate about all three axes": lambda: np.outer(elapsed, extra),
                "step at the longest pause": lambda: np.outer(extra[0] * later, [0.0, 0.0, 1.0])}.get(model)
        if turn is not None:
            local = np.einsum("tij,tj->ti", rotation_matrix(turn()), local)
        if model == "drift of the base position":
            shift = np.outer(elapsed, extra)
        static = x[:3] + shift + local @ rotation_matrix(x[3:6]).T
        return settle(static, both.time, m.time_constant)

    def registered(model: str, rows: np.ndarray) -> np.ndarray:
        count, scale = MODELS[model]
        start = np.concatenate([m.base_position, m.base_rotation, m.marker, np.zeros(count)])
        scored = rows & both.has_measurement
        return least_squares(lambda x: ((points(x, model)[scored] - both.measured[scored]) * 1e3).ravel(), start,
                             x_scale=np.r_[[1e-3] * 3, [1e-2] * 3, [1e-3] * 3, [scale] * count]).x

    def scored(x: np.ndarray, model: str, rows: np.ndarray) -> str:
        e = errors(replace(answer, points=points(x, model)).take(rows), both.take(rows))
        return f"{e.aligned:.2f} / {e.rmse:.2f}"

    in_train, in_val = np.arange(len(both.time)) < n, np.arange(len(both.time)) >= n
    print(f"\n{args.robot} on {n} train and {len(val.time)} val rows; train's longest pause: "
          f"{np.diff(train.time)[pause]:.1f} s, {train.time[pause] - train.time[0]:.0f} s in")
    print("\n| model | its values | train, aligned / plain mm | val, aligned / plain mm |\n|---|---|---|---|")
    for model in MODELS:
        x = registered(model, in_train)
        unit = "rad" if model.startswith("step") else "per 1000 s (rad or m)"
        values = f"{np.array2string(x[9:] * (1.0 if model.startswith('step') else 1e3), precision=4)} {unit}"
        print(f"| {model} | {values if x.size > 9 else ''} | {scored(x, model, in_train)} | "
              f"{scored(x, model, in_val)} |", flush=True)
    first, second = np.arange(len(both.time)) < n // 2, (np.arange(len(both.time)) >= n // 2) & in_train
    print("\nforward within train (train's first half fitted, its second half scored):")
    print("\n| model | its values | second half, aligned / plain mm |\n|---|---|---|")
    for model in ("none", "rate about the base's axis"):
        x = registered(model, first)
        print(f"| {model} | {np.array2string(x[9:] * 1e3, precision=4) if x.size > 9 else ''} | "
              f"{scored(x, model, second)} |")


if __name__ == "__main__":
    main()
