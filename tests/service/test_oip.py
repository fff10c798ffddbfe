"""The Open Inference Protocol v2 over REST, against a real server: JSON and binary tensors, the
answers equal to /predict and /exact, errors naming the tensor, and Triton's own client (in its own
process, as a user would run it: examples/tritonclient_http.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import numpy as np
import orjson
import pytest

from service.process import ServerProcess
from tdcr.robot.design_space import sample_designs
from tdcr.robot.designs import DesignBatch

MODELS = ["deeponet", "deeponet_pose", "fno", "fno_pose"]


@pytest.fixture(scope="module")
def server(tiny_models):
    srv = ServerProcess(tiny_models[1], max_designs=500)
    yield srv
    srv.stop()


def _design_input(features: np.ndarray, binary: bool) -> tuple[dict, bytes]:
    spec = {"name": "design", "shape": list(features.shape), "datatype": "FP64"}
    if binary:
        blob = np.ascontiguousarray(features, dtype="<f8").tobytes()
        return spec | {"parameters": {"binary_data_size": len(blob)}}, blob
    return spec | {"data": features.reshape(-1).tolist()}, b""


def _infer(url: str, model: str, features: np.ndarray, *, binary: bool, outputs=None) -> dict[str, np.ndarray]:
    spec, blob = _design_input(features, binary)
    request = {"inputs": [spec], "parameters": {"binary_data_output": binary}}
    if outputs:
        request["outputs"] = [{"name": n} for n in outputs]
    head = orjson.dumps(request)
    headers = {"content-type": "application/octet-stream" if binary else "application/json"}
    if binary:
        headers["inference-header-content-length"] = str(len(head))
    r = httpx.post(f"{url}/v2/models/{model}/infer", content=head + blob, headers=headers, timeout=60)
    assert r.status_code == 200, r.text
    length = int(r.headers.get("inference-header-content-length", len(r.content)))
    body = orjson.loads(r.content[:length])
    assert body["model_name"] == model
    out, offset = {}, length
    for o in body["outputs"]:
        dtype = {"FP32": "<f4", "FP64": "<f8", "BOOL": "?", "INT32": "<i4"}[o["datatype"]]
        if "parameters" in o:
            size = o["parameters"]["binary_data_size"]
            out[o["name"]] = np.frombuffer(r.content, dtype=dtype, count=size // np.dtype(dtype).itemsize,
                                           offset=offset).reshape(o["shape"])
            offset += size
        else:
            out[o["name"]] = np.asarray(o["data"], dtype=dtype).reshape(o["shape"])
    return out


def test_health_and_metadata(server):
    assert httpx.get(server.url + "/v2/health/live").json() == {"live": True}
    assert httpx.get(server.url + "/v2/health/ready").json() == {"ready": True}
    assert "binary_tensor_data" in httpx.get(server.url + "/v2").json()["extensions"]
    for model in [*MODELS, "exact"]:
        for path in (f"/v2/models/{model}", f"/v2/models/{model}/versions/1"):
            meta = httpx.get(server.url + path).json()
            assert meta["name"] == model and {i["name"] for i in meta["inputs"]} >= {"design", "s"}
            assert {o["name"] for o in meta["outputs"]} >= {"backbone", "rotation", "tendons", "in_distribution"}
        assert httpx.get(f"{server.url}/v2/models/{model}/ready").status_code == 200
    assert "sha256" in httpx.get(server.url + "/v2/models/fno").json()["parameters"]
    assert httpx.get(server.url + "/v2/models/nope").status_code == 404
    assert httpx.get(server.url + "/v2/models/fno/versions/2").status_code == 404


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("binary", [False, True])
def test_inference_equals_predict(server, model, binary):
    features = sample_designs(5, seed=8).features()
    out = _infer(server.url, model, features, binary=binary)
    ref = httpx.post(server.url + "/predict", json={"designs": DesignBatch.from_features(features).to_dicts(),
                                                    "model": model}).json()["results"]
    for name in ("backbone", "rotation", "tendons"):
        np.testing.assert_allclose(out[name], np.array([r[name] for r in ref]), rtol=1e-6, atol=1e-9)
    assert out["in_distribution"].tolist() == [r["in_distribution"] for r in ref]
    assert out["tendons"].dtype == np.float32 and out["tendons"].shape == (5, 42, 4, 3)


def test_the_solver_as_a_model_equals_exact(server):
    features = sample_designs(3, seed=9).features()
    out = _infer(server.url, "exact", features, binary=True, outputs=["tendons", "converged", "residual"])
    r = httpx.post(server.url + "/exact", json={"designs": DesignBatch.from_features(features).to_dicts()}, timeout=60)
    assert r.status_code == 200, r.text
    ref = r.json()
    np.testing.assert_allclose(out["tendons"], np.array([r["tendons"] for r in ref["results"]]), rtol=1e-6, atol=1e-9)
    assert out["converged"].all() and out["residual"].dtype == np.float64 and set(out) == {"tendons", "converged",
                                                                                            "residual"}
    status = _infer(server.url, "exact", features, binary=False, outputs=["status", "error_estimate"])
    assert status["status"].tolist() == [0, 0, 0]
    np.testing.assert_allclose(status["error_estimate"], [x["error_estimate"] for x in ref["results"]], rtol=1e-12)


def _post(server, model: str, request: dict) -> httpx.Response:
    return httpx.post(f"{server.url}/v2/models/{model}/infer", json=request)


def test_bad_tensors_get_a_clear_error(server):
    good = sample_designs(2, seed=0).features()
    spec = {"name": "design", "shape": [2, 15], "datatype": "FP64", "data": good.reshape(-1).tolist()}
    cases = [
        ({"inputs": [spec | {"name": "designs"}]}, 400, "unexpected input 'designs'"),
        ({"inputs": [spec | {"shape": [2, 14]}]}, 400, "input 'design': shape must be [-1, 15]"),
        ({"inputs": [spec | {"datatype": "INT32"}]}, 400, "input 'design': datatype must be one of"),
        ({"inputs": [spec | {"shape": [501, 15], "data": np.tile(good[0], 501).tolist()}]}, 413,
         "501 designs exceed the limit of 500"),
        ({"inputs": [spec], "outputs": [{"name": "everything"}]}, 400, "unknown output 'everything'"),
        ({"inputs": []}, 400, "missing input(s) ['design']"),
    ]
    for request, status, message in cases:
        r = httpx.post(f"{server.url}/v2/models/fno/infer", content=json.dumps(request, allow_nan=True),
                       headers={"content-type": "application/json"})
        assert r.status_code == status, (message, r.text)
        assert message in r.json()["error"], r.json()
    assert _post(server, "nope", {"inputs": [spec]}).status_code == 404
    bad = good.copy()
    bad[0, 0] = np.nan  # JSON has no NaN: it comes as a binary tensor
    nan_spec, blob = _design_input(bad, binary=True)
    head = orjson.dumps({"inputs": [nan_spec]})
    r = httpx.post(server.url + "/v2/models/fno/infer", content=head + blob,
                   headers={"inference-header-content-length": str(len(head))})
    assert r.status_code == 400 and "designs[0].E: must be a finite number, got nan" in r.json()["error"]


def test_tritonclient_http(server, run_triton_example):
    """Triton's HTTP client, in its own process: binary tensors in and out on every model."""
    run_triton_example("http", server.url, server.url, MODELS)


