"""The shipped error bounds and tolerances against the targets of issue #25, in one run on one machine.

    python benchmarks/error_bounds.py [--test 10000] [--ood 1000] [--ood-loaded 250] [--plot docs/error_bounds.png]

Held-out designs used for neither training (seeds 0 and 24) nor calibration (the seed in each
manifest calibration, 25): ``--test`` Table I designs (seed 4250), the loaded operators' in their
trained load space (``TRAINING_LOADS``).  Truth: the exact solver (``tdcr.physics.solve``, default
step; so an answer the guard sent to the solver counts as exact).  For every calibrated operator:

* coverage of ``Surrogate.error_bound`` (the shipped 99 % bound): overall, and the worst of its
  bending-angle bins (the calibration set's deciles);
* ``Surrogate.predict(..., tolerance=t)`` for t = 0.01 and 0.001: the share that fell back to the
  exact solver, the share of all answers within t, the worst answer;
* out of distribution, Table I widened by 20 %: the paper's OOD bins (every parameter at
  high (1 + p), p in the five bins up to +20 %; ``--ood`` designs over them) and every parameter
  outside its range in a random direction by up to 20 % of its width (``--ood`` designs; for the
  loaded operators ``--ood-loaded`` of each, in their load space: the exact loaded solver takes
  about 0.1 s for one of these extreme rods): the share within t and the share that fell back;
* at 1,000 designs and t = 0.01, designs/s guarded against plain ``Surrogate.predict`` (best of 5,
  same run).

The reliability diagram (``--plot``): observed coverage against nominal level (0.5-0.995; each
level's quantiles refitted on the recorded calibration set), overall and per bin.
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np
from loaded_operators import seconds  # best of n (benchmarks/ is the script's folder)

from service.process import ROOT
from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.surrogates.bounds import bending_angle, calibration_grid
from tdcr.surrogates.runtime import Surrogate, load_manifest, takes_loads
from training.operators.calibrate import SCORES, fit, measure

TOLERANCES = (0.01, 0.001)
LEVELS = (0.5, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995)
TEST_SEED, OOD_SEED = 4250, 4251


def ood_sets(n: int, loads_space) -> dict[str, tuple]:
    """The two OOD sets: designs and their loads (the trained space for a loaded operator)."""
    per_bin = max(1, n // len(design_space.OOD_BINS))
    paper = design_space.DesignBatch.from_features(np.concatenate([
        design_space.sample_ood_designs(per_bin, b, seed=OOD_SEED + k).features()
        for k, b in enumerate(design_space.OOD_BINS)]))
    outside = design_space.sample_outside_designs(n, seed=OOD_SEED)
    out = {}
    for label, designs in (("paper's OOD bins", paper), ("outside, random direction", outside)):
        loads = None if loads_space is None else loads_space.sample(designs.n_designs, seed=OOD_SEED)
        out[label] = (designs, loads)
    return out


def served(op: Surrogate, designs, loads, truth, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Errors against ``truth`` and sources of the guarded answers (converged truth only)."""
    ok = truth.converged
    matrix = None if loads is None else loads.matrix(designs.n_designs)
    out = op.predict(designs.features(), calibration_grid(), loads=matrix, pose=False, tolerance=tolerance,
                     check=False)
    return relative_l2(out["tendons"][ok], truth.tendons[ok]), out["source"][ok]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--test", type=int, default=10_000)
    parser.add_argument("--ood", type=int, default=1000)
    parser.add_argument("--ood-loaded", type=int, default=250)
    parser.add_argument("--plot", default=None, help="write the reliability diagram here (PNG)")
    parser.add_argument("--models-dir", default=str(ROOT / "models"))
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores\n")
    manifest = load_manifest(args.models_dir)
    calibrated = sorted(n for n, e in manifest["models"].items() if "calibration" in e)
    names = sorted(manifest["models"])
    table, throughput, ood_rows, reliability = [], [], [], {}
    grid = calibration_grid()
    for loaded in (False, True):
        group = [n for n in calibrated if takes_loads(manifest["models"][n]) == loaded]
        if not group:
            continue
        space = design_space.TRAINING_LOADS if loaded else None
        record = manifest["models"][group[0]]["calibration"]["calibration_set"]
        cal_designs = design_space.sample_designs(record["designs"], seed=record["seed"])
        cal = measure(args.models_dir, names, cal_designs,
                      None if space is None else space.sample(record["designs"], seed=record["seed"]))
        designs = design_space.sample_designs(args.test, seed=TEST_SEED)
        loads = None if space is None else space.sample(args.test, seed=TEST_SEED)
        test = measure(args.models_dir, names, designs, loads)
        truth = solve(designs, grid, loads=loads, workers=0)
        oods = {label: (d, ld, solve(d, grid, loads=ld, workers=0))
                for label, (d, ld) in ood_sets(args.ood_loaded if loaded else args.ood, space).items()}
        print(f"{'loaded' if loaded else 'load-free'}: calibration {len(cal.features)} designs "
              f"(seed {record['seed']}), test {len(test.features)} converged of {args.test} (seed {TEST_SEED})",
              flush=True)
        theta_cal = bending_angle(cal.features)
        for name in group:
            op = Surrogate.load(args.models_dir, name, manifest=manifest)
            err = test.error(name)
            bound = op.error_bound(test.features, loads=test.loads if op.takes_loads else None)
            bins = op.calibration.bins(test.features)
            covered = err <= bound
            per_bin = [covered[bins == k].mean() for k in range(len(op.calibration.quantiles)) if (bins == k).any()]
            row = [name, covered.mean(), min(per_bin)]
            for tolerance in TOLERANCES:
                e, source = served(op, designs, loads, truth, tolerance)
                row += [source.mean(), np.mean(e <= tolerance), e.max()]
            table.append(row)
            for label, (d, ld, t) in oods.items():
                cells = []
                for tolerance in TOLERANCES:
                    e, source = served(op, d, ld, t, tolerance)
                    cells += [np.mean(e <= tolerance), source.mean()]
                ood_rows.append([name, label, int(t.converged.sum()), *cells])
            f1000 = designs.features()[:1000]
            m1000 = None if loads is None else loads.matrix(args.test)[:1000]
            plain = seconds(lambda op=op, f=f1000, m=m1000: op.predict(f, grid, loads=m, pose=False), 5)
            guarded = seconds(lambda op=op, f=f1000, m=m1000: op.predict(f, grid, loads=m, pose=False,
                                                                        tolerance=0.01), 5)
            throughput.append([name, 1000 / plain, 1000 / guarded, plain / guarded])
            # the reliability diagram: each level refitted on the recorded calibration set
            score = SCORES[name]
            s_cal, s_test = cal.score(name, score), test.score(name, score)
            edges, q99 = fit(cal.error(name), s_cal, theta_cal, level=0.99)
            assert np.allclose(q99, op.calibration.quantiles, rtol=1e-9), f"{name}: calibration not reproduced"
            curves = {"overall": []} | {f"bin {k}": [] for k in range(len(q99))}
            for level in LEVELS:
                _, q = fit(cal.error(name), s_cal, theta_cal, level=level)
                b = q[np.maximum(bins, 0)] * ((1.0 if s_test is None else s_test) + op.calibration.record["floor"])
                hit = (err <= b) & (bins >= 0)
                curves["overall"].append(hit.mean())
                for k in range(len(q99)):
                    curves[f"bin {k}"].append(hit[bins == k].mean())
            reliability[name] = curves
            print(f"  {name}: done", flush=True)

    print("\n| operator | coverage | worst bin | fallback @0.01 | within 0.01 | worst | fallback @0.001 | "
          "within 0.001 | worst |\n|---|" + "---:|" * 8)
    for name, cov, worst, *cells in table:
        print(f"| {name} | {cov:.4f} | {worst:.4f} | " + " | ".join(
            f"{c:.4f}" if i % 3 != 2 else f"{c:.3g}" for i, c in enumerate(cells)) + " |")
    print("\nOut of distribution (Table I widened by 20 %; converged truth only):\n\n| operator | set | designs | "
          "within 0.01 | fallback @0.01 | within 0.001 | fallback @0.001 |\n|---|---|" + "---:|" * 5)
    for name, label, n, *cells in ood_rows:
        print(f"| {name} | {label} | {n} | " + " | ".join(f"{c:.4f}" for c in cells) + " |")
    print("\nAt 1,000 designs, tolerance 0.01 (best of 5, same run):\n\n| operator | plain designs/s | "
          "guarded designs/s | guarded / plain |\n|---|---:|---:|---:|")
    for name, plain, guarded, ratio in throughput:
        print(f"| {name} | {plain:,.0f} | {guarded:,.0f} | {ratio:.2f} |")
    print("\nReliability (observed coverage at nominal levels " + ", ".join(map(str, LEVELS)) + "):\n")
    for name, curves in reliability.items():
        worst = [min(curves[k][i] for k in curves if k != "overall") for i in range(len(LEVELS))]
        print(f"| {name} | overall " + " ".join(f"{c:.3f}" for c in curves["overall"]) + " | worst bin "
              + " ".join(f"{c:.3f}" for c in worst) + " |")
    if args.plot:
        plot(reliability, args.plot)
        print(f"\nwrote {args.plot}")


def plot(reliability: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(11, 7), sharex=True, sharey=True)
    for ax, (name, curves) in zip(axes.flat, reliability.items(), strict=False):
        ax.plot([0.45, 1.0], [0.45, 1.0], color="0.6", lw=1, ls="--", label="ideal")
        for key, values in curves.items():
            if key != "overall":
                ax.plot(LEVELS, values, color="tab:blue", lw=0.7, alpha=0.45)
        ax.plot(LEVELS, curves["overall"], color="black", lw=2, marker="o", ms=3, label="overall")
        ax.plot([], [], color="tab:blue", lw=0.7, alpha=0.6, label="each bending-angle bin")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("nominal level")
    for ax in axes[:, 0]:
        ax.set_ylabel("observed coverage (held out)")
    axes.flat[0].legend(fontsize=8, loc="upper left")
    fig.suptitle("Reliability of the calibrated error bounds (benchmarks/error_bounds.py)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
