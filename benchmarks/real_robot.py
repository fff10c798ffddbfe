"""The real robot's targets (issue: a real robot): fit on a recording, replay another, print a table.

    python benchmarks/real_robot.py                      # the shared FTDCR v4 recording
    python benchmarks/real_robot.py --robot R.json --train T.csv --validate V.csv
    python benchmarks/real_robot.py --fit GROUPS         # other parameter groups (tdcr fit's --fit)
    python benchmarks/real_robot.py --gravity=GX,GY,GZ --density RHO   # the robot in gravity (base frame)

Rows: the validation file's RMSE (aligned: the mean error over the file removed; plain), the fit's
time, and the replay's speed (rows/s on every core, each of 5 runs; the train file, with the fitted
friction and, for comparison, without it); the validation error without its worst pattern.
Figures depend on the machine: it is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import RobotFileError, load_robot, read_recording  # noqa: E402
from tdcr.search.fit import BUDGET, errors, fit  # noqa: E402

SHARED = ROOT.parent / "shared" / "real_robot" / "ftdcr_v4"
TARGETS = {"val aligned RMSE, mm": ("<=", 6.5), "val plain RMSE, mm": ("<=", 8.0), "fit, s": ("<=", 300.0),
           "replay, rows/s": (">=", 2000.0)}


def add_recording_arguments(parser: argparse.ArgumentParser, *, robot: str, help: str | None = None) -> None:
    """``--robot`` (default ``examples/ROBOT``), ``--train`` and ``--validate`` (default: the shared
    FTDCR v4 recording's files): the files every real-robot benchmark reads."""
    parser.add_argument("--robot", default=str(ROOT / "examples" / robot), help=help)
    parser.add_argument("--train", default=str(SHARED / "train.csv"))
    parser.add_argument("--validate", default=str(SHARED / "val.csv"))


def add_load_arguments(parser: argparse.ArgumentParser) -> None:
    """``--gravity`` and ``--density``: the robot file's loads set from the command line (also
    ``real_robot_floor.py``'s)."""
    parser.add_argument("--gravity", default=None, help="GX,GY,GZ m/s^2 in the robot's base frame: fit and replay "
                        "under it (the robot file's design then carries it, with --density)")
    parser.add_argument("--density", type=float, default=None, help="with --gravity: the rod's effective density")


def robot_under(path: str, args: argparse.Namespace):
    """The robot file at ``path``, with ``args``' gravity and density (:func:`add_load_arguments`)."""
    data = json.loads(Path(path).read_text())
    if args.gravity:
        data["design"] |= {"gravity": [float(g) for g in args.gravity.split(",")], "density": args.density}
    return load_robot(data)


def _rates(robot, recording, repeats: int = 5) -> np.ndarray:
    """Rows/s of ``repeats`` replays of the recording's commands (with its times: the lag too)."""
    replay(robot, recording.commands[:20])  # compiled
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        replay(robot, recording.commands, time=recording.time)
        seconds.append(time.perf_counter() - start)
    return len(recording.time) / np.array(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4.json")
    parser.add_argument("--budget", type=float, default=BUDGET, help="the fit's search budget, s")
    parser.add_argument("--out", default=None, help="write the fitted robot file here")
    parser.add_argument("--fit", default=None, help="the groups fitted (tdcr fit's --fit; default: its defaults)")
    add_load_arguments(parser)
    parser.add_argument("--repeats", type=int, default=5, help="replays timed, each way")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    try:  # an unseen robot's files: their problems named, as tdcr fit names them (exit 2)
        robot = robot_under(args.robot, args)
        train = read_recording(args.train, robot)
        val = read_recording(args.validate, robot)
        start = time.perf_counter()
        result = fit(robot, train, validate=val, budget=args.budget, groups=args.fit and tuple(args.fit.split(",")))
    except (RobotFileError, OSError, ValueError) as exc:
        parser.error(str(exc))
    fit_seconds = time.perf_counter() - start
    if args.out:
        result.robot.save(args.out)
    fitted = result.robot
    rates = _rates(fitted, train, args.repeats)
    frictionless = replace(fitted, design=fitted.design.replace(friction=np.zeros(fitted.design.offset.shape)))
    rates_frictionless = _rates(frictionless, train, args.repeats)
    start_errors = errors(replay(robot, val.commands, time=val.time), val)
    print(f"\nfit: {result.solves} replays of {len(train.time)} rows; train RMSE {result.train.rmse:.2f} mm, aligned "
          f"{result.train.aligned:.2f} mm (start {result.initial.rmse:.2f} / {result.initial.aligned:.2f})")
    if result.load_rounds:
        print("under loads, the loaded train RMSE after each round kept (the first fitted without them), mm: "
              + ", ".join(f"{e.rmse:.2f}" for e in result.load_rounds))
    for p in result.parameters:
        print(f"  {p.name:18s} {p.value:12.5g} +- {p.stderr:.2g} {p.unit}")
    rows = {"val aligned RMSE, mm": result.validate.aligned, "val plain RMSE, mm": result.validate.rmse,
            "fit, s": fit_seconds, "replay, rows/s": rates.max()}
    print("\n| quantity | measured | target | met |\n|---|---|---|---|")
    for name, value in rows.items():
        op, target = TARGETS[name]
        met = value <= target if op == "<=" else value >= target
        print(f"| {name} | {value:.2f} | {op} {target:g} | {'yes' if met else 'NO'} |")
    print(f"| val max error, mm | {result.validate.max:.2f} | | |")
    print(f"| val before the fit (robot file as given), aligned / plain mm | {start_errors.aligned:.2f} / "
          f"{start_errors.rmse:.2f} | | |")
    print(f"| replay, rows/s, each of {len(rates)} runs | {', '.join(f'{r:.0f}' for r in rates)} | | |")
    print(f"| replay without friction, rows/s, each run | {', '.join(f'{r:.0f}' for r in rates_frictionless)} | | |")
    print(f"| rows not converged (train, val) | {result.train.failed}, {result.validate.failed} | | |")
    worst = sorted(result.validate.per_pattern.items(), key=lambda kv: -kv[1])[:5]
    if not worst:  # a recording without pattern labels (the robot file names no label_column)
        return
    print("\nval patterns, aligned RMSE mm (worst 5): " + ", ".join(f"{k} {v:.2f}" for k, v in worst))
    keep = np.array([worst[0][0] not in str(label) for label in val.labels])
    rest = errors(result.validate_replay.take(keep), val.take(keep))
    print(f"val without {worst[0][0]}: aligned {rest.aligned:.2f} mm, plain {rest.rmse:.2f} mm "
          f"({int(keep.sum())} rows)")


if __name__ == "__main__":
    main()