def test_loadtest_speaks_v2(server, root):
    done = subprocess.run([sys.executable, "-m", "tdcr.cli", "loadtest", "--url", server.url, "--protocol", "v2",
                           "--concurrency", "1,4", "--batch", "1,32", "--requests", "30", "--seconds", "5"],
                          capture_output=True, text=True, cwd=root, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("| v2 binary |") == 4


def test_inverse_kinematics_model_over_rest(server):
    from tdcr.physics import solve

    design = sample_designs(1, seed=13)
    tip = solve(design, np.array([1.0])).backbone[0, -1]
    request = {"inputs": [{"name": "design", "shape": [1, 15], "datatype": "FP64",
                           "data": design.features().reshape(-1).tolist()},
                          {"name": "position", "shape": [1, 3], "datatype": "FP64", "data": tip.tolist()}],
               "outputs": [{"name": "status"}, {"name": "error"}]}
    r = _post(server, "inverse", request)
    assert r.status_code == 200, r.text
    outputs = {o["name"]: o["data"] for o in r.json()["outputs"]}
    assert outputs["status"] == [0] and outputs["error"][0] <= 1e-4 * design.L[0]
    two_designs = request | {"inputs": [request["inputs"][0] | {"shape": [2, 15], "data": [0.0] * 30}]}
    assert _post(server, "inverse", two_designs).status_code == 400


@pytest.mark.parametrize("model", ["deeponet", "fno_pose", "exact"])
def test_fractions_within_rounding_are_clamped_and_beyond_refused(server, model):
    """A client's s / L is 1.0000000000015 at the tip: accepted and clamped; 1 + 1e-8 is not."""
    features = sample_designs(2, seed=3).features()
    for tip, status in ((1 + 1.5e-12, 200), (1 + 1e-8, 400)):
        s = [0.0, 0.5, tip]
        request = {"inputs": [_design_input(features, False)[0],
                              {"name": "s", "shape": [3], "datatype": "FP64", "data": s}],
                   "outputs": [{"name": "backbone"}]}
        r = httpx.post(f"{server.url}/v2/models/{model}/infer", json=request, timeout=60)
        assert r.status_code == status, r.text
        if status == 400:
            assert "s[2]: must be a fraction of L in [0, 1]" in r.json()["error"]
        else:
            tip_z = np.asarray(r.json()["outputs"][0]["data"]).reshape(2, 3, 3)[:, -1, 2]
            assert (tip_z > 0).all()
