"""Reliability of /exact's solver processes against a real server: deadlines stop the work, dead
workers are replaced, and no solver process outlives the server."""

from __future__ import annotations

import asyncio
import io
import os
import pickle
import signal
import socket
import time
from pathlib import Path

import httpx
import numpy as np
import orjson
import pytest

from service.process import PATHS_TIMEOUT_S, ServerProcess, child_pids, solver_pids

pytestmark = pytest.mark.skipif(not Path("/proc").exists(), reason="needs /proc")


def _alive(pids: list[int]) -> list[int]:
    alive = []
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.append(pid)
    return alive


def _wait(condition, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.1)
    return condition()


@pytest.fixture(scope="module")
def server(tiny_models):
    # admission estimates made small, so that work past the deadline is admitted and killed
    srv = ServerProcess(tiny_models[1], exact_timeout_s=3, exact_workers=1, exact_max_pending=4,
                        max_body_bytes=2_000_000, exact_seconds_per_loaded_design=1e-4,
                        wait_for_paths=("loaded",))
    yield srv
    srv.stop()


def test_a_timed_out_request_stops_its_work(server, example_request):
    """The heavy request's worker is killed at the deadline, so a small request right after it is
    answered by a fresh worker instead of queueing behind the abandoned work."""
    # 1,000 loaded designs at 1,000 points: about 30 s of the compiled solver, far past the 3 s deadline
    heavy = {"designs": [{**example_request["designs"][1], "tip_force": [0.01, 0.0, 0.0]}] * 1000, "points": 1000}
    workers = solver_pids(server.proc.pid)
    assert workers
    r = httpx.post(server.url + "/exact", json=heavy, timeout=60)
    assert r.status_code == 504, r.text
    assert _wait(lambda: not _alive(workers)), "the timed-out worker is still running"
    small = httpx.post(server.url + "/exact", json=example_request, timeout=60)
    assert small.status_code == 200, small.text


def test_one_worker_serves_request_after_request(server, example_request):
    """The pipe to a worker stays usable across requests and pauses (an event loop that polled
    its fd once left it non-blocking, and the next exchange failed as if the worker had died)."""
    workers = _alive(solver_pids(server.proc.pid))
    for _ in range(4):
        r = httpx.post(server.url + "/exact", json={"designs": example_request["designs"] * 20}, timeout=60)
        assert r.status_code == 200, r.text
        time.sleep(0.5)
    assert _alive(solver_pids(server.proc.pid)) == workers


def test_a_killed_worker_is_replaced(server, example_request):
    before = _alive(solver_pids(server.proc.pid))
    assert before
    for pid in before:
        os.kill(pid, signal.SIGKILL)
    assert _wait(lambda: httpx.get(server.url + "/readyz").status_code == 200
                 and set(_alive(solver_pids(server.proc.pid))) - set(before))
    r = httpx.post(server.url + "/exact", json=example_request, timeout=60)
    assert r.status_code == 200, r.text


def test_solver_processes_die_with_a_killed_server(tiny_models):
    srv = ServerProcess(tiny_models[1], exact_workers=2)
    workers = _alive(child_pids(srv.proc.pid))  # the solvers and multiprocessing's resource tracker
    assert len(solver_pids(srv.proc.pid)) == 2
    srv.proc.send_signal(signal.SIGKILL)
    srv.proc.wait()
    srv.stop(check=False)
    assert _wait(lambda: not _alive(workers), 15), f"orphans: {_alive(workers)}"


def test_access_controls(tiny_models, example_request):
    """API keys on every route but health, a key of its own for /metrics, JSON only as JSON, docs off."""
    srv = ServerProcess(tiny_models[1], api_keys='["k1", "k2"]', metrics_api_key="m", docs="false")
    try:
        url = srv.url
        assert httpx.get(url + "/healthz").status_code == 200 and httpx.get(url + "/readyz").status_code == 200
        assert httpx.post(url + "/predict", json=example_request).status_code == 401
        assert httpx.post(url + "/predict", json=example_request, headers={"x-api-key": "nope"}).status_code == 401
        for headers in ({"x-api-key": "k2"}, {"authorization": "Bearer k1"}):
            assert httpx.post(url + "/predict", json=example_request, headers=headers).status_code == 200
        assert httpx.get(url + "/metrics", headers={"x-api-key": "k1"}).status_code == 401
        assert httpx.get(url + "/metrics", headers={"x-api-key": "m"}).status_code == 200
        plain = httpx.post(url + "/predict", content=httpx.Request("POST", url, json=example_request).content,
                           headers={"x-api-key": "k1", "content-type": "text/plain"})
        assert plain.status_code == 415 and "application/json" in plain.json()["message"]
        assert httpx.get(url + "/docs", headers={"x-api-key": "k1"}).status_code == 404
        preflight = {"origin": "http://evil.example", "access-control-request-method": "POST"}
        assert "access-control-allow-origin" not in httpx.options(url + "/predict", headers=preflight).headers
    finally:
        srv.stop()


