"""The HTTP service in a real uvicorn process on a free loopback port (tiny models from conftest)."""

from __future__ import annotations

import asyncio
import io
import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from service.model import RETRY_SATURATED_S
from service.process import ServerProcess, child_pids
from tdcr import design_space, relative_l2
from tdcr.api.checks import InvalidRequest
from tdcr.api.validation import validate_json
from tdcr.clients.client import AsyncClient, Client, TDCRError
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch


@pytest.fixture(scope="module")
def server(tiny_models):
    _, models = tiny_models
    srv = ServerProcess(models, max_designs=3000, max_design_points=200_000, max_body_bytes=2_000_000,
                        exact_max_designs=300, exact_max_pending=2, exact_timeout_s=60)
    yield srv
    srv.stop()


def test_health_ready_models(server):
    assert httpx.get(server.url + "/healthz").json() == {"status": "alive"}
    ready = httpx.get(server.url + "/readyz").json()
    assert ready["ready"] and sorted(ready["models"]) == ["deeponet", "deeponet_pose", "deeponet_pose_loaded", "fno",
                                                          "fno_pose", "fno_pose_loaded"]
    models = httpx.get(server.url + "/models").json()
    assert set(models["models"]) == set(ready["models"])
    assert models["models"]["fno"]["inputs"]["design"] == ["B", 15]


@pytest.mark.parametrize("model", ["deeponet", "deeponet_pose", "fno", "fno_pose"])
def test_predict_json_matches_the_runtime(example_request, designs_from_json, server, tiny_models, model):
    from tdcr.surrogates.runtime import Surrogate

    r = httpx.post(server.url + "/predict", json={**example_request, "model": model})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["model"] == model and len(body["results"]) == 2
    feats = designs_from_json(example_request["designs"]).features()
    ref = Surrogate.load(tiny_models[1], model).predict(feats, np.linspace(0, 1, 5))
    for j, res in enumerate(body["results"]):
        np.testing.assert_allclose(res["tendons"], ref["tendons"][j], rtol=1e-6, atol=1e-9)
        assert np.array(res["rotation"]).shape == (5, 3, 3)
        assert res["in_distribution"] is True and res["warnings"] == []


def test_out_of_range_designs_are_flagged(example_request, server):
    design = json.loads(json.dumps(example_request["designs"][0]))
    design["tendons"][2]["tension"] = 6.5
    design["E"] = 5e10
    r = httpx.post(server.url + "/predict", json={"designs": [design], "s": [0.0, 0.5, 1.0], "model": "fno"})
    res = r.json()["results"][0]
    assert res["in_distribution"] is False
    assert any(w.startswith("E = 5e+10 Pa") for w in res["warnings"])
    assert any(w.startswith("tension_2 = 6.5 N is outside the trained range [0, 5]") for w in res["warnings"])


def test_binary_request_and_response_equal_json(server):
    feats = design_space.sample_designs(64, seed=4).features()
    with Client(server.url) as c:
        out = c.predict(feats, model="fno_pose", points=42)
        js = c.predict_json({"designs": DesignBatch.from_features(feats).to_dicts(), "model": "fno_pose"})
    assert out["model"] == "fno_pose" and out["tendons"].shape == (64, 42, 4, 3)
    np.testing.assert_allclose(out["tendons"], np.array([r["tendons"] for r in js["results"]]), rtol=1e-5, atol=1e-7)
    assert out["in_distribution"].all()
    with Client(server.url) as c:
        only = c.predict(feats, model="deeponet", outputs=["tendons"])
        assert "rotation" not in only and only["tendons"].shape == (64, 42, 4, 3)
        with pytest.raises(TDCRError, match="outputs: must be"):
            c.predict(feats, outputs=["everything"])


def test_async_client_and_exact_endpoint(example_request, designs_from_json, server):
    async def go():
        async with AsyncClient(server.url) as c:
            return await c.exact(example_request), await c.predict(design_space.sample_designs(3, seed=0).features())

    exact, pred = asyncio.run(go())
    sol = solve(designs_from_json(example_request["designs"]), np.linspace(0, 1, 5))
    for j, res in enumerate(exact["results"]):
        assert res["converged"] and res["residual"] < 1e-8
        assert relative_l2(np.array(res["tendons"])[None], sol.tendons[j][None])[0] < 1e-12
    assert pred["tendons"].shape == (3, 42, 4, 3)


def _tendons(n: int) -> list[dict]:
    return [{"offset": 0.01, "tension": 1.0}] * n


