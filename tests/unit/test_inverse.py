"""Inverse kinematics (tdcr/search/inverse.py, POST /inverse, tdcr inverse) and the tip Jacobian of /exact
and /predict: round trips (inverse, then forward, gives back the target), the least sum of squared
tensions, unreachable targets, paths, and clear errors."""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import numpy as np
import pytest

from service.process import ServerProcess
from tdcr import design_space
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch
from tdcr.search.inverse import exact_forward, inverse, tip_by_differences

TIP = np.array([1.0])


def _one(tension, pitch=(0.0,) * 4) -> DesignBatch:
    return DesignBatch(E=[3e10], r=[1e-3], L=[0.25], offset=[[0.008] * 4], pitch=[list(pitch)], tension=[list(tension)])


def _tip(d: DesignBatch) -> tuple[np.ndarray, np.ndarray]:
    sol = solve(d, TIP)
    return sol.backbone[:, -1], sol.rotation[:, -1, :, 2]


def _design_json(d: DesignBatch, j: int = 0) -> dict:
    return d.to_dicts()[j]


def test_round_trip_on_random_table_i_equilibria():
    """Tips of random equilibria (tensions within the bounds) are reached within 1e-4 L from zero
    tensions, and the forward solve at the answer gives the target back."""
    designs = design_space.sample_designs(25, seed=11)
    positions, _ = _tip(designs)
    for j in range(designs.n_designs):
        d = designs.take(np.array([j]))
        length = float(d.L[0])
        (res,) = inverse(exact_forward(d), length, positions[j:j + 1], None, start=np.zeros(4), tension_max=5.0)
        assert res.status == "reached", (j, res)
        assert np.all((res.tensions >= 0) & (res.tensions <= 5.0))
        back, _ = _tip(DesignBatch(E=d.E, r=d.r, L=d.L, offset=d.offset, pitch=d.pitch, tension=res.tensions[None]))
        assert np.linalg.norm(back[0] - positions[j]) <= 1e-4 * length


def test_the_least_sum_of_squared_tensions_is_chosen():
    """Straight tendons: a tip reached by tendon 1 alone is answered without pulling the opposite
    tendon too (co-contraction reaches it as well, with more sum of squares)."""
    d = _one([2.0, 0.0, 0.0, 0.0])
    target, _ = _tip(d)
    cocontracted = _one([0.0, 0.0, 0.0, 0.0])
    (res,) = inverse(exact_forward(cocontracted), 0.25, target, None, start=np.array([3.0, 0.0, 1.0, 0.0]),
                     tension_max=5.0)
    assert res.status == "reached"
    np.testing.assert_allclose(res.tensions, [2.0, 0.0, 0.0, 0.0], atol=2e-3)


def test_unreachable_targets_get_the_closest_tip():
    d = _one([0.0] * 4)
    (res,) = inverse(exact_forward(d), 0.25, np.array([[0.2, 0.0, 0.1]]), None, start=np.zeros(4), tension_max=5.0)
    assert res.status == "closest" and res.error > 0.1
    assert res.tensions.max() == 5.0  # pulled as far as the bounds allow


def test_a_path_with_directions_is_followed_with_warm_starts():
    tensions = np.linspace([0.5, 0.0, 0.0, 0.2], [3.0, 0.0, 0.0, 1.5], 8)
    path = DesignBatch(E=[3e10] * 8, r=[1e-3] * 8, L=[0.25] * 8, offset=[[0.008] * 4] * 8,
                       pitch=[[2.0, -1.0, 0.0, 3.0]] * 8, tension=tensions)
    positions, directions = _tip(path)
    results = inverse(exact_forward(path.take(np.array([0]))), 0.25, positions, directions, start=np.zeros(4),
                      tension_max=5.0)
    assert [r.status for r in results] == ["reached"] * 8
    assert max(r.direction_error for r in results) <= 1e-4
    assert sum(r.iterations for r in results[1:]) < 8 * 6  # warm starts: a few evaluations each


