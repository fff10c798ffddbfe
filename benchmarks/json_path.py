"""Where the time of a large JSON /predict goes, and the server's own time for it.

1. In process: prepare (parse + validate), run (onnxruntime), encode (JSON) of one request of
   1,024 designs at 42 points on ``deeponet_pose``, through the data plane the server uses.
2. Over loopback: the same request to a real server process; the server's time per request read
   from its ``tdcr_request_seconds`` histogram (the client's parse of the answer is not counted).

    python benchmarks/json_path.py [--designs 1024] [--repeats 30]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import time

import httpx
import numpy as np
import orjson

from service.process import ROOT, ServerProcess
from tdcr.api.validation import Limits
from tdcr.robot.design_space import sample_designs
from tdcr.surrogates import engine
from tdcr.surrogates.runtime import Surrogate

MODEL = "deeponet_pose"


def request_body(n: int) -> bytes:
    return orjson.dumps({"designs": sample_designs(n, seed=0).to_dicts(), "model": MODEL})


def in_process(body: bytes, repeats: int) -> np.ndarray:
    model = Surrogate.load(ROOT / "models", MODEL)

    def once():
        t0 = time.perf_counter()
        request = engine.prepare_json(body, limits=Limits())
        t1 = time.perf_counter()
        prediction = engine.predict(model, request, model=MODEL)
        t2 = time.perf_counter()
        engine.encode_json(prediction)
        return t1 - t0, t2 - t1, time.perf_counter() - t2

    for _ in range(3):
        once()
    return np.array([once() for _ in range(repeats)]) * 1e3


def server_seconds(text: str) -> tuple[float, int]:
    """(sum, count) of the /predict request-duration histogram for MODEL."""
    labels = f'endpoint="/predict",model="{MODEL}",protocol="http"'
    total = float(re.search(rf"tdcr_request_seconds_sum\{{{labels}\}} (\S+)", text).group(1))
    count = int(float(re.search(rf"tdcr_request_seconds_count\{{{labels}\}} (\S+)", text).group(1)))
    return total, count


def over_loopback(body: bytes, repeats: int) -> tuple[float, float]:
    with ServerProcess(ROOT / "models") as server, httpx.Client(base_url=server.url, timeout=60) as client:
        headers = {"content-type": "application/json"}
        for _ in range(3):
            client.post("/predict", content=body, headers=headers).raise_for_status()
        s0, c0 = server_seconds(client.get("/metrics").text)
        started = time.perf_counter()
        for _ in range(repeats):
            client.post("/predict", content=body, headers=headers).raise_for_status()
        wall = (time.perf_counter() - started) / repeats
        s1, c1 = server_seconds(client.get("/metrics").text)
    return (s1 - s0) / (c1 - c0) * 1e3, wall * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--designs", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    body = request_body(args.designs)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; {MODEL}, {args.designs} designs x 42 points, "
          f"request {len(body) / 1e6:.2f} MB\n")
    stages = in_process(body, args.repeats)
    print("| stage (in process) | median (ms) | p90 (ms) |\n|---|---:|---:|")
    for name, column in zip(("prepare", "run", "encode", "total"), [*stages.T, stages.sum(axis=1)], strict=True):
        print(f"| {name} | {np.median(column):.1f} | {np.percentile(column, 90):.1f} |")
    server_ms, client_ms = over_loopback(body, args.repeats)
    print(f"\nover loopback: server's own time (histogram mean) {server_ms:.1f} ms per request; "
          f"client round trip incl. its parse {client_ms:.1f} ms")


if __name__ == "__main__":
    main()