#: (request from the example request, status, message): one case per class of mistake
BAD = [
    (lambda ex: {"designs": [{"E": -3e10, "r": 1e-3, "L": 0.2, "tendons": _tendons(4)}]}, 422,
     "designs[0].E: must be in [1e+06, 1e+12] Pa, got -3e+10"),
    (lambda ex: {"designs": [ex["designs"][0], {"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": _tendons(3)}]}, 422,
     "designs[1].tendons: List should have at least 4 items after validation, not 3"),
    (lambda ex: {**ex, "s": [0.1, 1.01], "points": None}, 422, "s[1]: must be a fraction of L in [0, 1], got 1.01"),
    (lambda ex: {**ex, "points": 5000}, 422, "points: must be an integer from 2 to 1000, got 5000"),
    (lambda ex: {**ex, "points": 5, "s": [0.5]}, 422, "give either 'points' or 's', not both"),
    (lambda ex: {**ex, "model": "gpt"}, 404, "unknown model 'gpt'"),
    (lambda ex: {**ex, "model": ""}, 422, "model: String should have at least 1 character"),
    (lambda ex: {"designs": [ex["designs"][0]] * 3001}, 413, "3001 designs exceed the limit of 3000"),
    (lambda ex: {"designs": [ex["designs"][0]] * 1000, "points": 1000}, 413, "exceed the budget of"),
    (lambda ex: {"designs": [{**ex["designs"][0], "tip_force": [0, 0, 1]}], "model": "fno"}, 422,
     "designs[0].tip_force: model 'fno' takes no external loads"),
    (lambda ex: {"designs": [{**ex["designs"][0], "E": True}]}, 422, "designs[0].E: Input should be a valid number"),
]


