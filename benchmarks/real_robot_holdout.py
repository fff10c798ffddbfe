"""A fit choice judged on train alone: fit on half of a recording's patterns, score the other half.

    python benchmarks/real_robot_holdout.py                         # tendon_angle, the shared FTDCR v4 train.csv
    python benchmarks/real_robot_holdout.py --group tendon_offset --robot R.json --train T.csv
    python benchmarks/real_robot_holdout.py --split halves
    python benchmarks/real_robot_holdout.py --group creep --split time   # the first half fitted, the second scored
    python benchmarks/real_robot_holdout.py --prior tendon_angle=0.5   # a prior judged instead of a group
    python benchmarks/real_robot_holdout.py --loss soft_l1             # a loss judged against the default
    python benchmarks/real_robot_holdout.py --f-scale 2.5,10           # the loss's scale (mm) judged

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
(at the default ``f_scale``).  With ``--f-scale MM[,MM...]`` they are the default fit and one under
the loss (``--loss``, else the default one) at each of those scales.  No validation file is read,
so a choice made on these figures has not seen it.  The folds are split in time, so the command
history (each tendon's motion) restarts where a fold resumes.
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
from tdcr.search.fit import (  # noqa: E402
    DEFAULT_GROUPS,
    F_SCALE,
    LOSS,
    LOSSES,
    PRIOR,
    check_f_scale,
    fit,
    format_prior,
    parse_prior,
)

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


def _f_scales(text: str) -> tuple[float, ...]:
    """``--f-scale``'s ``MM[,MM...]`` (argparse exits 2 with the reason)."""
    try:
        scales = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"numbers of mm separated by commas, got {text!r}") from None
    for scale in scales:
        if (problem := check_f_scale(scale)) is not None:
            raise argparse.ArgumentTypeError(problem)
    return scales


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
    parser.add_argument("--f-scale", type=_f_scales, default=None,
                        help=f"judge the loss's scale instead: MM[,MM...], against {F_SCALE:g} mm")
    args = parser.parse_args()
    if args.prior and (args.loss or args.f_scale):
        parser.error("--prior with --loss or --f-scale: judge one at a time")
    if args.f_scale and args.loss == "linear":
        parser.error("--f-scale with --loss linear: plain least squares has no scale")
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
    default = (f"loss {LOSS} at {F_SCALE:g} mm", DEFAULT_GROUPS, PRIOR, LOSS, F_SCALE)
    if args.prior:
        named = format_prior(args.prior)
        choices = (("no prior", DEFAULT_GROUPS, None, LOSS, F_SCALE),
                   (f"prior {named}", DEFAULT_GROUPS, args.prior, LOSS, F_SCALE))
    elif args.f_scale:
        loss = args.loss or LOSS
        choices = (default, *((f"loss {loss} at {scale:g} mm", DEFAULT_GROUPS, PRIOR, loss, scale)
                              for scale in args.f_scale))
    elif args.loss:
        choices = (default, (f"loss {args.loss}", DEFAULT_GROUPS, PRIOR, args.loss, F_SCALE))
    else:
        without = tuple(g for g in DEFAULT_GROUPS if g != args.group)
        choices = ((f"without {args.group}", without, PRIOR, LOSS, F_SCALE),
                   (f"with {args.group}", without + (args.group,), PRIOR, LOSS, F_SCALE))
    print("\n| fitted fold | groups | rows fitted / held out | fitted RMSE, mm | held-out aligned, mm "
          "| held-out plain, mm | fit, s |\n|---|---|---|---|---|---|---|")
    for k in (0,) if args.split == "time" else (0, 1):  # in time: the later half is never fitted
        fitted, held_out = recording.take(fold == k), recording.take(fold != k)
        for name, groups, prior, loss, f_scale in choices:
            start = time.perf_counter()
            result = fit(robot, fitted, validate=held_out, groups=groups, prior=prior, loss=loss, f_scale=f_scale)
            print(f"| {k} | {name} | {len(fitted.time)} / {len(held_out.time)} | {result.train.rmse:.2f} | "
                  f"{result.validate.aligned:.2f} | {result.validate.rmse:.2f} | {time.perf_counter() - start:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
