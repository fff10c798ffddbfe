"""The one batched Levenberg-Marquardt (tdcr.search.lm) against an independent reference:
scipy's bounded linear least squares, and the KKT conditions of its box QP."""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from tdcr.search.lm import Evaluation, box_qp, levenberg_marquardt


def _spd(rng, b, n):
    a = rng.normal(size=(b, n, n))
    return a @ a.transpose(0, 2, 1) + 1e-2 * np.eye(n)


def test_box_qp_meets_the_kkt_conditions():
    rng = np.random.default_rng(0)
    b, n = 500, 4
    h, g = _spd(rng, b, n), 3.0 * rng.normal(size=(b, n))
    low, high = -rng.uniform(0.0, 1.0, (b, n)), rng.uniform(0.0, 1.0, (b, n))
    x = box_qp(h, g, low, high)
    grad = np.einsum("bij,bj->bi", h, x) + g
    assert ((x >= low) & (x <= high)).all()
    at_low, at_high = np.isclose(x, low, atol=1e-12), np.isclose(x, high, atol=1e-12)
    free = ~at_low & ~at_high
    assert np.abs(np.where(free, grad, 0.0)).max() < 1e-9  # stationary in the free variables
    assert (np.where(at_low, grad, 0.0) >= -1e-9).all() and (np.where(at_high, grad, 0.0) <= 1e-9).all()
    # an interior minimum is the unconstrained one
    wide = box_qp(h, g, np.full((b, n), -1e9), np.full((b, n), 1e9))
    np.testing.assert_allclose(wide, -np.linalg.solve(h, g[..., None])[..., 0], rtol=1e-9, atol=1e-9)


def test_bounded_linear_least_squares_matches_scipy():
    rng = np.random.default_rng(1)
    b, m, n = 40, 6, 4
    a, y = rng.normal(size=(b, m, n)), 2.0 * rng.normal(size=(b, m))
    low, high = np.zeros((b, n)), np.full((b, n), 1.0)

    def evaluate(tau, rows):
        return Evaluation(np.einsum("bmi,bi->bm", a[rows], tau) - y[rows], a[rows], np.ones(rows.size, bool), {})

    solution = levenberg_marquardt(evaluate, np.full((b, n), 0.5), low, high, max_iterations=200)
    for k in range(b):
        reference = lsq_linear(a[k], y[k], bounds=(low[k], high[k]), tol=1e-14).x
        np.testing.assert_allclose(solution.tau[k], reference, atol=1e-7)
    assert (solution.iterations < 200).all()  # every problem stopped on its own


def test_invalid_starts_stay_and_rank_deficient_jacobians_do_not_fail():
    b, n = 8, 4
    ok = np.arange(b) % 2 == 0

    def evaluate(tau, rows):  # the residual ignores tensions 2 and 3: J has two zero columns
        j = np.zeros((rows.size, 2, n))
        j[:, 0, 0] = j[:, 1, 1] = 1.0
        return Evaluation(tau[:, :2] - 0.25, j, ok[rows], {"tau": tau.copy()})

    start = np.full((b, n), 0.75)
    solution = levenberg_marquardt(evaluate, start, np.zeros((b, n)), np.ones((b, n)), max_iterations=50)
    np.testing.assert_allclose(solution.tau[ok, :2], 0.25, atol=1e-9)
    np.testing.assert_array_equal(solution.tau[~ok], start[~ok])
    assert np.isinf(solution.cost[~ok]).all() and (solution.iterations[~ok] == 0).all()
    np.testing.assert_array_equal(solution.at.extra["tau"][ok], solution.tau[ok])  # kept with the accepted point
