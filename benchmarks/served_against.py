"""One design over loopback on two servers at once, this tree's and a git revision's, and each
transport's no-op beside its answer, interleaved and back to back (issue #34; prints two tables).

    python benchmarks/served_against.py --against REV [--requests 300]

Both servers (``tdcr serve`` on the shipped models, the revision's from its worktree: see
``benchmarks/against.py``) run side by side; a synchronous client sends each round's one Table I
design (seeded, 42 points) to every row on both, the trees' order alternating by round, so the VM's
drift hits both trees alike.  Rows: ``GET /healthz`` and gRPC ``ServerLive`` (each transport's
floor), ``/predict`` and ``/exact`` with the same JSON body, ``/predict`` with the binary request of
:meth:`tdcr.clients.Client.predict` (``.npy`` in, ``.npz`` out; its answer read, not decoded), and
OIP v2 ``ModelInfer`` on ``auto`` over gRPC.  The first table gives each tree's p50 and the
median of the per-round ratios.

The second table is this tree's alone: each row once interleaved as above and once back to back
(``--requests`` of it in a run, nothing else between them).  After other work the server's and the
client's threads have gone idle, and waking them costs on this VM; a planner that calls in a loop
sees the back-to-back figure.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable

import grpc
import httpx
import numpy as np
import orjson
from against import ROOT, worktree  # benchmarks/ is the script's folder
from exact_latency import design_json

from service.process import ServerProcess
from tdcr.clients import predict_request  # what Client.predict sends
from tdcr.clients.loadtest import grpc_request
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc
from tdcr.robot.design_space import sample_designs

ROWS = ("GET /healthz (no-op)", "gRPC ServerLive (no-op)", "/predict (router)", "/predict (router), .npy in, .npz out",
        "/exact", "gRPC ModelInfer auto")
#: Rounds before the timed ones (connections, caches and the solver processes warm).
WARM_UP = 30
JSON = {"content-type": "application/json"}


def _calls(server: ServerProcess) -> tuple[Callable, ...]:
    """One callable per row of :data:`ROWS`, on ``server``, taking the round's (JSON body, gRPC
    request, binary request); each raises on an error answer."""
    client = httpx.Client(base_url=server.url, timeout=60)
    stub = pb_grpc.GRPCInferenceServiceStub(grpc.insecure_channel(server.grpc_target))

    def post(path: str):
        return lambda body, *_: client.post(path, content=body, headers=JSON).raise_for_status()

    return (lambda *_: client.get("/healthz").raise_for_status(),
            lambda *_: stub.ServerLive(pb.ServerLiveRequest()),
            post("/predict"), lambda *item: client.post("/predict", **item[2]).raise_for_status(), post("/exact"),
            lambda _, message, __: stub.ModelInfer(message))


def _timed(call: Callable, *args) -> float:
    started = time.perf_counter()
    call(*args)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", required=True, help="a git revision, e.g. 1175eca")
    parser.add_argument("--requests", type=int, default=300)
    args = parser.parse_args()
    features = sample_designs(args.requests + WARM_UP, seed=5).features()
    work = [(orjson.dumps({"designs": [design_json(f, False)], "points": 42}), grpc_request("auto", f[None, :], None),
             predict_request(f[None, :], points=42))
            for f in features]
    trees = {"this tree": ROOT, args.against: worktree(args.against)}
    servers = {name: ServerProcess(root / "models", root=root) for name, root in trees.items()}
    try:
        calls = {name: _calls(server) for name, server in servers.items()}
        interleaved = {name: [[] for _ in ROWS] for name in trees}
        for k, item in enumerate(work):
            for name in list(trees)[:: 1 if k % 2 else -1]:
                for row, call in enumerate(calls[name]):
                    seconds = _timed(call, *item)
                    if k >= WARM_UP:
                        interleaved[name][row].append(seconds)
        mine = calls["this tree"]
        back_to_back = [[_timed(call, *item) for item in work[WARM_UP:]] for call in mine]
    finally:
        for server in servers.values():
            server.stop()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; both servers and the client on it; "
          f"one design, 42 points, {args.requests} rounds\n")
    print(f"| row | this tree p50 (ms) | {args.against} p50 (ms) | this / {args.against}, median of per-round "
          "ratios |\n|---|---:|---:|---:|")
    new, old = (interleaved[name] for name in trees)
    for row, label in enumerate(ROWS):
        a, b = np.array(new[row]), np.array(old[row])
        print(f"| {label} | {1e3 * np.median(a):.2f} | {1e3 * np.median(b):.2f} | {np.median(a / b):.2f} |")
    print("\n| this tree's row | interleaved p50 (ms) | back to back p50 (ms) |\n|---|---:|---:|")
    for row, label in enumerate(ROWS):
        print(f"| {label} | {1e3 * np.median(new[row]):.2f} | {1e3 * np.median(back_to_back[row]):.2f} |")


if __name__ == "__main__":
    main()
