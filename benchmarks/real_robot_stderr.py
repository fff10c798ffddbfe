"""Do the fit's standard errors say how far its values move with the data?  Two fits on halves of train.

    python benchmarks/real_robot_stderr.py                  # FTDCR v4, the shared recording's train
    python benchmarks/real_robot_stderr.py --robot examples/ftdcr_v6.json --train T.csv

Train's stretches (:func:`tdcr.search.fit.clusters`: its patterns) are dealt alternately into two
halves, and the robot file is fitted on each half and on all of train, with ``tdcr fit``'s defaults.
Were a parameter's standard errors right, the halves' difference over sqrt(se_A^2 + se_B^2) would be
a draw of N(0, 1): RMS 1, median |z| 0.67, |z| > 2 in 5 % of them.  Both kinds the fit reports are
judged so: ``stderr`` (the cluster-robust sandwich over the patterns) and ``stderr_independent``
(train's residuals taken as independent).  A value searched as a logarithm (E, stiffness, friction,
...) is compared in it: its difference and standard error relative.  A parameter whose standard
error is not finite in a half is left out.  Last, the pairs of parameters whose estimates correlate
strongly in the fit on all of train (its report's ``correlations``).

docs/real_robot.md ("Standard errors over the sweeps") gives the figures.  Figures depend on the
machine: it is printed.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from real_robot import add_recording_arguments  # noqa: E402  (this folder's)

from tdcr.robot.real import RobotFileError, load_robot, read_recording  # noqa: E402
from tdcr.search.fit import CORRELATION_SHOWN, LOG_SEARCHED, clusters, fit  # noqa: E402

#: The standard errors judged: the fit's Parameter attribute -> its name here.
KINDS = {"stderr": "clustered", "stderr_independent": "independent"}


def _searched(p) -> tuple[float, dict[str, float]]:
    """A parameter's value and standard errors in the search's terms (logs, relative errors for
    :data:`LOG_SEARCHED`)."""
    if p.group in LOG_SEARCHED:
        return math.log(p.value), {k: getattr(p, k) / p.value for k in KINDS}
    return p.value, {k: getattr(p, k) for k in KINDS}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_recording_arguments(parser, robot="ftdcr_v4.json")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    try:  # an unseen robot's files: their problems named, as tdcr fit names them (exit 2)
        robot = load_robot(args.robot)
        train = read_recording(args.train, robot)
    except (RobotFileError, OSError, ValueError) as exc:
        parser.error(str(exc))
    stretch = clusters(train)
    order = list(dict.fromkeys(stretch.tolist()))  # in the recording's order
    if len(order) < 4:
        parser.error(f"{args.train}: {len(order)} patterns (or runs between pauses); halves need at least 4")
    half = np.array([order.index(s) % 2 for s in stretch])
    results = {}
    for name, keep in (("A", half == 0), ("B", half == 1), ("all", np.ones(len(half), dtype=bool))):
        start = time.perf_counter()
        results[name] = fit(robot, train.take(keep))
        r = results[name]
        print(f"fit on {name}: {int(keep.sum())} rows, {r.stderr_clusters} clusters, {len(r.parameters)} parameters, "
              f"train aligned {r.train.aligned:.2f} mm, {time.perf_counter() - start:.0f} s", flush=True)
    print("\n| parameter | value (all) | stderr | independent | A - B | z | z independent |")
    print("|---|---|---|---|---|---|---|")
    z = {k: [] for k in KINDS}
    for a, b, p in zip(*(results[n].parameters for n in ("A", "B", "all")), strict=True):
        (va, sa), (vb, sb) = _searched(a), _searched(b)
        row = {}
        for k in KINDS:
            spread = math.hypot(sa[k], sb[k])
            row[k] = (va - vb) / spread if math.isfinite(spread) and spread > 0 else math.nan
            if math.isfinite(row[k]):
                z[k].append(row[k])
        log = " (log)" if p.group in LOG_SEARCHED else ""
        print(f"| {p.name} | {p.value:.4g} {p.unit} | {p.stderr:.2g} | {p.stderr_independent:.2g} | {va - vb:.3g}{log}"
              f" | {row['stderr']:.2f} | {row['stderr_independent']:.2f} |")
    print("\n| standard error | parameters | RMS z (1) | median abs z (0.67) | abs z > 2 (5 %) |")
    print("|---|---|---|---|---|")
    for k, name in KINDS.items():
        v = np.abs(np.array(z[k]))
        print(f"| {name} | {v.size} | {np.sqrt(np.mean(v**2)):.2f} | {np.median(v):.2f} | {np.mean(v > 2):.0%} |")
    print(f"\nthe fit on all of train, pairs correlating by {CORRELATION_SHOWN} or more: "
          + (", ".join(f"{a} / {b} {r:+.3f}" for a, b, r in results["all"].correlations) or "none"))


if __name__ == "__main__":
    main()
