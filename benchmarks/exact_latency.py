"""/exact latency over loopback: one design per request, one client at a time (prints a table).

    python benchmarks/exact_latency.py [--requests 300]

A real ``tdcr serve`` process (service.process.ServerProcess) answers a synchronous httpx client
on the same machine.  Rows: a tendon-only Table I design, and the same design under gravity
(horizontal robot, steel density) plus a tip force and moment; 42 points each.  Each request
sends a different design (seeded), so no answer is cached anywhere.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import httpx
import numpy as np

from service.process import ROOT, ServerProcess
from tdcr.robot.design_space import sample_designs

LOADS = {"gravity": [9.81, 0.0, 0.0], "density": 7800.0, "tip_force": [0.0, 0.01, 0.0], "tip_moment": [0.0, 0.0, 0.001]}


def design_json(features: np.ndarray, loaded: bool) -> dict:
    e, r, length = features[:3]
    tendons = [{"offset": float(features[3 + i]), "pitch": float(features[7 + i]), "tension": float(features[11 + i])}
               for i in range(4)]
    return {"E": float(e), "r": float(r), "L": float(length), "tendons": tendons, **(LOADS if loaded else {})}


def measure(client: httpx.Client, loaded: bool, n: int) -> tuple[np.ndarray, int]:
    feats = sample_designs(n + 20, seed=7).features()
    times, converged = [], 0
    for k, f in enumerate(feats):
        body = {"designs": [design_json(f, loaded)], "points": 42}
        t0 = time.perf_counter()
        r = client.post("/exact", json=body)
        dt = time.perf_counter() - t0
        r.raise_for_status()
        if k >= 20:  # the first 20 warm the connection and the solver process
            times.append(dt)
            converged += bool(r.json()["results"][0]["converged"])
    return np.array(times) * 1e3, converged


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=300)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    print("| design | requests | p50 (ms) | p90 (ms) | p99 (ms) | converged |")
    print("|---|---:|---:|---:|---:|---:|")
    with ServerProcess(ROOT / "models", grpc=False) as server, httpx.Client(base_url=server.url, timeout=60) as client:
        for label, loaded in (("tendon loads only", False), ("gravity + tip force + tip moment", True)):
            ms, ok = measure(client, loaded, args.requests)
            p50, p90, p99 = np.percentile(ms, [50, 90, 99])
            print(f"| {label} | {ms.size} | {p50:.2f} | {p90:.2f} | {p99:.2f} | {ok}/{ms.size} |")


if __name__ == "__main__":
    main()
