"""Every answer the cheapest one that meets its tolerance (issue #34): latency of one design over
HTTP and gRPC, and what an error bound costs, in one interleaved run on one machine (prints tables).

    python benchmarks/fast_paths.py [--requests 300]

1. A real ``tdcr serve`` on loopback answers a synchronous client, one request at a time, a different
   Table I design (seeded) each round; each round sends the same body to every row in turn, so drift
   hits the rows alike (42 points): ``/predict`` without a model (the router: the cheaper of the
   solver and the default operator), with tolerances, pinned to operators, ``/exact``; then OIP v2
   ``ModelInfer`` over gRPC (raw FP64 contents) on ``auto`` and on the pinned ``deeponet``, on this
   server (a few designs answered on the event loop) and on a second one started with
   ``TDCR_INLINE=false`` (every request handed to a worker thread), and the no-op calls gRPC's
   ``ServerLive`` and HTTP's ``GET /healthz``, the transports' own floors on this machine.  Each HTTP
   row counts the answers by ``source``.  The HTTP rows use httpx; ``/predict`` (router), ``/exact``
   and ``/healthz`` are also sent with the standard library's ``http.client`` (``LEAN_ROWS``), whose
   own cost per request is far smaller, so those rows show the server's latency.
2. In process: each operator's ``Surrogate.predict`` plain and with its bound (``bound=True``), at 1
   and 1,000 designs, interleaved (medians, and the median of the per-pair ratios; the difference
   carries the graphs' run-to-run spread), the bound's own work on an answer already computed
   (``keep_tolerance``), and the exact ``solve`` of the same designs.
3. The router's measured costs (``GET /v2/models/auto``) and where its choice flips.
"""

from __future__ import annotations

import argparse
import http.client
import os
import platform
import socket
import time

import grpc
import httpx
import numpy as np
import orjson
from exact_latency import design_json  # benchmarks/ is the script's folder

from service.process import ROOT, ServerProcess
from tdcr.clients.loadtest import grpc_request
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc
from tdcr.physics import solve
from tdcr.robot.design_space import sample_designs
from tdcr.surrogates.runtime import Surrogate, keep_tolerance, on_grid_tendons

HTTP_ROWS = {"/predict (router)": ("/predict", {}),
             "/predict (router), tolerance 0.01": ("/predict", {"tolerance": 0.01}),
             "/predict (router), tolerance 0.001": ("/predict", {"tolerance": 0.001}),
             "/predict deeponet (pinned, bounded)": ("/predict", {"model": "deeponet"}),
             "/predict fno_pose (pinned, bounded)": ("/predict", {"model": "fno_pose"}),
             "/predict deeponet_pose_loaded (pinned, bounded)": ("/predict", {"model": "deeponet_pose_loaded"}),
             "/exact": ("/exact", {})}
GRPC_ROWS = ("auto", "deeponet")
#: HTTP's floor with this client: a request that does no work.
HTTP_NO_OP = "HTTP GET /healthz (no-op)"
#: The same exchanges with the standard library's ``http.client`` (one keep-alive connection,
#: ``TCP_NODELAY``): httpx's own cost per request is about 0.7 ms on this VM, more than the server's
#: for a no-op.  The body is encoded before the clock starts; the answer is read, not parsed.
LEAN_ROWS = {"/predict (router), http.client": ("POST", "/predict"), "/exact, http.client": ("POST", "/exact"),
             "HTTP GET /healthz (no-op), http.client": ("GET", "/healthz")}
#: The gRPC rows' servers: this one (inline) and one with ``TDCR_INLINE=false``.
GRPC_SERVERS = ("", " (worker thread: TDCR_INLINE=false)")
JSON = {"content-type": "application/json"}
OPERATORS = ("deeponet", "deeponet_pose", "fno", "fno_pose", "deeponet_pose_loaded", "fno_pose_loaded")


