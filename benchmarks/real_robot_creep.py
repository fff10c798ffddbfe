"""A prototype, not the product's model: tendons that creep under their tension through a recording.

    python benchmarks/real_robot_creep.py                      # the shared FTDCR v4 recording
    python benchmarks/real_robot_creep.py --robot R.json --train T.csv --validate V.csv --creep 0,3e-7,1e-6

Each tendon (and its drive) lengthens at ``c`` tau_i (m/s per N of its drive-side tension, a series
dashpot of viscosity 1 / c that never recovers), so its pull-in falls behind its command by the creep

    e_i(t_k) = c sum_{j<k} tau_i(t_j) (t_{j+1} - t_j)        (explicit in time: row k sees the rows before)

from the start of the train recording; the validation recording, which the shared ones record right
after train, goes on from train's end.  Every row therefore depends on the tensions of all rows before
it, so each replay here is solved row by row, in order, on one thread (about 650 rows/s: slow, which is
why this is not in :func:`tdcr.replay`), self-consistent: each row's tension comes from its own
equilibrium at the commands minus the creep so far.  For each ``c`` (held, not fitted) the script runs
:func:`tdcr.search.fit.fit` with its default groups on train, every replay inside it (the search's and
the validation's) replaced by this one, and prints train's and val's errors.  ``c`` is chosen by train's
error, never by val's.  The fits of the values given run side by side, one process per core.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared" / "real_robot" / "ftdcr_v4"


def creep_fit(robot_path: str, train_path: str, val_path: str, creep: float) -> dict:
    """The default fit on train with every replay creeping at ``creep`` m/(N s) (see the module)."""
    os.environ["NUMBA_NUM_THREADS"] = "1"  # one process per core
    import tdcr.search.fit as fitting
    from tdcr.physics.replay import replay
    from tdcr.robot.real import load_robot, motions, read_recording

    robot = load_robot(robot_path)
    train, val = read_recording(train_path, robot), read_recording(val_path, robot)
    commands = np.concatenate([train.commands, val.commands])  # (T, N_t) m, in time order
    times = np.concatenate([train.time, val.time])
    motion = motions(commands, robot.actuation.deadband)  # from the commands' history, as replay's
    dt = np.append(np.diff(times), 0.0)  # s to the next row
    n = len(train.time)
    last = {}

    def creep_so_far(fitted, rows: int) -> np.ndarray:
        """Each row's creep ``(rows, N_t)`` m, the rows solved one by one in order."""
        e, out = np.zeros(commands.shape[1]), np.empty((rows, commands.shape[1]))
        for k in range(rows):
            out[k] = e
            tension = replay(fitted, (commands[k] - e)[None], motion=motion[k][None], workers=1).tension[0]
            e = e + creep * tension * dt[k]
        return out

    def creeping(fitted, rows_commands, *, time=None, workers=0, options=fitting.REPLAY_OPTIONS):
        part = slice(0, n) if len(rows_commands) == n else slice(n, None)  # train, or val after train
        assert np.array_equal(rows_commands, commands[part])
        e = creep_so_far(fitted, part.stop or len(commands))[part]
        last["end"] = e[-1]
        return replay(fitted, rows_commands - e, time=time, motion=motion[part], workers=1, options=options)

    start = time.perf_counter()
    with mock.patch.object(fitting, "replay", creeping):
        result = fitting.fit(robot, train, validate=val, progress=False, budget=1e5)
    return {"creep": creep, "train": result.train.aligned, "val": result.validate.aligned,
            "val_plain": result.validate.rmse, "val_max": result.validate.max,
            "creep_end_mm": 1e3 * float(np.max(last["end"])), "seconds": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", default=str(ROOT / "examples" / "ftdcr_v4.json"))
    parser.add_argument("--train", default=str(SHARED / "train.csv"))
    parser.add_argument("--validate", default=str(SHARED / "val.csv"))
    parser.add_argument("--creep", default="0,1e-7,3e-7,1e-6", help="comma-separated c, m/(N s)")
    args = parser.parse_args(argv)
    values = [float(c) for c in args.creep.split(",")]
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; robot {args.robot}")
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        rows = list(pool.map(creep_fit, *zip(*[(args.robot, args.train, args.validate, c) for c in values],
                                              strict=True)))
    print("| creep c, m/(N s) | train aligned, mm | val aligned / plain, mm | val max, mm "
          "| creep at val's end, mm | fit, s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['creep']:g} | {r['train']:.2f} | {r['val']:.2f} / {r['val_plain']:.2f} | {r['val_max']:.1f} "
              f"| {r['creep_end_mm']:.2f} | {r['seconds']:.0f} |")
    best = min(rows, key=lambda r: r["train"])
    print(f"chosen by train: c = {best['creep']:g} -> val {best['val']:.2f} aligned / {best['val_plain']:.2f} plain")


if __name__ == "__main__":
    main()