@pytest.mark.parametrize("make, status, message", BAD)
def test_bad_predict_requests(example_request, server, make, status, message):
    r = httpx.post(server.url + "/predict", json=make(example_request))
    assert r.status_code == status, r.text
    assert message in r.json()["message"]


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_bad_bodies_and_limits(example_request, server):
    r = httpx.post(server.url + "/predict", content=b"{nope", headers={"content-type": "application/json"})
    assert r.status_code == 422 and "Invalid JSON" in r.json()["message"]
    npy = {"content-type": "application/x-npy"}
    r = httpx.post(server.url + "/predict", content=b"not npy", headers=npy)
    assert r.status_code == 422 and "not a valid .npy" in r.json()["message"]
    r = httpx.post(server.url + "/predict", content=_npy(np.full((2, 15), np.nan)), headers=npy)
    assert r.status_code == 422 and "designs[0].E: must be a finite number, got nan" in r.json()["message"]
    r = httpx.post(server.url + "/predict", params={"points": "-1"}, headers=npy,
                   content=_npy(design_space.sample_designs(2, seed=0).features()))
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "points"]
    assert "points: must be an integer from 2 to 1000, got -1" in r.json()["message"]
    big = b"[" + b" " * 2_100_000 + b"]"
    r = httpx.post(server.url + "/predict", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413
    r = httpx.post(server.url + "/exact", json={"designs": [example_request["designs"][0]] * 301})
    assert r.status_code == 413 and "301 designs exceed the limit of 300" in r.json()["message"]
    r = httpx.post(server.url + "/exact", json={"designs": [{"E": "x"}]})
    assert r.status_code == 422 and "designs[0].E" in r.json()["message"]
    assert httpx.get(server.url + "/nowhere").status_code == 404


def test_one_validation_path_gives_one_message(root, server, tiny_models, tmp_path):
    """The same bad designs sent to JSON /predict, .npy /predict, /exact, `tdcr solve` and
    `tdcr predict` get the same problems, worded the same."""
    features = design_space.sample_designs(2, seed=3).features()
    features[1, 0] = -1.0  # E
    features[1, design_space.LAYOUT.group("tension").start + 2] = -0.5
    body = {"designs": DesignBatch.from_features(features).to_dicts()}
    (tmp_path / "bad.json").write_text(json.dumps(body))
    answers = {
        "json /predict": httpx.post(server.url + "/predict", json=body).json()["message"],
        "npy /predict": httpx.post(server.url + "/predict", content=_npy(features),
                                   headers={"content-type": "application/x-npy"}).json()["message"],
        "/exact": httpx.post(server.url + "/exact", json=body).json()["message"],
    }
    for command in (["solve"], ["predict", "--models-dir", str(tiny_models[1]), "--model", "fno"]):
        done = subprocess.run([sys.executable, "-m", "tdcr.cli", *command, str(tmp_path / "bad.json")],
                              capture_output=True, text=True, cwd=root, timeout=120)
        assert done.returncode == 2, done.stderr
        answers[f"tdcr {command[0]}"] = done.stderr.split("invalid request:")[1]
    expected = {"designs[1].E: must be in [1e+06, 1e+12] Pa, got -1",
                "designs[1].tendons[2].tension: must be in [0, 1000] N, got -0.5"}
    for where, text in answers.items():
        lines = {line.strip() for line in text.replace(";", "\n").splitlines() if line.strip()}
        assert lines == expected, where


def test_metrics_count_requests_designs_and_errors(example_request, server):
    httpx.post(server.url + "/predict", json={**example_request, "model": "deeponet"})
    assert httpx.post(server.url + "/predict", json={"designs": [{"E": -1}]}).status_code == 422
    text = httpx.get(server.url + "/metrics").text
    assert 'tdcr_requests_total{endpoint="/predict",protocol="http",status="200"}' in text
    assert 'tdcr_designs_total{endpoint="/predict",model="deeponet",protocol="http"}' in text
    assert 'tdcr_errors_total{endpoint="/predict",kind="validation",protocol="http"}' in text
    assert "tdcr_request_seconds_bucket" in text and "process_resident_memory_bytes" in text
    assert 'tdcr_graph_run_designs_count{model="deeponet"}' in text


async def solver_slots_in_use(client: httpx.AsyncClient) -> float:
    """The service's ``tdcr_solver_slots_in_use`` gauge, read from its /metrics."""
    families = text_string_to_metric_families((await client.get("/metrics")).text)
    return next(f.samples[0].value for f in families if f.name == "tdcr_solver_slots_in_use")


def test_exact_saturation_gives_503_and_the_deadline_504(example_request, tiny_models):
    """One slot and a 0.3 s deadline: a request that finds the slot taken gets 503 at once, with
    Retry-After (the client raises it as ``retry_after``, or with ``retry_for`` waits and sends again
    until the slot is free, and while the only solver process restarts after the deadline's kill);
    the slow one gets 504."""
    srv = ServerProcess(tiny_models[1], exact_max_pending=1, exact_timeout_s=0.3, exact_seconds_per_design=1e-6,
                        exact_seconds_per_loaded_design=1e-6, wait_for_paths=("loaded",))
    try:  # 400 loaded designs at 400 points: seconds of the compiled solver
        slow = {"designs": [{**example_request["designs"][1], "tip_force": [0.01, 0.0, 0.0]}] * 400, "points": 400}

        async def go():
            async with httpx.AsyncClient(base_url=srv.url, timeout=120) as c:
                assert await solver_slots_in_use(c) == 0
                first = asyncio.create_task(c.post("/exact", json=slow))
                given_up = time.monotonic() + 30.0
                while await solver_slots_in_use(c) < 1:  # until the slow request holds the only slot
                    assert time.monotonic() < given_up, "the slow request never took the solver slot"
                    await asyncio.sleep(0.005)
                second = await c.post("/exact", json=example_request)
                with pytest.raises(TDCRError, match="saturated") as refused:
                    async with AsyncClient(srv.url) as impatient:
                        await impatient.exact(example_request)
                statuses = []

                async def seen(response):
                    statuses.append(response.status_code)

                async with AsyncClient(srv.url, retry_for=30.0, event_hooks={"response": [seen]}) as patient:
                    waited = await patient.exact(example_request)
                return await first, second, refused.value, waited, statuses, await solver_slots_in_use(c)

        first, second, refused, waited, statuses, slots_after = asyncio.run(go())
        assert second.status_code == 503 and "saturated" in second.json()["message"]
        assert second.headers["retry-after"] == str(RETRY_SATURATED_S)
        assert refused.status == 503 and refused.retry_after == RETRY_SATURATED_S
        assert len(waited["results"]) == len(example_request["designs"])
        assert statuses[-1] == 200 and set(statuses[:-1]) <= {503}, statuses  # 503s while the slot was taken
        assert first.status_code == 504 and "did not finish within 0.3 s" in first.json()["message"]
        assert slots_after == 0  # every slot given back, the killed request's too
    finally:
        srv.stop()


def test_client_raises_with_the_server_message(server):
    with Client(server.url) as c, pytest.raises(TDCRError, match="unknown model"):
        c.predict(design_space.sample_designs(2, seed=0).features(), model="nope")


def test_loadtest_cli_against_the_server(root, server):
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "loadtest", "--url", server.url, "--concurrency", "1,4",
                          "--batch", "1,32", "--requests", "40", "--seconds", "5"],
                         capture_output=True, text=True, cwd=root, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.count("| json |") == 4 and "server memory" in out.stdout
    bad = subprocess.run([sys.executable, "-m", "tdcr.cli", "loadtest", "--url", server.url, "--batch", "x"],
                         capture_output=True, text=True, cwd=root, timeout=60)
    assert bad.returncode == 2


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)
tendon = st.fixed_dictionaries({"offset": finite, "pitch": finite, "tension": finite})
design = st.fixed_dictionaries({"E": finite, "r": finite, "L": finite,
                                "tendons": st.lists(tendon, min_size=0, max_size=6)})