def median_seconds(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return float(np.median(times))


def served(requests: int) -> None:
    feats = sample_designs(requests + 20, seed=8).features()
    grpc_rows = ["gRPC ServerLive (no-op)"] + [f"gRPC ModelInfer {m}{where}" for where in GRPC_SERVERS
                                               for m in GRPC_ROWS]
    rows = list(HTTP_ROWS) + [HTTP_NO_OP] + list(LEAN_ROWS) + grpc_rows
    times: dict[str, list[float]] = {label: [] for label in rows}
    sources: dict[str, dict[str, int]] = {label: {} for label in HTTP_ROWS}
    with ServerProcess(ROOT / "models") as server, ServerProcess(ROOT / "models", inline=False) as threaded, \
            httpx.Client(base_url=server.url, timeout=60) as client, \
            grpc.insecure_channel(server.grpc_target) as channel, \
            grpc.insecure_channel(threaded.grpc_target) as threaded_channel:
        stubs = dict(zip(GRPC_SERVERS, (pb_grpc.GRPCInferenceServiceStub(channel),
                                        pb_grpc.GRPCInferenceServiceStub(threaded_channel)), strict=True))
        auto = client.get("/v2/models/auto").json()["parameters"]
        lean = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
        lean.connect()
        lean.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for k, f in enumerate(feats):
            for label, (route, extra) in HTTP_ROWS.items():
                body = {"designs": [design_json(f, False)], "points": 42} | extra
                started = time.perf_counter()
                r = client.post(route, json=body)
                elapsed = time.perf_counter() - started
                r.raise_for_status()
                if k >= 20:  # after a warm-up
                    times[label].append(1e3 * elapsed)
                    source = r.json()["results"][0].get("source", "exact")
                    sources[label][source] = sources[label].get(source, 0) + 1
            started = time.perf_counter()
            client.get("/healthz").raise_for_status()
            if k >= 20:
                times[HTTP_NO_OP].append(1e3 * (time.perf_counter() - started))
            body = orjson.dumps({"designs": [design_json(f, False)], "points": 42})
            for label, (method, route) in LEAN_ROWS.items():
                started = time.perf_counter()
                lean.request(method, route, body=body if method == "POST" else None, headers=JSON)
                answer = lean.getresponse()
                answer.read()
                elapsed = time.perf_counter() - started
                if answer.status != 200:
                    raise RuntimeError(f"{route}: HTTP {answer.status}")
                if k >= 20:
                    times[label].append(1e3 * elapsed)
            started = time.perf_counter()
            stubs[""].ServerLive(pb.ServerLiveRequest())
            if k >= 20:
                times["gRPC ServerLive (no-op)"].append(1e3 * (time.perf_counter() - started))
            for where, stub in stubs.items():
                for model in GRPC_ROWS:
                    request = grpc_request(model, f[None, :], None)
                    started = time.perf_counter()
                    stub.ModelInfer(request)
                    elapsed = time.perf_counter() - started
                    if k >= 20:
                        times[f"gRPC ModelInfer {model}{where}"].append(1e3 * elapsed)
    print("| one design, 42 points | requests | p50 (ms) | p90 (ms) | p99 (ms) | answered by |")
    print("|---|---:|---:|---:|---:|---|")
    for label in rows:
        p50, p90, p99 = np.percentile(times[label], [50, 90, 99])
        by = ", ".join(f"{k} {v}" for k, v in sorted(sources.get(label, {}).items())) or "-"
        print(f"| {label} | {len(times[label])} | {p50:.2f} | {p90:.2f} | {p99:.2f} | {by} |")
    ratio = np.median(np.array(times["/predict (router)"]) / np.array(times["/exact"]))
    print(f"\n/predict (router) / /exact, same body, median of per-round ratios: {ratio:.2f}")
    ratio = np.median(np.array(times["/predict (router), http.client"]) / np.array(times["/exact, http.client"]))
    print(f"the same with http.client: {ratio:.2f}")
    for model in GRPC_ROWS:
        threaded = np.array(times[f"gRPC ModelInfer {model}{GRPC_SERVERS[1]}"])
        inline = np.array(times[f"gRPC ModelInfer {model}"]) / threaded
        print(f"gRPC {model}: on the event loop / on a worker thread, median of per-round ratios: "
              f"{np.median(inline):.2f}")
    print("router costs on the server (s, B designs): " + ", ".join(f"{k} {v}" for k, v in auto.items()))


def bound_alone(op: Surrogate, features: np.ndarray, grid: np.ndarray, repeats: int) -> float:
    """Median seconds of the bound's own work on an answer already computed: the one tolerance
    path (``keep_tolerance``: finiteness, the calibrated bound, the guard) without a tolerance."""
    matrix = op.load_matrix(None, len(features))
    out = op.predict(features, grid, loads=matrix, check=False)
    return median_seconds(lambda: keep_tolerance(out, features, grid, matrix, tendons=on_grid_tendons(out, grid),
                                                 own=op.predict, calibration=op.calibration,
                                                 companion=op.companion(), tolerance=None, exact=None), repeats)


def in_process() -> None:
    grid = np.linspace(0.0, 1.0, 42)
    print("\n| in process | designs | plain (ms) | with its bound (ms) | difference (ms) | difference / plain "
          "| the bound alone (ms) | alone / plain |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for batch, repeats in ((1, 300), (1000, 21)):
        designs = sample_designs(batch, seed=9)
        features = designs.features()
        for name in OPERATORS:
            op = Surrogate.shipped(name)
            op.predict(features, grid, bound=True)
            plain, bounded = [], []
            for _ in range(repeats):  # interleaved, so that drift hits both alike
                for out, bound in ((plain, False), (bounded, True)):
                    started = time.perf_counter()
                    op.predict(features, grid, bound=bound)
                    out.append(time.perf_counter() - started)
            p, b = float(np.median(plain)), float(np.median(bounded))
            ratio = float(np.median(np.array(bounded) / np.array(plain))) - 1.0
            own = bound_alone(op, features, grid, repeats)
            print(f"| {name} | {batch:,} | {1e3 * p:.3f} | {1e3 * b:.3f} | {1e3 * (b - p):.3f} | {ratio:+.0%} "
                  f"| {1e3 * own:.3f} | {own / p:.0%} |")
        exact = median_seconds(lambda d=designs: solve(d, grid, workers=0), repeats)
        print(f"| exact solve (all cores) | {batch:,} | {1e3 * exact:.3f} | - | - | - |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=300)
    parser.add_argument("--in-process-only", action="store_true", help="skip the served rows (item 1)")
    parser.add_argument("--served-only", action="store_true", help="skip the in-process rows (item 2)")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and client on the same machine\n")
    if not args.in_process_only:
        served(args.requests)
    if not args.served_only:
        in_process()


if __name__ == "__main__":
    main()
