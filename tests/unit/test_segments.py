"""Any robot: tendons that end before the tip (segments), any tendon angles, the Poisson ratio and
displacement actuation -- against closed forms and an independent formulation of the solver."""

from __future__ import annotations

import numpy as np
import pytest

from tdcr.metrics import relative_l2
from tdcr.physics import Status, solve
from tdcr.physics.cosserat import SolverOptions, _solve_loaded_compiled
from tdcr.robot.designs import DesignBatch, ExternalLoads

FRACTIONS = np.linspace(0.0, 1.0, 21)


def two_segments(n: int = 4, *, pitch: float = 0.0, seed: int = 0) -> DesignBatch:
    """``n`` two-segment robots: 3 tendons ending at L/2 (8 mm), 3 at the tip (6 mm), 120 degrees apart."""
    rng = np.random.default_rng(seed)
    angles = np.tile(np.deg2rad([90.0, -30.0, 210.0]), 2)
    return DesignBatch(E=rng.uniform(20e9, 60e9, n), r=np.full(n, 6e-4), L=np.full(n, 0.2),
                       offset=np.tile([0.008] * 3 + [0.006] * 3, (n, 1)), pitch=np.full((n, 6), pitch),
                       tension=rng.uniform(0.0, 2.0, (n, 6)), angle=np.tile(angles, (n, 1)),
                       end=np.tile([0.1] * 3 + [0.2] * 3, (n, 1)))


def test_a_tendon_ending_at_half_length_leaves_the_distal_half_straight_and_unstrained():
    d = DesignBatch(E=[30e9], r=[1e-3], L=[0.2], offset=[[0.008]], pitch=[[0.0]], tension=[[2.0]], end=[[0.1]])
    sol = solve(d, FRACTIONS)
    assert sol.converged.all()
    distal = FRACTIONS > 0.5
    assert np.abs(sol.force[0, distal]).max() == 0.0 and np.abs(sol.moment[0, distal]).max() == 0.0
    mid = np.searchsorted(FRACTIONS, 0.5)
    # zero strain: p(s) = p(s_e) + (s - s_e) R(s_e) e3 and R(s) = R(s_e)
    line = sol.backbone[0, mid] + np.outer(sol.s[0, distal] - 0.1, sol.rotation[0, mid][:, 2])
    np.testing.assert_allclose(sol.backbone[0, distal], line, atol=1e-12)
    np.testing.assert_allclose(sol.rotation[0, distal], np.broadcast_to(sol.rotation[0, mid], (distal.sum(), 3, 3)),
                               atol=1e-12)
    # the proximal half is bent (a constant-curvature arc: the local equation is the same at every s)
    assert np.linalg.norm(sol.backbone[0, mid, :2]) > 1e-3
    # beyond its end the tendon has no path: its rows hold its termination point
    np.testing.assert_array_equal(sol.tendons[0, distal, 0], np.broadcast_to(sol.tendons[0, mid, 0], (distal.sum(), 3)))


def test_consistent_termination_pointwise_equals_shooting_across_the_ends():
    """Two formulations of the consistent equilibrium: the pointwise local equation with the tendon
    sums over the tendons crossing each cut (Magnus), and shooting on M(0) with RK4 integrating
    M' = -p' x N across the zero-width end steps."""
    d = two_segments(pitch=8.0)
    pointwise = solve(d, FRACTIONS)
    shooting = _solve_loaded_compiled(d, FRACTIONS, ExternalLoads(), SolverOptions(), 1)
    assert pointwise.converged.all() and shooting.converged.all()
    assert relative_l2(shooting.tendons, pointwise.tendons).max() < 1e-8


