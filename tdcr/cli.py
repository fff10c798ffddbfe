"""The ``tdcr`` command line.  Bad input exits with code 2 and a message on stderr."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


class UsageError(Exception):
    """Bad input from the user: reported on stderr with exit code 2."""


def _read_request(path: str):
    from pydantic import ValidationError

    from training.schemas import SolveRequest, format_error_location

    try:
        text = sys.stdin.read() if path == "-" else Path(path).read_text()
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror}") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path}: not valid JSON: {exc}") from None
    try:
        return SolveRequest.model_validate(raw)
    except ValidationError as exc:
        lines = [f"{format_error_location(e['loc']) or 'request'}: {e['msg']}" for e in exc.errors()]
        raise UsageError(f"{path}: invalid request:\n  " + "\n  ".join(lines)) from None


def _cmd_solve(args) -> int:
    from training.exact import solve_designs

    request = _read_request(args.request)
    results = solve_designs(request.designs, request.fractions())
    json.dump({"results": results}, sys.stdout)
    sys.stdout.write("\n")
    return 0


def _cmd_generate(args) -> int:
    from training.dataset import DatasetMismatch, GenerateConfig, generate

    if args.n < 1 or args.shard_size < 1 or args.points < 2:
        raise UsageError("--n and --shard-size must be >= 1 and --points >= 2")
    cfg = GenerateConfig(n=args.n, seed=args.seed, points=args.points, shard_size=args.shard_size)
    try:
        meta = generate(args.out, cfg, workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    except DatasetMismatch as exc:
        raise UsageError(str(exc)) from None
    print(json.dumps({k: meta[k] for k in ("n", "converged", "not_converged", "n_train", "n_test", "last_run")}))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tdcr", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("solve", help="exact equilibria of the designs in a request JSON (Cosserat solver)")
    p.add_argument("request", help="request JSON file, or - for stdin")
    p.set_defaults(func=_cmd_solve)

    p = sub.add_parser("generate", help="generate a solver dataset of Table I designs")
    p.add_argument("--n", type=int, required=True, help="number of designs")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output directory (resumes if it exists)")
    p.add_argument("--points", type=int, default=42, help="equispaced arclengths per design")
    p.add_argument("--shard-size", type=int, default=1000)
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", default=None, help="address of a Dask distributed scheduler")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_generate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"tdcr {args.command}: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `tdcr solve r.json | head`
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"tdcr {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
