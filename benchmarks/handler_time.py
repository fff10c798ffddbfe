"""Where one-design /predict time goes: client latency vs the server's own handler time.

    tdcr serve --port 8000 &  python benchmarks/handler_time.py --url http://127.0.0.1:8000

For each model: 30 warm-up and 300 sequential one-design JSON requests on a persistent httpx
client; prints the client-side p50 / p99 and the mean server-side time of the same requests, read
from the ``tdcr_request_seconds`` histogram of /metrics.
"""

from __future__ import annotations

import argparse
import re
import time

import httpx
import numpy as np
import orjson

DESIGN = {"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": [{"offset": 0.008, "pitch": 5.0, "tension": 1.0}] * 4}


def _metric(text: str, key: str) -> float:
    return float(re.search(re.escape(key) + r" ([0-9.e+-]+)", text).group(1))


def _wait_ready(client: httpx.Client, timeout: float) -> None:
    """Until ``/readyz`` says 200 (a starting server answers 503 and has no model metrics yet)."""
    deadline = time.monotonic() + timeout
    while client.get("/readyz").status_code != 200:
        if time.monotonic() > deadline:
            raise SystemExit(f"{client.base_url} was not ready within {timeout:g} s (GET /readyz)")
        time.sleep(1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", default="http://127.0.0.1:8000")
    parser.add_argument("--requests", type=int, default=300)
    parser.add_argument("--ready-timeout", type=float, default=180.0, help="seconds to wait for /readyz 200")
    args = parser.parse_args()
    with httpx.Client(base_url=args.url) as client:
        _wait_ready(client, args.ready_timeout)
        print("| model | client p50 (ms) | client p99 (ms) | server handler mean (ms) |\n|---|---:|---:|---:|")
        for model in sorted(client.get("/models").json()["models"]):
            body = orjson.dumps({"model": model, "designs": [DESIGN]})
            headers = {"content-type": "application/json"}
            for _ in range(30):
                client.post("/predict", content=body, headers=headers).raise_for_status()
            before = client.get("/metrics").text
            times = []
            for _ in range(args.requests):
                t = time.perf_counter()
                client.post("/predict", content=body, headers=headers)
                times.append(time.perf_counter() - t)
            after = client.get("/metrics").text
            labels = f'{{endpoint="/predict",model="{model}",protocol="http"}}'
            total, count = (_metric(after, f"tdcr_request_seconds_{k}" + labels)
                            - _metric(before, f"tdcr_request_seconds_{k}" + labels) for k in ("sum", "count"))
            print(f"| {model} | {1e3 * np.median(times):.2f} | {1e3 * np.percentile(times, 99):.2f} | "
                  f"{1e3 * total / count:.2f} |")


if __name__ == "__main__":
    main()
