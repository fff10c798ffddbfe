"""Design search (`tdcr design`, tdcr/search/design.py) and the reachable workspace (`tdcr workspace`):
bad tasks name their field, a task built from a known design is solved and its answer verified by
the exact solver here, and the workspace's tips are the solver's."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tdcr import design_space
from tdcr.api.validation import InvalidRequest
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch
from tdcr.search.design import features_of, inner_ik, operator_tip, validate_task, workspace
from tdcr.surrogates.runtime import Surrogate

pytest.importorskip("cma")


def _task_from(seed: int, n_targets: int = 3, **extra) -> tuple[dict, DesignBatch]:
    """Targets from a Table I design's equilibria at random tensions: a solution exists."""
    design = design_space.sample_designs(1, seed=seed)
    rows = np.repeat(design.features(), n_targets, axis=0)
    rows[:, 11:15] = np.random.default_rng(seed).uniform(0.0, 5.0, size=(n_targets, 4))
    tips = solve(DesignBatch.from_features(rows), np.ones(1)).backbone[:, -1]
    return {"targets": [{"position": p.tolist()} for p in tips], **extra}, design


@pytest.mark.parametrize(("change", "where"), [
    ({"targets": []}, "targets: List should have at least 1 item"),
    ({"bounds": {"r": [0.002, 0.001]}}, "bounds.r: low must be below high"),
    ({"bounds": {"L": [0.001, 0.2]}}, "bounds.L: must lie in the admissible"),
    ({"targets": [{"position": [0.0, 0.0, 6.0]}]}, "targets[0].position: is 6 m from the base, farther than"),
    ({"fixed": {"L": 0.2}, "bounds": {"L": [0.1, 0.3]}}, "bounds.L: is also fixed"),
    ({"objective": "beauty"}, "objective: Input should be"),
])
def test_a_bad_task_names_its_field(change, where):
    task, _ = _task_from(1)
    with pytest.raises(InvalidRequest) as caught:
        validate_task(task | change)
    assert where in str(caught.value)


def test_bad_task_on_the_command_line_exits_2(tmp_path):
    path = tmp_path / "task.json"
    path.write_text(json.dumps({"targets": [{"position": [0.0, 0.0, 9.0]}]}))
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "design", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "targets[0].position: is 9 m from the base" in out.stderr


def test_the_batched_inverse_kinematics_reaches_an_operators_own_tips():
    op = Surrogate.shipped("deeponet_pose")
    features = design_space.sample_designs(64, seed=3).features()
    goal = features.copy()
    goal[:, 11:15] = np.random.default_rng(3).uniform(0, 5, (64, 4))
    targets = op.predict(goal, np.ones(1))["backbone"][:, -1].astype(float)
    tau, _, error, turn, _ = inner_ik(operator_tip(op), features, targets, np.full((64, 3), np.nan),
                                np.full((64, 4), 0.5), 5.0, iterations=30)
    assert np.median(error) < 1e-4 and np.mean(error < 1e-3) > 0.9  # m; a few starts end in local minima
    assert (tau >= 0).all() and (tau <= 5).all() and (turn == 0).all()  # no direction asked


def test_a_task_from_a_known_design_is_solved_and_proven_by_the_exact_solver(tmp_path):
    task, source = _task_from(1000, fixed={"L": None})
    task["fixed"] = {"L": float(source.L[0])}
    task |= {"seed": 0, "budget_s": 60, "tolerance": 1e-3}
    path = tmp_path / "task.json"
    path.write_text(json.dumps(task))
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "design", str(path)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["status"] == "solved" and result["design"]["L"] == pytest.approx(source.L[0])
    assert result["evaluations"]["surrogate"] > 100 * result["evaluations"]["exact"] > 0
    # the answer, checked here: the returned design at the returned tensions reaches every target
    design = result["design"]
    rows = np.array([[design["E"], design["r"], design["L"], *[t["offset"] for t in design["tendons"]],
                      *[t["pitch"] for t in design["tendons"]], *r["tensions"]] for r in result["targets"]])
    tips = solve(DesignBatch.from_features(rows), np.ones(1)).backbone[:, -1]
    for tip, target, reported in zip(tips, task["targets"], result["targets"], strict=True):
        assert np.linalg.norm(tip - target["position"]) <= 1e-3
        np.testing.assert_allclose(reported["position"], tip, atol=1e-12)
        assert reported["reached"] and reported["error"] == pytest.approx(np.linalg.norm(tip - target["position"]))
    assert max(max(r["tensions"]) for r in result["targets"]) == pytest.approx(result["objective"])
    # the same task again: the same answer (seeded)
    again = json.loads(subprocess.run([sys.executable, "-m", "tdcr.cli", "design", str(path)], capture_output=True,
                                      text=True, timeout=300).stdout)
    assert again["design"] == result["design"]


def test_features_of_maps_the_unit_box_onto_the_bounds_and_keeps_the_fixed():
    task = validate_task({"targets": [{"position": [0.0, 0.0, 0.2]}], "fixed": {"L": 0.2},
                          "bounds": {"E": [2e10, 3e10]}})
    low, high = features_of(task, np.zeros((1, 10))), features_of(task, np.ones((1, 10)))
    assert low[0, 0] == 2e10 and high[0, 0] == 3e10 and low[0, 2] == high[0, 2] == 0.2
    assert low[0, 1] == 0.0005 and high[0, 10] == 20.0 and (low[0, 11:] == 0).all()


def test_the_workspace_holds_the_exact_solvers_tips(tmp_path):
    features = design_space.sample_designs(1, seed=4).features()[0]
    space = workspace(features, samples=2000, seed=1)
    rows = np.repeat(features[None], 5, axis=0)
    rows[:, 11:15] = space.tensions[:5]
    np.testing.assert_allclose(space.tips[:5], solve(DesignBatch.from_features(rows), np.ones(1)).backbone[:, -1],
                               atol=1e-12)
    assert space.volume > 0 and (space.low <= space.tips).all() and (space.tips <= space.high).all()
    assert space.high[2] <= features[2] + 1e-9  # no tip beyond the rod's length
    design = DesignBatch.from_features(features[None]).to_dicts()[0]
    path = tmp_path / "design.json"
    path.write_text(json.dumps(design))
    png = tmp_path / "workspace.png"
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "workspace", str(path), "--samples", "2000",
                          "--model", "deeponet_pose", "--png", str(png)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    answer = json.loads(out.stdout)
    assert answer["model"] == "deeponet_pose" and answer["samples"] == len(answer["tips"]) == 2000
    assert "convex hull" in answer["volume"]["method"]
    assert answer["volume"]["m3"] == pytest.approx(space.volume, rel=0.05)  # the operator's tips vs the solver's
    assert png.stat().st_size > 10_000
    bad = subprocess.run([sys.executable, "-m", "tdcr.cli", "workspace", str(path), "--samples", "1"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--samples" in bad.stderr
