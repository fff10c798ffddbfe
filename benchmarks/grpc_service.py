"""The Open Inference Protocol v2 over gRPC against a real ``tdcr serve`` on loopback, and the three
protocols side by side.

    python benchmarks/grpc_service.py [--soak-seconds 60]

Prints (client and server on this machine, sharing its cores):

1. one-design ``ModelInfer`` latency at concurrency 1 (sync stub, raw tensors, 1,000 calls);
2. requests/s of one-design calls at concurrency 16 (``tdcr loadtest``'s gRPC cell);
3. designs/s of 8,192-design tendons-only ``deeponet`` calls through raw contents (sync, 10 calls);
4. the load-test table of the three protocols (http JSON, v2 REST binary, gRPC raw) at
   concurrency 1 and 16, one design per request;
5. a soak: concurrency 64 for ``--soak-seconds``, half gRPC and half HTTP (/predict JSON), batches of
   1 and 32: errors and the server's resident memory before (after a warm-up) and after.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import time

import grpc
import httpx
import numpy as np

from service.process import ROOT, ServerProcess
from tdcr.clients.loadtest import format_row, format_rows, grpc_request, run_cell, server_rss
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc
from tdcr.robot.design_space import sample_designs

MODEL = "deeponet"
UNLIMITED = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]


def latency(stub, model: str, n: int = 1000) -> tuple[float, float]:
    request = grpc_request(model, sample_designs(1, seed=0).features(), None)
    for _ in range(100):
        stub.ModelInfer(request)
    times = []
    for _ in range(n):
        started = time.perf_counter()
        stub.ModelInfer(request)
        times.append(time.perf_counter() - started)
    ms = np.array(times) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def bulk(stub, n: int = 10, batch: int = 8192) -> float:
    request = grpc_request(MODEL, sample_designs(batch, seed=1).features(), "tendons")
    for _ in range(2):
        stub.ModelInfer(request)
    started = time.perf_counter()
    for _ in range(n):
        stub.ModelInfer(request)
    return n * batch / (time.perf_counter() - started)


async def soak(server: ServerProcess, seconds: float) -> None:
    cell = {"max_requests": 10**9, "max_seconds": seconds, "model": MODEL, "binary": False}
    async with httpx.AsyncClient(base_url=server.url) as client:
        warm = {**cell, "max_seconds": 5.0}
        await asyncio.gather(run_cell(server.url, concurrency=32, batch=1, protocol="grpc",
                                      target=server.grpc_target, **warm),
                             run_cell(server.url, concurrency=32, batch=32, protocol="http", **warm))
        before = await server_rss(client)
        rows = await asyncio.gather(
            run_cell(server.url, concurrency=16, batch=1, protocol="grpc", target=server.grpc_target, **cell),
            run_cell(server.url, concurrency=16, batch=32, protocol="grpc", target=server.grpc_target, **cell),
            run_cell(server.url, concurrency=16, batch=1, protocol="http", **cell),
            run_cell(server.url, concurrency=16, batch=32, protocol="http", **cell))
        after = await server_rss(client)
    print(f"\n5. soak: concurrency 64 for {seconds:.0f} s, 32 gRPC + 32 HTTP clients "
          f"({sum(r.requests for r in rows):,} requests, {sum(r.errors for r in rows)} errors)")
    print(format_rows(rows, before, after))


async def protocols(server: ServerProcess) -> None:
    print("\n4. the three protocols, one design per request (`tdcr loadtest --protocol http|v2|grpc "
          "--concurrency 1,16 --batch 1`)")
    print(format_rows([], None, None))
    for protocol in ("http", "v2", "grpc"):
        for concurrency in (1, 16):
            row = await run_cell(server.url, concurrency=concurrency, batch=1, model=MODEL, binary=False,
                                 max_requests=3000, max_seconds=6.0, protocol=protocol, target=server.grpc_target)
            print(format_row(row).replace(f"| {row.encoding} |", f"| {protocol}: {row.encoding} |"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--soak-seconds", type=float, default=60.0)
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    with ServerProcess(ROOT / "models") as server, grpc.insecure_channel(server.grpc_target,
                                                                         options=UNLIMITED) as channel:
        stub = pb_grpc.GRPCInferenceServiceStub(channel)
        for model in (MODEL, "fno_pose"):
            p50, p99 = latency(stub, model)
            print(f"1. {model}, 1 design, all outputs, concurrency 1: p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        row = asyncio.run(run_cell(server.url, concurrency=16, batch=1, model=MODEL, binary=False,
                                   max_requests=10_000, max_seconds=8.0, protocol="grpc",
                                   target=server.grpc_target))
        print(f"2. {MODEL}, 1 design, concurrency 16: {row.rps:,.0f} requests/s "
              f"(p50 {row.p50_ms:.2f} ms, p99 {row.p99_ms:.2f} ms, {row.errors} errors)")
        print(f"3. {MODEL}, 8,192 designs, tendons only, raw: {bulk(stub):,.0f} designs/s")
        asyncio.run(protocols(server))
        asyncio.run(soak(server, args.soak_seconds))


if __name__ == "__main__":
    main()
