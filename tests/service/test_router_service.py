"""The router as the service's default (service/routed.py): a real server on the shipped models with
given costs (so the choice does not depend on this machine's speed), over /predict, OIP v2 REST and
gRPC."""

from __future__ import annotations

import json

import grpc
import httpx
import numpy as np
import pytest

from service.process import ROOT, ServerProcess
from tdcr import design_space
from tdcr.clients.loadtest import grpc_request
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc

#: the solver at 1 ms a design, an operator at 20 ms a call: the solver answers fewer than 20 designs
COSTS = {"exact": [0.0, 1e-3], "exact_loaded": [0.0, 5e-2], "operator": [2e-2, 1e-6], "loaded_operator": [2e-2, 1e-6]}


@pytest.fixture(scope="module")
def server():
    with ServerProcess(ROOT / "models", router_costs=json.dumps(COSTS)) as srv:
        yield srv


def _body(n: int, seed: int, **extra) -> dict:
    return {"designs": design_space.sample_designs(n, seed=seed).to_dicts(), "points": 42} | extra


def test_predict_without_a_model_is_the_routers_and_a_few_designs_are_solved_exactly(server):
    body = _body(3, 4280)
    r = httpx.post(server.url + "/predict", json=body, timeout=60)
    assert r.status_code == 200, r.text
    answer = r.json()
    assert answer["model"] == "exact" and [x["source"] for x in answer["results"]] == ["exact"] * 3
    exact = httpx.post(server.url + "/exact", json=body, timeout=60).json()["results"]
    for mine, theirs in zip(answer["results"], exact, strict=True):
        assert mine["error_bound"] == 1e-6 and mine["tendons"] == theirs["tendons"]
    # many designs: the default operator, every answer bounded
    r = httpx.post(server.url + "/predict", json=_body(40, 4281), timeout=60)
    answer = r.json()
    assert answer["model"] == "deeponet_pose_loaded"
    assert all(x["source"] == "surrogate" and x["error_bound"] < 0.01 for x in answer["results"])


def test_a_named_model_is_served_as_asked(server):
    r = httpx.post(server.url + "/predict", json=_body(1, 4282, model="deeponet"), timeout=60)
    assert r.status_code == 200 and r.json()["model"] == "deeponet"
    assert r.json()["results"][0]["source"] == "surrogate"


def test_designs_with_loads_go_to_the_loaded_operator(server):
    body = _body(1, 4283)
    body["designs"][0] |= {"gravity": [0.0, -9.81, 0.0], "density": 7000.0}
    answer = httpx.post(server.url + "/predict", json=body, timeout=60).json()
    assert answer["model"] == "deeponet_pose_loaded" and answer["results"][0]["source"] == "surrogate"


def test_the_router_is_an_oip_model_with_its_costs_and_readiness(server):
    meta = httpx.get(server.url + "/v2/models/auto").json()
    assert meta["platform"] == "tdcr_router" and meta["parameters"]["operator"] == "deeponet_pose_loaded"
    assert meta["parameters"]["exact_seconds"] == "0: 0 s, 1: 0.001 s"
    assert httpx.get(server.url + "/v2/models/auto/ready").status_code == 200
    assert httpx.get(server.url + "/readyz").json()["default_model"] == "auto"


def test_grpc_model_infer_on_auto_answers_one_design_exactly(server):
    features = design_space.sample_designs(1, seed=4284).features()
    with grpc.insecure_channel(server.grpc_target) as channel:
        request = grpc_request("auto", features, "tendons,error_bound,source")
        reply = pb_grpc.GRPCInferenceServiceStub(channel).ModelInfer(request)
    outputs = {o.name: i for i, o in enumerate(reply.outputs)}
    source = np.frombuffer(reply.raw_output_contents[outputs["source"]], dtype="<i4")
    assert source.tolist() == [1]
    bound = np.frombuffer(reply.raw_output_contents[outputs["error_bound"]], dtype="<f4")
    assert bound.tolist() == [np.float32(1e-6)]
