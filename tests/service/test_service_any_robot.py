"""Any robot through the served entry points: ``/exact`` JSON, the OIP v2 ``exact`` model over REST
and gRPC (tritonclient, in a process of its own), ``tdcr solve``, and the operators' refusals."""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import numpy as np
import pytest

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.robot.design_space import DEFAULT_POINTS
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.surrogates.runtime import DEFAULT_MODELS_DIR

S = np.linspace(0.0, 1.0, 11)


def robots() -> DesignBatch:
    """Two two-segment robots (3 + 3 tendons), one with a displacement-driven tendon and nu = 0.25."""
    d = design_space.sample_segmented_designs(2, seed=2710, segments=2, tendons_per_segment=3)
    displacement = np.full((2, 6), np.nan)
    displacement[1, 4] = 1e-3
    return d.replace(displacement=displacement, poisson=np.array([0.3, 0.25]),
                     tension=np.where(np.isnan(displacement), d.tension, 0.0))


@pytest.fixture(scope="module")
def server():
    from service.process import ServerProcess

    # a machine's first start compiles the kernels, the displacement and loaded paths after /readyz
    srv = ServerProcess(DEFAULT_MODELS_DIR, ready_timeout_s=300, wait_for_paths=("displacement", "loaded"))
    yield srv
    srv.stop()


def test_a_server_waits_only_for_solver_paths_it_knows():
    from service.process import ServerProcess

    with pytest.raises(ValueError, match=r"unknown solver paths \['tension'\]; they are \['tendon', 'loaded'"):
        ServerProcess(DEFAULT_MODELS_DIR, wait_for_paths=("loaded", "tension"))  # before any process starts


