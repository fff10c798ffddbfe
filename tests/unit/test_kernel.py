"""The compiled kernels (numba): the Jacobian path leaves the shapes as they are, per-design step
control against a 20x finer solve, status codes, threads, warm starts, every output written, and
the several-equilibria test."""

from __future__ import annotations

import numpy as np
import pytest

from tdcr import sample_designs
from tdcr.metrics import relative_l2
from tdcr.physics import SolverOptions, Status, TipSolver, cosserat, solve

FRACTIONS = np.linspace(0.0, 1.0, 42)


@pytest.fixture(scope="module")
def designs():
    return sample_designs(300, seed=1)


@pytest.mark.parametrize("fractions", [FRACTIONS, np.array([1.0, 0.0, 0.37, 0.37, 0.5, 0.05, 0.9]), np.ones(1),
                                   np.concatenate([np.linspace(0, 0.2, 30), np.linspace(0.25, 1, 4)])],
                         ids=["42-points", "unsorted-duplicates", "tip", "non-uniform"])
def test_the_jacobian_leaves_every_other_output_as_it_is(designs, fractions):
    """One implementation: asking for the Jacobian adds it and changes no bit of the rest."""
    plain, with_jacobian = solve(designs, fractions), solve(designs, fractions, jacobian=True)
    assert plain.jacobian is None and with_jacobian.jacobian.shape == (300, fractions.size, 6, 4)
    assert np.isfinite(with_jacobian.jacobian).all()
    for name in ("status", "steps", "tendons", "rotation", "force", "moment", "error_estimate", "s", "displacement"):
        np.testing.assert_array_equal(getattr(with_jacobian, name), getattr(plain, name), err_msg=name)


def test_warm_started_tip_solves_equal_cold_solves():
    """TipSolver starts Newton at every node from its last solve's strains: the same answers as a
    cold solve to Newton's tolerance, for new tensions and for a new number of rows."""
    design = sample_designs(1, seed=7)
    tip = TipSolver(design)
    rng = np.random.default_rng(0)
    for rows in (3, 3, 5):
        tensions = design.tension * rng.uniform(0.8, 1.2, (rows, 4))
        warm = tip(tensions)
        cold = solve(design.take(np.zeros(rows, dtype=np.int64)).replace(tension=tensions), np.ones(1),
                     jacobian=True)
        assert warm.converged.all()
        np.testing.assert_allclose(warm.backbone, cold.backbone, rtol=0, atol=1e-12)
        np.testing.assert_allclose(warm.jacobian, cold.jacobian, rtol=1e-8, atol=1e-12)
    assert tip._warm.valid and tip._warm.nodes.shape[0] == 5


def test_step_control_meets_1e_6_on_every_design_and_estimates_its_error(designs):
    """Against the same method at a 20x finer fixed step (its own error is ~1e-5 of ours)."""
    sol = solve(designs, FRACTIONS)
    fine = solve(designs, FRACTIONS, options=SolverOptions(max_step=1 / 820, max_level=0, step_tol=np.inf))
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
    base = solve(designs, FRACTIONS, options=SolverOptions(max_level=0, step_tol=np.inf))
    assert relative_l2(base.tendons, fine.tendons).max() > 1e-6


def test_continuation_in_s_solves_a_strongly_bent_helical_design():
    """Design 48,464 of ``sample_designs(100_000, seed=0)`` (r 0.5 mm, L 0.118 m, 4.8 N, pitches
    up to 20 rad/m; bending angle 5.9 rad): Newton from the strains at s = 0 fails at some node;
    the kernel's chain (each node from the nodes before) solves it, with its Jacobian too."""
    design = sample_designs(100_000, seed=0).take(slice(48_464, 48_465))
    sol = solve(design, FRACTIONS, jacobian=True)
    assert sol.status[0] == Status.CONVERGED and np.isfinite(sol.jacobian).all()


def test_a_status_per_design():
    d = sample_designs(6, seed=4)
    sol = solve(d, FRACTIONS, options=SolverOptions(max_newton=1))
    assert (sol.status == Status.NEWTON_FAILED).all() and not sol.converged.any()
    sol = solve(d, FRACTIONS, options=SolverOptions(max_level=0, step_tol=1e-15))
    assert (sol.status == Status.STEP_TOL_NOT_MET).all() and not sol.converged.any()
    assert np.isfinite(sol.tendons).all()  # the shape is still returned, flagged
    sol = solve(d, FRACTIONS)
    assert (sol.status == 0).all() and sol.converged.all() and (sol.residual < 1e-8).all()