anything = st.recursive(st.none() | st.booleans() | finite | st.text(max_size=5),
                        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c, max_size=3),
                        max_leaves=8)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(body=st.one_of(st.fixed_dictionaries({"designs": st.lists(design, max_size=3)},
                                            optional={"points": st.integers(-5, 2000), "model": st.text(max_size=8),
                                                      "s": st.lists(finite, max_size=4)}), anything))
def test_hypothesis_never_a_server_error(server, body):
    try:
        payload = json.dumps(body, allow_nan=True)
    except (TypeError, ValueError):
        return
    r = httpx.post(server.url + "/predict", content=payload, headers={"content-type": "application/json"})
    # the oracle: the one validation path, in process (a 404 is an unknown model, a 413 a size limit)
    try:
        validate_json(payload, target="surrogate")
        problems = None
    except InvalidRequest as exc:
        problems = exc.problems
    if problems is None:
        assert r.status_code in (200, 404), r.text  # valid for the core: answered, or a model it lacks
        if r.status_code == 200:
            results = r.json()["results"]
            assert len(results) == len(body["designs"])
            for res in results:
                assert np.isfinite(np.array(res["tendons"])).all()
    else:
        assert r.status_code in (413, 422), r.text
        detail = r.json()["detail"]
        assert detail and all(item["loc"] and item["msg"] for item in detail), detail  # each names a field


def test_the_answering_routes_and_their_dependency_run_on_the_event_loop():
    """FastAPI hands a sync dependency or endpoint to a worker thread on every request (a round trip
    that cost as much as ``GET /healthz`` itself): the state dependency, the routes that answer
    designs and the probes are coroutines (docs/results.md, issue #34)."""
    import inspect

    from service.deps import get_state
    from service.routers import exact, health, inverse, predict, v2

    for fn in (get_state, predict.predict, exact.exact, inverse.inverse, v2.infer, health.healthz, health.readyz,
               v2.live, v2.ready):
        assert inspect.iscoroutinefunction(fn), f"{fn.__module__}.{fn.__name__} is sync: a worker thread per call"


def test_openapi_document_is_committed_and_current(root):
    from service.app import create_app

    committed = json.loads((root / "openapi" / "openapi.json").read_text())
    assert committed == json.loads(json.dumps(create_app().openapi())), "run `tdcr openapi` and commit"


@pytest.mark.skipif(not Path("/proc").exists(), reason="needs /proc")
def test_stopping_the_server_stops_its_solver_processes(tiny_models):
    srv = ServerProcess(tiny_models[1])
    kids = child_pids(srv.proc.pid)
    assert kids, "the /exact solver pool should run in child processes"
    srv.stop()  # SIGTERM, as docker stop and the process manager send
    deadline = time.time() + 15
    while time.time() < deadline and any(Path(f"/proc/{k}").exists() for k in kids):
        time.sleep(0.2)
    assert not [k for k in kids if Path(f"/proc/{k}").exists()]


def _fractions_of(length: float) -> list[float]:
    """Arclength fractions as a client computes them, s / L: at the tip 1.0000000000000002 or so."""
    s = np.linspace(0.0, length, 42) * (1 + 1.5e-12)  # the tip lands at 1 + 1.5e-12
    return (s / length).tolist()


def test_fractions_within_rounding_are_clamped_and_beyond_refused(example_request, server):
    design = example_request["designs"][0]
    length = design["L"]
    fractions = _fractions_of(length)
    assert fractions[-1] > 1.0
    for route in ("/predict", "/exact"):
        r = httpx.post(server.url + route, json={"designs": [design], "s": fractions}, timeout=60)
        assert r.status_code == 200, r.text
        result = r.json()["results"][0]
        assert result["s"][-1] == 1.0 and result["arclength"][-1] == pytest.approx(length, rel=1e-15)  # clamped
        r = httpx.post(server.url + route, json={"designs": [design], "s": fractions[:-1] + [1 + 1e-8]}, timeout=60)
        assert r.status_code == 422 and "s[41]: must be a fraction of L in [0, 1]" in r.json()["message"]
    features = np.array([[design["E"], design["r"], length, *[t["offset"] for t in design["tendons"]],
                          *[t["pitch"] for t in design["tendons"]], *[t["tension"] for t in design["tendons"]]]])
    buf = io.BytesIO()
    np.save(buf, features)
    for tip, status in ((1 + 1.5e-12, 200), (1 + 1e-8, 422)):
        r = httpx.post(server.url + "/predict", params=[("s", "0"), ("s", "0.5"), ("s", repr(tip))],
                       content=buf.getvalue(), headers={"content-type": "application/x-npy"}, timeout=60)
        assert r.status_code == status, r.text
