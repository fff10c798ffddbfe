"""The Open Inference Protocol v2 over REST with binary tensors, against a real server on loopback.

    python benchmarks/oip_rest.py

Prints one-design latency on fno_pose (concurrency 1, 500 requests) and the designs/s of 8,192-design
tendons-only requests on deeponet (concurrency 1, 10 requests).
"""

from __future__ import annotations

import os
import platform
import time

import httpx
import numpy as np
import orjson

from service.oip import HEADER_LENGTH
from service.process import ROOT, ServerProcess
from tdcr.robot.design_space import sample_designs


def binary_request(features: np.ndarray, outputs: list[str]) -> tuple[bytes, dict]:
    blob = np.ascontiguousarray(features, "<f8").tobytes()
    head = orjson.dumps({"inputs": [{"name": "design", "shape": list(features.shape), "datatype": "FP64",
                                     "parameters": {"binary_data_size": len(blob)}}],
                         "outputs": [{"name": o, "parameters": {"binary_data": True}} for o in outputs]})
    return head + blob, {HEADER_LENGTH: str(len(head)), "content-type": "application/octet-stream"}


def main() -> None:
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    with ServerProcess(ROOT / "models") as server, httpx.Client(base_url=server.url, timeout=60) as client:
        body, headers = binary_request(sample_designs(1, seed=0).features(), ["backbone", "rotation", "tendons"])
        for _ in range(100):
            client.post("/v2/models/fno_pose/infer", content=body, headers=headers)
        times = []
        for _ in range(500):
            started = time.perf_counter()
            client.post("/v2/models/fno_pose/infer", content=body, headers=headers).raise_for_status()
            times.append(time.perf_counter() - started)
        ms = np.array(times) * 1e3
        print(f"fno_pose, 1 design, all outputs: p50 {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms")
        body, headers = binary_request(sample_designs(8192, seed=1).features(), ["tendons"])
        for _ in range(2):
            client.post("/v2/models/deeponet/infer", content=body, headers=headers)
        started = time.perf_counter()
        for _ in range(10):
            client.post("/v2/models/deeponet/infer", content=body, headers=headers).raise_for_status()
        print(f"deeponet, 8,192 designs, tendons only: {10 * 8192 / (time.perf_counter() - started):,.0f} designs/s")


if __name__ == "__main__":
    main()
