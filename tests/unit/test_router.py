"""Cost-aware answers (tdcr/surrogates/router.py): the cheaper path that meets the tolerance, chosen
from given costs (deterministic), and its answers equal to the path's own."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tdcr import design_space
from tdcr.physics import solve
from tdcr.surrogates.bounds import EXACT, EXACT_TOLERANCE, SURROGATE
from tdcr.surrogates.router import Cost, Costs, Router, choose

GRID = np.linspace(0.0, 1.0, 42)
#: a solver at 1 ms a design and an operator at 10 ms a call: the solver is cheaper below 10 designs
COSTS = Costs(exact=Cost.line(0.0, 1e-3), exact_loaded=Cost.line(0.0, 5e-2), operator=Cost.line(1e-2, 1e-6),
              loaded_operator=Cost.line(1e-2, 1e-6))


def test_a_cost_interpolates_its_measured_batches_and_extends_the_last_slope():
    cost = Cost((1.0, 16.0, 128.0), (0.002, 0.004, 0.010))
    assert cost(1) == pytest.approx(0.002) and cost(16) == pytest.approx(0.004)
    assert cost(72) == pytest.approx(0.007)  # halfway between 16 and 128
    assert cost(240) == pytest.approx(0.016)  # beyond: the last segment's slope, 6 ms per 112 designs
    assert Cost((1.0, 16.0), (0.002, 0.001))(100) == pytest.approx(0.001)  # never a falling extension
    assert Cost.line(0.01, 1e-3)(10) == pytest.approx(0.02)


def test_the_cheaper_path_wins_and_fallbacks_count_against_the_operator():
    tendon_only = lambda n: np.zeros(n, dtype=bool)  # noqa: E731
    assert choose(COSTS, np.zeros(5), loaded=tendon_only(5), tolerance=None).path == "exact"
    assert choose(COSTS, np.zeros(50), loaded=tendon_only(50), tolerance=None).path == "operator"
    # 50 designs, 45 of them over the tolerance: the operator would cost 10 ms + 45 exact solves
    bound = np.where(np.arange(50) < 45, 0.1, 1e-4)
    choice = choose(COSTS, bound, loaded=tendon_only(50), tolerance=1e-3)
    assert choice.path == "exact" and choice.operator_seconds == pytest.approx(1e-2 + 50e-6 + 45e-3)
    assert choose(COSTS, bound, loaded=tendon_only(50), tolerance=0.5).path == "operator"
    # loaded designs: the solver costs 50 ms each
    assert choose(COSTS, np.zeros(1), loaded=np.ones(1, dtype=bool), tolerance=None).path == "operator"
    # a path that is not ready is not taken
    assert choose(COSTS, np.zeros(5), loaded=tendon_only(5), tolerance=None, exact_ready=False).path == "operator"
    assert choose(COSTS, np.zeros(50), loaded=tendon_only(50), tolerance=None,
                  operator_ready=False).path == "exact"


@pytest.fixture(scope="module")
def router():
    return Router.shipped(costs=COSTS)


def test_the_router_answers_a_few_designs_exactly_and_many_with_its_operator(router):
    few = design_space.sample_designs(3, seed=4270)
    out = router.predict(few.features(), GRID, tolerance=1e-3)
    exact = solve(few, GRID)
    assert out["path"] == "exact" and (out["source"] == EXACT).all()
    np.testing.assert_array_equal(out["tendons"], exact.tendons)
    np.testing.assert_array_equal(out["error_bound"], np.where(exact.converged, EXACT_TOLERANCE, np.inf))
    many = design_space.sample_designs(200, seed=4271)
    out = router.predict(many.features(), GRID)
    op = router.operator
    assert out["path"] == op.name and (out["source"] == SURROGATE).all()
    np.testing.assert_array_equal(out["tendons"], op.predict(many.features(), GRID)["tendons"])
    np.testing.assert_array_equal(out["error_bound"], op.error_bound(many.features()))


def test_the_router_takes_the_most_accurate_operator_and_validates_like_the_operators(router):
    assert router.operator.name == "deeponet_pose_loaded"  # load-free error 1.6e-5 (docs/operators.md)
    bad = design_space.sample_designs(1, seed=0).features()
    bad[0, 0] = -1.0
    with pytest.raises(ValueError, match=r"designs\[0\]\.E"):
        router.predict(bad, GRID)
    with pytest.raises(ValueError, match="tolerance"):
        router.predict(design_space.sample_designs(1, seed=0).features(), GRID, tolerance=1e-9)


def test_measured_costs_are_lines_of_each_path():
    """What the router weighs is measured here (no assertion on how fast: tests never time)."""
    router = Router.shipped()
    costs = router.costs
    for cost in (costs.exact, costs.exact_loaded, costs.operator, costs.loaded_operator):
        assert np.isfinite(cost.seconds).all() and min(cost.seconds) > 0
    assert costs.exact(10) > costs.exact(1)  # a design's solve costs something


def test_cli_predict_without_a_model_answers_one_design_exactly(tmp_path):
    designs = design_space.sample_designs(1, seed=4273)
    request = tmp_path / "request.json"
    request.write_text(json.dumps({"designs": designs.to_dicts(), "points": 42}))
    out = subprocess.run([sys.executable, "-m", "tdcr.cli", "predict", str(request)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    answer = json.loads(out.stdout)
    assert answer["model"] == "exact" and answer["results"][0]["source"] == "exact"
    np.testing.assert_array_equal(answer["results"][0]["tendons"], solve(designs, GRID).tendons[0])
    pinned = subprocess.run([sys.executable, "-m", "tdcr.cli", "predict", str(request), "--model", "fno_pose"],
                            capture_output=True, text=True, timeout=120)
    assert json.loads(pinned.stdout)["results"][0]["source"] == "surrogate"