def test_threads_give_the_same_bits(designs):
    one, two = solve(designs, FRACTIONS, workers=1), solve(designs, FRACTIONS, workers=2)
    np.testing.assert_array_equal(one.tendons, two.tendons)
    np.testing.assert_array_equal(one.error_estimate, two.error_estimate)


@pytest.mark.parametrize("loaded", [False, True], ids=["tendon-loads", "external-loads"])
def test_every_output_of_the_kernels_is_written(loaded):
    """The kernels write into preallocated arrays: each is filled with a sentinel first, and none
    may be left (numba's parallel loops can drop item assignments, tdcr/physics/_kernel.py:_store)."""
    d, fractions, opts = sample_designs(7, seed=2), np.linspace(0.0, 1.0, 9), SolverOptions()
    mat = cosserat.material(d)
    edges0, _, _ = cosserat._step_grid(np.append(fractions, 1.0) if loaded else fractions,
                                       opts.max_step_loads if loaded else opts.max_step)
    kernel, rods, grid, tols, out = cosserat._kernel_inputs(d, mat, edges0, fractions, opts, loaded=loaded,
                                                            jacobian=not loaded,
                                                            warm=None if loaded else cosserat._WarmStart())
    for array in out:
        array[...] = -7
    if loaded:
        f_g = np.tile([0.0, 0.0, -9.81 * 7800.0], (7, 1)) * mat.area[:, None]
        kernel.solve_loaded_batch(rods, kernel.Loads(f_g=f_g, f_tip=np.zeros((7, 3)), m_tip=np.zeros((7, 3))),
                                  grid, tols, out)
    else:
        kernel.solve_batch(rods, grid, tols, out)
    for name, array in zip(out._fields, out, strict=True):
        assert not (array == -7).any(), f"{name} was not written"
    assert (out.status == Status.CONVERGED).all() and (out.iterations > 0).all() and (out.level >= 0).all()


