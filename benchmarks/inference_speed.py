"""onnxruntime inference time of the shipped models on this machine (prints a Markdown table).

    python benchmarks/inference_speed.py [--models-dir models] [--repeats 5]

Batch sizes 1, 1,000 and 80,000 designs at 42 points; best of ``--repeats``; all cores
(onnxruntime intra-op threads = 0).  Times include the numpy post-processing of
``Surrogate.predict`` (the Kabsch pose fit for tendon models).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.surrogates.runtime import Surrogate


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models-dir", default="models")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    manifest = json.loads((Path(args.models_dir) / "manifest.json").read_text())
    feats = design_space.sample_designs(80_000, seed=123).features()
    fractions = np.linspace(0, 1, 42)
    print(f"{os.cpu_count()} cores; best of {args.repeats}\n")
    print("| model | B = 1 (ms) | B = 1,000 (ms) | B = 80,000 (s) | 80,000 graph only (s) |")
    print("|---|---:|---:|---:|---:|")
    for name in sorted(manifest["models"]):
        model = Surrogate.load(args.models_dir, name)
        model.predict(feats[:10], fractions)  # warm-up
        t1 = best_time(lambda m=model: m.predict(feats[:1], fractions), args.repeats)
        t1k = best_time(lambda m=model: m.predict(feats[:1000], fractions), args.repeats)
        t80 = best_time(lambda m=model: m.predict(feats, fractions), max(1, args.repeats // 2))
        g80 = best_time(lambda m=model: m.run(feats, fractions), max(1, args.repeats // 2))
        print(f"| {name} | {1e3 * t1:.2f} | {1e3 * t1k:.1f} | {t80:.3f} | {g80:.3f} |")


if __name__ == "__main__":
    main()
