"""The hardening issue's attacks against a real server on loopback: status, time and memory.

Starts ``tdcr serve`` on the shipped models (``TDCR_EXACT_TIMEOUT_S=2`` and
``TDCR_EXACT_ADMISSION_FACTOR=10``, so that work estimated up to 20 s is admitted and the deadline
case is reached; other settings default),
then replays each defect of the issue and prints one row per attack: the answer, the seconds it
took and the server's RSS growth (``/proc``).  Every request loop is bounded in count and time and
sends only to 127.0.0.1.

    python benchmarks/abuse.py
"""

from __future__ import annotations

import asyncio
import io
import os
import platform
import signal
import socket
import time
from pathlib import Path

import httpx
import numpy as np
import orjson

from service.process import ROOT, ServerProcess, solver_pids
from tdcr.robot.design_space import sample_designs

ONE = sample_designs(1, seed=0).to_dicts()
LOADED = {"gravity": [0.0, 9.81, 0.0], "density": 7800.0, "tip_force": [0.01, 0.0, 0.0]}
ROWS: list[tuple[str, str, str, float, float]] = []


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def row(defect: str, attack: str, fn, server: ServerProcess) -> None:
    before = rss_mb(server.proc.pid)
    started = time.perf_counter()
    answer = fn()
    seconds = time.perf_counter() - started
    ROWS.append((defect, attack, answer, seconds, rss_mb(server.proc.pid) - before))
    print(f"| {defect} | {attack} | {answer} | {seconds:.2f} | {ROWS[-1][4]:+.1f} |", flush=True)


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def lying_npy(array: np.ndarray, rows: int) -> bytes:
    """A .npy whose header claims ``rows`` rows, followed by ``array``'s data only."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (rows, 15)})
    return header.getvalue() + array.astype("<f8").tobytes()


def model_name_answer(server: ServerProcess) -> str:
    body = orjson.dumps({"designs": ONE})[:-1] + b', "model": "' + b"x" * 10_000_000 + b'"}'
    r = httpx.post(server.url + "/predict", content=body, headers={"content-type": "application/json"}, timeout=60)
    return f"{r.status_code}, {len(r.content)} bytes: {r.json()['message'][:50]!r}"


def post(server, path, **kwargs) -> str:
    r = httpx.post(server.url + path, timeout=120, **kwargs)
    return f"{r.status_code} {r.text[:60]!r}" if r.status_code >= 400 else str(r.status_code)


async def predict_under_exact_flood(server: ServerProcess, seconds: float = 10.0) -> str:
    """64 concurrent /exact of 2,000 loaded designs (re-sent as they are refused) while one client
    sends one-design /predict requests; the /predict latencies."""
    heavy = orjson.dumps({"designs": [{**d, **LOADED} for d in ONE] * 2000})  # encoded once, as attackers do
    light = orjson.dumps({"designs": ONE})
    headers = {"content-type": "application/json"}
    latencies: list[float] = []
    stop = time.perf_counter() + seconds
    statuses: dict[int | str, int] = {}

    async def flood(client):
        while time.perf_counter() < stop:
            try:
                answer = (await client.post("/exact", content=heavy, headers=headers)).status_code
            except httpx.TransportError:  # a 503 closes the connection while the body is still going
                answer = "closed"
            statuses[answer] = statuses.get(answer, 0) + 1
            await asyncio.sleep(0.05)

    async def probe(client):
        while time.perf_counter() < stop:
            t = time.perf_counter()
            r = await client.post("/predict", content=light, headers=headers)
            r.raise_for_status()
            latencies.append(time.perf_counter() - t)

    limits = httpx.Limits(max_connections=100)
    async with httpx.AsyncClient(base_url=server.url, timeout=120, limits=limits) as flood_client, \
            httpx.AsyncClient(base_url=server.url, timeout=30) as probe_client:
        await asyncio.gather(*[flood(flood_client) for _ in range(64)], probe(probe_client))
    ms = np.array(latencies) * 1e3
    return (f"/predict p50 {np.median(ms):.1f} ms, p99 {np.percentile(ms, 99):.1f} ms ({len(ms)} requests); "
            f"/exact answers {statuses}")


def slow_headers(server: ServerProcess) -> str:
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.send(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        sock.settimeout(1.0)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if sock.recv(64) == b"":
                    return "closed by the server"
            except TimeoutError:
                sock.send(b"X")
            except ConnectionResetError:
                return "reset by the server"
    return "still open after 60 s"


def half_open(server: ServerProcess, n: int = 1200) -> str:
    socks = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(n)]
    try:
        during = httpx.get(server.url + "/healthz", timeout=10).status_code
    finally:
        for s in socks:
            s.close()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if httpx.get(server.url + "/healthz", timeout=10).status_code == 200:
            return f"{during} while {n} were open, then 200"
        time.sleep(0.2)
    return f"{during}, not recovered"


def metric_paths(server: ServerProcess, n: int = 20_000) -> str:
    before = len(httpx.get(server.url + "/metrics").content)
    with httpx.Client(base_url=server.url) as client:
        for i in range(n):
            client.get(f"/nowhere/{i}")
    after = len(httpx.get(server.url + "/metrics").content)
    return f"/metrics {before / 1e3:.1f} kB -> {after / 1e3:.1f} kB"


def killed_worker(server: ServerProcess) -> str:
    pid = solver_pids(server.proc.pid)[0]
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    seen_unready = False
    while time.monotonic() < deadline:
        ready = httpx.get(server.url + "/readyz").status_code == 200
        seen_unready |= not ready
        if ready and pid not in solver_pids(server.proc.pid) and solver_pids(server.proc.pid):
            r = httpx.post(server.url + "/exact", json={"designs": ONE}, timeout=30)
            return f"replaced; /readyz said 503 meanwhile: {seen_unready}; next /exact {r.status_code}"
        time.sleep(0.05)
    return "not replaced"


def orphans_after_sigkill() -> str:
    server = ServerProcess(ROOT / "models")
    workers = solver_pids(server.proc.pid)
    server.proc.send_signal(signal.SIGKILL)
    server.proc.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in workers):
        time.sleep(0.05)
    server.stop(check=False)
    left = [p for p in workers if Path(f"/proc/{p}").exists()]
    return f"{len(workers)} solver processes, {len(left)} left"


def main() -> None:
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server and attacker on the same machine\n")
    print("| defect | attack | answer | seconds | server RSS growth (MB) |\n|---|---|---|---:|---:|")
    with ServerProcess(ROOT / "models", exact_timeout_s=2, exact_admission_factor=10) as server:
        feats = sample_designs(2, seed=0).features()
        row("1", ".npy /predict ?points=1e9", lambda: post(server, "/predict", params={"points": "1000000000"},
            content=npy(feats), headers={"content-type": "application/x-npy"}), server)
        row("1", ".npy /predict ?points=1e10", lambda: post(server, "/predict", params={"points": "10000000000"},
            content=npy(feats), headers={"content-type": "application/x-npy"}), server)
        row("1", ".npy /predict 100,000 designs x 1,000 points", lambda: post(
            server, "/predict", params={"points": "1000"}, content=npy(sample_designs(100_000, seed=1).features()),
            headers={"content-type": "application/x-npy"}), server)
        row("1", ".npy header claiming 1e12 designs", lambda: post(
            server, "/predict", content=lying_npy(feats, 10**12),
            headers={"content-type": "application/x-npy"}), server)
        row("2", "/exact 2,000 loaded designs (about 800 s of work)", lambda: post(
            server, "/exact", json={"designs": [{**d, **LOADED} for d in ONE] * 2000}), server)
        row("2", "then /exact of 1 design", lambda: post(server, "/exact", json={"designs": ONE}), server)
        row("2", "/exact 30 loaded designs (admitted, about 12 s of work)", lambda: post(
            server, "/exact", json={"designs": [{**d, **LOADED} for d in ONE] * 30}), server)
        row("2", "then /exact of 1 design", lambda: post(server, "/exact", json={"designs": ONE}), server)
        row("3", "/exact flood (64 x 2,000 loaded designs, 10 s)",
            lambda: asyncio.run(predict_under_exact_flood(server)), server)
        row("4", "SIGKILL an idle solver process", lambda: killed_worker(server), server)
        row("5", "E = 1e308", lambda: post(server, "/predict", json={"designs": [{**ONE[0], "E": 1e308}]}), server)
        row("5", "tension = 1e30", lambda: post(server, "/predict", json={"designs": [
            {**ONE[0], "tendons": [{**t, "tension": 1e30} for t in ONE[0]["tendons"]]}]}), server)
        row("5", "E = 5e-324", lambda: post(server, "/predict", json={"designs": [{**ONE[0], "E": 5e-324}]}), server)
        row("6", "/exact E = 1e-308", lambda: post(server, "/exact", json={"designs": [{**ONE[0], "E": 1e-308}]}),
            server)
        row("6", "/exact tip_force [1e6, 0, 0]", lambda: post(server, "/exact", json={"designs": [
            {**ONE[0], "tip_force": [1e6, 0, 0]}]}), server)
        row("7", "request headers trickled a byte a second", lambda: slow_headers(server), server)
        row("7", "1,200 idle connections (cap 1,000)", lambda: half_open(server), server)
        row("8", "20,000 distinct 404 paths", lambda: metric_paths(server), server)
        row("10", "JSON as text/plain", lambda: post(server, "/predict", content=b'{"designs": []}',
            headers={"content-type": "text/plain"}), server)
        row("10", "10 MB model name (answer size)", lambda: model_name_answer(server), server)
        row("10", "/readyz shows a file path", lambda: str("/" in httpx.get(server.url + "/readyz").json().get(
            "problems", []).__str__()), server)
    before_kill = time.perf_counter()
    result = orphans_after_sigkill()
    ROWS.append(("9", "SIGKILL the server", result, time.perf_counter() - before_kill, float("nan")))
    print(f"| 9 | SIGKILL the server | {result} | {ROWS[-1][3]:.2f} | - |")


if __name__ == "__main__":
    main()