def test_several_equilibria_is_a_real_eigenvalue_at_or_below_zero():
    rotation = np.array([[0.0, -2.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # eigenvalues +-2i and 1
    jacobians = np.stack([np.eye(3), np.diag([-1.0, 1.0, 1.0]), np.diag([-1.0, -1.0, 1.0]), -rotation @ rotation,
                          rotation, np.full((3, 3), np.nan)])
    # identity; one crossing (det < 0); two (det > 0, which a determinant test misses); -R^2 has the
    # real eigenvalue -1; R only a complex pair with real part 0 (no real eigenvalue <= 0) and 1;
    # not finite
    assert cosserat.several_equilibria(jacobians).tolist() == [False, True, True, True, False, True]


# --------------------------------------------------------------------------- external loads

from tdcr.robot.design_space import LoadSpace  # noqa: E402
from tdcr.robot.designs import DesignBatch, ExternalLoads  # noqa: E402

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
    sol = solve(d, FRACTIONS, loads=loads, workers=2)
    fine = solve(d, FRACTIONS, loads=loads,
                 options=SolverOptions(max_step_loads=1 / 1230, max_level=0, step_tol=np.inf))
    error = relative_l2(sol.tendons, fine.tendons)
    assert sol.converged.all() and (sol.status == 0).all()
    assert error.max() <= 1e-6 and (sol.error_estimate <= SolverOptions().step_tol).all()
    big = error > 1e-9
    ratio = sol.error_estimate[big] / error[big]
    assert big.sum() >= 10 and ratio.min() > 0.5 and ratio.max() < 2.0
    np.testing.assert_allclose(np.linalg.det(sol.rotation), 1.0, atol=1e-10)


def test_the_slender_bent_designs_the_old_fixed_step_got_wrong():
    """r = 0.5 mm, L = 0.31-0.35 m, 5 N on one tendon, horizontal gravity: the old fixed step L/100
    is off by ~1e-5 here; the controlled step is within 1e-6 and says so."""
    d, loads = slender_bent(12, seed=9)
    sol = solve(d, FRACTIONS, loads=loads)
    fine = solve(d, FRACTIONS, loads=loads,
                 options=SolverOptions(max_step_loads=1 / 2000, max_level=0, step_tol=np.inf))
    old = solve(d, FRACTIONS, loads=loads, options=SolverOptions(max_level=0, step_tol=np.inf))
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
    sol = solve(d, FRACTIONS, loads=loads)
    assert sol.status.tolist() == [Status.CONVERGED, Status.MULTIPLE_EQUILIBRIA]
    assert sol.converged.tolist() == [True, False]
    np.testing.assert_allclose(sol.backbone[:, -1, :2], 0.0, atol=1e-12)  # the straight shape, flagged


def test_the_numpy_routing_is_the_kernels_routing():
    """eq. RHO: the runtime's vectorised tendon_routing (numba-free, for the operators' pose fit)
    gives the kernel's _routing at every node, angles and helices included."""
    from tdcr.physics._compiled import kernel

    rng = np.random.default_rng(4)
    designs = sample_designs(20, seed=4)
    designs = designs.replace(angle=rng.uniform(-3, 3, (20, 4)))
    fractions = np.linspace(0.0, 1.0, 7)
    rho, drho = cosserat.tendon_routing(designs, fractions)
    mine, mine_d = np.empty((4, 2)), np.empty((4, 2))
    for b in range(20):
        for k, fraction in enumerate(fractions):
            kernel._routing(fraction, designs.L[b], designs.offset[b], designs.pitch[b], designs.angles[b], mine,
                            mine_d)
            np.testing.assert_allclose(rho[b, k, :, :2], mine, rtol=0, atol=1e-15)
            np.testing.assert_allclose(drho[b, k, :, :2], mine_d, rtol=0, atol=1e-14)
    assert (rho[..., 2] == 0).all() and (drho[..., 2] == 0).all()


def test_the_secant_update_of_the_tension_newton_matches_its_last_step():
    """Broyden's update (friction's tension Newton): afterwards the miss's Jacobian J = -dlen + diag(c)
    maps the last step dt onto the change in miss dm on every driven tendon's row, and leaves the
    tension-driven tendon's row (target NaN) and any direction orthogonal to dt as they were."""
    from tdcr.physics._compiled import kernel

    rng = np.random.default_rng(3)
    n_t = 4
    dlen, comp = rng.normal(size=(n_t, n_t)), rng.uniform(0.0, 1e-3, n_t)
    target = np.array([0.01, np.nan, 0.02, 0.0])
    tau_before, tau = rng.uniform(0, 5, n_t), rng.uniform(0, 5, n_t)
    miss_before, misses = rng.normal(size=n_t), rng.normal(size=n_t)
    updated = dlen.copy()
    kernel._secant_update(updated, comp, target, tau, tau_before, misses, miss_before)
    dt = tau - tau_before
    jacobian = -updated + np.diag(comp)
    driven = ~np.isnan(target)
    np.testing.assert_allclose((jacobian @ dt)[driven], (misses - miss_before)[driven], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(updated[~driven], dlen[~driven])
    orthogonal = np.linalg.svd(dt[None, :])[2][1]  # a direction with dt . v = 0
    np.testing.assert_allclose(updated @ orthogonal, dlen @ orthogonal, rtol=0, atol=1e-12)
    unchanged = dlen.copy()
    kernel._secant_update(unchanged, comp, target, tau_before, tau_before, misses, miss_before)  # no step
    np.testing.assert_array_equal(unchanged, dlen)


def test_read_only_inputs_reach_the_kernels_compiled_for_writable_ones():
    """A ``.npy`` body is a read-only buffer, and numba types a read-only array apart: designs and
    loads read from one must reach the same compiled kernels as any others, not compile the solver
    again where they are solved (minutes on a cold cache, on the service's event loop: found by a
    fresh clone's ``scripts/run.sh``).  Tendon loads, displacement actuation and external loads."""
    from tdcr.physics._compiled import kernel
    from tdcr.robot.designs import DesignBatch, ExternalLoads

    def read_only(a):
        a = np.array(a, dtype=np.float64)
        a.setflags(write=False)
        return a

    def solves(writable: bool):
        conv = (lambda a: np.array(a, dtype=np.float64)) if writable else read_only
        designs = DesignBatch.from_features(conv(sample_designs(2, seed=1).features()))
        fractions = conv(np.linspace(0.0, 1.0, 5))
        solve(designs, fractions)
        solve(designs.replace(displacement=conv(np.full((2, 4), 1e-4))), fractions)
        solve(designs, fractions, loads=ExternalLoads(tip_force=conv([[0.0, 0.01, 0.0]] * 2)))

    dispatchers = {name: f for name, f in vars(kernel).items() if hasattr(f, "signatures")}
    solves(writable=True)
    compiled = {name: len(f.signatures) for name, f in dispatchers.items()}
    solves(writable=False)
    assert {name: len(f.signatures) for name, f in dispatchers.items()} == compiled