def test_exact_json_takes_any_robot_and_answers_tensions_and_displacements(server):
    d = robots()
    body = {"s": S.tolist(), "designs": d.to_dicts()}
    for termination in ("exact", "rucker_webster"):
        if termination == "rucker_webster":  # displacement actuation is the consistent model's
            body = {"s": S.tolist(), "designs": d.take([0]).to_dicts(), "termination": termination}
        answer = httpx.post(server.url + "/exact", json=body, timeout=60)
        assert answer.status_code == 200, answer.text
        results = answer.json()["results"]
        designs = d if termination == "exact" else d.take([0])
        local = solve(designs, S, termination=termination)
        for j, r in enumerate(results):
            assert r["status"] == "converged"
            assert float(relative_l2(np.array(r["tendons"])[None], local.tendons[j:j + 1])[0]) < 1e-12
            np.testing.assert_allclose(r["tension"], local.tension[j], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(r["displacement"], local.displacement[j], rtol=1e-12, atol=1e-15)
    assert "slack" not in results[0]  # no displacement-driven tendon: no slack list
    first = httpx.post(server.url + "/exact", json={"s": S.tolist(), "designs": d.to_dicts()}).json()["results"]
    assert first[1]["displacement"][4] == pytest.approx(1e-3, abs=1e-10) and first[1]["slack"] == [False] * 6


@pytest.mark.parametrize(("change", "field", "words"), [
    (lambda t: t[0].update(end=9.0), "designs[0].tendons[0].end", "(0, L]"),
    (lambda t: t[0].update(displacement=1e-3), "designs[0].tendons[0].tension", "not both"),
    (lambda t: t[0].pop("tension"), "designs[0].tendons[0].tension", "tension (N) or its displacement"),
])
def test_exact_refuses_bad_layouts_by_name(server, change, field, words):
    design = robots().take([0]).to_dicts()[0]
    change(design["tendons"])
    answer = httpx.post(server.url + "/exact", json={"points": 5, "designs": [design]})
    assert answer.status_code == 422, answer.text
    assert field in answer.text and words in answer.text


def test_displacement_in_gravity_is_answered_and_a_bad_termination_refused(server):
    """A displacement-driven tendon under gravity and a tip force: /exact answers what the Python API
    does (the loaded displacement solve); the shortcut termination or an unknown one is refused."""

    loads = {"gravity": [9.81, 0.0, 0.0], "density": 8000.0, "tip_force": [0.01, 0.0, 0.0]}
    design = robots().take([1]).to_dicts()[0] | loads
    answer = httpx.post(server.url + "/exact", json={"s": S.tolist(), "designs": [design]}, timeout=60)
    assert answer.status_code == 200, answer.text
    (result,) = answer.json()["results"]
    local = solve(robots().take([1]), S, loads=ExternalLoads(gravity=np.array([loads["gravity"]]),
                                                             density=np.array([8000.0]),
                                                             tip_force=np.array([loads["tip_force"]])))
    assert result["status"] == "converged" and local.converged.all()
    assert result["displacement"][4] == pytest.approx(1e-3, abs=1e-10) and result["tension"][4] > 0.0
    np.testing.assert_allclose(result["tension"], local.tension[0], rtol=1e-12, atol=1e-12)
    assert float(relative_l2(np.array(result["tendons"])[None], local.tendons)[0]) < 1e-12
    answer = httpx.post(server.url + "/exact", json={"points": 5, "designs": [design], "termination": "rucker_webster"})
    assert answer.status_code == 422 and "designs[0].tendons[4].displacement" in answer.text
    answer = httpx.post(server.url + "/exact", json={"points": 5, "designs": robots().take([0]).to_dicts(),
                                                     "termination": "tip"})
    assert answer.status_code == 422 and "termination" in answer.text


@pytest.mark.parametrize(("extra", "field"), [({"poisson": 0.25}, "designs[0].poisson"),
                                              ({"end": 0.05}, "designs[0].tendons[1].end"),
                                              ({"angle": 0.3}, "designs[0].tendons[1].angle")])
def test_the_operators_refuse_other_layouts_by_name(server, extra, field):
    design = design_space.sample_designs(1, seed=2711).to_dicts()[0]
    if "poisson" in extra:
        design |= extra
    else:
        design["tendons"][1] |= extra
    answer = httpx.post(server.url + "/predict", json={"designs": [design]})
    assert answer.status_code == 422, answer.text
    assert field in answer.text and "the exact solver takes it" in answer.text


TRITON_SCRIPT = """
import json, sys
import numpy as np
import tritonclient.grpc as grpcclient
import tritonclient.http as httpclient

protocol, url, path = sys.argv[1:4]
module = httpclient if protocol == "http" else grpcclient
arrays = np.load(path)
client = module.InferenceServerClient(url)
inputs = []
for name in ("design", "layout", "poisson", "s", *(n for n in ("gravity", "density", "tip_force") if n in arrays)):
    tensor = module.InferInput(name, list(arrays[name].shape), "FP64")
    tensor.set_data_from_numpy(arrays[name])
    inputs.append(tensor)
names = ("tendons", "tension", "displacement", "slack", "status", "tension_profile")
out = {}
for termination in ("exact", "rucker_webster"):
    rows = inputs if termination == "exact" else inputs[:1] + inputs[3:]  # no displacement: the shortcut
    result = client.infer("exact", rows, outputs=[module.InferRequestedOutput(n) for n in names],
                          parameters={"termination": termination})
    out.update({f"{termination}_{n}": result.as_numpy(n) for n in names})
errors = []
try:
    client.infer("exact", inputs, parameters={"termination": "tip"})
except Exception as exc:
    errors.append(str(exc))
np.savez(path + ".npz", **out)
print(json.dumps(errors))
"""


def _triton(server, tmp_path, protocol: str, d: DesignBatch, layout: np.ndarray, loads: dict | None = None):
    """:data:`TRITON_SCRIPT` in a process of its own on designs ``d`` with the ``layout`` tensor (and
    the load tensors ``loads`` by name): the finished process and the arrays it received."""
    path = tmp_path / "robots.npz"
    np.savez(path, design=d.features(), layout=layout, poisson=d.poissons, s=S, **(loads or {}))
    script = tmp_path / "client.py"
    script.write_text(TRITON_SCRIPT)
    url = server.url.removeprefix("http://") if protocol == "http" else server.grpc_target
    run = subprocess.run([sys.executable, str(script), protocol, url, str(path)], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    return run, np.load(str(path) + ".npz")


def real_robots() -> DesignBatch:
    """:func:`robots` with series-elastic tendons, drive zeros and friction, pulling and releasing."""
    d = robots()
    shape = d.offset.shape
    return d.replace(stiffness=np.full(shape, 2500.0), zero=np.full(shape, -2e-4), friction=np.full(shape, 0.2),
                     motion=np.where(np.arange(shape[1]) % 2, -1.0, 1.0)[None, :].repeat(shape[0], axis=0))


def test_exact_json_takes_a_real_robot_file_design_and_answers_tension_profiles(server):
    from pathlib import Path

    from tdcr.robot.real import load_robot

    robot = load_robot(Path(__file__).resolve().parents[2] / "examples" / "ftdcr_v4.json")
    design = robot.design.to_dicts()[0]  # the robot file's design, as the file gives it
    design["tendons"][0] |= {"displacement": 0.002, "friction": 0.1, "motion": "release"}
    answer = httpx.post(server.url + "/exact", json={"points": 11, "designs": [design]})
    assert answer.status_code == 200, answer.text
    (result,) = answer.json()["results"]
    local_design = robot.design.replace(displacement=np.where(np.arange(9) == 0, 0.002, robot.design.displacement),
                                        friction=np.where(np.arange(9) == 0, 0.1, 0.0)[None],
                                        motion=np.where(np.arange(9) == 0, -1.0, 1.0)[None])
    local = solve(local_design, np.linspace(0, 1, 11))
    assert result["status"] == "converged"
    np.testing.assert_allclose(result["tension_profile"], local.tension_profile[0], rtol=1e-12, atol=1e-12)
    assert result["tension_profile"][-1][0] == 0.0 < result["tension_profile"][0][0]  # ends at 0.06 m
    design["tip_force"] = [0.01, 0.0, 0.0]  # friction under a tip load: the loaded kernel carries it
    answer = httpx.post(server.url + "/exact", json={"points": 11, "designs": [design]})
    assert answer.status_code == 200, answer.text
    (pushed,) = answer.json()["results"]
    local = solve(local_design, np.linspace(0, 1, 11), loads=ExternalLoads(tip_force=np.array([[0.01, 0.0, 0.0]])))
    assert pushed["status"] == "converged" and local.converged.all()
    np.testing.assert_allclose(pushed["tension"], local.tension[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(pushed["tension_profile"], local.tension_profile[0], rtol=1e-12, atol=1e-12)
    assert np.abs(np.array(pushed["backbone"]) - result["backbone"]).max() > 1e-4  # the load acted
    shortcut = {"points": 11, "designs": [design], "termination": "rucker_webster"}
    answer = httpx.post(server.url + "/exact", json=shortcut)  # friction covers consistent termination only
    assert answer.status_code == 422 and "designs[0].tendons[0].friction" in answer.text


def test_exact_json_takes_a_fitted_robot_file_as_tdcr_solve_does(server, root):
    """The file `tdcr fit` writes, posted as it is: /exact answers its design at the default points, the
    same bits as `tdcr solve FITTED.json`; a bad value is named under ``design`` as `tdcr replay` names it,
    and a bad actuation or measurement (which the answer does not use) by its key, as `tdcr replay` refuses it."""
    fitted = json.loads((root / "examples" / "ftdcr_v4_fitted.json").read_text())  # as tdcr fit wrote it
    answer = httpx.post(server.url + "/exact", json=fitted)
    assert answer.status_code == 200, answer.text
    (result,) = answer.json()["results"]
    robot_file = str(root / "examples" / "ftdcr_v4_fitted.json")
    solved = subprocess.run([sys.executable, "-m", "tdcr.cli", "solve", robot_file], capture_output=True, text=True,
                            timeout=300)
    assert solved.returncode == 0, solved.stderr
    assert result == json.loads(solved.stdout)["results"][0] and result["status"] == "converged"
    assert len(result["s"]) == DEFAULT_POINTS and np.array(result["tendons"]).shape == (DEFAULT_POINTS, 9, 3)
    fitted["design"]["tendons"][2]["friction"] = 3.0
    answer = httpx.post(server.url + "/exact", json=fitted)
    assert answer.status_code == 422
    assert answer.json()["detail"][0]["loc"] == ["body", "design", "tendons", 2, "friction"], answer.text
    assert "must be in [0, 2], got 3" in answer.json()["message"]
    # the rest of the file passes the same checks as `tdcr replay`'s: a file they refuse is refused here
    for key, bad, reason in [(("time_column",), 7, "must be a column's name"),
                             (("time_column",), None, "must be a column's name"),
                             (("actuation", "columns"), ["servo_1_mm"], "must be a list of 9 column names"),
                             (("measurement", "unit"), "inch", "must be one of")]:
        broken = json.loads((root / "examples" / "ftdcr_v4_fitted.json").read_text())
        (broken if len(key) == 1 else broken[key[0]])[key[-1]] = bad
        answer = httpx.post(server.url + "/exact", json=broken)
        assert answer.status_code == 422, answer.text
        assert answer.json()["detail"][0]["loc"] == ["body", *key] and reason in answer.json()["message"]


@pytest.mark.parametrize("protocol", ["http", "grpc"])
def test_oip_exact_model_takes_the_real_robot_layout_columns(server, tmp_path, protocol):
    d = real_robots()
    layout = np.stack([d.angles, d.ends, np.nan_to_num(d.displacement), d.displacement_driven.astype(float),
                       d.resolved("stiffness"), d.resolved("zero"), d.resolved("friction"), d.resolved("motion")],
                      axis=-1)
    run, got = _triton(server, tmp_path, protocol, d, layout)
    exact = solve(d, S)
    assert (got["exact_status"] == 0).all()
    np.testing.assert_allclose(got["exact_tension"], exact.tension, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got["exact_tension_profile"], exact.tension_profile, rtol=1e-12, atol=1e-12)
    assert not np.allclose(exact.tension_profile[:, 0], exact.tension_profile[:, -1])  # friction acted


@pytest.mark.parametrize("protocol", ["http", "grpc"])
def test_oip_exact_model_takes_displacement_in_gravity(server, tmp_path, protocol):
    """The OIP ``exact`` model answers a displacement-driven tendon in gravity and under a tip force
    as the Python API does (the loaded displacement solve)."""

    d = robots()
    layout = np.stack([d.angles, d.ends, np.nan_to_num(d.displacement), d.displacement_driven.astype(float)], axis=-1)
    loads = {"gravity": np.tile([0.0, 9.81, 0.0], (2, 1)), "density": np.full(2, 7000.0),
             "tip_force": np.tile([0.0, 0.0, -0.01], (2, 1))}
    run, got = _triton(server, tmp_path, protocol, d, layout, loads)
    exact = solve(d, S, loads=ExternalLoads(**loads))
    assert (got["exact_status"] == 0).all() and exact.converged.all()
    np.testing.assert_allclose(got["exact_tension"], exact.tension, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got["exact_displacement"][1, 4], 1e-3, atol=1e-10)
    assert got["exact_tension"][1, 4] > 0.0 and not np.allclose(exact.tension, solve(d, S).tension)


@pytest.mark.parametrize("protocol", ["http", "grpc"])
def test_oip_exact_model_takes_the_layout_tensor_and_termination(server, tmp_path, protocol):
    d = robots()
    layout = np.stack([d.angles, d.ends, np.nan_to_num(d.displacement), d.displacement_driven.astype(float)], axis=-1)
    run, got = _triton(server, tmp_path, protocol, d, layout)
    exact = solve(d, S)
    assert (got["exact_status"] == 0).all()
    assert relative_l2(got["exact_tendons"].astype(np.float64), exact.tendons).max() < 1e-6  # FP32 on the wire
    np.testing.assert_allclose(got["exact_tension"], exact.tension, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got["exact_displacement"], exact.displacement, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(got["exact_slack"], exact.slack)
    np.testing.assert_allclose(got["exact_tension_profile"], exact.tension_profile, rtol=1e-12, atol=1e-12)
    # without the layout tensor: 6 evenly spaced tendons to the tip, nu 0.3 (its own defaults)
    plain = solve(DesignBatch.from_features(d.features()), S, termination="rucker_webster")
    assert relative_l2(got["rucker_webster_tendons"].astype(np.float64), plain.tendons).max() < 1e-6
    assert "termination" in json.loads(run.stdout)[0]
