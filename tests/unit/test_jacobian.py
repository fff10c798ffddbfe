"""The exact pose Jacobian of the solver (``solve(..., jacobian=True)``): against central finite
differences of the solver itself (<= 1e-6 relative), against the closed form of a straight rod at
zero tension (Euler-Bernoulli with extension), and its invariances."""

from __future__ import annotations

import numpy as np
import pytest

from tdcr import design_space
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch

S42 = np.linspace(0.0, 1.0, 42)


def _with_tension(d: DesignBatch, tension: np.ndarray) -> DesignBatch:
    return DesignBatch(E=d.E, r=d.r, L=d.L, offset=d.offset, pitch=d.pitch, tension=tension)


def _vee(skew: np.ndarray) -> np.ndarray:
    return np.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], axis=-1)


def finite_difference_jacobian(d: DesignBatch, s: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Central differences of the pose at every arclength, ``(B, n, 6, N_t)``."""
    base = solve(d, s)
    out = np.zeros(base.backbone.shape[:2] + (6, d.n_tendons))
    for i in range(d.n_tendons):
        step = np.zeros_like(d.tension)
        step[:, i] = eps
        plus, minus = solve(_with_tension(d, d.tension + step), s), solve(_with_tension(d, d.tension - step), s)
        out[:, :, :3, i] = (plus.backbone - minus.backbone) / (2 * eps)
        d_rot = (plus.rotation - minus.rotation) / (2 * eps)
        out[:, :, 3:, i] = _vee(d_rot @ np.swapaxes(base.rotation, -1, -2))
    return out


def test_matches_central_differences_on_table_i_designs():
    designs = design_space.sample_designs(12, seed=21)
    exact = solve(designs, S42, jacobian=True).jacobian
    fd = finite_difference_jacobian(designs, S42)
    scale = np.abs(fd).max(axis=(1, 2, 3))  # per design
    err = np.abs(exact - fd).max(axis=(1, 2, 3)) / scale
    assert err.max() < 1e-6, err


def test_straight_rod_at_zero_tension_is_euler_bernoulli():
    """At tau = 0 (straight rod, tendons of pitch 0 at rho_i): d p_xy / d tau_i = L^2 rho_i,xy / (2 E I),
    d p_z / d tau_i = -L / (E A), d theta / d tau_i = L (-rho_i,y, rho_i,x, 0) / (E I), exactly."""
    E, r, L = 3e10, 8e-4, 0.27
    offsets = [0.006, 0.007, 0.008, 0.009]
    d = DesignBatch(E=[E], r=[r], L=[L], offset=[offsets], pitch=[[0.0] * 4], tension=[[0.0] * 4])
    jac = solve(d, np.array([0.0, 0.5, 1.0]), jacobian=True).jacobian[0, -1]
    area, inertia = np.pi * r**2, np.pi * r**4 / 4
    angles = 2 * np.pi * np.arange(4) / 4
    rho = np.array(offsets)[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (4, 2)
    expected = np.zeros((6, 4))
    expected[:2] = (L**2 / (2 * E * inertia) * rho).T
    expected[2] = -L / (E * area)
    expected[3] = -L * rho[:, 1] / (E * inertia)
    expected[4] = L * rho[:, 0] / (E * inertia)
    np.testing.assert_allclose(jac, expected, rtol=1e-10, atol=1e-12 * np.abs(expected).max())


def test_base_is_clamped_and_processes_agree():
    designs = design_space.sample_designs(4, seed=3)
    sol = solve(designs, S42, jacobian=True)
    assert sol.jacobian.shape == (4, 42, 6, 4)
    assert np.all(sol.jacobian[:, 0] == 0.0)  # s = 0 does not move
    assert solve(designs, S42).jacobian is None
    np.testing.assert_allclose(solve(designs, S42[::-1], jacobian=True).jacobian[:, ::-1], sol.jacobian, rtol=1e-12,
                               atol=1e-15)


def test_loads_and_the_linearized_model_are_refused():
    from tdcr.physics import SolverOptions
    from tdcr.robot.designs import ExternalLoads

    designs = design_space.sample_designs(1, seed=0)
    gravity = ExternalLoads(gravity=np.array([[0.0, 0.0, -9.81]]), density=np.array([7800.0]))
    with pytest.raises(ValueError, match="tendon loads only"):
        solve(designs, S42, loads=gravity, jacobian=True)
    with pytest.raises(ValueError, match="tendon loads only"):
        solve(designs, S42, options=SolverOptions(linearized=True), jacobian=True)


def test_tip_solver_warm_starts_give_the_solvers_answers():
    """TipSolver (Newton from the last solve's strains) answers as solve() does, to Newton's tolerance,
    along a sequence of tensions that jumps around."""
    from tdcr.physics import TipSolver

    design = design_space.sample_designs(1, seed=8)
    tip = TipSolver(design)
    rng = np.random.default_rng(0)
    for tension in [design.tension[0], *rng.uniform(0.0, 5.0, (5, 4))]:
        warm = tip(tension[None])
        cold = solve(_with_tension(design, tension[None]), np.array([1.0]), jacobian=True)
        np.testing.assert_allclose(warm.backbone, cold.backbone, rtol=0, atol=1e-12)
        np.testing.assert_allclose(warm.jacobian, cold.jacobian, rtol=0, atol=1e-9 * np.abs(cold.jacobian).max())
        assert warm.converged.all()