def test_the_termination_rules_agree_for_straight_routing_without_loads_and_differ_otherwise():
    straight = two_segments()
    exact, shortcut = solve(straight, FRACTIONS), solve(straight, FRACTIONS, termination="rucker_webster")
    assert exact.converged.all() and shortcut.converged.all()
    assert relative_l2(shortcut.tendons, exact.tendons).max() < 1e-9  # no kink forces for parallel tendons
    helical = two_segments(pitch=15.0)
    exact, shortcut = solve(helical, FRACTIONS), solve(helical, FRACTIONS, termination="rucker_webster")
    assert shortcut.converged.all()
    assert relative_l2(shortcut.tendons, exact.tendons).min() > 1e-4  # the dropped kink forces
    loads = ExternalLoads(tip_force=np.tile([0.05, 0.0, 0.0], (len(straight), 1)))
    a = solve(straight, FRACTIONS, loads=loads)
    b = solve(straight, FRACTIONS, loads=loads, termination="rucker_webster")
    assert 1e-7 < relative_l2(b.tendons, a.tendons).max() < 1e-3


def test_single_segment_designs_do_not_depend_on_the_rule():
    d = two_segments().replace(end=None)
    shortcut = solve(d, FRACTIONS, termination="rucker_webster")
    np.testing.assert_array_equal(solve(d, FRACTIONS).tendons, shortcut.tendons)


def test_unknown_termination_is_refused_by_name():
    with pytest.raises(ValueError, match="termination"):
        solve(two_segments(1), FRACTIONS, termination="bogus")


