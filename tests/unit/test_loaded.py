"""The loaded operators (gravity and a tip wrench): the loaded reference robot against closed forms
and the exact loaded solver, the shipped models against the exact loaded solver, and every way a
model is used (Python, /predict JSON and .npy, OIP REST and gRPC, tdcr predict, /inverse).

Tolerances: the closed forms hold to first order in the load (a deflection of 1e-4 L: relative
1e-3); the shipped models' figures are measured in benchmarks/loaded_operators.py (docs/operators.md)
and the tests hold them to about 3x their measured mean on a smaller sample.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import httpx
import numpy as np
import pytest

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.surrogates.runtime import DEFAULT_MODELS_DIR, Surrogate, load_manifest

GRID = np.linspace(0.0, 1.0, 42)
SHIPPED = load_manifest(DEFAULT_MODELS_DIR)["models"]
LOADED = sorted(n for n, e in SHIPPED.items() if "loads" in e["inputs"])


def _benchmark(n: int, seed: int) -> tuple[DesignBatch, ExternalLoads]:
    return design_space.sample_designs(n, seed=seed), design_space.BENCHMARK_LOADS.sample(n, seed=seed)


# -- the loaded reference robot (in the graph: torch) ---------------------------------------------


@pytest.fixture(scope="module")
def kinematics():
    pytest.importorskip("torch")
    from training.operators import kinematics

    return kinematics


def _reference(kinematics, features, loads, fractions=None, *, iterations=4):
    import torch

    base_angle = 2.0 * math.pi * torch.arange(4, dtype=torch.float64) / 4
    ref = kinematics.loaded_reference(torch.as_tensor(features), torch.as_tensor(loads), torch.as_tensor(GRID),
                                      base_angle, None if fractions is None else torch.as_tensor(fractions),
                                      iterations=iterations)
    return ref, kinematics.batch_first(ref.tendons()).numpy()


def test_no_pass_is_the_linearized_reference_and_tangents_of_the_straight_rod_are_its_strains(kinematics):
    import torch

    designs, loads = _benchmark(20, seed=1)
    features = designs.features()
    ref, _ = _reference(kinematics, features, loads.matrix(20), iterations=0)
    base_angle = 2.0 * math.pi * torch.arange(4, dtype=torch.float64) / 4
    linear = kinematics.linearized_reference(torch.as_tensor(features), torch.as_tensor(GRID), base_angle)
    torch.testing.assert_close(ref.backbone, linear.backbone, rtol=0, atol=0)
    trig = kinematics.tendon_trig(torch.as_tensor(features), torch.as_tensor(GRID), base_angle)
    straight = torch.zeros(6, 42, 20, dtype=torch.float64)
    straight[2] = 1.0
    torch.testing.assert_close(kinematics.tendon_strains(torch.as_tensor(features), trig, straight),
                               kinematics.strain_prior(torch.as_tensor(features), torch.as_tensor(GRID), base_angle),
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("load", ["tip_force", "tip_moment", "weight"])
def test_small_loads_bend_a_cantilever_as_the_closed_forms(kinematics, load):
    """No tendon tension; tip force F: deflection F L^3 / (3 E I); tip moment M: M L^2 / (2 E I);
    weight per length w: w L^4 / (8 E I) (Euler-Bernoulli), each loading sideways along x."""
    e, r, length = 30e9, 1e-3, 0.2
    ei = e * math.pi * r**4 / 4
    design = DesignBatch(E=[e], r=[r], L=[length], offset=[[0.008] * 4], pitch=[[0.0] * 4], tension=[[0.0] * 4])
    target = 1e-4 * length  # tip deflection: small against L, so the linear theory holds to ~1e-4
    if load == "tip_force":
        force = target * 3 * ei / length**3
        loads, closed = ExternalLoads(tip_force=[[force, 0, 0]]), target
    elif load == "tip_moment":
        moment = target * 2 * ei / length**2
        loads, closed = ExternalLoads(tip_moment=[[0, moment, 0]]), target  # +y moment bends towards +x
    else:
        density = 7800.0
        g = target * 8 * ei / length**4 / (density * math.pi * r * r)
        loads, closed = ExternalLoads(gravity=[[g, 0, 0]], density=[density]), target
    exact = solve(design, GRID, loads=loads).backbone[0, -1, 0]
    ref, _ = _reference(kinematics, design.features(), loads.matrix(1))
    graph = float(ref.backbone[0, -1, 0])
    assert exact == pytest.approx(closed, rel=2e-3)
    assert graph == pytest.approx(closed, rel=2e-3)


def test_the_fixed_point_is_the_exact_tendon_only_solution(kinematics):
    designs = design_space.sample_designs(60, seed=3)
    _, tendons = _reference(kinematics, designs.features(), np.zeros((60, 10)), iterations=8)
    err = relative_l2(tendons, solve(designs, GRID).tendons)
    assert np.median(err) < 1e-5 and np.percentile(err, 90) < 1e-3  # Magnus on 42 points, slow passes aside


def test_the_loaded_reference_on_its_own(kinematics):
    """Measured on 1,000 benchmark designs: mean 9e-5, p99 1.3e-4 (docs/operators.md)."""
    designs, loads = _benchmark(200, seed=5)
    exact = solve(designs, GRID, loads=loads)
    _, tendons = _reference(kinematics, designs.features(), loads.matrix(200))
    err = relative_l2(tendons[exact.converged], exact.tendons[exact.converged])
    ignored = relative_l2(solve(designs, GRID).tendons, exact.tendons)
    assert err.mean() < 1e-3 and np.median(err) < 1e-4
    assert ignored.mean() > 30 * err.mean()  # the loads matter: the reference captures them
    # at any arclengths: one partial step from the grid
    fractions = np.array([0.0, 0.013, 0.5123, 0.77, 1.0])
    exact_at = solve(designs.take(np.arange(50)), fractions, loads=loads.take(np.arange(50)))
    _, at = _reference(kinematics, designs.features()[:50], loads.matrix(200)[:50], fractions)
    assert np.median(relative_l2(at, exact_at.tendons)) < 1e-4


# -- loads as data ------------------------------------------------------------------------------


def test_load_space_mixes_unloaded_and_untipped_designs():
    space = design_space.LoadSpace(gravity="sphere", density=(6450.0, 8000.0), tip_force=0.02, tip_moment=0.002,
                                   tip_fraction=0.3, unloaded_fraction=0.2)
    matrix = space.sample(5000, seed=0).matrix(5000)
    unloaded = ~np.any(matrix[:, :3], axis=1)
    tipped = np.any(matrix[:, 4:], axis=1)
    assert 0.17 < unloaded.mean() < 0.23 and not np.any(matrix[unloaded][:, 4:])
    assert 0.2 < tipped.mean() < 0.3  # 0.3 of the 0.8 in gravity
    np.testing.assert_allclose(np.linalg.norm(matrix[~unloaded, :3], axis=1), 9.81)
    assert np.linalg.norm(matrix[:, 4:7], axis=1).max() <= 0.02
    # the shares draw from a stream of their own: the loads of a plain space are unchanged
    plain = design_space.LoadSpace(gravity="sphere", density=(6450.0, 8000.0), tip_force=0.02, tip_moment=0.002)
    np.testing.assert_array_equal(plain.sample(5000, seed=0).gravity[~unloaded], matrix[~unloaded, :3])
    with pytest.raises(ValueError, match="tip fraction"):
        design_space.LoadSpace(tip_fraction=1.5)


def test_the_loads_matrix_round_trips_and_warns_outside_the_trained_range():
    _, loads = _benchmark(50, seed=2)
    matrix = loads.matrix(50)
    assert matrix.shape == (50, 10)
    np.testing.assert_array_equal(ExternalLoads.from_matrix(matrix).matrix(50), matrix)
    ranges = design_space.TRAINING_LOADS.ranges()
    assert design_space.load_warnings(matrix, ranges) == [[] for _ in range(50)]
    matrix[0, 4:7] = [0.05, 0, 0]
    matrix[1, :3], matrix[1, 3] = 0.0, 100.0  # no gravity: its density says nothing
    matrix[2, 3] = 9000.0
    warnings = design_space.load_warnings(matrix, ranges)
    assert warnings[0] == ["|tip_force| = 0.05 N is outside the trained range [0, 0.02]"]
    assert warnings[1] == [] and warnings[2] == ["density = 9000 kg/m^3 is outside the trained range [6450, 8000]"]


# -- the shipped loaded operators -----------------------------------------------------------------


@pytest.fixture(scope="module")
def benchmark_cases():
    designs, loads = _benchmark(300, seed=77)
    exact = solve(designs, GRID, loads=loads, workers=0)
    free = design_space.sample_designs(300, seed=78)
    return designs, loads, exact, free, solve(free, GRID, workers=0)


def test_two_loaded_operators_ship():
    assert {e["architecture"] for n, e in SHIPPED.items() if n in LOADED} == {"DeepONet", "FNO"}
    for name in LOADED:
        entry = SHIPPED[name]
        assert entry["inputs"]["loads"] == ["B", 10]
        assert entry["load_ranges"] == design_space.TRAINING_LOADS.ranges()
        assert entry["training"]["train_seconds"] <= 3600  # the budget: an hour per model
        assert entry["metrics"]["test_relative_l2"]["mean"] < 0.01


@pytest.mark.parametrize("name", LOADED)
def test_shipped_loaded_operators_against_the_exact_loaded_solver(benchmark_cases, name):
    designs, loads, exact, free, free_exact = benchmark_cases
    model = Surrogate.shipped(name)
    ok = exact.converged
    pred = model.predict(designs.features(), GRID, loads=loads)
    err = relative_l2(pred["tendons"][ok], exact.tendons[ok])
    ignored = relative_l2(Surrogate.shipped("fno_pose").predict(designs.features(), GRID)["tendons"][ok],
                          exact.tendons[ok])
    assert err.mean() < 0.01 and err.mean() < ignored.mean() / 3
    # the loads as their (B, 10) matrix give the same answer
    np.testing.assert_array_equal(model.predict(designs.features(), GRID, loads=loads.matrix(300))["tendons"],
                                  pred["tendons"])
    # load-free designs: one model answers both
    keep = free_exact.converged
    assert relative_l2(model.predict(free.features()[keep], GRID)["tendons"], free_exact.tendons[keep]).mean() < 0.01
    # poses: tendons = p + R rho
    rotation = pred["rotation"]
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", rotation, rotation),
                               np.broadcast_to(np.eye(3), rotation.shape), atol=1e-5)


def test_python_api_refuses_loads_an_operator_cannot_take_and_bad_loads():
    designs, loads = _benchmark(3, seed=4)
    with pytest.raises(ValueError, match=r"designs\[0\]\.gravity: model 'fno' takes no external loads"):
        Surrogate.shipped("fno").predict(designs.features(), GRID, loads=loads)
    bad = ExternalLoads(gravity=loads.gravity, density=-np.ones(3), tip_force=loads.tip_force)
    with pytest.raises(ValueError, match=r"designs\[0\]\.density: must be in \(0, 100000\] kg/m\^3, got -1"):
        Surrogate.shipped(LOADED[0]).predict(designs.features(), GRID, loads=bad)
    # zero loads are no loads, for any operator
    zero = ExternalLoads(tip_force=np.zeros((3, 3)))
    np.testing.assert_array_equal(Surrogate.shipped("fno").predict(designs.features(), GRID, loads=zero)["tendons"],
                                  Surrogate.shipped("fno").predict(designs.features(), GRID)["tendons"])


# -- served ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server():
    from service.process import ServerProcess

    srv = ServerProcess(DEFAULT_MODELS_DIR, max_designs=2000)
    yield srv
    srv.stop()


def _loaded_request(designs: DesignBatch, loads: ExternalLoads, **extra) -> dict:
    rows = designs.to_dicts()
    for j, row in enumerate(rows):
        row["gravity"], row["density"] = loads.gravity[j].tolist(), float(loads.density[j])
        if np.any(loads.tip_force[j]):
            row["tip_force"], row["tip_moment"] = loads.tip_force[j].tolist(), loads.tip_moment[j].tolist()
    return {"designs": rows, **extra}


def test_predict_takes_load_fields_and_defaults_to_a_loaded_operator(server):
    designs, loads = _benchmark(8, seed=9)
    body = _loaded_request(designs, loads, points=42)
    r = httpx.post(server.url + "/predict", json=body, timeout=60)
    assert r.status_code == 200, r.text
    answer = r.json()
    router = httpx.get(server.url + "/v2/models/auto").json()["parameters"]  # the default: the router
    assert httpx.get(server.url + "/models").json()["default_loaded_model"] == "auto"
    assert router["loaded_operator"] in LOADED and answer["model"] in (router["loaded_operator"], "exact")
    assert all(res["in_distribution"] for res in answer["results"])
    exact = httpx.post(server.url + "/exact", json=body, timeout=120).json()["results"]
    if answer["model"] != "exact":  # the loaded operator's answers, as it gives them here
        local = Surrogate.shipped(answer["model"]).predict(designs.features(), GRID, loads=loads)
        np.testing.assert_allclose([res["tendons"] for res in answer["results"]], local["tendons"], rtol=1e-5,
                                   atol=1e-8)
    err = relative_l2(np.array([res["tendons"] for res in answer["results"]]), np.array([x["tendons"] for x in exact]))
    assert err.mean() < 0.01
    # a model that takes no loads: a 422 naming the field
    r = httpx.post(server.url + "/predict", json=body | {"model": "fno"})
    assert r.status_code == 422 and "designs[0].gravity: model 'fno' takes no external loads" in r.json()["message"]
    # outside the trained loads: answered, flagged
    strong = json.loads(json.dumps(body))
    strong["designs"][0]["tip_force"] = [0.05, 0.0, 0.0]
    r = httpx.post(server.url + "/predict", json=strong | {"model": LOADED[0]})
    first = r.json()["results"][0]
    assert r.status_code == 200 and not first["in_distribution"]
    assert first["warnings"] == ["|tip_force| = 0.05 N is outside the trained range [0, 0.02]"]


def test_binary_predict_takes_the_loads_after_the_design(server):
    from tdcr.clients import Client

    designs, loads = _benchmark(50, seed=10)
    with Client(server.url) as client:
        out = client.predict(designs.features(), loads=loads, model=LOADED[-1])
        assert out["model"] == LOADED[-1]
        with pytest.raises(Exception, match="takes no external loads"):
            client.predict(designs.features(), loads=loads, model="deeponet")
    local = Surrogate.shipped(LOADED[-1]).predict(designs.features(), GRID, loads=loads)
    np.testing.assert_allclose(out["tendons"], local["tendons"], rtol=1e-6, atol=1e-9)


def test_oip_rest_and_grpc_take_the_load_inputs(server):
    import grpc

    from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
    from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc

    designs, loads = _benchmark(4, seed=12)
    inputs = {"design": designs.features(), "gravity": loads.gravity, "density": loads.density,
              "tip_force": loads.tip_force, "tip_moment": loads.tip_moment}
    name = LOADED[0]
    local = Surrogate.shipped(name).predict(designs.features(), GRID, loads=loads)["tendons"]
    meta = httpx.get(f"{server.url}/v2/models/{name}").json()
    assert {i["name"] for i in meta["inputs"]} >= {"design", "gravity", "density", "tip_force", "tip_moment"}
    body = {"inputs": [{"name": k, "datatype": "FP64", "shape": list(np.shape(v)), "data": np.ravel(v).tolist()}
                       for k, v in inputs.items()], "outputs": [{"name": "tendons"}]}
    r = httpx.post(f"{server.url}/v2/models/{name}/infer", json=body, timeout=60)
    assert r.status_code == 200, r.text
    tendons = np.array(r.json()["outputs"][0]["data"]).reshape(4, 42, 4, 3)
    np.testing.assert_allclose(tendons, local, rtol=1e-5, atol=1e-8)
    refused = httpx.post(f"{server.url}/v2/models/fno/infer", json=body)
    assert refused.status_code == 400 and "unexpected input 'gravity'" in refused.json()["error"]
    request = pb.ModelInferRequest(model_name=name, outputs=[pb.ModelInferRequest.InferRequestedOutputTensor(
        name="tendons")])
    for k, v in inputs.items():
        request.inputs.add(name=k, datatype="FP64", shape=list(np.shape(v)))
        request.raw_input_contents.append(np.ascontiguousarray(v, "<f8").tobytes())
    with grpc.insecure_channel(server.grpc_target) as channel:
        reply = pb_grpc.GRPCInferenceServiceStub(channel).ModelInfer(request, timeout=60)
    got = np.frombuffer(reply.raw_output_contents[0], "<f4").reshape(4, 42, 4, 3)
    np.testing.assert_allclose(got, local, rtol=1e-5, atol=1e-8)


def test_inverse_kinematics_with_a_loaded_operator(server):
    designs, loads = _benchmark(1, seed=14)
    design = _loaded_request(designs, loads)["designs"][0]
    target_tensions = np.array([1.0, 0.0, 0.5, 0.0])
    goal = designs.take([0])
    goal = DesignBatch(E=goal.E, r=goal.r, L=goal.L, offset=goal.offset, pitch=goal.pitch, tension=[target_tensions])
    tip = solve(goal, np.ones(1), loads=loads).backbone[0, -1]
    body = {"design": design, "targets": [{"position": tip.tolist()}], "model": LOADED[0], "tolerance": 2e-3}
    r = httpx.post(server.url + "/inverse", json=body, timeout=120)
    assert r.status_code == 200, r.text
    result = r.json()["results"][0]
    assert result["status"] == "reached"
    reached = DesignBatch(E=goal.E, r=goal.r, L=goal.L, offset=goal.offset, pitch=goal.pitch,
                          tension=[result["tensions"]])
    # the operator's tensions, checked by the exact loaded solver: within a few tolerances of the target
    assert np.linalg.norm(solve(reached, np.ones(1), loads=loads).backbone[0, -1] - tip) < 0.01 * float(goal.L[0])
    for refused in ({"model": "exact"}, {"model": LOADED[0], "polish": True}, {"model": "fno"}):
        r = httpx.post(server.url + "/inverse", json=body | refused)
        assert r.status_code == 422, r.text
    r = httpx.post(server.url + "/inverse", json=body | {"model": "fno"})
    assert "design.gravity: model 'fno' takes no external loads" in r.json()["message"]


def test_cli_predict_with_loads(root, tmp_path):
    designs, loads = _benchmark(2, seed=15)
    request = tmp_path / "loaded.json"
    request.write_text(json.dumps(_loaded_request(designs, loads, points=5)))
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "predict", str(request)], capture_output=True, text=True,
                         cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    answer = json.loads(out.stdout)
    assert answer["model"] in LOADED
    local = Surrogate.shipped(answer["model"]).predict(designs.features(), np.linspace(0, 1, 5), loads=loads)
    np.testing.assert_allclose([r["tendons"] for r in answer["results"]], local["tendons"], rtol=1e-6, atol=1e-9)
    bad = subprocess.run([sys.executable, "-m", "tdcr.cli", "predict", str(request), "--model", "fno"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert bad.returncode == 2 and "designs[0].gravity: model 'fno' takes no external loads" in bad.stderr