def test_metric_labels_never_hold_user_input(server):
    for i in range(30):
        assert httpx.get(f"{server.url}/no/such/path/{i}").status_code == 404
    text = httpx.get(server.url + "/metrics").text
    assert "/no/such/path" not in text
    assert 'tdcr_errors_total{endpoint="other",kind="http_404",protocol="http"}' in text


def test_readiness_shows_no_file_paths(server, tiny_models):
    body = httpx.get(server.url + "/readyz").text
    assert str(tiny_models[1]) not in body and "/tmp" not in body


def test_minor_protocol_details(server, example_request):
    """405 names the allowed methods; bad UTF-8 is a documented 422; ?s= with ?points= is refused;
    a 413 of a streamed body is counted as 413, not 500."""
    r = httpx.get(server.url + "/predict")
    assert r.status_code == 405 and r.headers["allow"] == "POST"
    r = httpx.post(server.url + "/exact", content=b'{"designs": "\xff\xfe"}',
                   headers={"content-type": "application/json"})
    assert r.status_code == 422 and "detail" in r.json()
    features = np.zeros((1, 15))
    buf = io.BytesIO()
    np.save(buf, features)
    r = httpx.post(server.url + "/predict", params=[("points", "5"), ("s", "0.5")], content=buf.getvalue(),
                   headers={"content-type": "application/x-npy"})
    assert r.status_code == 422 and "give either 'points' or 's'" in r.json()["message"]

    def chunks():
        for _ in range(40):
            yield b" " * 100_000

    r = httpx.post(server.url + "/predict", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    text = httpx.get(server.url + "/metrics").text
    assert 'tdcr_requests_total{endpoint="/predict",protocol="http",status="413"}' in text
    assert 'status="500"' not in text


@pytest.fixture(scope="module")
def strict_server(tiny_models):
    srv = ServerProcess(tiny_models[1], header_timeout_s=1, body_timeout_s=1, max_connections=20)
    yield srv
    srv.stop()


def _closed_by_server(sock: socket.socket, trickle: bytes) -> bool:
    """Send ``trickle`` a byte every 0.2 s until the server closes the connection (True) or 15 s
    pass (False)."""
    sock.settimeout(0.2)
    deadline = time.monotonic() + 15
    i = 0
    while time.monotonic() < deadline:
        try:
            if sock.recv(1024) == b"":
                return True
        except TimeoutError:
            pass
        except (ConnectionResetError, BrokenPipeError):
            return True
        try:
            sock.send(trickle[i % len(trickle):i % len(trickle) + 1])
        except (ConnectionResetError, BrokenPipeError):
            return True
        i += 1
    return False


def test_slow_headers_and_slow_bodies_are_disconnected(strict_server):
    with socket.create_connection(("127.0.0.1", strict_server.port)) as sock:
        sock.send(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        assert _closed_by_server(sock, b"X-Slow: 1\r\n")
    with socket.create_connection(("127.0.0.1", strict_server.port)) as sock:
        sock.send(b"POST /predict HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 100000\r\n\r\n")
        assert _closed_by_server(sock, b" ")
    assert httpx.get(strict_server.url + "/healthz").status_code == 200


def test_the_connection_cap_refuses_then_recovers(strict_server):
    idle = [socket.create_connection(("127.0.0.1", strict_server.port)) for _ in range(25)]
    try:
        r = httpx.get(strict_server.url + "/healthz")
        assert r.status_code == 503
    finally:
        for sock in idle:
            sock.close()
    assert _wait(lambda: httpx.get(strict_server.url + "/healthz").status_code == 200, 15)


def test_exact_refuses_work_its_deadline_cannot_cover(strict_server, example_request):
    """Defaults: 0.01 s per loaded design at 42 points, 30 s deadline, factor 3: 1,000 loaded designs
    at 1,000 points (238 s) are refused after parsing, before any solver work; a bad load is a 422
    naming the component."""
    heavy = {"designs": [{**example_request["designs"][1], "tip_force": [0.01, 0.0, 0.0]}] * 1000, "points": 1000}
    r = httpx.post(strict_server.url + "/exact", json=heavy, timeout=60)
    assert r.status_code == 413 and "would take the solver about 238 s" in r.json()["message"], r.text
    bad = {"designs": [{**example_request["designs"][0], "tip_force": [1e6, 0.0, 0.0]}]}
    r = httpx.post(strict_server.url + "/exact", json=bad)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "designs", 0, "tip_force", 0]
    assert "designs[0].tip_force[0]: must be in [-100, 100] N, got 1e+06" in r.json()["message"]


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_oversized_requests_allocate_nothing(server):
    """Defect 1: sizes are checked before allocating (points, a lying .npy header, designs x
    points, a huge model name); the server's RSS stays put and the answers stay small."""
    features = np.zeros((2, 15))
    buf = io.BytesIO()
    np.save(buf, features)
    lying = io.BytesIO()
    np.lib.format.write_array_header_1_0(lying, {"descr": "<f8", "fortran_order": False, "shape": (10**12, 15)})
    npy = {"content-type": "application/x-npy"}
    before = _rss_mb(server.proc.pid)
    for points in ("1000000000", "10000000000"):
        r = httpx.post(server.url + "/predict", params={"points": points}, content=buf.getvalue(), headers=npy)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "points"]
    r = httpx.post(server.url + "/predict", content=lying.getvalue() + features.tobytes(), headers=npy)
    assert r.status_code == 422 and "does not match" in r.json()["message"]
    r = httpx.post(server.url + "/predict", content=b'{"designs": [], "model": "' + b"x" * 1_000_000 + b'"}',
                   headers={"content-type": "application/json"})
    assert r.status_code == 422 and len(r.content) < 2000
    r = httpx.post(server.url + "/predict", content=b'{"designs": [{"' + b"k" * 1_000_000 + b'": 1}]}',
                   headers={"content-type": "application/json"})  # an unknown key is quoted, but short
    assert r.status_code == 422 and len(r.content) < 2000 and "kkkk..." in r.json()["message"]
    assert _rss_mb(server.proc.pid) - before < 50