def test_difference_jacobian_of_the_solver_matches_its_exact_jacobian():
    designs = design_space.sample_designs(3, seed=4)

    def tip_pose(features):
        sol = solve(DesignBatch.from_features(features), TIP)
        return sol.backbone[:, -1], sol.rotation[:, -1]

    _, _, jac = tip_by_differences(designs.features(), tip_pose, step=1e-4)
    exact = solve(designs, TIP, jacobian=True).jacobian[:, -1]
    np.testing.assert_allclose(jac, exact, rtol=0, atol=1e-6 * np.abs(exact).max())


@pytest.fixture(scope="module")
def server(tiny_models):
    srv = ServerProcess(tiny_models[1])
    yield srv
    srv.stop()


def test_inverse_endpoint_exact_operator_and_polish(server):
    d = _one([2.0, 0.0, 0.0, 0.5], pitch=(1.0, 0.0, -2.0, 0.0))
    target, direction = _tip(d)
    start = _one([0.0] * 4, pitch=(1.0, 0.0, -2.0, 0.0))
    body = {"design": _design_json(start), "targets": [{"position": target[0].tolist()},
                                                       {"position": target[0].tolist(),
                                                        "direction": direction[0].tolist()}]}
    exact = httpx.post(server.url + "/inverse", json=body, timeout=60)
    assert exact.status_code == 200, exact.text
    answer = exact.json()
    assert answer["model"] == "exact" and [r["status"] for r in answer["results"]] == ["reached", "reached"]
    assert "direction" in answer["results"][1] and "direction" not in answer["results"][0]
    np.testing.assert_allclose(answer["results"][0]["tensions"], [2.0, 0.0, 0.0, 0.5], atol=1e-3)
    operator = httpx.post(server.url + "/inverse", json=body | {"model": "fno"}, timeout=60).json()
    assert operator["model"] == "fno" and len(operator["results"]) == 2  # tiny model: its own tip, not exact
    polished = httpx.post(server.url + "/inverse", json=body | {"model": "fno", "polish": True}, timeout=60).json()
    assert [r["status"] for r in polished["results"]] == ["reached", "reached"]
    assert max(r["error"] for r in polished["results"]) <= 1e-4 * 0.25


@pytest.mark.parametrize("change, status, message", [
    ({"targets": []}, 422, "targets: List should have at least 1 item"),
    ({"targets": [{"position": [0, 0]}]}, 422, "targets[0].position"),
    ({"targets": [{"position": [0, 0, 0.2], "direction": [0, 0, 0]}]}, 422, "targets[0].direction: must be a "
                                                                             "finite, non-zero vector"),
    ({"tension_max": -1}, 422, "tension_max"),
    ({"model": "nope"}, 404, "unknown model 'nope'"),
    ({"design": {"E": 3e10, "r": 1e-3, "L": 0.25, "tendons": [{"offset": 0.008, "tension": 0.0}] * 3},
      "model": "fno"}, 422, "design.tendons: the operators take 4 tendons, got 3"),
    ({"design": {"E": 3e10, "r": 1e-3, "L": 0.25, "tendons": [{"offset": 0.008, "tension": 0.0}] * 4,
                 "gravity": [0, 0, -9.81], "density": 7800}}, 422,
     "model: the exact inverse kinematics covers tendon loads only"),
    ({"design": {"E": -1.0, "r": 1e-3, "L": 0.25, "tendons": [{"offset": 0.008, "tension": 0.0}] * 4}}, 422,
     "design.E: must be in"),
    ({"design": {"E": 3e10, "r": 1e-3, "L": 0.25, "tendons": [{"offset": 0.008, "tension": 0.0}] * 4,
                 "tip_force": [0, 0.01, 0]}, "model": "fno"}, 422, "design.tip_force: model 'fno' takes no external"),
])
def test_bad_inverse_requests_get_a_clear_error(server, change, status, message):
    body = {"design": _design_json(_one([0.0] * 4)), "targets": [{"position": [0.0, 0.0, 0.25]}]} | change
    r = httpx.post(server.url + "/inverse", json=body, timeout=60)
    assert r.status_code == status, r.text
    assert message in r.json()["message"], r.json()


