"""The in-graph rod kinematics and the linearised reference robot, against the float64 solver."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tdcr import design_space, relative_l2  # noqa: E402
from tdcr.physics import SolverOptions, solve  # noqa: E402
from tdcr.robot.designs import DesignBatch  # noqa: E402
from training.operators import kinematics as K  # noqa: E402
from training.operators.models import TENDON_ONLY, build_model  # noqa: E402

GRID = np.linspace(0.0, 1.0, 42)
MID = 0.5 * (GRID[1:] + GRID[:-1])
BASE_ANGLE = torch.arange(4, dtype=torch.float64) * (np.pi / 2)


def body_strains(designs, fractions):
    """The solver's body strains (nu, kappa) at ``fractions`` ``(M,)``: ``((B, M, 6), converged (B,))``."""
    sol = solve(designs, np.asarray(fractions))
    return sol.strains, sol.converged


def se3_exp_numpy(v, w):
    """The solver's exponential on SE(3) (``tdcr.physics._kernel._se3_exp``), twist by twist:
    ``(R (K, 3, 3), p (K, 3))``."""
    from tdcr.physics._compiled import kernel

    rot, pos = np.empty((len(v), 3, 3)), np.empty((len(v), 3))
    for k in range(len(v)):
        kernel._se3_exp(np.concatenate([v[k], w[k]]), rot[k], pos[k])
    return rot, pos


def _batch_first(backbone, rotation):
    return backbone.permute(2, 1, 0).numpy(), rotation.permute(3, 2, 0, 1).numpy()


def test_se3_exp_matches_the_solvers_float64_version():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3))
    w = rng.normal(size=(50, 3)) * np.logspace(-6, 0.5, 50)[:, None]  # across the series switch at |w| = 0.1
    rot, pos = K.se3_exp(torch.as_tensor(v.T), torch.as_tensor(w.T))
    rot_ref, pos_ref = se3_exp_numpy(v, w)
    np.testing.assert_allclose(rot.permute(2, 0, 1).numpy(), rot_ref, atol=1e-12)
    np.testing.assert_allclose(pos.T.numpy(), pos_ref, atol=1e-12)


def test_magnus_kinematics_of_the_exact_strains_is_the_solver():
    designs = design_space.sample_designs(50, seed=3)
    strains, ok = body_strains(designs, np.concatenate([GRID, MID]))
    assert ok.all()
    xi = torch.as_tensor(strains).permute(2, 1, 0)  # (6, 83, B)
    backbone, rotation = _batch_first(*K.magnus_kinematics(xi[:, :42], xi[:, 42:], torch.as_tensor(designs.L / 41)))
    sol = solve(designs, GRID, options=SolverOptions(max_level=0, step_tol=np.inf))  # the same grid: no step control
    assert np.abs(backbone - sol.backbone).max() < 1e-9
    assert np.abs(rotation - sol.rotation).max() < 1e-8


def test_strain_prior_is_the_first_order_solution():
    """The prior is exact to first order in the tensions: its error is O(tension^2), so its error
    relative to the strains (which are O(tension)) falls 10x when the tensions do."""
    base = design_space.sample_designs(20, seed=4)
    errors = []
    for factor in (1e-2, 1e-3):
        designs = DesignBatch(E=base.E, r=base.r, L=base.L, offset=base.offset, pitch=base.pitch,
                              tension=base.tension * factor)
        exact, _ = body_strains(designs, GRID)
        prior = K.strain_prior(torch.as_tensor(designs.features()), torch.as_tensor(GRID), BASE_ANGLE)
        prior = prior.permute(2, 1, 0).numpy()
        errors.append(np.abs(prior[..., 3:] - exact[..., 3:]).max() / np.abs(exact[..., 3:]).max())
    assert 8.0 < errors[0] / errors[1] < 12.0
    assert errors[1] < 1e-4