def test_predict_stays_live_during_an_exact_flood(server, example_request):
    """Defect 3: while 32 clients flood /exact with large bodies, every /predict is answered (each
    within the 10 s client timeout; it took 6 ms unloaded and hung past 10 s before the fix)."""
    heavy = orjson.dumps({"designs": [{**example_request["designs"][1], "tip_force": [0.01, 0.0, 0.0]}] * 2000})
    light = orjson.dumps(example_request)
    headers = {"content-type": "application/json"}
    answers: list[int] = []

    async def go():
        stop = asyncio.get_running_loop().time() + 4.0

        async def flood(client):
            while asyncio.get_running_loop().time() < stop:
                try:
                    await client.post("/exact", content=heavy, headers=headers)
                except httpx.TransportError:  # refused by closing the connection
                    pass

        async def probe(client):
            while asyncio.get_running_loop().time() < stop:
                answers.append((await client.post("/predict", content=light, headers=headers)).status_code)

        async with httpx.AsyncClient(base_url=server.url, timeout=60, limits=httpx.Limits(max_connections=64)) as a, \
                httpx.AsyncClient(base_url=server.url, timeout=10) as b:
            await asyncio.gather(*[flood(a) for _ in range(32)], probe(b))

    asyncio.run(go())
    assert answers and set(answers) == {200}


def test_solver_workers_outlive_the_thread_that_started_the_pool():
    """Linux's parent-death signal follows the thread that started a process: a pool built on a
    short-lived thread (the lifespan's worker thread) once lost its workers when that thread ended."""
    import threading

    from service.solver_pool import SolverPool

    built = {}
    starter = threading.Thread(target=lambda: built.setdefault("pool", SolverPool(1)))
    starter.start()
    starter.join()
    time.sleep(1.0)  # the signal, if any, has arrived
    pool = built["pool"]
    try:
        assert all(w.process.is_alive() for w in pool.workers)
    finally:
        pool.close()