def test_loads_given_as_zeros_are_none_for_an_operator_that_takes_no_loads(server):
    """A load-free operator answers a design whose loads are all zero (found by schemathesis: it
    answered 422 with an empty message), as it answers the same design without them."""
    body = {"design": _design_json(_one([0.0] * 4)), "targets": [{"position": [0.0, 0.0, 0.25]}], "model": "fno"}
    zeros = body | {"design": body["design"] | {"tip_force": [0.0, 0.0, 0.0], "tip_moment": [0.0, 0.0, 0.0]}}
    plain, zero = (httpx.post(server.url + "/inverse", json=b, timeout=60) for b in (body, zeros))
    assert plain.status_code == 200 and zero.status_code == 200, zero.text
    assert zero.json()["results"] == plain.json()["results"]


def test_tip_jacobian_of_exact_and_predict(server):
    designs = design_space.sample_designs(2, seed=6)
    body = {"designs": designs.to_dicts(), "points": 5, "jacobian": True}
    exact = httpx.post(server.url + "/exact", json=body, timeout=60).json()["results"]
    expected = solve(designs, np.linspace(0.0, 1.0, 5), jacobian=True).jacobian[:, -1]  # the same step grid
    np.testing.assert_allclose([r["tip_jacobian"] for r in exact], expected, rtol=1e-9, atol=1e-15)
    assert len(exact[0]["s"]) == 5
    del body["points"]
    unasked = httpx.post(server.url + "/exact", json=body | {"s": [0.0, 0.5]}, timeout=60).json()["results"]
    assert len(unasked[0]["s"]) == 2  # the tip is solved for the Jacobian, not returned
    expected = solve(designs, np.array([0.0, 0.5, 1.0]), jacobian=True).jacobian[:, -1]
    np.testing.assert_allclose([r["tip_jacobian"] for r in unasked], expected, rtol=1e-9, atol=1e-15)

    predicted = httpx.post(server.url + "/predict", json=body | {"model": "fno"}).json()["results"]
    tips = []
    for sign in (-1, 1):  # the test's own central differences of /predict's tip, tendon 2
        shifted = designs.tension.copy()
        shifted[:, 1] += sign * 1e-3
        moved = DesignBatch(E=designs.E, r=designs.r, L=designs.L, offset=designs.offset, pitch=designs.pitch,
                            tension=shifted)
        out = httpx.post(server.url + "/predict", json={"designs": moved.to_dicts(), "model": "fno", "points": 5})
        tips.append(np.array([r["backbone"][-1] for r in out.json()["results"]], dtype=np.float64))
    # the same differences up to float32 round-off of the tips (an ulp at 0.35 m, over the 2 mN step)
    float32_noise = 2 * np.finfo(np.float32).eps * 0.35 / 2e-3
    np.testing.assert_allclose(np.array([r["tip_jacobian"] for r in predicted])[:, :3, 1], (tips[1] - tips[0]) / 2e-3,
                               rtol=0, atol=float32_noise)
    loaded = body | {"designs": [designs.to_dicts()[0] | {"gravity": [0, 0, -9.81], "density": 7800.0}]}
    r = httpx.post(server.url + "/exact", json=loaded, timeout=60)
    assert r.status_code == 422 and "tip Jacobian covers tendon loads only" in r.json()["message"]


def test_cli_inverse(root, tmp_path):
    d = _one([1.0, 0.0, 0.5, 0.0])
    target, _ = _tip(d)
    request = tmp_path / "ik.json"
    request.write_text(json.dumps({"design": _design_json(_one([0.0] * 4)),
                                   "targets": [{"position": target[0].tolist()}]}))
    done = subprocess.run([sys.executable, "-m", "tdcr.cli", "inverse", str(request)], cwd=root, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["results"][0]["status"] == "reached"
    request.write_text(json.dumps({"design": _design_json(d), "targets": [{"position": [0, 0, "x"]}]}))
    bad = subprocess.run([sys.executable, "-m", "tdcr.cli", "inverse", str(request)], cwd=root, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "targets[0].position" in bad.stderr


def test_resolved_rate_example_ends_on_its_goal(root):
    done = subprocess.run([sys.executable, "examples/resolved_rate.py"], cwd=root, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith("step 30/30") and float(last.split("tracking error")[1].split()[0]) < 0.1  # mm
