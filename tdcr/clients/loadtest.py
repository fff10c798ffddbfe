"""Load test of a running service (httpx, asyncio), bounded in requests and seconds.

For each (concurrency, batch size) it keeps ``concurrency`` requests in flight until
``requests`` are done or ``seconds`` pass, then reports latency percentiles, requests/s,
designs/s and errors.  Server memory (resident set size from /metrics) is read before and after.

Each of the ``concurrency`` virtual clients has its own ``httpx.AsyncClient`` with one keep-alive
connection.  One shared client with many connections costs about twice the CPU per request at
concurrency 16 (httpcore scans its whole pool on every request event, encode/httpx#3215), and on
a machine shared with the server that made the load generator the bottleneck.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from dataclasses import dataclass

import httpx
import numpy as np
import orjson

from tdcr import design_space
from tdcr.clients.client import INFERENCE_HEADER_LENGTH, NPY, NPZ, _npy


@dataclass
class Row:
    concurrency: int
    batch: int
    encoding: str
    requests: int
    errors: int
    seconds: float
    p50_ms: float
    p95_ms: float
    p99_ms: float

    @property
    def rps(self) -> float:
        return self.requests / self.seconds

    @property
    def designs_per_s(self) -> float:
        return self.requests * self.batch / self.seconds


async def server_rss(client: httpx.AsyncClient) -> float | None:
    """Resident memory of the server process in bytes, from its Prometheus metrics."""
    try:
        text = (await client.get("/metrics")).text
    except httpx.HTTPError:
        return None
    for line in text.splitlines():
        if line.startswith("process_resident_memory_bytes"):
            return float(line.split()[-1])
    return None


#: What a load test speaks: the service's own /predict (JSON or .npy/.npz), or the Open Inference
#: Protocol v2 over REST with binary tensors, or over gRPC with raw tensors.
PROTOCOLS = ("http", "v2", "grpc")
#: The outputs of a v2 request when none are named.
V2_OUTPUTS = ("backbone", "rotation", "tendons")


def grpc_target(url: str, port: int = 8001) -> str:
    """The gRPC address beside an HTTP ``url``: the same host, ``port``."""
    return f"{httpx.URL(url).host}:{port}"


def grpc_request(model: str, features: np.ndarray, outputs: str | None):
    """A ``ModelInferRequest`` with the designs as raw FP64 contents."""
    from tdcr.oip_grpc import open_inference_grpc_pb2 as pb  # gRPC is an optional extra

    wanted = outputs.split(",") if outputs else V2_OUTPUTS
    return pb.ModelInferRequest(
        model_name=model, inputs=[pb.ModelInferRequest.InferInputTensor(name="design", datatype="FP64",
                                                                        shape=features.shape)],
        outputs=[pb.ModelInferRequest.InferRequestedOutputTensor(name=o) for o in wanted],
        raw_input_contents=[np.ascontiguousarray(features, dtype="<f8").tobytes()])


def _v2_body(features: np.ndarray, outputs: str | None) -> dict:
    """A v2 inference request with the designs as a binary FP64 tensor and binary outputs."""
    blob = np.ascontiguousarray(features, dtype="<f8").tobytes()
    wanted = outputs.split(",") if outputs else V2_OUTPUTS
    head = orjson.dumps({"inputs": [{"name": "design", "shape": list(features.shape), "datatype": "FP64",
                                     "parameters": {"binary_data_size": len(blob)}}],
                         "outputs": [{"name": o, "parameters": {"binary_data": True}} for o in wanted]})
    return {"content": head + blob,
            "headers": {INFERENCE_HEADER_LENGTH: str(len(head)), "content-type": "application/octet-stream"}}


async def run_cell(url: str, *, concurrency: int, batch: int, model: str | None, binary: bool,
                   max_requests: int, max_seconds: float, seed: int = 0, outputs: str | None = None,
                   timeout: float = 120.0, protocol: str = "http", target: str | None = None) -> Row:
    """One cell against the service at ``url``: ``concurrency`` clients of one connection each.

    ``protocol="v2"`` and ``"grpc"`` need ``model`` and always send binary (raw) tensors; gRPC goes
    to ``target`` (default: :func:`grpc_target` of ``url``).
    """
    designs = design_space.sample_designs(batch, seed=seed)
    feats = designs.features()
    if protocol in ("v2", "grpc") and model is None:
        raise ValueError(f"the {protocol} protocol needs a model name")
    if protocol == "grpc":
        session = _grpc_session(target or grpc_target(url), grpc_request(model, feats, outputs), timeout)
        encoding = "grpc raw" + (f" ({outputs})" if outputs else "")
    else:
        path = "/predict"
        if protocol == "v2":
            body, path = _v2_body(feats, outputs), f"/v2/models/{model}/infer"
        elif binary:
            params = ({"model": model} if model else {}) | ({"outputs": outputs} if outputs else {})
            body = {"content": _npy(feats), "headers": {"content-type": NPY, "accept": NPZ}, "params": params}
        else:
            # serialised once, as load generators do: the client's CPU is shared with the server here
            payload = orjson.dumps({"designs": designs.to_dicts(), **({"model": model} if model else {})})
            body = {"content": payload, "headers": {"content-type": "application/json"}}
        session = _http_session(url, path, body, timeout)
        encoding = "v2 binary" if protocol == "v2" else "npy" if binary else "json"
        encoding += f" ({outputs})" if outputs and (binary or protocol == "v2") else ""
    latencies, errors, elapsed = await _drive(session, concurrency=concurrency, max_requests=max_requests,
                                              max_seconds=max_seconds)
    lat = np.array(latencies) * 1e3
    return Row(concurrency, batch, encoding, len(latencies), errors, elapsed,
               *(float(np.percentile(lat, q)) for q in (50, 95, 99)))


#: A client's session: an async context manager giving a call that sends one request, True if it succeeded.
Session = Callable[[], AbstractAsyncContextManager[Callable[[], Awaitable[bool]]]]


async def _drive(session: Session, *, concurrency: int, max_requests: int,
                 max_seconds: float) -> tuple[list[float], int, float]:
    """``concurrency`` clients, a ``session`` each, calling until ``max_requests`` are issued or
    ``max_seconds`` pass: the latencies (s), the errors and the elapsed time (s)."""
    latencies: list[float] = []
    errors = issued = 0
    deadline = time.perf_counter() + max_seconds

    async def worker():
        nonlocal errors, issued
        async with session() as call:
            while issued < max_requests and time.perf_counter() < deadline:
                issued += 1
                t = time.perf_counter()
                ok = await call()
                latencies.append(time.perf_counter() - t)
                errors += not ok

    start = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    return latencies, errors, time.perf_counter() - start


def _http_session(url: str, path: str, body: dict, timeout: float) -> Session:
    """One ``httpx.AsyncClient`` with one keep-alive connection per client, POSTing ``body``."""
    @asynccontextmanager
    async def session():
        one = httpx.Limits(max_connections=1, max_keepalive_connections=1)
        async with httpx.AsyncClient(base_url=url, timeout=timeout, limits=one) as client:
            async def call() -> bool:
                try:
                    return (await client.post(path, **body)).status_code == 200
                except httpx.HTTPError:
                    return False
            yield call
    return session


def _grpc_session(target: str, request, timeout: float) -> Session:
    """One ``grpc.aio`` channel (one HTTP/2 connection) per client, sending ``request`` to ModelInfer."""
    import grpc  # gRPC is an optional extra

    from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc

    unlimited = [("grpc.max_receive_message_length", -1), ("grpc.max_send_message_length", -1)]

    @asynccontextmanager
    async def session():
        async with grpc.aio.insecure_channel(target, options=unlimited) as channel:
            infer = pb_grpc.GRPCInferenceServiceStub(channel).ModelInfer

            async def call() -> bool:
                try:
                    await infer(request, timeout=timeout)
                    return True
                except grpc.RpcError:
                    return False
            yield call
    return session


async def sweep(url: str, *, concurrencies=(1, 4, 16, 64), batches=(1, 32, 1024), model: str | None = None,
                binary: bool = False, max_requests: int = 2000, max_seconds: float = 10.0, protocol: str = "http",
                target: str | None = None, outputs: str | None = None):
    """Run every cell; returns ``(rows, rss_before, rss_after)``.  (v2 and gRPC without a model:
    the server's default model.)"""
    async with httpx.AsyncClient(base_url=url, timeout=60.0) as client:
        before = await server_rss(client)
        if protocol in ("v2", "grpc") and model is None:
            model = (await client.get("/models")).json()["default_model"]
        rows = []
        for batch in batches:
            for c in concurrencies:
                rows.append(await run_cell(url, concurrency=c, batch=batch, model=model, binary=binary,
                                           max_requests=max_requests, max_seconds=max_seconds, protocol=protocol,
                                           target=target, outputs=outputs))
        after = await server_rss(client)
    return rows, before, after


def format_rows(rows: list[Row], before: float | None, after: float | None) -> str:
    lines = ["| encoding | batch | concurrency | requests | errors | p50 (ms) | p95 (ms) | p99 (ms) | requests/s "
             "| designs/s |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [format_row(r) for r in rows]
    if before and after:
        lines.append(f"\nserver memory: {before / 2**20:.1f} MiB before, {after / 2**20:.1f} MiB after "
                     f"({100 * (after - before) / before:+.1f} %)")
    return "\n".join(lines)


def format_row(r: Row) -> str:
    return (f"| {r.encoding} | {r.batch} | {r.concurrency} | {r.requests} | {r.errors} | {r.p50_ms:.2f} | "
            f"{r.p95_ms:.2f} | {r.p99_ms:.2f} | {r.rps:,.0f} | {r.designs_per_s:,.0f} |")