def test_rotating_every_tendon_angle_rotates_the_shape_about_the_axis():
    d = two_segments(pitch=5.0)
    phi = 0.7
    turned = solve(d.replace(angle=d.angles + phi), FRACTIONS)
    base = solve(d, FRACTIONS)
    rz = np.array([[np.cos(phi), -np.sin(phi), 0.0], [np.sin(phi), np.cos(phi), 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(turned.backbone, base.backbone @ rz.T, atol=1e-10)


def test_default_angles_and_ends_change_nothing():
    d = two_segments().replace(end=None)
    explicit = d.replace(angle=np.tile(2 * np.pi * np.arange(6) / 6, (len(d), 1)), end=np.tile(d.L[:, None], (1, 6)))
    plain = d.replace(angle=None)
    np.testing.assert_array_equal(solve(explicit, FRACTIONS).tendons, solve(plain, FRACTIONS).tendons)


def test_the_jacobian_leaves_the_shapes_of_segments_as_they_are():
    d = two_segments(pitch=6.0)
    plain, with_jacobian = solve(d, FRACTIONS), solve(d, FRACTIONS, jacobian=True)
    np.testing.assert_array_equal(with_jacobian.tendons, plain.tendons)
    np.testing.assert_array_equal(with_jacobian.displacement, plain.displacement)
    assert np.isfinite(with_jacobian.jacobian).all()
    # an ended tendon no longer moves the distal tip... but its pull still bends the proximal part
    assert np.abs(with_jacobian.jacobian[:, -1, :3, :3]).max() > 0


def test_step_control_estimate_holds_with_segments():
    sol = solve(two_segments(8, pitch=12.0, seed=3), FRACTIONS)
    assert sol.converged.all() and (sol.error_estimate <= SolverOptions().step_tol).all()


def test_poisson_ratio_sets_the_shear_modulus():
    """Torsion of a straight rod by a tip moment: twist rate M / (G J), G = E / (2 (1 + nu))."""
    moment = 1e-3
    for nu in (0.25, 0.33):
        d = DesignBatch(E=[50e9], r=[1e-3], L=[0.2], offset=[[0.005]], pitch=[[0.0]], tension=[[0.0]], poisson=[nu])
        sol = solve(d, np.array([1.0]), loads=ExternalLoads(tip_moment=np.array([[0.0, 0.0, moment]])))
        g_j = 50e9 / (2 * (1 + nu)) * np.pi * 1e-3**4 / 2
        angle = np.arctan2(sol.rotation[0, 0, 1, 0], sol.rotation[0, 0, 0, 0])
        assert angle == pytest.approx(moment * 0.2 / g_j, rel=1e-9)


def test_displacement_round_trip_returns_the_tensions():
    """tension -> displacement -> tension.  Co-contraction (all tendons together) only compresses
    the rod, d ~ L / (E A) per newton, so a displacement known to 1e-11 m fixes the tensions to
    about 1e-5 N."""
    rng = np.random.default_rng(7)
    d = two_segments(6, pitch=4.0).replace(tension=rng.uniform(0.2, 2.0, (6, 6)))
    forward = solve(d, FRACTIONS)
    driven = d.replace(displacement=forward.displacement, tension=np.zeros((6, 6)))
    back = solve(driven, FRACTIONS)
    assert back.converged.all() and not back.slack.any()
    np.testing.assert_allclose(back.tension, d.tension, atol=2e-5)
    np.testing.assert_allclose(back.displacement, forward.displacement, atol=1e-10)
    assert relative_l2(back.tendons, forward.tendons).max() < 1e-6


def test_displacement_closed_form_for_one_straight_tendon():
    """One straight tendon: constant strains, so its path length is L |nu + kappa x rho|."""
    d = DesignBatch(E=[30e9], r=[8e-4], L=[0.25], offset=[[0.007]], pitch=[[0.0]], tension=[[1.5]])
    sol = solve(d, np.array([0.5]))
    strain_force = sol.rotation[0, 0].T @ sol.force[0, 0]
    strain_moment = sol.rotation[0, 0].T @ sol.moment[0, 0]
    area, inertia = np.pi * 8e-4**2, np.pi * 8e-4**4 / 4
    nu = np.array([0.0, 0.0, 1.0]) + strain_force / np.array([30e9 / 2.6 * area, 30e9 / 2.6 * area, 30e9 * area])
    kappa = strain_moment / np.array([30e9 * inertia, 30e9 * inertia, 30e9 / 2.6 * 2 * inertia])
    g = nu + np.cross(kappa, [0.007, 0.0, 0.0])
    assert sol.displacement[0, 0] == pytest.approx(0.25 * (1.0 - np.linalg.norm(g)), rel=1e-9)


def test_a_displacement_that_would_need_a_push_leaves_the_tendon_slack():
    d = DesignBatch(E=[30e9] * 2, r=[8e-4] * 2, L=[0.2] * 2, offset=[[0.008] * 4] * 2, pitch=[[0.0] * 4] * 2,
                    tension=[[0.0, 0.0, 0.0, 0.0]] * 2, displacement=[[-1e-3, 2e-3, np.nan, np.nan]] * 2)
    sol = solve(d, FRACTIONS)
    assert sol.converged.all()
    assert sol.slack[:, 0].all() and not sol.slack[:, 1].any()
    assert (sol.tension[:, 0] == 0).all() and (sol.tension[:, 1] > 0).all()
    np.testing.assert_allclose(sol.displacement[:, 1], 2e-3, atol=1e-10)
    assert (sol.displacement[:, 0] > -1e-3).all()  # it shortened on its own less than it was let out


#: Gravity across the rod and a small tip force: the shape moves by centimetres.
def _in_gravity(n: int) -> ExternalLoads:
    return ExternalLoads(gravity=np.tile([9.81, 0.0, 0.0], (n, 1)), density=np.full(n, 8000.0),
                         tip_force=np.tile([0.0, 0.02, 0.0], (n, 1)))


def test_displacement_in_gravity_round_trips_the_tensions():
    """tension -> displacement -> tension in gravity and under a tip force (the loaded kernel both
    ways): the tensions come back as in the unloaded round trip, the displacements to 1e-10 m."""
    rng = np.random.default_rng(11)
    d = two_segments(4, pitch=4.0).replace(tension=rng.uniform(0.2, 2.0, (4, 6)))
    loads = _in_gravity(4)
    forward = solve(d, FRACTIONS, loads=loads)
    unloaded = solve(d, FRACTIONS)
    assert forward.converged.all()
    assert np.abs(forward.backbone[:, -1] - unloaded.backbone[:, -1]).max() > 5e-3  # the loads matter
    back = solve(d.replace(displacement=forward.displacement, tension=np.zeros((4, 6))), FRACTIONS, loads=loads)
    assert back.converged.all() and not back.slack.any()
    np.testing.assert_allclose(back.tension, d.tension, atol=2e-5)
    np.testing.assert_allclose(back.displacement, forward.displacement, atol=1e-10)
    assert relative_l2(back.tendons, forward.tendons).max() < 1e-6


@pytest.mark.parametrize("sequence", [False, True])
def test_a_loaded_displacement_answer_is_the_loaded_solve_at_its_tensions(sequence):
    """The loaded displacement solve answers with Newton's last accepted shooting of each design
    (it does not shoot again at the found tensions): that answer is a loaded tension solve at the
    found tensions, to the shooting's tolerance (the two start their shooting from different M(0)),
    and it meets the pull-ins: eq. SE, tau = k (u - d) with d the answer's own shortening, to k times
    the displacement tolerance."""
    rng = np.random.default_rng(23)
    d = two_segments(5, pitch=4.0)
    pull = rng.uniform(2e-4, 1.5e-3, (5, 6))
    stiffness = np.full((5, 6), 3000.0)
    driven = d.replace(displacement=pull, tension=np.zeros((5, 6)), stiffness=stiffness)
    loads = _in_gravity(5)
    sol = solve(driven, FRACTIONS, loads=loads, sequence=sequence)
    again = solve(d.replace(tension=sol.tension, stiffness=stiffness), FRACTIONS, loads=loads)
    assert sol.converged.all() and again.converged.all() and (sol.tension > 0.05).all()
    assert relative_l2(sol.tendons, again.tendons).max() < 1e-9
    np.testing.assert_allclose(sol.displacement, again.displacement, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(sol.tension, stiffness * (pull - sol.displacement), rtol=0.0,
                               atol=3000.0 * SolverOptions().displacement_tol)


def test_a_series_spring_in_gravity_pulls_with_k_times_the_pull_in_it_takes_up():
    """eq. SE under loads: tau = k max(0, u - zero - d) to 1e-9 N, d the loaded path's shortening;
    a tendon let out further than its path shortens hangs slack."""
    d = DesignBatch(E=[30e9] * 2, r=[8e-4] * 2, L=[0.2] * 2, offset=[[0.008] * 4] * 2, pitch=[[0.0] * 4] * 2,
                    tension=[[0.0, 0.0, 0.0, 0.5]] * 2, displacement=[[4e-3, 1e-3, -2e-2, np.nan]] * 2,
                    stiffness=[[800.0, 2000.0, 1500.0, 1000.0], [300.0, 5000.0, 1500.0, 1000.0]],
                    zero=[[1e-4, -2e-4, 0.0, 0.0]] * 2)
    sol = solve(d, FRACTIONS, loads=_in_gravity(2))
    assert sol.converged.all()
    pull_in = d.displacement[:, :3] - d.zero[:, :3]
    np.testing.assert_allclose(sol.tension[:, :3], d.stiffness[:, :3] * np.maximum(0.0, pull_in
                                                                                   - sol.displacement[:, :3]),
                               rtol=0.0, atol=1e-9)
    assert (sol.tension[:, :2] > 0.1).all() and (sol.tension[:, 2] == 0.0).all() and sol.slack[:, 2].all()
    np.testing.assert_array_equal(sol.tension[:, 3], 0.5)  # tension-driven: as given


def test_a_warm_started_loaded_solve_gives_the_cold_answer_in_fewer_passes():
    """The loaded shooting started from a nearby solve's M(0) (the loaded displacement solve's
    Newton steps): the answer of the cold first guess to the shooting's tolerance, in no more passes; a
    NaN start is the cold solve, bit for bit, and every start is overwritten with its result's M(0)."""
    rng = np.random.default_rng(17)
    d, loads, opts = two_segments(6, pitch=4.0), _in_gravity(6), SolverOptions()
    first = np.full((6, 3), np.nan)
    cold = _solve_loaded_compiled(d, FRACTIONS, loads, opts, 1)
    unstarted = _solve_loaded_compiled(d, FRACTIONS, loads, opts, 1, base_moment=first)
    np.testing.assert_array_equal(unstarted.tendons, cold.tendons)
    np.testing.assert_array_equal(unstarted.iterations, cold.iterations)
    assert cold.converged.all() and np.isfinite(first).all()
    nearby = d.replace(tension=d.tension * rng.uniform(0.98, 1.02, d.tension.shape))
    again = _solve_loaded_compiled(nearby, FRACTIONS, loads, opts, 1)
    warm = _solve_loaded_compiled(nearby, FRACTIONS, loads, opts, 1, base_moment=first.copy())
    assert warm.converged.all()
    assert relative_l2(warm.tendons, again.tendons).max() < 1e-9
    # (the cold first guess's tendon-only pass, which a warm start skips, is not among the passes counted)
    assert (warm.iterations <= again.iterations).all() and warm.iterations.sum() < again.iterations.sum()


def test_vanishing_loads_give_the_unloaded_displacement_answer():
    """A tip force of 1e-12 N: the loaded displacement solve returns the unloaded one's tensions."""
    rng = np.random.default_rng(5)
    d = two_segments(3).replace(displacement=rng.uniform(1e-4, 1e-3, (3, 6)), tension=np.zeros((3, 6)))
    plain = solve(d, FRACTIONS)
    tiny = solve(d, FRACTIONS, loads=ExternalLoads(tip_force=np.tile([1e-12, 0.0, 0.0], (3, 1))))
    assert plain.converged.all() and tiny.converged.all()
    np.testing.assert_allclose(tiny.tension, plain.tension, atol=1e-7)
    np.testing.assert_allclose(tiny.backbone, plain.backbone, atol=1e-8)


def test_a_loaded_displacement_solve_that_cannot_move_stops_instead_of_repeating_itself(monkeypatch):
    """A command of the FTDCR v6 recording (its sysid train file's row 443) upright in gravity (its
    project's 37,708 kg/m^3), with friction 0.05, whose pull-ins the semismooth Newton cannot meet: from some
    tensions on no step along a freshly differenced Jacobian solves, and each further iteration would
    repeat the same solves (they are deterministic).  It stops there with displacement_not_met; it
    used to repeat them to the 30th iteration: 357 loaded solves, 49 s on the 2-core VM (now 69)."""
    import tdcr.physics.cosserat as cosserat
    from tdcr.physics.replay import REPLAY_OPTIONS

    angles = [0.0, 2.094395, -2.094395, 0.5236, 2.617995, -1.570795, 1.0472, -3.14159, -1.047195]
    pull_in = [0.0, -9.2039e-05, -1.22718e-04, 0.0, -1.53398e-04, 0.0, 1.932816e-03, -3.788933e-03, 1.825437e-03]
    motion = [1, -1, 1, -1, 1, 1, -1, 1, -1]
    d = DesignBatch(E=[1e10], r=[5e-4], L=[0.222], offset=[[0.0045] * 9], pitch=[[0.0] * 9], tension=[[0.0] * 9],
                    angle=[angles], end=[[0.1] * 3 + [0.2] * 3 + [0.222] * 3], displacement=[pull_in],
                    stiffness=[[3000.0] * 9], friction=[[0.05] * 9], motion=[motion])
    loads = ExternalLoads(gravity=[[0.2351, 0.0168, -9.8072]], density=[37708.0])
    solves = [0]
    loaded = cosserat._solve_loaded_compiled

    def counted(*args, **kwargs):
        solves[0] += 1
        return loaded(*args, **kwargs)

    monkeypatch.setattr(cosserat, "_solve_loaded_compiled", counted)
    sol = solve(d, np.ones(1), loads=loads, options=REPLAY_OPTIONS)
    assert sol.status[0] == Status.DISPLACEMENT_NOT_MET
    # each Newton iteration differences 9 tendons and tries 7 step lengths: 30 of them are ~480 solves
    assert solves[0] < 120, solves[0]


def test_friction_with_the_shortcut_termination_or_a_jacobian_is_refused_by_name():
    d = DesignBatch(E=[30e9], r=[8e-4], L=[0.2], offset=[[0.008] * 4], pitch=[[0.0] * 4],
                    tension=[[1.0, 0.0, 0.0, 0.0]], friction=[[0.1] * 4])
    assert solve(d, FRACTIONS, loads=_in_gravity(1)).converged.all()  # in gravity: the loaded kernel carries it
    with pytest.raises(ValueError, match="friction covers consistent termination"):
        solve(d.replace(end=np.array([[0.1, 0.2, 0.2, 0.2]])), FRACTIONS, termination="rucker_webster")
    with pytest.raises(ValueError, match="friction covers consistent termination"):
        solve(d, FRACTIONS, jacobian=True)


def test_high_tension_converges_or_is_flagged():
    from tdcr.robot.design_space import sample_designs

    d = sample_designs(300, seed=3)
    d = d.replace(tension=np.tile([20.0, 0.0, 0.0, 0.0], (300, 1)))
    sol = solve(d, np.linspace(0.0, 1.0, 42))
    assert set(np.unique(sol.status)) <= {Status.CONVERGED, Status.TENDON_COLLAPSED}
    assert (sol.status == Status.TENDON_COLLAPSED).any()


def test_inverse_kinematics_reaches_a_target_of_a_two_segment_robot():
    """The exact inverse (tip Jacobian of the vectorised path, with the ends) on a segmented design:
    the tensions it returns put the tip on the target in the forward solver."""
    from tdcr.api.validation import validate_inverse
    from tdcr.search.inverse import answer_exact

    robot = two_segments(1)
    target = solve(robot, np.array([1.0])).backbone[0, 0]
    body = {"design": robot.replace(tension=np.zeros((1, 6))).to_dicts()[0],
            "targets": [{"position": target.tolist()}], "tension_max": 5.0}
    (result,) = answer_exact(validate_inverse(body))
    assert result["status"] == "reached"
    reached = solve(robot.replace(tension=np.array([result["tensions"]])), np.array([1.0])).backbone[0, 0]
    assert np.linalg.norm(reached - target) < 1e-4 * 0.2


def test_admission_counts_a_displacement_in_gravity_as_several_loaded_solves():
    """The service's work estimate: a loaded design costs one loaded solve, a displacement-driven one
    under the same loads LOADED_DISPLACEMENT_COST of them (and the displacement's unloaded start)."""
    from tdcr.api.validation import validate_json
    from tdcr.physics.exact import DISPLACEMENT_COST, LOADED_DISPLACEMENT_COST, WorkBudget

    tendons = [{"offset": 0.008, "pitch": 0.0, "tension": 1.0}] + [{"offset": 0.008, "pitch": 0.0, "tension": 0.0}] * 3
    gravity = {"gravity": [0.0, 0.0, -9.81], "density": 7800.0}
    design = {"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": tendons} | gravity
    driven = design | {"tendons": [{"offset": 0.008, "pitch": 0.0, "displacement": 1e-3}] + tendons[1:]}
    budget = WorkBudget(seconds_per_design=1.0, seconds_per_loaded_design=10.0, max_seconds=1e9)
    one = budget.estimate(validate_json({"points": 42, "designs": [design]}, target="solver"))
    request = validate_json({"points": 42, "designs": [design, driven]}, target="solver")
    assert request.n_loaded == 2 and request.n_displacement == 1 and request.n_loaded_displacement == 1
    assert one == 10.0
    assert budget.estimate(request) == 10.0 * (1 + LOADED_DISPLACEMENT_COST) + (DISPLACEMENT_COST - 1)
