"""Diagnostic (issue: a real robot): can what the physics misses be learned from train?

    python benchmarks/real_robot_residual.py          # the shipped FTDCR v4 fit, the shared recording
    python benchmarks/real_robot_residual.py --robot FITTED.json --train T.csv --validate V.csv

A fitted robot's train residuals (measured minus predicted points, mm) are regressed on features of
its own replay (standardised on train), and the regression is added to its val predictions.  Three
regressors from scikit-learn (the ``design`` extra has it, through crepes): ridge (alpha 1), 10
nearest neighbours (distance-weighted) and a Gaussian process (constant x anisotropic RBF + white
noise, hyperparameters by marginal likelihood, seeded).  Printed: val aligned RMSE per feature set
and regressor (train aligned in brackets for the GP), against the physics alone.  Not a product
feature (docs/real_robot.md, "A second robot").
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from real_robot import add_recording_arguments  # noqa: E402  (this folder's)

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import load_robot, read_recording  # noqa: E402
from tdcr.search.fit import errors  # noqa: E402

#: Each feature set: the replay's values it stacks (tip position mm, tip direction x 100, tensions
#: x 10 N, commands mm, motions x 5), before standardisation.
FEATURES = {
    "predicted tip position": lambda a, rec: a.tip_position * 1e3,
    "tip position and direction": lambda a, rec: np.column_stack([a.tip_position * 1e3, a.tip_rotation[:, :, 2] * 100]),
    "tip position and tensions": lambda a, rec: np.column_stack([a.tip_position * 1e3, a.tension * 10]),
    "tensions": lambda a, rec: a.tension,
    "commands": lambda a, rec: rec.commands * 1e3,
    "tip position and motions": lambda a, rec: np.column_stack([a.tip_position * 1e3, a.motion * 5]),
}


def corrected(answer, recording, correction: np.ndarray) -> float:
    """Aligned RMSE, mm, of ``answer``'s points moved by ``correction`` ``(rows with a measurement, 3)`` mm."""
    points = answer.points.copy()
    points[recording.has_measurement] += correction * 1e-3
    return errors(replace(answer, points=points), recording).aligned


def main() -> None:
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    from sklearn.linear_model import Ridge
    from sklearn.neighbors import KNeighborsRegressor

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4_fitted.json", help="a fitted robot")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    robot = load_robot(args.robot)
    train, val = read_recording(args.train, robot), read_recording(args.validate, robot)
    keep_t, keep_v = train.has_measurement, val.has_measurement
    answers = [replay(robot, rec.commands, time=rec.time) for rec in (train, val)]
    residual_t = (train.measured - answers[0].points)[keep_t] * 1e3  # mm
    print(f"physics alone: val aligned {errors(answers[1], val).aligned:.2f} mm, "
          f"train aligned {errors(answers[0], train).aligned:.2f} mm")
    print("\n| features | ridge | kNN | GP (train) |\n|---|---|---|---|")
    for name, features in FEATURES.items():
        x_t, x_v = features(answers[0], train)[keep_t], features(answers[1], val)[keep_v]
        mean, std = x_t.mean(axis=0), x_t.std(axis=0) + 1e-9
        z_t, z_v = (x_t - mean) / std, (x_v - mean) / std
        kernel = ConstantKernel(10.0) * RBF(np.ones(z_t.shape[1])) + WhiteKernel(4.0)
        cells = []
        for model in (Ridge(alpha=1.0), KNeighborsRegressor(10, weights="distance"),
                      GaussianProcessRegressor(kernel, normalize_y=True, random_state=0)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                model.fit(z_t, residual_t)
            cells.append(f"{corrected(answers[1], val, model.predict(z_v)):.2f}")
        cells[-1] += f" ({corrected(answers[0], train, model.predict(z_t)):.2f})"
        print(f"| {name} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
