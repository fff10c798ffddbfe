"""Closed-form checks of the Cosserat solver (tolerances stated per test)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tdcr import design_space
from tdcr.physics import SolverOptions, material, solve
from tdcr.physics import cosserat as _c
from tdcr.robot.designs import DesignBatch, ExternalLoads

S42 = np.linspace(0.0, 1.0, 42)


def one(E=3e10, r=1e-3, L=0.25, offset=(0.008,) * 4, pitch=(0.0,) * 4, tension=(0.0,) * 4) -> DesignBatch:
    return DesignBatch(E=[E], r=[r], L=[L], offset=[list(offset)], pitch=[list(pitch)], tension=[list(tension)])


def test_zero_tension_gives_the_straight_rod():
    d = one(pitch=(5.0, -3.0, 0.0, 20.0))
    sol = solve(d, S42)
    s = sol.s[0]
    np.testing.assert_allclose(sol.backbone[0], np.stack([0 * s, 0 * s, s], axis=1), atol=1e-15)
    np.testing.assert_allclose(sol.rotation[0], np.broadcast_to(np.eye(3), (42, 3, 3)), atol=1e-15)
    rho, _ = _c.tendon_routing(d, S42)
    np.testing.assert_allclose(sol.tendons[0], rho[0] + sol.backbone[0][:, None, :], atol=1e-15)


@pytest.mark.parametrize("n_tendons", [2, 3, 4, 6])
def test_equal_tensions_compress_a_straight_rod(n_tendons):
    """Symmetric pull: kappa = 0, nu_z = 1 - N tau / (E A), so the tip sits at L (1 - N tau / (E A))."""
    tau, E, r, L = 3.0, 2e10, 6e-4, 0.3
    d = one(E=E, r=r, L=L, offset=(0.007,) * n_tendons, pitch=(0.0,) * n_tendons, tension=(tau,) * n_tendons)
    sol = solve(d, S42)
    tip = sol.backbone[0, -1]
    expected = L * (1.0 - n_tendons * tau / (E * np.pi * r**2))
    assert abs(tip[2] - expected) < 1e-12 * L
    assert np.abs(tip[:2]).max() < 1e-12 * L


def test_parallel_tendon_gives_an_exact_planar_circle():
    """A single straight (pitch 0) tendon: constant strains, so the backbone is a circle in the x-z plane."""
    d = one(offset=(0.009, 0.009, 0.009, 0.009), tension=(4.0, 0.0, 0.0, 0.0), r=6e-4, E=2e10, L=0.3)
    sol = solve(d, S42)
    p = sol.backbone[0]
    assert np.abs(p[:, 1]).max() < 1e-14
    # strains from the constitutive law at the base and the circle they imply
    mat = material(d)
    nu = np.array([0, 0, 1.0]) + sol.rotation[0, 0].T @ sol.force[0, 0] / mat.kse[0]
    kappa = sol.rotation[0, 0].T @ sol.moment[0, 0] / mat.kbt[0]
    assert abs(kappa[0]) < 1e-12 and abs(kappa[2]) < 1e-12 and kappa[1] > 0
    radius = np.linalg.norm(nu) / kappa[1]
    # centre: from the base, perpendicular to the initial velocity nu, towards +x
    v0 = nu / np.linalg.norm(nu)
    centre = radius * np.array([v0[2], 0.0, -v0[0]])
    dist = np.linalg.norm(p - centre, axis=1)
    np.testing.assert_allclose(dist, radius, rtol=1e-10)
    # the bending angle grows linearly: R(s) is a rotation about y by kappa s
    angles = np.arctan2(sol.rotation[0, :, 0, 2], sol.rotation[0, :, 2, 2])
    np.testing.assert_allclose(np.unwrap(angles), kappa[1] * sol.s[0], rtol=1e-10, atol=1e-12)


def test_parallel_tendons_keep_body_strains_constant():
    d = one(tension=(2.0, 0.7, 0.0, 1.3), offset=(0.005, 0.008, 0.01, 0.006), r=5e-4, E=1.6e10)
    sol = solve(d, S42)
    nb = np.einsum("nji,nj->ni", sol.rotation[0], sol.force[0])
    mb = np.einsum("nji,nj->ni", sol.rotation[0], sol.moment[0])
    assert np.ptp(nb, axis=0).max() < 1e-12 * np.abs(nb).max()
    assert np.ptp(mb, axis=0).max() < 1e-10 * np.abs(mb).max()


def test_pure_tip_moment_gives_a_circle_of_curvature_M_over_EI():
    E, r, L, M = 3e10, 1e-3, 0.25, 0.02
    d = one(E=E, r=r, L=L)
    EI = E * np.pi * r**4 / 4
    k = M / EI  # 1/m
    loads = ExternalLoads(tip_moment=np.array([[0.0, M, 0.0]]))
    sol = solve(d, S42, loads=loads)
    assert sol.converged[0]
    s = sol.s[0]
    expected = np.stack([(1 - np.cos(k * s)) / k, 0 * s, np.sin(k * s) / k], axis=1)
    assert np.linalg.norm(sol.backbone[0] - expected) / np.linalg.norm(expected) < 1e-8


@pytest.mark.parametrize("E", [3e10, 2e11])
def test_pure_tip_torque_twists_by_M_L_over_G_J(E):
    """A torque M about the axis twists the straight rod uniformly: angle M s / (G J), with
    G = E / (2 (1 + POISSON_RATIO)) and J = pi r^4 / 2 (the material law of every path)."""
    r, L, M = 1e-3, 0.25, 1e-3
    sol = solve(one(E=E, r=r, L=L), S42, loads=ExternalLoads(tip_moment=np.array([[0.0, 0.0, M]])))
    assert sol.converged[0]
    g = E / (2 * (1 + _c.POISSON_RATIO))
    angle = np.arctan2(sol.rotation[0, :, 1, 0], sol.rotation[0, :, 0, 0])  # of the body x axis about z
    np.testing.assert_allclose(angle, M * sol.s[0] / (g * np.pi * r**4 / 2), rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(sol.backbone[0, :, :2], 0.0, atol=1e-15)


#: Tip loads and a coarse shooting step for the consistency tests below (they compare the solver
#: with itself, so the step only has to be the same on both sides).
TIP_LOADS = ExternalLoads(tip_force=np.array([[0.05, 0.0, -0.02]]), tip_moment=np.array([[0.0, 0.01, 0.0]]))
COARSE = SolverOptions(max_step_loads=1 / 25)
GRID5 = np.linspace(0, 1, 5)


@pytest.fixture(scope="module")
def tip_loaded_on_grid():
    """One design under TIP_LOADS, solved once on GRID5 and shared."""
    return solve(one(), GRID5, loads=TIP_LOADS, options=COARSE)


@pytest.mark.parametrize("s", [[0.0], [0.0, 0.5], [0.25, 0.5, 1.0]])
def test_loads_use_the_tip_condition_whatever_points_are_asked(tip_loaded_on_grid, s):
    """Shooting always integrates to s = L: sub-sets of points agree with the full grid."""
    part = solve(one(), np.array(s), loads=TIP_LOADS, options=COARSE)
    assert part.converged[0] and tip_loaded_on_grid.converged[0]
    idx = [int(np.argmin(np.abs(GRID5 - v))) for v in s]
    np.testing.assert_allclose(part.backbone[0], tip_loaded_on_grid.backbone[0, idx], atol=1e-9)


def test_only_the_base_point():
    d = design_space.sample_designs(2, seed=0)
    sol = solve(d, np.array([0.0]))
    assert sol.converged.all() and sol.backbone.shape == (2, 1, 3)
    np.testing.assert_allclose(sol.backbone, 0.0)


def test_small_tip_force_matches_beam_theory():
    """Cantilever, tip force F perpendicular: delta = F L^3 / (3 E I) + F L / (G A) (shear), small load."""
    E, r, L, F = 3e10, 1e-3, 0.25, 1e-4
    d = one(E=E, r=r, L=L)
    sol = solve(d, S42, loads=ExternalLoads(tip_force=np.array([[F, 0.0, 0.0]])))
    G = E / 2.6
    delta = F * L**3 / (3 * E * np.pi * r**4 / 4) + F * L / (G * np.pi * r**2)
    assert sol.converged[0]
    assert abs(sol.backbone[0, -1, 0] - delta) < 1e-3 * delta


def test_small_gravity_matches_beam_theory():
    """Uniform load q = rho A g across the rod: tip deflection q L^4 / (8 E I) + q L^2 / (2 G A)."""
    E, r, L, rho, g = 3e10, 1e-3, 0.25, 8000.0, 1e-3
    d = one(E=E, r=r, L=L)
    loads = ExternalLoads(gravity=np.array([[g, 0.0, 0.0]]), density=np.array([rho]))
    sol = solve(d, S42, loads=loads)
    A = np.pi * r**2
    q = rho * A * g
    delta = q * L**4 / (8 * E * np.pi * r**4 / 4) + q * L**2 / (2 * E / 2.6 * A)
    assert sol.converged[0]
    assert abs(sol.backbone[0, -1, 0] - delta) < 1e-3 * delta


def _tangents(path: np.ndarray) -> np.ndarray:
    """Unit tangents of sampled curves (..., n, 3) by central differences (interior points)."""
    d = path[..., 2:, :] - path[..., :-2, :]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@pytest.mark.parametrize("with_loads", [False, True])
def test_wrench_invariant_holds_along_s(with_loads):
    """n(s) + sum_i tau_i t_i(s) = F + f_g (L - s) and m(s) + sum_i tau_i (p_i - p) x t_i = M(s).

    t_i comes from finite differences of the returned tendon paths, so this checks the
    statics against the geometry.  The O(h^2) difference error sets the tolerance: 1e-5 of the
    tendon load with 2001 points (tendons only), 1e-3 with 101 points (external loads, RK4).
    """
    d = design_space.sample_designs(3, seed=7)
    s = np.linspace(0, 1, 101 if with_loads else 2001)
    tol = 1e-3 if with_loads else 1e-5
    loads = None
    F = np.zeros((3, 3))
    if with_loads:
        F = np.array([[0.1, -0.2, 0.05], [0.0, 0.3, 0.0], [-0.1, 0.0, -0.2]])
        loads = ExternalLoads(tip_force=F)
    sol = solve(d, s, loads=loads)
    assert sol.converged.all()
    t = _tangents(sol.tendons.swapaxes(1, 2)).swapaxes(1, 2)  # (B, n-2, N_t, 3)
    tau = d.tension[:, None, :, None]
    total_force = sol.force[:, 1:-1] + (tau * t).sum(axis=2)
    scale = d.tension.sum(axis=1)[:, None, None]
    assert np.abs(total_force - F[:, None, :]).max() / scale.min() < tol
    if not with_loads:
        arm = sol.tendons[:, 1:-1] - sol.backbone[:, 1:-1, None, :]
        total_moment = sol.moment[:, 1:-1] + (tau * np.cross(arm, t)).sum(axis=2)
        assert np.abs(total_moment).max() / (scale.min() * 0.01) < 1e-5


def test_batch_equals_one_at_a_time():
    d = design_space.sample_designs(12, seed=3)
    s = np.array([0.0, 0.13, 0.5, 0.77, 1.0])
    batch = solve(d, s)
    for j in range(12):
        single = solve(d.take([j]), s)
        np.testing.assert_allclose(batch.tendons[j], single.tendons[0], rtol=0, atol=1e-14)
        np.testing.assert_allclose(batch.rotation[j], single.rotation[0], rtol=0, atol=1e-14)


def test_unsorted_and_repeated_arclengths():
    d = design_space.sample_designs(2, seed=5)
    s = np.array([1.0, 0.2, 0.2, 0.0, 0.6])
    sol = solve(d, s)
    ref = solve(d, np.sort(np.unique(s)))
    np.testing.assert_allclose(sol.tendons[:, 0], ref.tendons[:, -1], atol=1e-14)
    np.testing.assert_allclose(sol.tendons[:, 1], sol.tendons[:, 2], atol=0)


def test_a_failing_design_never_fails_the_batch():
    """One Newton iteration solves the untensioned rod exactly and no tensioned one: the batch
    answers each design, flagged alone, and the others equal their solves on their own."""
    d = design_space.sample_designs(3, seed=1)
    feats = d.features()
    feats[1, design_space.LAYOUT.group("tension")] = 0.0
    batch, short = DesignBatch.from_features(feats), SolverOptions(max_newton=1, max_level=0)
    sol = solve(batch, S42, options=short)
    assert list(sol.converged) == [False, True, False]
    np.testing.assert_allclose(sol.tendons[[1]], solve(batch.take([1]), S42, options=short).tendons, atol=0)


@pytest.mark.parametrize("column, value, message", [
    (0, np.nan, "designs[1].E: must be a finite number, got nan"),
    (11, -2.0, "designs[1].tendons[0].tension: must be in [0, 1000] N, got -2"),
])
def test_the_python_api_refuses_bad_designs_with_the_services_words(column, value, message):
    feats = design_space.sample_designs(3, seed=1).features()
    feats[1, column] = value
    with pytest.raises(ValueError, match=re.escape(message)):
        solve(DesignBatch.from_features(feats), S42)
    with pytest.raises(ValueError, match=re.escape("fractions[1]: must be a fraction of L in [0, 1], got 1.01")):
        solve(design_space.sample_designs(1, seed=1), [0.0, 1.01])
    with pytest.raises(ValueError, match=re.escape("designs[0].gravity: needs a density")):
        solve(design_space.sample_designs(1, seed=1), S42, loads=ExternalLoads(gravity=[[0.0, 0.0, -9.81]]))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), start=st.integers(0, 2**31 - 1))
def test_local_equation_has_one_root(seed, start):
    """(W1, W2) is the gradient of a strictly convex potential: the kernel's Newton from anywhere
    finds the same root."""
    from tdcr.physics._compiled import kernel

    d = design_space.sample_designs(1, seed=seed)
    mat = material(d)
    opts = SolverOptions()
    rng = np.random.default_rng(start)
    rho, drho = np.empty((4, 2)), np.empty((4, 2))
    work, jac, low = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))

    def newton(x, fraction):
        kernel._routing(fraction, float(d.L[0]), d.offset[0], d.pitch[0], d.angles[0], rho, drho)
        ok, _, _ = kernel._newton(x, rho, drho, d.tension[0], mat.kse[0], mat.kbt[0], float(d.r[0]), float(d.L[0]),
                                  opts.newton_tol, opts.max_newton, work, jac, low, np.zeros(6), False)
        return ok

    for fraction in (0.0, 0.37, 1.0):
        x_ref = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        x = x_ref + np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 30.0, 3)])
        assert newton(x_ref, fraction) and newton(x, fraction)
        np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-9)


def test_a_batch_split_over_threads_equals_one_thread():
    d = design_space.sample_designs(1000, seed=12)
    s = np.linspace(0, 1, 9)
    one = solve(d, s)
    two = solve(d, s, workers=2)
    for field in ("tendons", "rotation", "force", "residual"):
        np.testing.assert_allclose(getattr(two, field), getattr(one, field), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(two.converged, one.converged)
    loads = ExternalLoads(tip_force=np.tile([0.0, 0.0, -1e-3], (1000, 1)))
    small = solve(d.take(slice(0, 3)), s, loads=loads.take(slice(0, 3)), workers=2)
    np.testing.assert_allclose(small.tendons, solve(d.take(slice(0, 3)), s, loads=loads.take(slice(0, 3))).tendons,
                               rtol=0, atol=0)
