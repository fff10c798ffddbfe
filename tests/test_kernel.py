"""The compiled tendon-only kernel (numba) against the vectorised path (the same method and step
control), per-design step control against a 16x finer solve, status codes, threads, and the
fallback without numba."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from tdcr import sample_designs
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, solve
from tdcr.physics.cosserat import STATUS

pytest.importorskip("numba")

NUMPY = SolverOptions(kernel="numpy")
SIGMA = np.linspace(0.0, 1.0, 42)
#: the kernel and the vectorised path differ only in Newton's starting points and summation order
SAME_METHOD_RTOL = 1e-10


@pytest.fixture(scope="module")
def designs():
    return sample_designs(300, seed=1)


@pytest.mark.parametrize("sigma", [SIGMA, np.array([1.0, 0.0, 0.37, 0.37, 0.5, 0.05, 0.9]), np.ones(1),
                                   np.concatenate([np.linspace(0, 0.2, 30), np.linspace(0.25, 1, 4)])],
                         ids=["42-points", "unsorted-duplicates", "tip", "non-uniform"])
def test_kernel_equals_the_vectorised_path(designs, sigma):
    fast, slow = solve(designs, sigma), solve(designs, sigma, options=NUMPY)
    assert fast.status is not None and fast.error_estimate is not None
    np.testing.assert_array_equal(fast.status, slow.status)
    np.testing.assert_array_equal(fast.steps, slow.steps)
    assert relative_l2(fast.tendons, slow.tendons).max() < SAME_METHOD_RTOL
    assert relative_l2(fast.rotation, slow.rotation).max() < SAME_METHOD_RTOL
    np.testing.assert_allclose(fast.force, slow.force, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(fast.moment, slow.moment, rtol=1e-7, atol=1e-11)
    np.testing.assert_allclose(fast.error_estimate, slow.error_estimate, rtol=1e-5, atol=1e-14)
    np.testing.assert_allclose(fast.s, slow.s, rtol=0, atol=0)


def test_step_control_meets_1e_6_on_every_design_and_estimates_its_error(designs):
    """Against the same method at a 20x finer fixed step (its own error is ~1e-5 of ours)."""
    sol = solve(designs, SIGMA)
    fine = solve(designs, SIGMA, options=replace(NUMPY, max_step=1 / 820, max_level=0, step_tol=np.inf))
    error = relative_l2(sol.tendons, fine.tendons)
    assert sol.converged.all() and error.max() <= 1e-6
    assert (sol.error_estimate <= SolverOptions().step_tol).all()
    assert (sol.steps > 41).any(), "some designs of this sample need a finer step"
    # where the error is well above the reference's own, the estimate is within a factor 2 of it
    big = error > 1e-9
    assert big.sum() > 50
    ratio = sol.error_estimate[big] / error[big]
    assert ratio.min() > 0.5 and ratio.max() < 2.0
    # the base grid alone is not enough for some designs: that is what the step control is for
    base = solve(designs, SIGMA, options=SolverOptions(max_level=0, step_tol=np.inf))
    assert relative_l2(base.tendons, fine.tendons).max() > 1e-6


def test_the_vectorised_path_continues_along_s_where_newton_fails_from_the_base_strains():
    """Design 48,464 of ``sample_designs(100_000, seed=0)`` (r 0.5 mm, L 0.118 m, 4.8 N, pitches
    up to 20 rad/m; bending angle 5.9 rad): Newton from the strains at s = 0 failed at some node
    (60 iterations, `newton_failed`) on the vectorised path, which the kernel's continuation in s
    solves in 4; the vectorised path now retries such designs by continuation in s."""
    design = sample_designs(100_000, seed=0).take(slice(48_464, 48_465))
    fast, slow = solve(design, SIGMA), solve(design, SIGMA, options=NUMPY)
    assert STATUS[fast.status[0]] == STATUS[slow.status[0]] == "converged"
    np.testing.assert_array_equal(slow.steps, fast.steps)
    assert relative_l2(slow.tendons, fast.tendons)[0] < SAME_METHOD_RTOL


def test_a_status_per_design():
    d = sample_designs(6, seed=4)
    sol = solve(d, SIGMA, options=SolverOptions(max_newton=1))
    assert (sol.status == STATUS.index("newton_failed")).all() and not sol.converged.any()
    sol = solve(d, SIGMA, options=SolverOptions(max_level=0, step_tol=1e-15))
    assert (sol.status == STATUS.index("step_tol_not_met")).all() and not sol.converged.any()
    assert np.isfinite(sol.tendons).all()  # the shape is still returned, flagged
    sol = solve(d, SIGMA)
    assert (sol.status == 0).all() and sol.converged.all() and (sol.residual < 1e-8).all()


def test_threads_give_the_same_bits(designs):
    one, two = solve(designs, SIGMA, workers=1), solve(designs, SIGMA, workers=2)
    np.testing.assert_array_equal(one.tendons, two.tendons)
    np.testing.assert_array_equal(one.error_estimate, two.error_estimate)


def test_without_numba_the_fallback_gives_the_same_results(designs, tmp_path):
    """TDCR_KERNEL=numpy stands for a machine without numba: the vectorised path answers."""
    script = (
        "import json, sys, numpy as np\n"
        "from tdcr import sample_designs\nfrom tdcr.physics import solve\nfrom tdcr.physics import _compiled\n"
        "assert _compiled.kernel is None\n"
        "sol = solve(sample_designs(300, seed=1), np.linspace(0, 1, 42))\n"
        f"np.save({str(tmp_path / 't.npy')!r}, sol.tendons)\n"
        "print(json.dumps({'status': sol.status.tolist(), 'steps': sol.steps.tolist()}))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], env={**os.environ, "TDCR_KERNEL": "numpy"},
                         capture_output=True, text=True, check=True)
    fallback = json.loads(out.stdout)
    compiled = solve(designs, SIGMA)
    assert fallback["status"] == compiled.status.tolist() and fallback["steps"] == compiled.steps.tolist()
    assert relative_l2(np.load(tmp_path / "t.npy"), compiled.tendons).max() < SAME_METHOD_RTOL


# --------------------------------------------------------------------------- external loads

from tdcr.design_space import LoadSpace  # noqa: E402
from tdcr.designs import DesignBatch, ExternalLoads  # noqa: E402

#: the issue's loaded design space: |g| = 9.81 m/s^2 in any direction, density 6,450-8,000 kg/m^3,
#: tip force up to 0.02 N and tip moment up to 0.002 N m in any direction
LOADED_SPACE = LoadSpace(gravity="sphere", density=(6450.0, 8000.0), tip_force=0.02, tip_moment=0.002)


def loaded_space(n: int, seed: int) -> ExternalLoads:
    return LOADED_SPACE.sample(n, seed=seed)


def slender_bent(m: int, seed: int) -> tuple[DesignBatch, ExternalLoads]:
    """r = 0.5 mm, L = 0.31-0.35 m, 5 N on one tendon, horizontal gravity (steel)."""
    rng = np.random.default_rng(seed)
    f = np.zeros((m, 15))
    f[:, 0], f[:, 1], f[:, 2] = rng.uniform(15.5e9, 45.5e9, m), 0.0005, rng.uniform(0.31, 0.35, m)
    f[:, 3:7], f[:, 7:11], f[:, 11] = rng.uniform(0.005, 0.01, (m, 4)), rng.uniform(-20, 20, (m, 4)), 5.0
    loads = ExternalLoads(gravity=np.tile([9.81, 0.0, 0.0], (m, 1)), density=np.full(m, 7800.0))
    return DesignBatch.from_features(f), loads


def test_loaded_kernel_meets_1e_6_against_its_own_10x_finer_solve():
    d, loads = sample_designs(200, seed=3), loaded_space(200, 4)
    sol = solve(d, SIGMA, loads=loads, workers=2)
    fine = solve(d, SIGMA, loads=loads, options=SolverOptions(max_step_loads=1 / 1230, max_level=0, step_tol=np.inf))
    error = relative_l2(sol.tendons, fine.tendons)
    assert sol.converged.all() and (sol.status == 0).all()
    assert error.max() <= 1e-6 and (sol.error_estimate <= SolverOptions().step_tol).all()
    big = error > 1e-9
    ratio = sol.error_estimate[big] / error[big]
    assert big.sum() >= 10 and ratio.min() > 0.5 and ratio.max() < 2.0
    np.testing.assert_allclose(np.linalg.det(sol.rotation), 1.0, atol=1e-10)


def test_loaded_kernel_solves_the_vectorised_paths_discrete_problem():
    """Same RK4 grid, no step control: the kernel (variational shooting Jacobian) and the vectorised
    path (finite differences, load continuation) converge to the same discrete equilibrium."""
    d, loads = sample_designs(40, seed=8), loaded_space(40, 9)
    fixed = SolverOptions(max_step_loads=1 / 100, max_level=0, step_tol=np.inf)
    fast = solve(d, SIGMA, loads=loads, options=fixed)
    slow = solve(d, SIGMA, loads=loads, options=replace(fixed, kernel="numpy"))
    assert fast.converged.all() and slow.converged.all()
    assert relative_l2(fast.tendons, slow.tendons).max() < 1e-8


def test_the_slender_bent_designs_the_old_fixed_step_got_wrong():
    """r = 0.5 mm, L = 0.31-0.35 m, 5 N on one tendon, horizontal gravity: the old fixed step L/100
    is off by ~1e-5 here; the controlled step is within 1e-6 and says so."""
    d, loads = slender_bent(12, seed=9)
    sol = solve(d, SIGMA, loads=loads)
    fine = solve(d, SIGMA, loads=loads, options=SolverOptions(max_step_loads=1 / 2000, max_level=0, step_tol=np.inf))
    old = solve(d, SIGMA, loads=loads, options=SolverOptions(max_level=0, step_tol=np.inf))
    assert sol.converged.all() and relative_l2(sol.tendons, fine.tendons).max() <= 1e-6
    assert (sol.steps > 123).any()  # the controller refined some
    assert relative_l2(old.tendons, fine.tendons).max() > 3e-6


def test_euler_buckling_is_flagged_as_several_equilibria():
    """A compressive tip force on a straight rod: below Euler's load pi^2 EI / (4 L^2) one
    equilibrium (converged); above it the straight shape is one of several (flagged)."""
    e, r, length = 30e9, 0.0005, 0.3
    critical = np.pi**2 * e * np.pi * r**4 / 4 / (4 * length**2)
    d = DesignBatch(E=[e, e], r=[r, r], L=[length, length], offset=[[0.008] * 4] * 2, pitch=[[0.0] * 4] * 2,
                    tension=[[0.0] * 4] * 2)
    loads = ExternalLoads(tip_force=np.array([[0, 0, -0.5 * critical], [0, 0, -1.5 * critical]]))
    sol = solve(d, SIGMA, loads=loads)
    assert sol.status.tolist() == [0, STATUS.index("multiple_equilibria")]
    assert sol.converged.tolist() == [True, False]
    np.testing.assert_allclose(sol.backbone[:, -1, :2], 0.0, atol=1e-12)  # the straight shape, flagged


def test_the_numpy_loaded_path_has_the_same_step_control():
    """The fallback for loads: the same grids and refinements as the kernel.  Its estimates agree
    to ~10 %, not to round-off: it projects R onto SO(3) after every RK4 step, the kernel only at
    the outputs (two discretisations that differ at O(h^5))."""
    d, loads = slender_bent(6, seed=9)
    fast, slow = solve(d, SIGMA, loads=loads), solve(d, SIGMA, loads=loads, options=NUMPY)
    assert fast.converged.all() and slow.converged.all() and (fast.steps > 123).any()
    np.testing.assert_array_equal(fast.steps, slow.steps)
    np.testing.assert_allclose(fast.error_estimate, slow.error_estimate, rtol=0.2)
    assert relative_l2(fast.tendons, slow.tendons).max() < 1e-8
