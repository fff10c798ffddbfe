"""Load test of the HTTP service on the shipped models (prints Markdown tables).

    python benchmarks/service_load.py [--models-dir models] [--soak 60]

Starts a real uvicorn process on a free loopback port, waits for /readyz, then runs
(1) a JSON sweep over concurrency 1, 4, 16, 64 and batch 1, 32, 1024 (default model),
(2) binary .npy / .npz requests of large batches on ``deeponet``, all outputs and tendons only,
(3) a soak at concurrency 64 with one-design requests for ``--soak`` seconds, with the server's
resident memory before and after.  Every cell is bounded in requests and seconds.  Client and
server share this machine's cores.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
from pathlib import Path

import httpx

from service.process import ServerProcess
from tdcr.clients.loadtest import Row, format_row, run_cell, server_rss

ROOT = Path(__file__).resolve().parents[1]
HEADER = ("| encoding | batch | concurrency | requests | errors | p50 (ms) | p95 (ms) | p99 (ms) | requests/s "
          "| designs/s |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")


async def main_async(url: str, soak: float, quick: bool) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=120.0) as client:
        for _ in range(50):  # warm-up
            await client.post("/predict", json={"designs": [{"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": [
                {"offset": 0.008, "tension": 1.0}] * 4}]})
        print("JSON requests, default model:\n\n" + HEADER)
        for batch in (1, 32, 1024):
            for c in (1, 4, 16, 64):
                row = await run_cell(url, concurrency=c, batch=batch, model=None, binary=False,
                                     max_requests=200 if quick else 2000, max_seconds=2 if quick else 10)
                print(format_row(row), flush=True)
        print("\nBinary requests (.npy in, .npz out), deeponet:\n\n" + HEADER)
        for batch in (1024, 8192):
            for outputs in (None, "tendons"):
                for c in (1, 2):
                    row = await run_cell(url, concurrency=c, batch=batch, model="deeponet", binary=True,
                                         outputs=outputs, max_requests=100 if quick else 400,
                                         max_seconds=2 if quick else 10)
                    print(format_row(row), flush=True)
        before = await server_rss(client)
        row: Row = await run_cell(url, concurrency=64, batch=1, model=None, binary=False,
                                  max_requests=10**7, max_seconds=soak)
        after = await server_rss(client)
        print(f"\nSoak: {soak:.0f} s at concurrency 64, one design per request (JSON):\n\n" + HEADER)
        print(format_row(row))
        print(f"\nserver resident memory: {before / 2**20:.1f} MiB before, {after / 2**20:.1f} MiB after "
              f"({100 * (after - before) / before:+.1f} %); errors: {row.errors}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models-dir", default=str(ROOT / "models"))
    parser.add_argument("--soak", type=float, default=60.0)
    parser.add_argument("--quick", action="store_true", help="short cells (smoke run)")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    with ServerProcess(args.models_dir) as server:
        asyncio.run(main_async(server.url, args.soak, args.quick))


if __name__ == "__main__":
    main()