def test_linearized_reference_is_close_to_the_solver():
    designs = design_space.sample_designs(300, seed=6)
    feats = torch.as_tensor(designs.features())
    backbone, rotation = K.linearized_pose(feats, torch.as_tensor(GRID), BASE_ANGLE)
    tendons = K.tendon_positions(backbone, rotation, K.tendon_offsets(feats, torch.as_tensor(GRID), BASE_ANGLE))
    errors = relative_l2(tendons.permute(3, 2, 0, 1).numpy(), solve(designs, GRID).tendons)
    assert np.median(errors) < 1e-3 and np.mean(errors) < 0.02


def test_partial_step_off_the_grid_matches_a_grid_through_those_points():
    designs = design_space.sample_designs(30, seed=7)
    feats = torch.as_tensor(designs.features())
    coarse = K.linearized_pose(feats, torch.as_tensor(GRID), BASE_ANGLE)
    fine_grid = np.linspace(0.0, 1.0, 83)  # contains GRID and its midpoints
    fine_p, fine_r = _batch_first(*K.linearized_pose(feats, torch.as_tensor(fine_grid), BASE_ANGLE))
    p, r = _batch_first(*K.partial_step(*coarse, feats, torch.as_tensor(fine_grid[1::2]), BASE_ANGLE))
    scale = designs.L[:, None, None]
    assert np.abs((p - fine_p[:, 1::2]) / scale).max() < 1e-5  # two 4th-order discretisations
    assert np.abs(r - fine_r[:, 1::2]).max() < 1e-5
    # on the grid, the partial step has zero length
    p0, r0 = _batch_first(*K.partial_step(*coarse, feats, torch.as_tensor(GRID), BASE_ANGLE))
    np.testing.assert_allclose(p0, coarse[0].permute(2, 1, 0).numpy(), atol=1e-12)


@pytest.mark.parametrize("name", TENDON_ONLY)
def test_zero_network_output_is_the_linearized_reference(tiny_hyperparameters, name):
    feats = torch.as_tensor(design_space.sample_designs(4, seed=0).features(), dtype=torch.float32)
    fractions = torch.linspace(0, 1, 42)
    model = build_model(name, dict(tiny_hyperparameters[name], inputs="physics", reference="linearized"))
    heads = model.heads(feats, fractions, torch.zeros(4, 42, model.out_channels))
    tendons = heads if model.kind == "tendons" else heads[2]
    backbone, rotation = K.linearized_pose(feats, torch.linspace(0, 1, 42), model.geometry.base_angle)
    expected = K.tendon_positions(backbone, rotation, K.tendon_offsets(feats, fractions, model.geometry.base_angle))
    torch.testing.assert_close(tendons, expected.permute(3, 2, 0, 1), atol=1e-6, rtol=1e-5)


def test_solver_linearized_option_is_the_graph_reference():
    """Two implementations of the reference robot: the numpy solver's and the in-graph torch one."""
    from tdcr.physics import SolverOptions

    designs = design_space.sample_designs(40, seed=8)
    sol = solve(designs, GRID, options=SolverOptions(linearized=True))
    feats = torch.as_tensor(designs.features())
    backbone, rotation = _batch_first(*K.linearized_pose(feats, torch.as_tensor(GRID), BASE_ANGLE))
    assert np.abs(sol.backbone - backbone).max() < 1e-10  # m, round-off of two summation orders
    assert np.abs(sol.rotation - rotation).max() < 1e-10
    assert sol.converged.all()


@pytest.mark.parametrize("points", [42, 5, 2, 17])
def test_grid_trig_by_angle_addition_equals_direct_evaluation(points):
    feats = torch.as_tensor(design_space.sample_designs(20, seed=9).features())
    grid = torch.linspace(0.0, 1.0, points, dtype=torch.float64)
    sin, cos = K._grid_trig(feats, grid, BASE_ANGLE)
    sin_ref, cos_ref = K.tendon_trig(feats, grid, BASE_ANGLE)
    assert sin.shape == sin_ref.shape == (4, points, 20)
    torch.testing.assert_close(sin, sin_ref, atol=1e-13, rtol=0)
    torch.testing.assert_close(cos, cos_ref, atol=1e-13, rtol=0)