def test_a_pool_says_which_solver_paths_its_processes_still_compile():
    """Each solver process sets a shared flag per path as it compiles it (or loads it from the cache),
    after the default path it says ready with: the pool's ``compiling`` (``/readyz``'s) lists the others
    until every process has them, and a process's own check (``cold_paths``) reads the same flags."""
    from service.solver_pool import SolverPool, cold_paths
    from tdcr.physics.exact import DEFAULT_PATHS, PATHS

    pool = SolverPool(2)
    try:
        assert set(pool.compiling()) <= set(PATHS) - set(DEFAULT_PATHS)  # said ready: the default path is in
        deadline = time.monotonic() + PATHS_TIMEOUT_S  # a machine's first start compiles them (two minutes)
        while pool.compiling() and time.monotonic() < deadline:
            time.sleep(0.5)
        assert pool.compiling() == []
        assert [list(w.warm) for w in pool.workers] == [[1] * len(PATHS)] * 2

        async def in_each_process():  # both processes at once: each answers one
            return sorted(await asyncio.gather(*(pool.run(cold_paths, PATHS, timeout=60) for _ in pool.workers)))

        assert asyncio.run(in_each_process()) == [[], []]
        pool.workers[0].warm[PATHS.index("loaded")] = 0  # as a replaced process before it has loaded the path
        assert pool.compiling() == ["loaded"]
        assert asyncio.run(in_each_process()) == [[], ["loaded"]]
    finally:
        pool.close()


def test_waiting_for_a_free_worker_past_the_deadline_is_a_refusal_not_a_deadline():
    """A request that finds no worker free within its deadline never started: the pool raises
    ``NoFreeWorker`` (the service's 503 "saturated" with Retry-After), not ``TimeoutError`` (504), and
    leaves the busy worker alone.  (After a deadline's kill, the only worker restarting took longer
    than a 0.3 s deadline on a slow machine, and a client that waited politely got 504.)"""
    from service.solver_pool import NoFreeWorker, SolverPool

    pool = SolverPool(1)
    try:
        async def go():
            busy = asyncio.create_task(pool.run(time.sleep, 3.0, timeout=60))
            await asyncio.sleep(0.5)
            with pytest.raises(NoFreeWorker, match="within 0.2 s"):
                await pool.run(time.sleep, 0.0, timeout=0.2)
            return await busy

        worker = pool.workers[0]
        assert asyncio.run(go()) is None
        assert pool.workers == [worker] and worker.process.is_alive()
    finally:
        pool.close()


def test_a_request_on_a_path_still_compiling_is_answered_starting_at_once(root, monkeypatch):
    """In a solver process that has compiled only the default path (a machine's first start), a request
    that needs another path is refused as "unavailable" (503, retry) at once: waiting for numba's
    compiler, it ran into the 30 s deadline, whose kill threw the compilation away (a robot file's
    design, displacement-driven, got 504 on a cold start).  Outside the solver processes nothing is
    refused."""
    from service import solver, solver_pool
    from service.model import RETRY_STARTING_S, InferenceError
    from tdcr.api.validation import validate_json
    from tdcr.physics.exact import PATHS, paths_of

    requests = {name: validate_json((root / "examples" / name).read_text(), target="solver")
                for name in ("request.json", "request_loaded.json", "ftdcr_v4_fitted.json")}
    assert [sorted(paths_of(r)) for r in requests.values()] == [["tendon"], ["loaded"], ["displacement"]]
    for request in requests.values():  # not a solver process: no check
        solver._refuse_cold(request)
    monkeypatch.setattr(solver_pool, "_WARM", [int(path in ("tendon", "loaded")) for path in PATHS])
    solver._refuse_cold(requests["request.json"])
    solver._refuse_cold(requests["request_loaded.json"])
    with pytest.raises(InferenceError) as refused:
        solver.solve_job(requests["ftdcr_v4_fitted.json"], None)
    assert refused.value.kind == "unavailable" and "compiles its displacement path" in str(refused.value)
    piped = pickle.loads(pickle.dumps(refused.value))  # as it crosses the solver process's pipe
    assert (piped.kind, piped.message, piped.retry_after) == ("unavailable", refused.value.message, RETRY_STARTING_S)
