"""What the error bound costs one design over loopback: /predict (every answer bounded) against
/predict with a tolerance and /exact, interleaved in one run (prints a table).

    python benchmarks/bound_latency.py [--requests 300]

A real ``tdcr serve`` process answers a synchronous httpx client on the same machine, one request
at a time, a different Table I design (seeded) each round; each round sends the design to every
row in turn, so drift hits the rows alike.  42 points.  The graph time of the default operator
and of its companion (the score of its bound) at one design, ``Surrogate.predict`` in-process,
is printed below the table.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import httpx
import numpy as np
from exact_latency import design_json  # benchmarks/ is the script's folder
from loaded_operators import seconds

from service.process import ROOT, ServerProcess
from tdcr.robot.design_space import sample_designs
from tdcr.surrogates.runtime import Surrogate

ROWS = {"/predict (bound on every answer)": ("/predict", {}),
        "/predict, tolerance 0.01": ("/predict", {"tolerance": 0.01}),
        "/predict, tolerance 0.001": ("/predict", {"tolerance": 0.001}),
        "/exact": ("/exact", {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=300)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    feats = sample_designs(args.requests + 20, seed=8).features()
    times: dict[str, list[float]] = {label: [] for label in ROWS}
    exact_answers = 0
    with ServerProcess(ROOT / "models", grpc=False) as server, httpx.Client(base_url=server.url, timeout=60) as client:
        model = client.get("/models").json()["default_model"]
        for k, f in enumerate(feats):
            for label, (route, extra) in ROWS.items():
                body = {"designs": [design_json(f, False)], "points": 42} | extra
                started = time.perf_counter()
                r = client.post(route, json=body)
                elapsed = time.perf_counter() - started
                r.raise_for_status()
                if k >= 20:  # after a warm-up
                    times[label].append(1e3 * elapsed)
                    if extra.get("tolerance") == 0.001:
                        exact_answers += r.json()["results"][0]["source"] == "exact"
    print(f"| route ({model}) | requests | p50 (ms) | p90 (ms) | p99 (ms) |\n|---|---:|---:|---:|---:|")
    for label, ms in times.items():
        p50, p90, p99 = np.percentile(ms, [50, 90, 99])
        print(f"| {label} | {len(ms)} | {p50:.2f} | {p90:.2f} | {p99:.2f} |")
    print(f"\nat tolerance 0.001 the solver answered {exact_answers} of {args.requests} designs")
    op = Surrogate.shipped(model)
    one, grid = feats[:1], np.linspace(0.0, 1.0, 42)
    plain = seconds(lambda: op.predict(one, grid), 200)
    companion = op.companion()
    theirs = seconds(lambda: companion.predict(one, grid, pose=False, check=False), 200) if companion else 0.0
    print(f"in-process, one design: {model} {1e3 * plain:.2f} ms, its companion "
          f"{companion.name if companion else '-'} {1e3 * theirs:.2f} ms")


if __name__ == "__main__":
    main()
