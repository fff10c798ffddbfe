"""A fit choice judged on train alone: fit on half of a recording's patterns, score the other half.

    python benchmarks/real_robot_holdout.py                         # tendon_angle, the shared FTDCR v4 train.csv
    python benchmarks/real_robot_holdout.py --group tendon_offset --robot R.json --train T.csv
    python benchmarks/real_robot_holdout.py --split halves
    python benchmarks/real_robot_holdout.py --group creep --split time   # the first half fitted, the second scored
    python benchmarks/real_robot_holdout.py --prior tendon_angle=0.5   # a prior judged instead of a group
    python benchmarks/real_robot_holdout.py --loss soft_l1             # a loss judged against the default

Two folds: ``--split patterns`` deals the patterns (labels, a ``_hold`` row with its pattern)
alternately into them, so a pattern is either fitted or scored (but a single-tendon sweep then
informs only one fold); ``--split halves`` puts each pattern's first half of rows in one and its
second half in the other (every pattern in both, neighbouring rows apart); ``--split time`` fits the
recording's first half in time and scores its second half only, which goes on from the state the first
left (the tendons' creep, eq. CREEP, as a later recording goes on from train's).  Each fold is fitted
with the default groups with and without ``--group`` (with it added when it is not a default) and
scores the other fold: aligned and plain RMSE, mm (:func:`tdcr.search.fit.errors`).  With
``--prior GROUP=WIDTH[,...]`` the two fits are the default groups without any prior and with that
one (:func:`tdcr.search.fit.fit`'s ``prior``, widths in search units); else both take the default
prior.  With ``--loss LOSS`` they are the default groups under the default loss and under that one
(at the default ``f_scale``).  No validation file is read, so a choice made on these figures has not
seen it.  The folds are split in time, so the command history (each tendon's motion) restarts where a fold resumes.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tdcr.robot.real import load_robot, read_recording  # noqa: E402
from tdcr.search.fit import DEFAULT_GROUPS, LOSS, LOSSES, PRIOR, fit, format_prior, parse_prior  # noqa: E402

SHARED = ROOT.parent / "shared" / "real_robot" / "ftdcr_v4"


def _prior(text: str) -> dict[str, float]:
    """``--prior``'s ``GROUP=WIDTH[,GROUP=WIDTH...]`` (argparse exits 2 with the reason)."""
    try:
        prior = parse_prior(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if prior is None:
        raise argparse.ArgumentTypeError("judge a prior: GROUP=WIDTH[,GROUP=WIDTH...], not none")
    return prior


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robot", default=str(ROOT / "examples" / "ftdcr_v4.json"))
    parser.add_argument("--train", default=str(SHARED / "train.csv"))
    parser.add_argument("--group", default="tendon_angle", help="the group judged")
    parser.add_argument("--split", choices=("patterns", "halves", "time"), default="patterns",
                        help="how the folds are made")
    parser.add_argument("--prior", type=_prior, default=None,
                        help="judge a prior instead: GROUP=WIDTH[,GROUP=WIDTH...]")
    parser.add_argument("--loss", choices=LOSSES, default=None, help=f"judge a loss instead, against {LOSS}")
    args = parser.parse_args()
    if args.prior and args.loss:
        parser.error("--prior and --loss: judge one at a time")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    robot = load_robot(args.robot)
    recording = read_recording(args.train, robot)
    patterns = np.array([re.sub(r"_hold$", "", str(label)) for label in recording.labels])
    if args.split == "patterns":
        fold_of = {p: k % 2 for k, p in enumerate(dict.fromkeys(patterns))}
        fold = np.array([fold_of[p] for p in patterns])
    elif args.split == "time":
        fold = (np.arange(len(patterns)) >= len(patterns) // 2).astype(int)
    else:
        fold = np.zeros(len(patterns), dtype=int)
        for p in dict.fromkeys(patterns):
            rows = np.nonzero(patterns == p)[0]
            fold[rows[len(rows) // 2:]] = 1
    print(f"split: {args.split}")
    if args.prior:
        named = format_prior(args.prior)
        choices = (("no prior", DEFAULT_GROUPS, None, LOSS), (f"prior {named}", DEFAULT_GROUPS, args.prior, LOSS))
    elif args.loss:
        choices = ((f"loss {LOSS}", DEFAULT_GROUPS, PRIOR, LOSS),
                   (f"loss {args.loss}", DEFAULT_GROUPS, PRIOR, args.loss))
    else:
        without = tuple(g for g in DEFAULT_GROUPS if g != args.group)
        choices = ((f"without {args.group}", without, PRIOR, LOSS),
                   (f"with {args.group}", without + (args.group,), PRIOR, LOSS))
    print("\n| fitted fold | groups | rows fitted / held out | fitted RMSE, mm | held-out aligned, mm "
          "| held-out plain, mm | fit, s |\n|---|---|---|---|---|---|---|")
    for k in (0,) if args.split == "time" else (0, 1):  # in time: the later half is never fitted
        fitted, held_out = recording.take(fold == k), recording.take(fold != k)
        for name, groups, prior, loss in choices:
            start = time.perf_counter()
            result = fit(robot, fitted, validate=held_out, groups=groups, prior=prior, loss=loss)
            print(f"| {k} | {name} | {len(fitted.time)} / {len(held_out.time)} | {result.train.rmse:.2f} | "
                  f"{result.validate.aligned:.2f} | {result.validate.rmse:.2f} | {time.perf_counter() - start:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
