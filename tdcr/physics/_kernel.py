"""The compiled solver kernels (numba), one design per thread: tendon loads (:func:`solve_batch`)
and external loads (:func:`solve_loaded_batch`).

The method (:mod:`tdcr.physics.cosserat`'s docstring gives the equations): at every node, Newton
with an Armijo line search on Phi (eq. PHI) for the strains x = (nu, kappa) solving (W1, W2); under
tendon loads the 4th-order Magnus integrator (eq. MAG) on SE(3), under external loads shooting on
M(0) with RK4 (eq. MT).  Nodes are solved in order of s, each Newton starting from the strains of
the nodes before, and the step is chosen per design:

* level 0 integrates on the caller's step grid (``edges``, outputs at ``out_step``), level m on
  that grid with every step split into 2^m;
* after level m >= 1 the error of the tendon positions at the outputs is estimated by
  Richardson's rule for a 4th-order method, est = ||T_m - T_{m-1}|| / (15 ||T_m||) (relative l2,
  the project's error measure), and the design stops at the first level with est <= ``step_tol``
  or at ``max_level``.  Level m+1 reuses all strains of level m (its edges are level m's edges and
  midpoints).

Floating-point errors follow IEEE (``error_model='numpy'``): a division by zero gives inf or NaN,
which the status flags; it never raises.

Arguments come grouped as named tuples (:class:`Rods`, :class:`Grid`, :class:`Tolerances`,
:class:`Shapes`, :class:`Loads`), built by :mod:`tdcr.physics.cosserat` and read by field name.
Import this module only through :mod:`tdcr.physics._compiled` (numba's cache directory).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from tdcr.physics.status import Status

#: the right-hand side of (W1, W2) without external loads
_NO_TARGET = np.zeros(6)
#: status codes per design (:class:`tdcr.physics.status.Status`), as numba's compile-time integers
OK, NEWTON_FAILED, NOT_FINITE = int(Status.CONVERGED), int(Status.NEWTON_FAILED), int(Status.NOT_FINITE)
STEP_TOL_NOT_MET, SHOOTING_FAILED = int(Status.STEP_TOL_NOT_MET), int(Status.SHOOTING_FAILED)


class Rods(NamedTuple):
    """The designs of a batch, batch first: stiffness diagonals ``kse`` K_se (B, 3) N and ``kbt``
    K_bt (B, 3) N m^2 (:func:`tdcr.physics.cosserat.material`), ``radius`` (B,) m, ``length``
    (B,) m, tendon ``offset`` (B, N_t) m, ``pitch`` (B, N_t) rad/m, ``tension`` (B, N_t) N,
    ``angle`` (B, N_t) rad at s = 0 and ``end`` (B, N_t) fractions of L where each tendon
    terminates (1: the tip), ``compliance`` (B, N_t) m/N, 1 / stiffness of each tendon's series
    elasticity (0: rigid), and ``capstan`` (B, N_t), each tendon's signed Capstan coefficient:
    tau_i(s) = tau_i(0) exp(capstan_i theta_i(s)) with theta_i the tendon's wrap angle from the base
    (eq. CAP; -mu pulling, +mu releasing, 0 without friction)."""

    kse: np.ndarray
    kbt: np.ndarray
    radius: np.ndarray
    length: np.ndarray
    offset: np.ndarray
    pitch: np.ndarray
    tension: np.ndarray
    angle: np.ndarray
    end: np.ndarray
    compliance: np.ndarray
    capstan: np.ndarray


class Rod(NamedTuple):
    """One design of :class:`Rods` (:func:`_rod`): ``kse``, ``kbt`` (3,), ``radius`` and ``length``
    m, tendon ``offset``, ``pitch``, ``tension`` (at s = 0), ``angle`` and ``end`` (N_t,).  The
    tendons' ``compliance`` and ``capstan`` of :class:`Rods` travel beside it, to the functions that
    read them (a named tuple of more arrays costs every call that passes it: the loaded kernel's
    RK4 stages ran 10 % slower with them in it)."""

    kse: np.ndarray
    kbt: np.ndarray
    radius: float
    length: float
    offset: np.ndarray
    pitch: np.ndarray
    tension: np.ndarray
    angle: np.ndarray
    end: np.ndarray


@njit(cache=True, error_model="numpy")
def _rod(rods, b):
    """Design ``b`` of :class:`Rods` ``rods`` as a :class:`Rod` (views, no copies)."""
    return Rod(rods.kse[b], rods.kbt[b], rods.radius[b], rods.length[b], rods.offset[b], rods.pitch[b],
               rods.tension[b], rods.angle[b], rods.end[b])


class Grid(NamedTuple):
    """The base step grid: ``edges`` (K+1,) fractions of L, the outputs at edges ``out_step`` (n,)
    and the output fractions ``fractions`` (n,)."""

    edges: np.ndarray
    out_step: np.ndarray
    fractions: np.ndarray


class Tolerances(NamedTuple):
    """Newton's ``newton_tol`` and ``max_newton``, the step control's ``step_tol`` and
    ``max_level``, the shooting's ``shooting_tol`` and ``max_shooting`` (``SolverOptions``)."""

    newton_tol: float
    max_newton: int
    step_tol: float
    max_level: int
    shooting_tol: float
    max_shooting: int
    shortcut: bool  #: termination "rucker_webster": only the ending tendon's pull at each end (see _jump)
    linearized: bool  #: the first-order strains at every node instead of Newton (the operators' reference robot)
    #: tendon-only: level 0's Newton starts from ``Shapes.nodes`` (the last solve's strains) instead of the chain;
    #: loaded: the shooting starts from ``Shapes.m0`` where finite (a nearby solve's M(0); LOADED_WARM_PASSES)
    warm: bool
    displacement_tol: float  #: displacement actuation: Newton on the tensions stops within this, m (find_tensions)


class Loads(NamedTuple):
    """External loads, base frame, (B, 3) each: weight per length ``f_g`` N/m, ``f_tip`` N, ``m_tip`` N m."""

    f_g: np.ndarray
    f_tip: np.ndarray
    m_tip: np.ndarray


class Load(NamedTuple):
    """One design's external loads of :class:`Loads` (:func:`_load`), base frame, (3,) each."""

    f_g: np.ndarray
    f_tip: np.ndarray
    m_tip: np.ndarray


@njit(cache=True, error_model="numpy")
def _load(loads, b):
    """Design ``b``'s :class:`Load` of :class:`Loads` ``loads`` (views)."""
    return Load(loads.f_g[b], loads.f_tip[b], loads.m_tip[b])


class Shapes(NamedTuple):
    """The outputs, written in place: ``backbone`` (B, n, 3), ``rotation`` (B, n, 3, 3), ``strains``
    (B, n, 6), ``tendons`` (B, n, N_t, 3); per design ``status``, ``residual`` N, ``iterations``
    (Newton iterations, or shooting passes), ``level`` (halvings) and ``estimate``; loaded only,
    ``m0`` (B, 3) M(0) (in: the warm starts of ``Tolerances.warm``; out: this solve's) and
    ``shoot_jac`` (B, 3, 3) dM(L)/dM(0) (empty otherwise); ``displacement`` (B, N_t) m: each
    tendon's undeformed minus deformed path length (:func:`_path_lengths`); ``jacobian`` (B, n, 6,
    N_t) the pose's sensitivity to the tensions, base frame (rows 0-2 dp/dtau m/N, 3-5 the rotation
    vector of dR R^T / dtau rad/N; :func:`_pose_tangent`), or (0, ...) when not wanted; ``nodes``
    (B, 2 K0 + 1, 6) level 0's node strains (in: the warm starts of ``Tolerances.warm``; out: this
    solve's), or (0, 0, 6) when not kept; ``profile`` (B, n, N_t) N every tendon's tension at the
    outputs (eq. CAP; 0 beyond its end)."""

    backbone: np.ndarray
    rotation: np.ndarray
    strains: np.ndarray
    tendons: np.ndarray
    status: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    level: np.ndarray
    estimate: np.ndarray
    m0: np.ndarray
    shoot_jac: np.ndarray
    displacement: np.ndarray
    jacobian: np.ndarray
    nodes: np.ndarray
    profile: np.ndarray


class Level0(NamedTuple):
    """Level 0 of one design's tendon-only solve (:func:`level0_arrays`): the nodes ``sig`` (M,) of
    the base grid with the tendons' ends (:func:`_with_ends`, edges and midpoints in order of s),
    their acting tendons ``act`` (:func:`_node_activity`), and a chain's results there, written by
    it: node strains ``xs`` (M, 6), each tendon's |g_i| ``stretch`` (M, N_t), the friction gains
    ``gains`` (M or 0, N_t) and ``chain`` (3,): converged (1 or 0), Newton iterations, residual N.
    :func:`find_tensions` shoots into it and :func:`finish_design` goes on from it."""

    sig: np.ndarray
    act: np.ndarray
    xs: np.ndarray
    stretch: np.ndarray
    gains: np.ndarray
    chain: np.ndarray


@njit(cache=True, error_model="numpy", inline="always")
def _tendon(nu0, nu1, nu2, k0, k1, k2, ox, oy, dx, dy):
    """g_i = nu + kappa x rho_i + rho_i' with rho_i = (ox, oy, 0), rho_i' = (dx, dy, 0)."""
    return nu0 - k2 * oy + dx, nu1 + k2 * ox + dy, nu2 + k0 * oy - k1 * ox


@njit(cache=True, error_model="numpy", inline="always")
def _tendon_angle(angle, pitch, s):
    """Body-frame angle of a tendon at arclength ``s`` m: angle_i + pitch_i s (rad)."""
    return angle + pitch * s


@njit(cache=True, error_model="numpy", inline="always")
def _active_tensions(tau, end, act, out):
    """The tensions ``out`` (N_t,) acting at a node whose step lies around the fraction ``act``:
    tau_i where tendon i continues past it (end_i > act), else 0 (it has terminated)."""
    for i in range(tau.shape[0]):
        out[i] = tau[i] if end[i] > act else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _node_tensions(tau, end, act, gains, k, out):
    """:func:`_active_tensions` at node ``k`` with friction: tau_i exp(capstan_i theta_i) (eq. CAP),
    the factors ``gains`` (M, N_t) kept per node; without rows (no friction) the tensions as given."""
    if gains.shape[0] == 0:
        _active_tensions(tau, end, act, out)
        return
    for i in range(tau.shape[0]):
        out[i] = tau[i] * gains[k, i] if end[i] > act else 0.0


@njit(cache=True, error_model="numpy")
def has_friction(capstan):
    """Some tendon of ``capstan`` (N_t,) has friction (eq. CAP)."""
    for c in capstan:
        if c != 0.0:
            return True
    return False


@njit(cache=True, error_model="numpy", inline="always")
def _relative_rotation(kappa_prev, kappa, h, twist, out, step_p):
    """``out`` (3, 3) = exp(hat(w)), w = h (kappa_prev + kappa) / 2: the rotation between the frames
    of two nodes h m apart (second order in h, exact for constant curvature), by the Magnus step's
    exponential (:func:`_se3_exp` of the twist (0, w); ``twist`` (6,) and ``step_p`` (3,) workspace)."""
    for a in range(3):
        twist[a] = 0.0
        twist[3 + a] = 0.5 * h * (kappa_prev[a] + kappa[a])
    _se3_exp(twist, out, step_p)


@njit(cache=True, error_model="numpy", inline="always")
def _wrap_angle(t_prev, t, turn):
    """The angle (rad) the tangent of a tendon's path turns between two nodes: the angle between the
    body-frame unit tangents ``t_prev`` and ``turn`` ``t`` (3,), ``turn`` (3, 3) the frames'
    relative rotation (:func:`_relative_rotation`).  Summed along s it is theta_i = int |d t_i / ds|
    ds (a tendon's kink at an end: the jump of its tangent), the wrap angle of eq. (CAP)."""
    u0 = turn[0, 0] * t[0] + turn[0, 1] * t[1] + turn[0, 2] * t[2]
    u1 = turn[1, 0] * t[0] + turn[1, 1] * t[1] + turn[1, 2] * t[2]
    u2 = turn[2, 0] * t[0] + turn[2, 1] * t[1] + turn[2, 2] * t[2]
    x0, x1, x2 = t_prev[1] * u2 - t_prev[2] * u1, t_prev[2] * u0 - t_prev[0] * u2, t_prev[0] * u1 - t_prev[1] * u0
    return math.atan2(math.sqrt(x0 * x0 + x1 * x1 + x2 * x2), t_prev[0] * u0 + t_prev[1] * u1 + t_prev[2] * u2)


@njit(cache=True, error_model="numpy", inline="always")
def _capstan_gain(capstan, theta):
    """exp(capstan theta): a tendon's tension over its tension at the drive where its path has turned
    by the wrap angle ``theta`` rad (eq. CAP; ``capstan`` -mu pulling, +mu releasing)."""
    return math.exp(capstan * theta)


@njit(cache=True, error_model="numpy", inline="always")
def _predict_wraps(theta, rate, h, wraps):
    """The wrap angles ``h`` m on, ``wraps`` (N_t,) = theta + rate h, from the last ones ``theta``
    (N_t,) and their ``rate`` (N_t,) rad/m (exact for constant curvature)."""
    for i in range(theta.shape[0]):
        wraps[i] = theta[i] + rate[i] * h


@njit(cache=True, error_model="numpy", inline="always")
def _correct_wraps(theta, t_prev, t, turn, capstan, tau, wraps):
    """The wrap angles corrected by the solved geometry: ``wraps`` (N_t,) = theta (the last node's)
    plus the angle each tendon's unit tangent turned from ``t_prev`` to ``t`` (N_t, 3)
    (:func:`_wrap_angle`, ``turn`` the frames' relative rotation).  Returns how far that moves the
    gains, max |capstan_i (new - old)| over the tendons that pull (``tau`` (N_t,) not 0: a slack or
    ended tendon's tension does not move)."""
    move = 0.0
    for i in range(theta.shape[0]):
        new = theta[i] + _wrap_angle(t_prev[i], t[i], turn)
        if tau[i] != 0.0:
            move = max(move, abs(capstan[i] * (new - wraps[i])))
        wraps[i] = new
    return move


@njit(cache=True, error_model="numpy", inline="always")
def _accept_wraps(theta, rate, h, wraps):
    """Move on to the corrected wrap angles ``wraps`` (N_t,): ``rate`` = (wraps - theta) / h (rad/m)
    for the next prediction (a kink at an end, h = 0, is no rate), then ``theta`` = wraps."""
    for i in range(theta.shape[0]):
        if h > 0.0:
            rate[i] = (wraps[i] - theta[i]) / h
        theta[i] = wraps[i]


@njit(cache=True, error_model="numpy", inline="always")
def _unit_tangents(x, rho, drho, out):
    """Every tendon's body-frame unit tangent t_i = g_i / |g_i| (:func:`_tendon`) at strains ``x``, (N_t, 3)."""
    for i in range(rho.shape[0]):
        g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])
        inv = 1.0 / math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        out[i, 0], out[i, 1], out[i, 2] = g0 * inv, g1 * inv, g2 * inv


@njit(cache=True, error_model="numpy")
def _with_ends(edges0, out_step0, end):
    """The design's step grid: the base ``edges0`` (K+1,) with every tendon end below the tip
    (``end`` (N_t,) fractions) inserted twice, as a step of zero width: its left edge carries the
    strains just before the end, its right edge those just after (an end within 1e-9 of an edge
    falls on that edge).  Returns ``(edges, out_step, end_step)``: the outputs' edges (an output at
    an end: the left edge) and each tendon's end edge (the left one; -1 for the tip)."""
    n_t = end.shape[0]
    snapped = end.copy()  # each end, on the edge it falls on (1e-9)
    for i in range(n_t):
        for k in range(edges0.shape[0]):
            if abs(edges0[k] - end[i]) <= 1e-9:
                snapped[i] = edges0[k]
    cuts = np.empty(n_t)
    n_cut = 0
    for i in range(n_t):
        e = snapped[i]
        if end[i] >= 1.0 - 1e-12:
            continue
        dup = False
        for c in range(n_cut):
            dup = dup or cuts[c] == e
        if not dup:
            cuts[n_cut] = e
            n_cut += 1
    cuts = np.sort(cuts[:n_cut])
    edges = np.empty(edges0.shape[0] + 2 * n_cut)
    n, c = 0, 0
    for k in range(edges0.shape[0]):
        while c < n_cut and cuts[c] < edges0[k]:
            edges[n], edges[n + 1] = cuts[c], cuts[c]
            n += 2
            c += 1
        if c < n_cut and cuts[c] == edges0[k]:
            edges[n] = edges0[k]  # the end falls on an edge: that edge twice
            n += 1
            c += 1
        edges[n] = edges0[k]
        n += 1
    edges = edges[:n]
    out_step = np.empty(out_step0.shape[0], dtype=np.int64)
    for j in range(out_step0.shape[0]):
        out_step[j] = np.searchsorted(edges, edges0[out_step0[j]])  # the first (left) of equal edges
    end_step = np.full(n_t, -1, dtype=np.int64)
    for i in range(n_t):
        if end[i] < 1.0 - 1e-12:
            end_step[i] = np.searchsorted(edges, snapped[i])
    return edges, out_step, end_step


@njit(cache=True, error_model="numpy")
def _node_activity(sig):
    """For the interleaved nodes ``sig`` (2K+1,) (edge 0, mid 0, edge 1, ...), the fraction whose
    tendons act at each node (:func:`_active_tensions`): a midpoint of a step of non-zero width --
    an edge takes its left step's (the strains just before an end), or its right step's after a
    zero-width step (just after the end); a node inside a zero-width step its own fraction."""
    k_steps = (sig.shape[0] - 1) // 2
    act = np.empty(sig.shape[0])
    for k in range(k_steps):
        act[2 * k + 1] = sig[2 * k + 1]
    for k in range(k_steps + 1):
        if k > 0 and sig[2 * k] > sig[2 * k - 2]:
            act[2 * k] = sig[2 * k - 1]
        elif k < k_steps and sig[2 * k + 2] > sig[2 * k]:
            act[2 * k] = sig[2 * k + 1]
        else:
            act[2 * k] = sig[2 * k]
    return act


@njit(cache=True, error_model="numpy")
def _potential(x, rho, drho, tau, kse, kbt, target):
    """Phi of eq. (PHI) minus target . x at strains ``x`` (6,) (target: body-frame (R^T N, R^T M))."""
    phi = 0.5 * (kse[0] * x[0] ** 2 + kse[1] * x[1] ** 2 + kse[2] * (x[2] - 1.0) ** 2)
    phi += 0.5 * (kbt[0] * x[3] ** 2 + kbt[1] * x[4] ** 2 + kbt[2] * x[5] ** 2)
    for i in range(tau.shape[0]):
        if tau[i] == 0.0:  # a slack or ended tendon adds nothing
            continue
        g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])
        phi += tau[i] * math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    for a in range(6):
        phi -= target[a] * x[a]
    return phi


@njit(cache=True, error_model="numpy")
def _residual_jacobian(x, rho, drho, tau, kse, kbt, res, jac, want_jac, av, target):
    """Residual of (W1, W2) into ``res`` (6,) and (if ``want_jac``) its Jacobian, the Hessian of
    Phi, into ``jac`` (6, 6): J = diag(K_se, K_bt) + sum_i w_i (A_i^T A_i - a_i a_i^T), w_i = tau_i /
    |g_i|, a_i = (t_i, rho_i x t_i), A_i = [I, -hat(rho_i)].  The sums run in local scalars (kept in
    registers: five times faster than accumulating into the arrays); ``av`` is unused workspace."""
    x0, x1, x2, x3, x4, x5 = x[0], x[1], x[2], x[3], x[4], x[5]
    r0, r1, r2 = kse[0] * x0 - target[0], kse[1] * x1 - target[1], kse[2] * (x2 - 1.0) - target[2]
    r3, r4, r5 = kbt[0] * x3 - target[3], kbt[1] * x4 - target[4], kbt[2] * x5 - target[5]
    j00, j11, j22, j33, j44, j55 = kse[0], kse[1], kse[2], kbt[0], kbt[1], kbt[2]
    j01 = j02 = j03 = j04 = j05 = j12 = j13 = j14 = j15 = j23 = j24 = j25 = j34 = j35 = j45 = 0.0
    for i in range(tau.shape[0]):
        ti = tau[i]
        if ti == 0.0:  # a slack or ended tendon adds nothing to (W1, W2) or its Jacobian
            continue
        ox, oy = rho[i, 0], rho[i, 1]
        g0, g1, g2 = _tendon(x0, x1, x2, x3, x4, x5, ox, oy, drho[i, 0], drho[i, 1])
        inv = 1.0 / math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)  # 1 / |g_i|
        t0, t1, t2 = g0 * inv, g1 * inv, g2 * inv
        c0, c1, c2 = oy * t2, -ox * t2, ox * t1 - oy * t0  # rho_i x t_i
        r0 += ti * t0
        r1 += ti * t1
        r2 += ti * t2
        r3 += ti * c0
        r4 += ti * c1
        r5 += ti * c2
        if want_jac:
            # w (A^T A - a a^T), A^T A = [[I, -hat(rho)], [hat(rho), |rho|^2 I - rho rho^T]], rho = (ox, oy, 0)
            w = ti * inv
            j00 += w * (1.0 - t0 * t0)
            j01 -= w * t0 * t1
            j02 -= w * t0 * t2
            j03 -= w * t0 * c0
            j04 -= w * t0 * c1
            j05 -= w * (oy + t0 * c2)
            j11 += w * (1.0 - t1 * t1)
            j12 -= w * t1 * t2
            j13 -= w * t1 * c0
            j14 -= w * t1 * c1
            j15 += w * (ox - t1 * c2)
            j22 += w * (1.0 - t2 * t2)
            j23 += w * (oy - t2 * c0)
            j24 -= w * (ox + t2 * c1)
            j25 -= w * t2 * c2
            j33 += w * (oy * oy - c0 * c0)
            j34 -= w * (ox * oy + c0 * c1)
            j35 -= w * c0 * c2
            j44 += w * (ox * ox - c1 * c1)
            j45 -= w * c1 * c2
            j55 += w * (ox * ox + oy * oy - c2 * c2)
    res[0], res[1], res[2], res[3], res[4], res[5] = r0, r1, r2, r3, r4, r5
    if want_jac:
        jac[0, 0], jac[1, 1], jac[2, 2], jac[3, 3], jac[4, 4], jac[5, 5] = j00, j11, j22, j33, j44, j55
        jac[0, 1] = jac[1, 0] = j01
        jac[0, 2] = jac[2, 0] = j02
        jac[0, 3] = jac[3, 0] = j03
        jac[0, 4] = jac[4, 0] = j04
        jac[0, 5] = jac[5, 0] = j05
        jac[1, 2] = jac[2, 1] = j12
        jac[1, 3] = jac[3, 1] = j13
        jac[1, 4] = jac[4, 1] = j14
        jac[1, 5] = jac[5, 1] = j15
        jac[2, 3] = jac[3, 2] = j23
        jac[2, 4] = jac[4, 2] = j24
        jac[2, 5] = jac[5, 2] = j25
        jac[3, 4] = jac[4, 3] = j34
        jac[3, 5] = jac[5, 3] = j35
        jac[4, 5] = jac[5, 4] = j45


@njit(cache=True, error_model="numpy", inline="always")
def _factor_spd(jac, d, low):
    """Cholesky factor ``low`` (6, 6) of D jac D with the Jacobi scaling ``d`` (6,), D = diag(d);
    the diagonal of ``low`` holds the factor's reciprocal diagonal (the solves multiply).  False
    if ``jac`` is not positive definite or not finite."""
    n = 6
    for a in range(n):
        if not (jac[a, a] > 0.0) or not math.isfinite(jac[a, a]):
            return False
        d[a] = 1.0 / math.sqrt(jac[a, a])
    for a in range(n):
        for b in range(a + 1):
            s = jac[a, b] * d[a] * d[b]
            for k in range(b):
                s -= low[a, k] * low[b, k]
            if a == b:
                if not (s > 0.0):
                    return False
                low[a, a] = 1.0 / math.sqrt(s)
            else:
                low[a, b] = s * low[b, b]
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _solve_factored(d, low, rhs, out, y):
    """``out`` = jac^-1 rhs from :func:`_factor_spd`'s factor; False if not finite."""
    n = 6
    for a in range(n):
        s = rhs[a] * d[a]
        for k in range(a):
            s -= low[a, k] * y[k]
        y[a] = s * low[a, a]
    for a in range(n - 1, -1, -1):
        s = y[a]
        for k in range(a + 1, n):
            s -= low[k, a] * y[k]
        y[a] = s * low[a, a]
    for a in range(n):
        out[a] = y[a] * d[a]
        if not math.isfinite(out[a]):
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _solve_spd(jac, rhs, out, d, low, y):
    """``out`` = jac^-1 rhs for SPD ``jac`` (6, 6) by Cholesky after Jacobi scaling; False if not
    positive definite or not finite.  ``d`` (6,), ``low`` (6, 6), ``y`` (6,) are workspace."""
    return _factor_spd(jac, d, low) and _solve_factored(d, low, rhs, out, y)


@njit(cache=True, error_model="numpy", inline="always")
def _newton(x, rho, drho, tau, kse, kbt, radius, length, tol, max_iter, work, jac, low, target, final_factor):
    """Damped Newton on (W1, W2) (right-hand side ``target`` (6,)) at one node, in place on ``x``
    (6,).  Returns ``(converged, iterations, residual)``, residual = sqrt(|F|^2 + |M / L|^2) of the
    result, N.  ``work`` (6, 6) and ``jac``, ``low`` (6, 6) are workspace; with ``final_factor``
    the Jacobian at the result is left factored in ``low`` and ``work[4]`` (:func:`_factor_spd`)."""
    res, step, trial, av, d, y = work[0], work[1], work[2], work[3], work[4], work[5]
    sqrt_tol = math.sqrt(tol)
    converged = False
    it = 0
    while it < max_iter:
        _residual_jacobian(x, rho, drho, tau, kse, kbt, res, jac, True, av, target)
        if not _solve_spd(jac, res, step, d, low, y):
            break
        it += 1
        for a in range(6):
            step[a] = -step[a]
        size = math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
        size += radius * math.sqrt(step[3] ** 2 + step[4] ** 2 + step[5] ** 2)
        alpha = 1.0
        if size > 1e-3:  # Armijo on Phi, only far from the root (small steps are in the quadratic basin)
            phi0 = _potential(x, rho, drho, tau, kse, kbt, target)
            slope = 0.0
            for a in range(6):
                slope += res[a] * step[a]
            slack = 1e-13 * (abs(phi0) + 1.0)
            for _ in range(40):
                for a in range(6):
                    trial[a] = x[a] + alpha * step[a]
                if _potential(trial, rho, drho, tau, kse, kbt, target) <= phi0 + 1e-4 * alpha * slope + slack:
                    break
                alpha *= 0.5
        for a in range(6):
            x[a] += alpha * step[a]
        if not math.isfinite(size):
            break
        if alpha == 1.0 and size < sqrt_tol:
            converged = True
            break
    _residual_jacobian(x, rho, drho, tau, kse, kbt, res, jac, final_factor, av, target)
    if final_factor and not _factor_spd(jac, d, low):
        converged = False
    residual = math.sqrt(res[0] ** 2 + res[1] ** 2 + res[2] ** 2
                         + (res[3] ** 2 + res[4] ** 2 + res[5] ** 2) / (length * length))
    return converged, it, residual


@njit(cache=True, error_model="numpy")
def _routing(fraction, length, offset, pitch, angle, rho, drho):
    """rho_i(s) and rho_i'(s) (x, y components; z is 0) at s = fraction L, each (N_t, 2)."""
    n_t = offset.shape[0]
    for i in range(n_t):
        phi = _tendon_angle(angle[i], pitch[i], fraction * length)
        c, s = math.cos(phi), math.sin(phi)
        rho[i, 0], rho[i, 1] = offset[i] * c, offset[i] * s
        drho[i, 0], drho[i, 1] = -offset[i] * pitch[i] * s, offset[i] * pitch[i] * c


@njit(cache=True, error_model="numpy", inline="always")
def _first_order(x, rho, drho, tau, kse, kbt, length, work):
    """The first-order strains at one node, in place on ``x`` (6,): the root of (W1, W2) with the
    tendon tangents of the undeformed rod, x = x0 - K^-1 res(x0) with x0 = (e3, 0) and K =
    diag(K_se, K_bt) ((W1, W2) are K (x - x0) plus the tendon terms, frozen at x0).  Exact to first
    order in the tensions (the neural operators' reference robot).  Returns the residual of (W1,
    W2) at the result, sqrt(|F|^2 + |M / L|^2) N.  ``work`` (6, 6) is workspace."""
    res, av = work[0], work[3]
    for a in range(6):
        x[a] = 0.0
    x[2] = 1.0
    _residual_jacobian(x, rho, drho, tau, kse, kbt, res, work, False, av, _NO_TARGET)
    for a in range(3):
        x[a] -= res[a] / kse[a]
        x[3 + a] -= res[3 + a] / kbt[a]
    _residual_jacobian(x, rho, drho, tau, kse, kbt, res, work, False, av, _NO_TARGET)
    return math.sqrt(res[0] ** 2 + res[1] ** 2 + res[2] ** 2
                     + (res[3] ** 2 + res[4] ** 2 + res[5] ** 2) / (length * length))


@njit(cache=True, error_model="numpy", inline="always")
def _node_strains(x, rho, drho, tau_node, rod, tols, work, jac, low):
    """The strains at one node, in place on ``x`` (6,) (the start): Newton on (W1, W2) or, with
    ``tols.linearized``, :func:`_first_order`.  Returns ``(converged, iterations, residual N)``."""
    if tols.linearized:
        return True, 0, _first_order(x, rho, drho, tau_node, rod.kse, rod.kbt, rod.length, work)
    return _newton(x, rho, drho, tau_node, rod.kse, rod.kbt, rod.radius, rod.length, tols.newton_tol,
                   tols.max_newton, work, jac, low, _NO_TARGET, False)


@njit(cache=True, error_model="numpy")
def _solve_nodes(node_fractions, act, x_nodes, rod, tols, order, stretch, gains):
    """The strains at the nodes ``node_fractions[order]`` of :class:`Rod` ``rod`` (their tendons those
    acting at ``act``, see :func:`_node_activity`, with friction the tensions times ``gains`` (M,
    N_t), :func:`_node_tensions`), each from the start in ``x_nodes`` (M, 6), and (where
    ``stretch`` (M, N_t) has rows) every tendon's |g_i| there (:func:`_node_stretch`).
    Returns (all converged, max iterations, max residual)."""
    n_t = rod.offset.shape[0]
    rho = np.empty((n_t, 2))
    drho = np.empty((n_t, 2))
    tau_node = np.empty(n_t)
    work, jac, low = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    ok = True
    iters = 0
    worst = 0.0
    for j in range(order.shape[0]):
        k = order[j]
        _routing(node_fractions[k], rod.length, rod.offset, rod.pitch, rod.angle, rho, drho)
        _node_tensions(rod.tension, rod.end, act[k], gains, k, tau_node)
        conv, it, r = _node_strains(x_nodes[k], rho, drho, tau_node, rod, tols, work, jac, low)
        _node_stretch(x_nodes[k], rho, drho, stretch, k)
        ok = ok and conv
        iters = max(iters, it)
        if not (r <= worst):  # NaN-propagating max
            worst = r
    return ok, iters, worst


@njit(cache=True, error_model="numpy")
def _exp_coefficients(theta):
    if theta < 1e-2:
        t2 = theta * theta
        return (1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0,
                1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0)
    s, c = math.sin(theta), math.cos(theta)
    return s / theta, (1.0 - c) / (theta * theta), (theta - s) / (theta * theta * theta)


@njit(cache=True, error_model="numpy", inline="always")
def _magnus_omega(h, a0, a1, m, omega):
    """eq. (MAG)'s Omega (6,) = h/6 (xi_0 + 4 xi_m + xi_1) + h^2/12 [xi_0, xi_1] of one step of length
    ``h`` m from the twists ``a0``, ``m``, ``a1`` (6,) at its start, middle and end, with the bracket
    [xi_0, xi_1] = (w0 x v1 - w1 x v0, w0 x w1)."""
    cv0 = a0[4] * a1[2] - a0[5] * a1[1] - (a1[4] * a0[2] - a1[5] * a0[1])
    cv1 = a0[5] * a1[0] - a0[3] * a1[2] - (a1[5] * a0[0] - a1[3] * a0[2])
    cv2 = a0[3] * a1[1] - a0[4] * a1[0] - (a1[3] * a0[1] - a1[4] * a0[0])
    cw0 = a0[4] * a1[5] - a0[5] * a1[4]
    cw1 = a0[5] * a1[3] - a0[3] * a1[5]
    cw2 = a0[3] * a1[4] - a0[4] * a1[3]
    h12 = h * h / 12.0
    omega[0] = h * (a0[0] + 4.0 * m[0] + a1[0]) / 6.0 + h12 * cv0
    omega[1] = h * (a0[1] + 4.0 * m[1] + a1[1]) / 6.0 + h12 * cv1
    omega[2] = h * (a0[2] + 4.0 * m[2] + a1[2]) / 6.0 + h12 * cv2
    omega[3] = h * (a0[3] + 4.0 * m[3] + a1[3]) / 6.0 + h12 * cw0
    omega[4] = h * (a0[4] + 4.0 * m[4] + a1[4]) / 6.0 + h12 * cw1
    omega[5] = h * (a0[5] + 4.0 * m[5] + a1[5]) / 6.0 + h12 * cw2


@njit(cache=True, error_model="numpy", inline="always")
def _se3_exp(omega, ex, step_p):
    """exp of the twist ``omega`` = (v, w) (6,) on SE(3): rotation ``ex`` (3, 3) = I + A W + B W^2 and
    translation ``step_p`` (3,) = (I + B W + C W^2) v with W = hat(w), A = sin t / t, B = (1 - cos t)
    / t^2, C = (t - sin t) / t^3, t = |w| (:func:`_exp_coefficients`)."""
    v0, v1, v2, w0, w1, w2 = omega[0], omega[1], omega[2], omega[3], omega[4], omega[5]
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    ca, cb, cc = _exp_coefficients(theta)
    ww00, ww11, ww22 = -(w1 * w1 + w2 * w2), -(w0 * w0 + w2 * w2), -(w0 * w0 + w1 * w1)
    ww01, ww02, ww12 = w0 * w1, w0 * w2, w1 * w2
    ex[0, 0] = 1.0 + cb * ww00
    ex[1, 1] = 1.0 + cb * ww11
    ex[2, 2] = 1.0 + cb * ww22
    ex[0, 1] = -ca * w2 + cb * ww01
    ex[1, 0] = ca * w2 + cb * ww01
    ex[0, 2] = ca * w1 + cb * ww02
    ex[2, 0] = -ca * w1 + cb * ww02
    ex[1, 2] = -ca * w0 + cb * ww12
    ex[2, 1] = ca * w0 + cb * ww12
    step_p[0] = (1.0 + cc * ww00) * v0 + (-cb * w2 + cc * ww01) * v1 + (cb * w1 + cc * ww02) * v2
    step_p[1] = (cb * w2 + cc * ww01) * v0 + (1.0 + cc * ww11) * v1 + (-cb * w0 + cc * ww12) * v2
    step_p[2] = (-cb * w1 + cc * ww02) * v0 + (cb * w0 + cc * ww12) * v1 + (1.0 + cc * ww22) * v2


@njit(cache=True, error_model="numpy")
def _magnus(edges, x_edge, x_mid, length, out_step, pos_out, rot_out):
    """eq. (MAG) along the steps: Omega = h/6 (xi_0 + 4 xi_m + xi_1) + h^2/12 [xi_0, xi_1],
    g_{k+1} = g_k exp(Omega); poses at the edges ``out_step`` into pos_out (n, 3), rot_out (n, 3, 3)."""
    k_steps = edges.shape[0] - 1
    rot = np.eye(3)
    pos = np.zeros(3)
    new_rot = np.empty((3, 3))
    ex = np.empty((3, 3))
    order = np.argsort(out_step)  # outputs in order of their edge (-1: not wanted)
    n_out = out_step.shape[0]
    q = 0
    while q < n_out and out_step[order[q]] < 0:
        q += 1
    while q < n_out and out_step[order[q]] == 0:  # outputs at s = 0 (edge 0)
        pos_out[order[q], :] = 0.0
        rot_out[order[q]] = np.eye(3)
        q += 1
    omega, step_p = np.empty(6), np.empty(3)
    for k in range(k_steps):
        _magnus_omega((edges[k + 1] - edges[k]) * length, x_edge[k], x_edge[k + 1], x_mid[k], omega)
        _se3_exp(omega, ex, step_p)
        p0, p1, p2 = step_p[0], step_p[1], step_p[2]
        for a in range(3):
            pos[a] += rot[a, 0] * p0 + rot[a, 1] * p1 + rot[a, 2] * p2
        for a in range(3):
            for b in range(3):
                new_rot[a, b] = rot[a, 0] * ex[0, b] + rot[a, 1] * ex[1, b] + rot[a, 2] * ex[2, b]
        rot[:, :] = new_rot
        while q < n_out and out_step[order[q]] == k + 1:
            pos_out[order[q], :] = pos
            rot_out[order[q], :, :] = rot
            q += 1


@njit(cache=True, error_model="numpy")
def _output_offsets(fractions_out, length, offset, pitch, angle):
    """rho_i at the outputs (x, y; z is 0), m, (n, N_t, 2) (angles by :func:`_advance_angles`:
    equispaced outputs cost one rotation each)."""
    n_t = offset.shape[0]
    out = np.empty((fractions_out.shape[0], n_t, 2))
    cos_phi, sin_phi, cos_d, sin_d = np.empty(n_t), np.empty(n_t), np.empty(n_t), np.empty(n_t)
    last_delta = np.inf  # none yet
    for j in range(fractions_out.shape[0]):
        last_delta = _advance_angles(j, fractions_out[j], fractions_out[j - 1] if j else 0.0, length, angle, pitch,
                                     cos_phi, sin_phi, cos_d, sin_d, last_delta)
        for i in range(n_t):
            out[j, i, 0], out[j, i, 1] = offset[i] * cos_phi[i], offset[i] * sin_phi[i]
    return out


@njit(cache=True, error_model="numpy")
def _tendon_positions(pos, rot, rho_out, out):
    """p + R rho_i at the outputs, (n, N_t, 3), from rho_out (n, N_t, 2)."""
    for j in range(rho_out.shape[0]):
        for i in range(rho_out.shape[1]):
            rx, ry = rho_out[j, i, 0], rho_out[j, i, 1]
            for a in range(3):
                out[j, i, a] = pos[j, a] + rot[j, a, 0] * rx + rot[j, a, 1] * ry


@njit(cache=True, error_model="numpy")
def _coarse_estimate(edges, xs, length, out_step, rho_out, fine):
    """Richardson estimate of the error of the solution ``fine`` (n, N_t, 3) on ``edges`` (K+1,)
    with nodes ``xs`` (2K+1, 6), at no new Newton solve: the coarse solution joins each two
    consecutive steps of equal width into one (its midpoint node is their shared edge) and keeps a
    step without an equal neighbour as it is (a shared step adds nothing to the difference).
    Compared at the outputs on coarse edges: ||T_fine - T_coarse|| / (15 ||T_fine||)."""
    k_steps = edges.shape[0] - 1
    c_edges = np.empty(k_steps + 1)
    c_xe = np.empty((k_steps + 1, 6))
    c_xm = np.empty((k_steps, 6))
    to_coarse = np.full(k_steps + 1, -1, dtype=np.int64)
    c_edges[0], c_xe[0], to_coarse[0] = edges[0], xs[0], 0
    kc, k = 0, 0
    while k < k_steps:
        w0 = edges[k + 1] - edges[k]
        if k + 1 < k_steps and abs((edges[k + 2] - edges[k + 1]) - w0) <= 1e-12 * w0:
            c_xm[kc] = xs[2 * k + 2]  # the shared edge is the coarse midpoint
            k += 2
        else:
            c_xm[kc] = xs[2 * k + 1]
            k += 1
        kc += 1
        c_edges[kc], c_xe[kc], to_coarse[k] = edges[k], xs[2 * k], kc
    n_out, n_t = rho_out.shape[0], rho_out.shape[1]
    c_out = np.empty(n_out, dtype=np.int64)
    for j in range(n_out):
        c_out[j] = to_coarse[out_step[j]]
    pos = np.zeros((n_out, 3))
    rot = np.zeros((n_out, 3, 3))
    _magnus(c_edges[:kc + 1], c_xe[:kc + 1], c_xm[:kc], length, c_out, pos, rot)
    coarse = np.empty((n_out, n_t, 3))
    _tendon_positions(pos, rot, rho_out, coarse)
    diff, norm = 0.0, 0.0
    for j in range(n_out):
        if c_out[j] < 0:
            continue
        for i in range(n_t):
            for a in range(3):
                diff += (fine[j, i, a] - coarse[j, i, a]) ** 2
                norm += fine[j, i, a] ** 2
    if norm == 0.0:
        return math.sqrt(diff) / 15.0
    return math.sqrt(diff / norm) / 15.0


@njit(cache=True, error_model="numpy")
def _all_finite(residual, tendons):
    """The residual and every tendon coordinate (n, N_t, 3) are finite."""
    if not math.isfinite(residual):
        return False
    for v in tendons.ravel():
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _stretch(x, ox, oy, dx, dy):
    """|g_i| = |nu + kappa x rho_i + rho_i'|, the tendon's path length per unit arclength."""
    g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], ox, oy, dx, dy)
    return math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)


@njit(cache=True, error_model="numpy")
def least_stretch(length, offset, pitch, angle, end, fractions, strains):
    """Per design ``(B,)``: the least |g_i| (:func:`_stretch`) of the tendons acting (end_i >= s)
    at the output ``fractions`` ``(n,)`` for the strains ``(B, n, 6)``; NaN where one is not finite
    (0 / 0 in its direction).  Designs: ``length`` ``(B,)`` m, ``offset``, ``pitch``, ``angle``,
    ``end`` ``(B, N_t)`` (end as a fraction of L)."""
    n_designs, n_t = offset.shape
    out = np.full(n_designs, np.inf)
    rho, drho = np.empty((n_t, 2)), np.empty((n_t, 2))
    for b in range(n_designs):
        for k in range(fractions.shape[0]):
            _routing(fractions[k], length[b], offset[b], pitch[b], angle[b], rho, drho)
            for i in range(n_t):
                if end[b, i] >= fractions[k]:
                    g = _stretch(strains[b, k], rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])
                    if g != g:  # not finite: NaN, and it stays
                        out[b] = g
                    elif g < out[b]:
                        out[b] = g
    return out


@njit(cache=True, error_model="numpy")
def undeformed_length(length, offset, pitch, end):
    """A tendon's path length on the straight rod, m: int_0^end |e3 + rho'| ds = end L sqrt(1 + (o p)^2)
    (``end`` a fraction of L)."""
    return end * length * math.sqrt(1.0 + (offset * pitch) ** 2)


@njit(cache=True, error_model="numpy", inline="always")
def _advance_angles(j, fraction, previous, length, angle, pitch, cos_phi, sin_phi, cos_d, sin_d, last_delta):
    """cos and sin of every tendon's angle angle_i + pitch_i s at the ``j``-th node of a walk along s
    (at ``fraction``, the node before at ``previous``): by angle addition from the node before (a
    rotation per distinct spacing, ``cos_d``, ``sin_d``), recomputed exactly every ``_RESYNC``
    nodes.  Returns the spacing whose rotation ``cos_d``, ``sin_d`` now hold."""
    n_t = angle.shape[0]
    if j % _RESYNC == 0:
        for i in range(n_t):
            phi = _tendon_angle(angle[i], pitch[i], fraction * length)
            cos_phi[i], sin_phi[i] = math.cos(phi), math.sin(phi)
        return last_delta
    delta = fraction - previous
    if abs(delta - last_delta) > 1e-14 * abs(delta):
        for i in range(n_t):
            cos_d[i], sin_d[i] = math.cos(pitch[i] * delta * length), math.sin(pitch[i] * delta * length)
        last_delta = delta
    for i in range(n_t):
        c = cos_phi[i] * cos_d[i] - sin_phi[i] * sin_d[i]
        sin_phi[i] = sin_phi[i] * cos_d[i] + cos_phi[i] * sin_d[i]
        cos_phi[i] = c
    return last_delta


#: the walks along s recompute the tendon angles exactly every this many nodes (between: angle addition)
_RESYNC = 16


@njit(cache=True, error_model="numpy", inline="always")
def _node_stretch(x, rho, drho, stretch, k):
    """``stretch[k, i]`` = |g_i| (:func:`_stretch`) of every tendon at the strains ``x`` (6,) and the
    routing ``rho``, ``drho`` (N_t, 2) of node k; nothing where ``stretch`` has no rows."""
    if stretch.shape[0] == 0:
        return
    for i in range(rho.shape[0]):
        stretch[k, i] = _stretch(x, rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])


@njit(cache=True, error_model="numpy", inline="always")
def _simpson_weight(sig, node, length):
    """Simpson's weight (m) of the interleaved node ``node`` (edge, midpoint, edge, ...) of ``sig``
    (2K+1,) in int_0^L f ds: 4 h / 6 at a midpoint, h / 6 from each step an edge bounds."""
    k_steps = (sig.shape[0] - 1) // 2
    if node % 2 == 1:  # a midpoint
        return 4.0 * (sig[node + 1] - sig[node - 1]) * length / 6.0
    k = node // 2
    w = 0.0
    if k > 0:
        w += (sig[node] - sig[node - 2]) * length / 6.0
    if k < k_steps:
        w += (sig[node + 2] - sig[node]) * length / 6.0
    return w


@njit(cache=True, error_model="numpy")
def _path_lengths_of(sig, act, stretch, rod, lengths):
    """Each tendon's deformed path length ``lengths`` (N_t,) m, int_0^end |g_i| ds by Simpson's rule
    (:func:`_simpson_weight`) from the |g_i| the node solves kept, ``stretch`` (2K+1, N_t), over
    the nodes where the tendon acts (as :func:`_path_lengths`, without its walk of the angles)."""
    end = rod.end
    for i in range(end.shape[0]):
        lengths[i] = 0.0
    for node in range(sig.shape[0]):
        w = _simpson_weight(sig, node, rod.length)
        if w == 0.0:
            continue
        for i in range(end.shape[0]):
            if end[i] > act[node]:
                lengths[i] += w * stretch[node, i]


@njit(cache=True, error_model="numpy")
def _path_lengths(sig, act, xs, rod, sens, lengths, dlen):
    """Each tendon's deformed path length ``lengths`` (N_t,) m, int_0^end |g_i| ds by Simpson's rule
    on every step of non-zero width (its edge, midpoint and edge nodes ``xs`` of the interleaved
    layout ``sig``, 4th order like the Magnus steps), over the steps where the tendon acts: one
    pass over the nodes, each weighted by the steps it belongs to (an edge beside an end belongs to
    one step only, and acts as that step, :func:`_node_activity`).  With ``sens`` (2K+1, 6, N_t)
    the strains' sensitivities dx/dtau_k, also ``dlen`` (N_t, N_t) = d length_i / d tau_k =
    int t_i . (dnu_k + dkappa_k x rho_i) ds = int a_i . dx_k ds."""
    length, offset, pitch, angle, end = rod.length, rod.offset, rod.pitch, rod.angle, rod.end
    n_t = offset.shape[0]
    rho, drho = np.empty((n_t, 2)), np.empty((n_t, 2))
    cos_phi, sin_phi, cos_d, sin_d = np.empty(n_t), np.empty(n_t), np.empty(n_t), np.empty(n_t)
    last_delta = np.inf  # none yet
    want = sens.shape[0] > 0
    for i in range(n_t):
        lengths[i] = 0.0
        if want:
            for k in range(n_t):
                dlen[i, k] = 0.0
    for node in range(sig.shape[0]):
        last_delta = _advance_angles(node, sig[node], sig[node - 1] if node else 0.0, length, angle, pitch, cos_phi,
                                     sin_phi, cos_d, sin_d, last_delta)
        w = _simpson_weight(sig, node, length)
        if w == 0.0:
            continue
        for i in range(n_t):
            rho[i, 0], rho[i, 1] = offset[i] * cos_phi[i], offset[i] * sin_phi[i]
            drho[i, 0], drho[i, 1] = -offset[i] * pitch[i] * sin_phi[i], offset[i] * pitch[i] * cos_phi[i]
        x = xs[node]
        for i in range(n_t):
            if not end[i] > act[node]:
                continue
            g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])
            gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
            lengths[i] += w * gn
            if want:
                t0, t1, t2 = g0 / gn, g1 / gn, g2 / gn
                ox, oy = rho[i, 0], rho[i, 1]
                c0, c1, c2 = oy * t2, -ox * t2, ox * t1 - oy * t0  # rho_i x t_i
                for q in range(n_t):
                    dx = sens[node, :, q]
                    dlen[i, q] += w * (t0 * dx[0] + t1 * dx[1] + t2 * dx[2] + c0 * dx[3] + c1 * dx[4] + c2 * dx[5])


@njit(cache=True, error_model="numpy")
def _sensitivities(sig, act, xs, rod, sens, gains):
    """dx/dtau_k at every node, ``sens`` (2K+1, 6, N_t), by the implicit-function theorem on (W1, W2):
    J dx_k = -a_k with J the Hessian of Phi and a_k = (t_k, rho_k x t_k) for a tendon acting at the
    node (0 otherwise).  With friction (``gains`` (2K+1, N_t) rows) tau_k(s) = tau_k gain_k(s), and
    a_k is scaled by gain_k(s) (the wrap angles held fixed).  False where J is not positive definite."""
    length, offset, pitch, angle, tau, end, kse, kbt = (rod.length, rod.offset, rod.pitch, rod.angle, rod.tension,
                                                        rod.end, rod.kse, rod.kbt)
    n_t = offset.shape[0]
    rho, drho = np.empty((n_t, 2)), np.empty((n_t, 2))
    tau_node = np.empty(n_t)
    res, jac, low = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
    av, d, y, rhs, out = np.empty(6), np.empty(6), np.empty(6), np.empty(6), np.empty(6)
    for node in range(sig.shape[0]):
        _routing(sig[node], length, offset, pitch, angle, rho, drho)
        _node_tensions(tau, end, act[node], gains, node, tau_node)
        _residual_jacobian(xs[node], rho, drho, tau_node, kse, kbt, res, jac, True, av, _NO_TARGET)
        if not _factor_spd(jac, d, low):
            return False
        x = xs[node]
        for q in range(n_t):
            if not end[q] > act[node]:
                for a in range(6):
                    sens[node, a, q] = 0.0
                continue
            g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], rho[q, 0], rho[q, 1], drho[q, 0], drho[q, 1])
            gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
            t0, t1, t2 = g0 / gn, g1 / gn, g2 / gn
            ox, oy = rho[q, 0], rho[q, 1]
            if gains.shape[0]:
                t0, t1, t2 = t0 * gains[node, q], t1 * gains[node, q], t2 * gains[node, q]
            rhs[0], rhs[1], rhs[2] = -t0, -t1, -t2
            rhs[3], rhs[4], rhs[5] = -oy * t2, ox * t2, -(ox * t1 - oy * t0)
            if not _solve_factored(d, low, rhs, out, y):
                return False
            for a in range(6):
                sens[node, a, q] = out[a]
    return True


#: displacement actuation: a step keeps the last Jacobian (a chord step) while each cuts the miss by this factor
_CHORD_RATE = 0.25
#: and with friction while each cuts it by this factor (the secant updates keep the Jacobian current)
_SECANT_RATE = 0.6
#: a step moves no tension by more than _MAX_STEP_N + _MAX_STEP_FRACTION of it (antagonistic tendons
#: can have several equilibria: small steps follow the one the start is on), and one that does not
#: lower the squared miss is halved, down to _MIN_DAMPING
_MAX_STEP_N, _MAX_STEP_FRACTION, _MIN_DAMPING = 1.0, 0.5, 1.0 / 64.0
#: and Newton on the tensions gives up after this many iterations
MAX_DISPLACEMENT_ITERATIONS = 50


@njit(cache=True, error_model="numpy")
def find_tensions(rod, compliance, capstan, target, tols, slack, dlen, known, carried, level):
    """The tensions (in place on ``tau`` (N_t,), N) that pull in the displacements ``target``
    (N_t,) m of the tendons where it is not NaN (the others keep their tensions), on level 0's nodes
    of :class:`Level0` ``level`` (the base grid with the ends).  A tendon with series elasticity (``compliance`` c_i =
    1 / k_i) takes up the pull-in u_i = d_i + c_i tau_i (eq. SE: tau_i = k_i max(0, u_i - d_i)).
    The displacement d_i = l0_i - l_i(tau) has the Jacobian -dl/dtau = int A^T J^-1 A ds,
    symmetric positive semi-definite (with friction scaled by each node's gain, the wrap angles
    held fixed): Newton on the driven tendons with that Jacobian plus diag(c) (:func:`_path_lengths`),
    projected onto tau >= 0, the Jacobian kept while each step cuts the miss by ``_CHORD_RATE``
    (with friction, whose Jacobian misses the wrap angles' change, by ``_SECANT_RATE``, and updated
    after each kept step by Broyden's secant, :func:`_secant_update`),
    each step capped (``_MAX_STEP_N``, ``_MAX_STEP_FRACTION``) and halved while it does not lower
    the squared miss.
    A tendon whose displacement would need a push (d_i > target_i at tau_i = 0: its path shortened
    more than it was pulled in) is slack: tension 0, ``slack[i]`` True.  ``dlen`` (N_t, N_t) holds
    the path lengths' Jacobian, in and out: with ``known[0]`` the one left by the design before in a
    sequence (its first step then a chord step: the commands of neighbouring rows are close), and
    ``known[0]`` is set once one is computed here.  ``carried`` (N_t,) m holds the path lengths at the
    start tensions where ``known[1]`` (the design before in a sequence, the same robot at the same motions,
    ended at these tensions: its last shooting is this one's first, so it is skipped), and the lengths of
    the last shooting on return (``known[1]`` then says whether they are the returned tensions').  The
    last shooting's results are left in ``level``, for :func:`finish_design`.  Returns (converged,
    shootings)."""
    length, offset, pitch, end, tau, comp = rod.length, rod.offset, rod.pitch, rod.end, rod.tension, compliance
    sig, act, xs, stretch, gains, chain = level
    n_t = offset.shape[0]
    order = np.arange(sig.shape[0])
    sens = np.empty((sig.shape[0], 6, n_t))
    lengths = np.empty(n_t)
    l0 = np.empty(n_t)
    for i in range(n_t):
        l0[i] = undeformed_length(length, offset[i], pitch[i], end[i])
        slack[i] = False
    free = np.zeros(n_t, dtype=np.bool_)
    last_worst, last_merit, alpha = np.inf, np.inf, 1.0
    tau_before, full_step = np.empty(n_t), np.zeros(n_t)
    # with friction the Jacobian holds the wrap angles fixed: a secant (Broyden) update adds what it misses
    secant = has_friction(capstan)
    misses, miss_before = np.zeros(n_t), np.zeros(n_t)
    shootings = 0
    for it in range(MAX_DISPLACEMENT_ITERATIONS):
        if it == 0 and known[1] and known[0]:
            lengths[:] = carried
        else:
            xs[:, :] = 0.0
            xs[0, 2] = 1.0
            shootings += 1
            ok, chain_it, chain_res = _solve_nodes_chain(sig, act, xs, rod, tols, order, stretch, gains, capstan)
            chain[0], chain[1], chain[2] = 1.0 if ok else 0.0, chain_it, chain_res
            if not ok:
                known[1] = False
                return False, shootings
            _path_lengths_of(sig, act, stretch, rod, lengths)
        carried[:] = lengths
        known[1] = True
        # residual and the free set: driven tendons that pull, or at zero tension but short of their target
        n_free, worst, merit = 0, 0.0, 0.0
        for i in range(n_t):
            free[i] = False
            if target[i] != target[i]:
                continue
            miss = (l0[i] - lengths[i]) + comp[i] * tau[i] - target[i]
            misses[i] = miss
            if tau[i] > 0.0 or miss < 0.0:
                free[i] = True
                n_free += 1
                worst = max(worst, abs(miss))
                merit += miss * miss
            slack[i] = tau[i] == 0.0 and miss > 0.0
        if worst <= tols.displacement_tol:
            return True, shootings
        if not (merit < last_merit) and alpha > _MIN_DAMPING:  # the step overshot: half as far along it
            alpha *= 0.5
            for i in range(n_t):
                tau[i] = max(tau_before[i] + alpha * full_step[i], 0.0)
            known[1] = False
            continue
        last_merit, alpha = merit, 1.0
        if (it == 0 and not known[0]) or worst > (_SECANT_RATE if secant else _CHORD_RATE) * last_worst:
            # the Jacobian anew (else the last one, or the row before's: a chord step, with friction
            # updated by the secant after each kept step)
            if not _sensitivities(sig, act, xs, rod, sens, gains):
                known[1] = False
                return False, shootings
            _path_lengths(sig, act, xs, rod, sens, lengths, dlen)
            known[0] = True
        elif secant and it > 0:
            _secant_update(dlen, comp, target, tau, tau_before, misses, miss_before)
        last_worst = worst
        idx = np.empty(n_free, dtype=np.int64)
        c = 0
        for i in range(n_t):
            if free[i]:
                idx[c] = i
                c += 1
        a = np.empty((n_free, n_free))
        b = np.empty(n_free)
        for p in range(n_free):
            i = idx[p]
            b[p] = target[i] - (l0[i] - lengths[i]) - comp[i] * tau[i]
            for q in range(n_free):
                a[p, q] = -dlen[i, idx[q]] + (comp[i] if p == q else 0.0)
        step = np.empty(n_free)
        _solve_dense(a, b, step)
        reach = 1.0  # at most _MAX_STEP_N + _MAX_STEP_FRACTION tau per tendon and step: stay on the branch
        for p in range(n_free):
            cap = _MAX_STEP_N + _MAX_STEP_FRACTION * tau[idx[p]]
            if abs(step[p]) * reach > cap:
                reach = cap / abs(step[p])
        for i in range(n_t):
            tau_before[i], full_step[i], miss_before[i] = tau[i], 0.0, misses[i]
        for p in range(n_free):
            full_step[idx[p]] = reach * step[p]
            tau[idx[p]] = max(tau[idx[p]] + reach * step[p], 0.0)
        known[1] = False  # the tensions moved past the lengths' shooting
    return False, shootings


@njit(cache=True, error_model="numpy")
def _secant_update(dlen, comp, target, tau, tau_before, misses, miss_before):
    """Broyden's update of the path lengths' Jacobian ``dlen`` (N_t, N_t) (in place) with the last
    step: J = -dlen + diag(c) the miss's Jacobian, dt = tau - tau_before and dm its change in miss
    (``misses`` - ``miss_before``, each (N_t,)), J += (dm - J dt) dt^T / (dt^T dt), on the rows of the
    driven tendons (``target`` not NaN), so that J dt = dm holds afterwards."""
    n_t = tau.shape[0]
    norm = 0.0
    for j in range(n_t):
        norm += (tau[j] - tau_before[j]) ** 2
    if not norm > 0.0:
        return
    for i in range(n_t):
        if target[i] != target[i]:
            continue
        predicted = comp[i] * (tau[i] - tau_before[i])
        for j in range(n_t):
            predicted -= dlen[i, j] * (tau[j] - tau_before[j])
        surprise = (misses[i] - miss_before[i]) - predicted
        for j in range(n_t):
            dlen[i, j] -= surprise * (tau[j] - tau_before[j]) / norm


@njit(cache=True, error_model="numpy")
def _same_rod(rods, b, target):
    """Whether design ``b`` of :class:`Rods` ``rods`` is design ``b - 1`` but for its driven tendons'
    targets (``target`` (B, N_t), NaN: tension-driven, whose tensions must agree too): a shooting of
    the one at given tensions is the other's."""
    for a in range(3):
        if rods.kse[b, a] != rods.kse[b - 1, a] or rods.kbt[b, a] != rods.kbt[b - 1, a]:
            return False
    if rods.radius[b] != rods.radius[b - 1] or rods.length[b] != rods.length[b - 1]:
        return False
    for i in range(target.shape[1]):
        if (rods.offset[b, i] != rods.offset[b - 1, i] or rods.pitch[b, i] != rods.pitch[b - 1, i]
                or rods.angle[b, i] != rods.angle[b - 1, i] or rods.end[b, i] != rods.end[b - 1, i]
                or rods.compliance[b, i] != rods.compliance[b - 1, i] or rods.capstan[b, i] != rods.capstan[b - 1, i]):
            return False
        if target[b, i] != target[b, i] and not (target[b - 1, i] != target[b - 1, i]
                                                 and rods.tension[b, i] == rods.tension[b - 1, i]):
            return False
    return True


@njit(cache=True, error_model="numpy")
def level0_arrays(grid, rod, capstan):
    """A :class:`Level0` for :class:`Rod` ``rod`` with its tendons' ``capstan`` on the base
    :class:`Grid` ``grid``: its nodes, and zeros and empty arrays for a chain's results."""
    edges, _, _ = _with_ends(grid.edges, grid.out_step, rod.end)
    sig = _interleaved(edges)
    m, n_t = sig.shape[0], rod.offset.shape[0]
    return Level0(sig, _node_activity(sig), np.zeros((m, 6)), np.empty((m, n_t)),
                  np.empty((m if has_friction(capstan) else 0, n_t)), np.zeros(3))


@njit(cache=True, error_model="numpy", nogil=True)
def find_tensions_batch(rods, target, grid, tols, slack, status, iterations, sequence, creep, crept, out):
    """:func:`find_tensions` for every design of :class:`Rods` ``rods`` (tensions in place) with
    targets ``target`` (B, N_t) (NaN: tension-driven); ``status`` (B,) 0 or NEWTON_FAILED,
    ``iterations`` (B,) the shootings each took.  ``creep`` (B, N_t) m/N: how far each driven tendon
    lengthens per newton of its drive's tension after its design (eq. CREEP, explicit in time: the
    creep of design b is crept_b = sum_{j<b} creep_j tau_j, and its target is the command minus it);
    ``crept`` (B, N_t) m receives each design's.  All zeros: each design alone (the designs may be
    split in any chunks); else they are one chain in this order.  With ``sequence`` the designs are one robot's
    commands in order: each driven tendon's Newton starts from the tension found for the design
    before (a warm start), and with the Jacobian it left; where the design is the one before but for
    its targets (:func:`_same_rod`: the same motions too), also with that design's last shooting,
    so it shoots once less (a held row, not at all); a warm start that fails (a large step of the
    commands, e.g. a release from 8 mm to 0, can lead Newton away) is followed by one more try from
    the design's own start, as alone.  Then each design's answer at its tensions into the
    :class:`Shapes` ``out``, as :func:`solve_batch` writes it: where its last shooting (or, a held
    design, the one before's) was at those tensions, :func:`finish_design` from that shooting (the
    same chain, so the same bits), else :func:`solve_design`."""
    n_t = target.shape[1]
    dlen, known, carried = np.empty((n_t, n_t)), np.zeros(2, dtype=np.bool_), np.empty(n_t)
    cold, so_far, row_target = np.empty(n_t), np.zeros(n_t), np.empty(n_t)
    if rods.length.shape[0] == 0:
        return
    last = level0_arrays(grid, _rod(rods, 0), rods.capstan[0])  # the last shooting's (none yet: unused)
    for b in range(rods.length.shape[0]):
        warm = sequence and b > 0 and status[b - 1] == OK
        known[0] = known[0] and warm
        known[1] = known[1] and warm and _same_rod(rods, b, target)
        for i in range(n_t):
            cold[i] = rods.tension[b, i]
            if warm and target[b, i] == target[b, i]:
                rods.tension[b, i] = rods.tension[b - 1, i]
        for i in range(n_t):  # eq. CREEP: the tendon's pull-in less what it crept so far (NaN stays NaN)
            crept[b, i] = so_far[i]
            row_target[i] = target[b, i] - so_far[i]
        rod, capstan = _rod(rods, b), rods.capstan[b]
        level = level0_arrays(grid, rod, capstan)
        ok, it = find_tensions(rod, rods.compliance[b], capstan, row_target, tols, slack[b], dlen, known, carried,
                               level)
        if warm and not ok:
            for i in range(n_t):
                rods.tension[b, i] = cold[i]
            known[0], known[1] = False, False
            ok, more = find_tensions(rod, rods.compliance[b], capstan, row_target, tols, slack[b], dlen, known,
                                     carried, level)
            it += more
        for i in range(n_t):
            if target[b, i] == target[b, i] and np.isfinite(rods.tension[b, i]):
                so_far[i] += creep[b, i] * rods.tension[b, i]
        _store(status, b, OK if ok else NEWTON_FAILED)
        _store(iterations, b, it)
        if it > 0:  # else a held design: the last shooting is the design before's
            last = level
        view = _design_shapes(out, b)
        if known[1] and last.sig.shape[0] == level.sig.shape[0]:  # the last shooting was at these tensions
            res = finish_design(rod, capstan, grid, tols, view, last)
        else:
            res = solve_design(rod, capstan, grid, tols, view)
        _store_summary(out, b, res)


@njit(cache=True, error_model="numpy")
def _terminal_points(edges, xs, rod, end_step):
    """Each tendon's termination point p(s_e) + R(s_e) rho_i(s_e), (N_t, 3) (rows of tendons that
    end at the tip are not written), from the converged nodes ``xs`` (2K+1, 6) on ``edges``."""
    length, offset, pitch, angle, end = rod.length, rod.offset, rod.pitch, rod.angle, rod.end
    n_t = end.shape[0]
    pos, rot = np.zeros((n_t, 3)), np.zeros((n_t, 3, 3))
    terminal = np.zeros((n_t, 3))
    if end_step.max() < 0:  # every tendon ends at the tip
        return terminal
    _magnus(edges, xs[0::2], xs[1::2], length, end_step, pos, rot)
    _end_points(pos, rot, length, end_step, end, offset, pitch, angle, terminal)
    return terminal


@njit(cache=True, error_model="numpy")
def _end_points(pos, rot, length, end_step, end, offset, pitch, angle, terminal):
    """``terminal`` (N_t, 3) = p + R rho_i(s_e) from each tendon's pose at its end, ``pos`` (N_t, 3),
    ``rot`` (N_t, 3, 3) (tendons with ``end_step`` < 0, ending at the tip, skipped)."""
    for i in range(end.shape[0]):
        if end_step[i] < 0:
            continue
        phi = _tendon_angle(angle[i], pitch[i], end[i] * length)
        rx, ry = offset[i] * math.cos(phi), offset[i] * math.sin(phi)
        for a in range(3):
            terminal[i, a] = pos[i, a] + rot[i, a, 0] * rx + rot[i, a, 1] * ry


@njit(cache=True, error_model="numpy")
def _clamp_ended(fractions_out, end, terminal, tendons_out):
    """Beyond its end a tendon has no path: its rows of ``tendons_out`` (n, N_t, 3) at outputs past
    ``end`` (N_t,) hold its termination point ``terminal`` (N_t, 3)."""
    for j in range(fractions_out.shape[0]):
        for i in range(end.shape[0]):
            if end[i] < 1.0 - 1e-12 and fractions_out[j] > end[i]:
                tendons_out[j, i, :] = terminal[i]


@njit(cache=True, error_model="numpy", inline="always")
def _ad_apply(xi, u, out):
    """``out`` (6,) = ad_xi u = [[hat(w), hat(v)], [0, hat(w)]] u = (w x u_v + v x u_w, w x u_w) for the
    twist ``xi`` = (v, w) (6,) and ``u`` (6,) (``out`` must not be ``u``)."""
    v0, v1, v2, w0, w1, w2 = xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]
    a0, a1, a2, b0, b1, b2 = u[0], u[1], u[2], u[3], u[4], u[5]
    out[0] = w1 * a2 - w2 * a1 + v1 * b2 - v2 * b1
    out[1] = w2 * a0 - w0 * a2 + v2 * b0 - v0 * b2
    out[2] = w0 * a1 - w1 * a0 + v0 * b1 - v1 * b0
    out[3] = w1 * b2 - w2 * b1
    out[4] = w2 * b0 - w0 * b2
    out[5] = w0 * b1 - w1 * b0


#: the series of dexp stops at the first term below this fraction of the tangent it is applied to
_DEXP_TOL = 1e-17


@njit(cache=True, error_model="numpy")
def _pose_tangent(edges, xs, sens, length, out_step, rot_out, jac_out):
    """The pose's sensitivity to the tensions at the output edges ``out_step`` (n,), base frame, into
    ``jac_out`` (n, 6, N_t): rows 0-2 R eta_v (dp/dtau, m/N), rows 3-5 R eta_w (the rotation vector
    of dR R^T / dtau, rad/N), from the node strains ``xs`` (2K+1, 6) on ``edges`` (K+1,) and their
    sensitivities ``sens`` (2K+1, 6, N_t) (:func:`_sensitivities`), frames ``rot_out`` (n, 3, 3).

    Differentiating eq. (MAG), Omega = h mean + h^2/12 [xi_0, xi_1] and g_{k+1} = g_k exp(Omega), for the
    body-frame tangents eta_k = (g_k^-1 dg_k / dtau)^v (eta_0 = 0: the base is clamped):
      d Omega = h (dxi_0 + 4 dxi_m + dxi_1) / 6 + h^2/12 (ad_{xi_0} dxi_1 - ad_{xi_1} dxi_0),
      eta_{k+1} = Ad_{exp(-Omega)} eta_k + dexp_{-Omega} d Omega,
    with dexp_{-Omega} = sum_j (-ad_Omega)^j / (j+1)! (summed until a term is below ``_DEXP_TOL``) and
    Ad_{exp(-Omega)} (u_v, u_w) = (R^T (u_v - p x u_w), R^T u_w) for exp(Omega) = (R, p)."""
    k_steps = edges.shape[0] - 1
    n_t = sens.shape[2]
    eta = np.zeros((6, n_t))
    omega, step_p, ex = np.empty(6), np.empty(3), np.empty((3, 3))
    d_om, t1, t2, term, nxt, carry, u = (np.empty(6), np.empty(6), np.empty(6), np.empty(6), np.empty(6),
                                         np.empty(6), np.empty(6))
    dx0, dxm, dx1 = np.empty(6), np.empty(6), np.empty(6)
    order = np.argsort(out_step)
    n_out = out_step.shape[0]
    q = 0
    while q < n_out and out_step[order[q]] < 0:
        q += 1
    while q < n_out and out_step[order[q]] == 0:  # at the clamped base the pose does not move
        jac_out[order[q]] = 0.0
        q += 1
    for k in range(k_steps):
        h = (edges[k + 1] - edges[k]) * length
        a0, am, a1 = xs[2 * k], xs[2 * k + 1], xs[2 * k + 2]
        _magnus_omega(h, a0, a1, am, omega)
        _se3_exp(omega, ex, step_p)
        for c in range(n_t):
            for a in range(6):
                dx0[a], dxm[a], dx1[a] = sens[2 * k, a, c], sens[2 * k + 1, a, c], sens[2 * k + 2, a, c]
            _ad_apply(a0, dx1, t1)
            _ad_apply(a1, dx0, t2)
            scale = 0.0
            for a in range(6):
                d_om[a] = h * (dx0[a] + 4.0 * dxm[a] + dx1[a]) / 6.0 + h * h / 12.0 * (t1[a] - t2[a])
                term[a], carry[a] = d_om[a], d_om[a]
                scale = max(scale, abs(d_om[a]))
            for j in range(1, 80):
                _ad_apply(omega, term, nxt)
                big = 0.0
                for a in range(6):
                    term[a] = -nxt[a] / (j + 1)
                    carry[a] += term[a]
                    big = max(big, abs(term[a]))
                if not (big > _DEXP_TOL * scale):  # converged, zero, or not finite
                    break
            ev0, ev1, ev2, ew0, ew1, ew2 = eta[0, c], eta[1, c], eta[2, c], eta[3, c], eta[4, c], eta[5, c]
            p0, p1, p2 = step_p[0], step_p[1], step_p[2]
            u[0], u[1], u[2] = ev0 - (p1 * ew2 - p2 * ew1), ev1 - (p2 * ew0 - p0 * ew2), ev2 - (p0 * ew1 - p1 * ew0)
            u[3], u[4], u[5] = ew0, ew1, ew2
            for a in range(3):
                eta[a, c] = ex[0, a] * u[0] + ex[1, a] * u[1] + ex[2, a] * u[2] + carry[a]
                eta[3 + a, c] = ex[0, a] * u[3] + ex[1, a] * u[4] + ex[2, a] * u[5] + carry[3 + a]
        while q < n_out and out_step[order[q]] == k + 1:
            j = order[q]
            for c in range(n_t):
                for a in range(3):
                    jac_out[j, a, c] = rot_out[j, a, 0] * eta[0, c] + rot_out[j, a, 1] * eta[1, c] + \
                        rot_out[j, a, 2] * eta[2, c]
                    jac_out[j, 3 + a, c] = rot_out[j, a, 0] * eta[3, c] + rot_out[j, a, 1] * eta[4, c] + \
                        rot_out[j, a, 2] * eta[5, c]
            q += 1


@njit(cache=True, error_model="numpy")
def _interleaved(edges):
    """The nodes of a step grid ``edges`` (K+1,), in order of s: edge 0, mid 0, edge 1, ..., (2K+1,)."""
    k0 = edges.shape[0] - 1
    sig = np.empty(2 * k0 + 1)
    for k in range(k0):
        sig[2 * k] = edges[k]
        sig[2 * k + 1] = 0.5 * (edges[k] + edges[k + 1])
    sig[2 * k0] = edges[k0]
    return sig


class DesignShapes(NamedTuple):
    """One design's outputs of :class:`Shapes` (views, :func:`_design_shapes`), written in place."""

    backbone: np.ndarray
    rotation: np.ndarray
    strains: np.ndarray
    tendons: np.ndarray
    displacement: np.ndarray
    jacobian: np.ndarray
    nodes: np.ndarray
    profile: np.ndarray


@njit(cache=True, error_model="numpy")
def _design_shapes(out, b):
    """Design ``b``'s views of the :class:`Shapes` ``out``."""
    return DesignShapes(out.backbone[b], out.rotation[b], out.strains[b], out.tendons[b], out.displacement[b],
                        out.jacobian[b], out.nodes[b], out.profile[b])


@njit(cache=True, error_model="numpy")
def solve_design(rod, capstan, grid, tols, view):
    """One design, the :class:`Rod` ``rod`` with its tendons' ``capstan`` (N_t,) (eq. CAP), on the
    base :class:`Grid` ``grid`` with every tendon end
    added (:func:`_with_ends`) and :class:`Tolerances` ``tols``.  Writes into the :class:`DesignShapes`
    ``view``: backbone (n, 3), frames (n, 3, 3), strains (n, 6), tendon positions (n, N_t, 3) and
    displacements (N_t,) at the outputs, the pose Jacobian (n, 6, N_t) where ``view.jacobian`` has
    rows, level 0's node strains where ``view.nodes`` has rows (read first with ``tols.warm``).
    Returns ``(status, residual N, Newton iterations, level, error estimate)``; with
    ``tols.linearized`` the first-order strains on the base grid (level 0, no estimate)."""
    # level 0: edges and midpoints in order of s, the first from the undeformed strains; |g_i| at the
    # nodes (the path lengths) and exp(capstan theta) there (eq. CAP)
    level = level0_arrays(grid, rod, capstan)
    sig, act, xs, stretch, gains, chain = level
    order = np.arange(sig.shape[0])
    keep = view.nodes.shape[0] == sig.shape[0]
    if tols.warm and keep and not has_friction(capstan):  # Newton at every node from the last solve's strains
        xs[:, :] = view.nodes
        n_ok, it, res = _solve_nodes(sig, act, xs, rod, tols, order, stretch, gains)
    else:
        xs[0, 2] = 1.0  # nu = e3, kappa = 0; every later node starts from the one before
        n_ok, it, res = _solve_nodes_chain(sig, act, xs, rod, tols, order, stretch, gains, capstan)
    chain[0], chain[1], chain[2] = 1.0 if n_ok else 0.0, it, res
    if keep:
        view.nodes[:, :] = xs
    return finish_design(rod, capstan, grid, tols, view, level)


@njit(cache=True, error_model="numpy")
def finish_design(rod, capstan, grid, tols, view, level):
    """:func:`solve_design` from its level 0 on, the :class:`Level0` ``level`` as a chain left it (read,
    not written): the outputs, the step control's estimate and its finer levels."""
    sig, act, xs, stretch, gains, chain = level
    length, offset, pitch, angle, end = rod.length, rod.offset, rod.pitch, rod.angle, rod.end
    fractions_out = grid.fractions
    edges, out_step0, end_step = _with_ends(grid.edges, grid.out_step, end)
    step_tol, max_level = tols.step_tol, tols.max_level
    n_out = fractions_out.shape[0]
    n_t = offset.shape[0]
    friction = has_friction(capstan)
    ok, res = chain[0] > 0.0, chain[2]
    iters = max(0, int(chain[1]))
    worst = max(0.0, res) if res == res else res
    out_step = out_step0.copy()
    pos_out, rot_out, tendons_out = view.backbone, view.rotation, view.tendons
    _magnus(edges, xs[0::2], xs[1::2], length, out_step, pos_out, rot_out)
    rho_out = _output_offsets(fractions_out, length, offset, pitch, angle)
    prev = np.empty((n_out, n_t, 3))
    _tendon_positions(pos_out, rot_out, rho_out, prev)
    tendons_out[:, :, :] = prev
    level = 0
    estimate = np.nan if tols.linearized else _coarse_estimate(edges, xs, length, out_step, rho_out, prev)
    while level < max_level and not (estimate <= step_tol) and not tols.linearized:
        # refine: the new edges are the old edges and midpoints; new midpoints by Newton
        level += 1
        k_steps = sig.shape[0] - 1
        edges = sig.copy()
        new_sig = _interleaved(sig)
        new_xs = np.empty((2 * k_steps + 1, 6))
        new_stretch = np.empty((2 * k_steps + 1, n_t))
        # friction: the wrap angle is level 0's; a new node's gain is its neighbours' geometric mean
        new_gains = np.empty((2 * k_steps + 1 if friction else 0, n_t))
        for k in range(k_steps):
            new_xs[2 * k] = xs[k]
            new_xs[2 * k + 1] = 0.5 * (xs[k] + xs[k + 1])  # start: the neighbours' mean (error O(h^2))
            new_stretch[2 * k] = stretch[k]
            if friction:
                new_gains[2 * k] = gains[k]
                new_gains[2 * k + 1] = np.sqrt(gains[k] * gains[k + 1])
        new_xs[2 * k_steps] = xs[k_steps]
        new_stretch[2 * k_steps] = stretch[k_steps]
        if friction:
            new_gains[2 * k_steps] = gains[k_steps]
        act = _node_activity(new_sig)
        for k in range(k_steps):  # beside a zero-width step (an end) the neighbours' strains jump
            if sig[k + 1] == sig[k]:
                new_xs[2 * k + 1] = xs[k + 1]
                if friction:
                    new_gains[2 * k + 1] = gains[k + 1]
        mids = np.arange(1, 2 * k_steps + 1, 2)
        n_ok, it, res = _solve_nodes(new_sig, act, new_xs, rod, tols, mids, new_stretch, new_gains)
        ok = ok and n_ok
        iters = max(iters, it)
        worst = max(worst, res) if res == res else res
        sig, xs, stretch, gains = new_sig, new_xs, new_stretch, new_gains
        out_step = out_step * 2
        end_step = np.where(end_step >= 0, end_step * 2, end_step)
        _magnus(edges, xs[0::2], xs[1::2], length, out_step, pos_out, rot_out)
        _tendon_positions(pos_out, rot_out, rho_out, tendons_out)
        estimate = _masked_richardson(tendons_out, prev, out_step)
        prev[:, :, :] = tendons_out
    # strains at the outputs: the output edges of the last level (node 2 e is edge e)
    profile = view.profile
    for j in range(n_out):
        node = 2 * out_step[j]
        view.strains[j, :] = xs[node]
        for i in range(n_t):  # :func:`_node_tensions` at the output's node, without a view per output
            gain = gains[node, i] if friction else 1.0
            profile[j, i] = rod.tension[i] * gain if end[i] > act[node] else 0.0
    if view.jacobian.shape[0] > 0:  # the exact Jacobian: the implicit-function theorem, then eq. (MAG)'s tangent
        sens = np.empty((sig.shape[0], 6, n_t))
        if _sensitivities(sig, act, xs, rod, sens, gains):
            _pose_tangent(edges, xs, sens, length, out_step, rot_out, view.jacobian)
        else:
            view.jacobian[:, :, :] = np.nan
    displacement_out = view.displacement
    _path_lengths_of(sig, act, stretch, rod, displacement_out)
    for i in range(n_t):
        displacement_out[i] = undeformed_length(length, offset[i], pitch[i], end[i]) - displacement_out[i]
    _clamp_ended(fractions_out, end, _terminal_points(edges, xs, rod, end_step), tendons_out)
    status = OK
    if not _all_finite(worst, tendons_out):
        status = NOT_FINITE
    elif not ok:
        status = NEWTON_FAILED
    elif not (estimate <= step_tol) and not tols.linearized:
        status = STEP_TOL_NOT_MET
    return status, worst, iters, level, estimate




@njit(cache=True, error_model="numpy", inline="always")
def _extrapolate_cubic(sig, x_nodes, k, k1, k2, k3, k4):
    """x_nodes[k] (6,) by the cubic through the nodes k1..k4 (Lagrange, at the fractions ``sig``); the
    last node's strains where two of them coincide (a zero-width step)."""
    s0, s1, s2, s3, s4 = sig[k], sig[k1], sig[k2], sig[k3], sig[k4]
    d12, d13, d14, d23, d24, d34 = s1 - s2, s1 - s3, s1 - s4, s2 - s3, s2 - s4, s3 - s4
    if not (d12 > 0.0 and d23 > 0.0 and d34 > 0.0):
        x_nodes[k, :] = x_nodes[k1]
        return
    e1, e2, e3, e4 = s0 - s1, s0 - s2, s0 - s3, s0 - s4
    l1 = e2 * e3 * e4 / (d12 * d13 * d14)
    l2 = -e1 * e3 * e4 / (d12 * d23 * d24)
    l3 = e1 * e2 * e4 / (d13 * d23 * d34)
    l4 = -e1 * e2 * e3 / (d14 * d24 * d34)
    for a in range(6):
        x_nodes[k, a] = l1 * x_nodes[k1, a] + l2 * x_nodes[k2, a] + l3 * x_nodes[k3, a] + l4 * x_nodes[k4, a]


@njit(cache=True, error_model="numpy")
def _solve_nodes_chain(node_fractions, act, x_nodes, rod, tols, order, stretch, gains, capstan):
    """As :func:`_solve_nodes` (``stretch`` too), each node starting from the solved strains of the nodes before
    (Lagrange extrapolation from the last four since the last end, where the strains jump).  The
    tendon angles advance by angle addition between nodes (a rotation per distinct spacing),
    recomputed exactly every ``_RESYNC`` nodes.

    Friction (``gains`` (M, N_t) has rows): the tensions fall (pull) or grow (release) along the
    path, tau_i(s) = tau_i(0) exp(capstan_i theta_i(s)) (eq. CAP).  The wrap angle theta_i is summed
    node to node (:func:`_wrap_angle`, so it needs the nodes in order of s): each node's tensions
    start from theta predicted by the last increment, and the node is solved again with the
    corrected theta until the tensions move by less than ``_WRAP_TOL`` of themselves.  The factors
    exp(capstan_i theta_i) are written to ``gains``."""
    length, offset, pitch, angle, tau, end = rod.length, rod.offset, rod.pitch, rod.angle, rod.tension, rod.end
    n_t = offset.shape[0]
    rho = np.empty((n_t, 2))
    drho = np.empty((n_t, 2))
    tau_node, tau_prev = np.empty(n_t), np.empty(n_t)
    since = 0  # nodes solved since the tendons acting last changed
    work, jac, low = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    cos_phi, sin_phi = np.empty(n_t), np.empty(n_t)
    cos_d, sin_d = np.empty(n_t), np.empty(n_t)
    last_delta = np.inf  # none yet
    ok = True
    iters = 0
    worst = 0.0
    friction = gains.shape[0] > 0
    theta, theta_new, rate = np.zeros(n_t), np.zeros(n_t), np.zeros(n_t)  # wrap angles, their last rate (rad/m)
    t_prev, t_now, turn = np.empty((n_t, 3)), np.empty((n_t, 3)), np.empty((3, 3))
    twist, step_p = np.empty(6), np.empty(3)
    h = 0.0
    for j in range(order.shape[0]):
        k = order[j]
        last_delta = _advance_angles(j, node_fractions[k], node_fractions[order[j - 1]] if j else 0.0, length, angle,
                                     pitch, cos_phi, sin_phi, cos_d, sin_d, last_delta)
        for i in range(n_t):
            rho[i, 0], rho[i, 1] = offset[i] * cos_phi[i], offset[i] * sin_phi[i]
            drho[i, 0], drho[i, 1] = -offset[i] * pitch[i] * sin_phi[i], offset[i] * pitch[i] * cos_phi[i]
        if friction:  # the tensions at the predicted wrap angle; the steps restart where the acting tendons change
            h = (node_fractions[k] - node_fractions[order[j - 1]]) * length if j else 0.0
            _predict_wraps(theta, rate, h, theta_new)
            for i in range(n_t):
                gains[k, i] = _capstan_gain(capstan[i], theta_new[i])
            _node_tensions(tau, end, act[k], gains, k, tau_node)
            changed = False
            for i in range(n_t):
                acting = 1.0 if end[i] > act[k] else 0.0
                changed = changed or (j > 0 and acting != tau_prev[i])
                tau_prev[i] = acting
        else:
            _active_tensions(tau, end, act[k], tau_node)
            changed = False
            for i in range(n_t):
                changed = changed or (j > 0 and tau_node[i] != tau_prev[i])
                tau_prev[i] = tau_node[i]
        since = 0 if changed or j == 0 else since + 1
        if since == 0 and j > 0 or since == 1:
            x_nodes[k, :] = x_nodes[order[j - 1]]
        elif since == 2:  # linear extrapolation from the two nodes before (start error O(h^2))
            k1, k2 = order[j - 1], order[j - 2]
            span = node_fractions[k1] - node_fractions[k2]
            f = (node_fractions[k] - node_fractions[k1]) / span if span > 0.0 else 0.0
            for a in range(6):
                x_nodes[k, a] = x_nodes[k1, a] + f * (x_nodes[k1, a] - x_nodes[k2, a])
        elif since > 3:  # cubic (Lagrange) extrapolation from the four nodes before (start error O(h^4))
            _extrapolate_cubic(node_fractions, x_nodes, k, order[j - 1], order[j - 2], order[j - 3], order[j - 4])
        elif since == 3:  # quadratic (Lagrange) extrapolation from the three nodes before (start error O(h^3))
            k1, k2, k3 = order[j - 1], order[j - 2], order[j - 3]
            s0, s1, s2, s3 = node_fractions[k], node_fractions[k1], node_fractions[k2], node_fractions[k3]
            d12, d13, d23 = s1 - s2, s1 - s3, s2 - s3
            if d12 > 0.0 and d13 > 0.0 and d23 > 0.0:
                l1 = (s0 - s2) * (s0 - s3) / (d12 * d13)
                l2 = -(s0 - s1) * (s0 - s3) / (d12 * d23)
                l3 = (s0 - s1) * (s0 - s2) / (d13 * d23)
            else:
                l1, l2, l3 = 1.0, 0.0, 0.0
            for a in range(6):
                x_nodes[k, a] = l1 * x_nodes[k1, a] + l2 * x_nodes[k2, a] + l3 * x_nodes[k3, a]
        conv, it, r = _node_strains(x_nodes[k], rho, drho, tau_node, rod, tols, work, jac, low)
        if friction:
            for correction in range(_MAX_WRAP_CORRECTIONS + 1):
                _unit_tangents(x_nodes[k], rho, drho, t_now)
                if not j:  # the base: no turn yet
                    break
                _relative_rotation(x_nodes[order[j - 1], 3:], x_nodes[k, 3:], h, twist, turn, step_p)
                move = _correct_wraps(theta, t_prev, t_now, turn, capstan, tau_node, theta_new)
                if not (move > _WRAP_TOL) or correction == _MAX_WRAP_CORRECTIONS:
                    break
                for i in range(n_t):
                    gains[k, i] = _capstan_gain(capstan[i], theta_new[i])
                _node_tensions(tau, end, act[k], gains, k, tau_node)
                conv, more, r = _node_strains(x_nodes[k], rho, drho, tau_node, rod, tols, work, jac, low)
                it += more
            _accept_wraps(theta, rate, h, theta_new)
            for i in range(n_t):
                gains[k, i] = _capstan_gain(capstan[i], theta[i])
                t_prev[i, 0], t_prev[i, 1], t_prev[i, 2] = t_now[i, 0], t_now[i, 1], t_now[i, 2]
        _node_stretch(x_nodes[k], rho, drho, stretch, k)
        ok = ok and conv
        iters = max(iters, it)
        if not (r <= worst):
            worst = r
    return ok, iters, worst


#: friction: a node is solved again with its corrected wrap angle at most this many times, while its
#: tensions would move by more than this fraction (the wrap angle's prediction is exact for
#: constant curvature; between segments its error is O(h^2))
_MAX_WRAP_CORRECTIONS = 4
_WRAP_TOL = 1e-7


@njit(cache=True, error_model="numpy", nogil=True)
def solve_batch(rods, grid, tols, out):
    """:func:`solve_design` for every design of :class:`Rods` ``rods``,
    without the GIL (:func:`tdcr.physics.cosserat._run_kernel` runs chunks side by side), into
    the :class:`Shapes` ``out``."""
    for b in range(rods.length.shape[0]):
        res = solve_design(_rod(rods, b), rods.capstan[b], grid, tols, _design_shapes(out, b))
        _store_summary(out, b, res)


@njit(cache=True, error_model="numpy")
def _store_summary(out, b, res):
    """Design ``b``'s status, residual, iterations, level and estimate (``res[:5]``) into :class:`Shapes` ``out``."""
    _store(out.status, b, res[0])
    _store(out.residual, b, res[1])
    _store(out.iterations, b, res[2])
    _store(out.level, b, res[3])
    _store(out.estimate, b, res[4])


@njit(cache=True, error_model="numpy")
def _store(array, index, value):
    """``array[index] = value``.  Inside a parallel loop numba 0.68 drops a plain item assignment
    to an array that is a field of a tuple argument (views passed to a function are written); this
    call is written (tests/unit/test_kernel.py checks every output)."""
    array[index] = value


# --------------------------------------------------------------------------- external loads
#
# With gravity and tip loads the moment about p(s) depends on the shape: shooting on M(0) (3
# unknowns), RK4 on y = (p, R, M) with M' = -p' x N (eq. MT), N(s) = F_tip + f_g (L - s), the
# strains at every stage from (W1, W2) with the right-hand side (R^T N, R^T M).  The shooting
# Jacobian dM(L)/dM(0) comes from the variational equations integrated with the same RK4 stages
# (the exact derivative of the discrete map):
#   d target = (dR^T N, dR^T M + R^T dM),  dx = J^-1 d target  (J: the Hessian of Phi at the stage),
#   dp' = dR nu + R dnu,  dR' = dR hat(kappa) + R hat(dkappa),  dM' = -dp' x N.

@njit(cache=True, error_model="numpy")
def _stage(s, state, x, want_var, rod, tau, force, tols, ws, deriv):
    """Derivatives ``deriv`` = (p', R', M', dp', dR', dM') of the ``state`` (p (3,), R (3, 3), M (3,)
    and their tangents to M(0), dp (3, 3), dR (3, 3, 3), dM (3, 3)) at arclength ``s`` m of the
    :class:`Rod` ``rod`` under the total force ``force`` N(s) (3,) of the loads beyond s, with the
    tendons' tensions ``tau`` (N_t,) acting there; strains into ``x`` (warm).  Returns (converged,
    residual)."""
    p, rot, mom, dp, drot, dmom = state
    fp, frot, fmom, fdp, fdrot, fdmom = deriv
    offset, pitch, angle = rod.offset, rod.pitch, rod.angle
    rho, drho, work, jac, low, target, dtarget, dx = ws
    n_t = offset.shape[0]
    for i in range(n_t):
        phi = _tendon_angle(angle[i], pitch[i], s)
        c, sn = math.cos(phi), math.sin(phi)
        rho[i, 0], rho[i, 1] = offset[i] * c, offset[i] * sn
        drho[i, 0], drho[i, 1] = -offset[i] * pitch[i] * sn, offset[i] * pitch[i] * c
    n0, n1, n2 = force[0], force[1], force[2]
    for a in range(3):
        target[a] = rot[0, a] * n0 + rot[1, a] * n1 + rot[2, a] * n2
        target[3 + a] = rot[0, a] * mom[0] + rot[1, a] * mom[1] + rot[2, a] * mom[2]
    conv, _, res = _newton(x, rho, drho, tau, rod.kse, rod.kbt, rod.radius, rod.length, tols.newton_tol,
                           tols.max_newton, work, jac, low, target, want_var)
    for a in range(3):
        fp[a] = rot[a, 0] * x[0] + rot[a, 1] * x[1] + rot[a, 2] * x[2]
    k0, k1, k2 = x[3], x[4], x[5]
    for a in range(3):  # R hat(kappa)
        frot[a, 0] = rot[a, 1] * k2 - rot[a, 2] * k1
        frot[a, 1] = rot[a, 2] * k0 - rot[a, 0] * k2
        frot[a, 2] = rot[a, 0] * k1 - rot[a, 1] * k0
    fmom[0] = -(fp[1] * n2 - fp[2] * n1)
    fmom[1] = -(fp[2] * n0 - fp[0] * n2)
    fmom[2] = -(fp[0] * n1 - fp[1] * n0)
    if want_var:
        d, y = work[4], work[5]
        for q in range(3):  # the three directions of dM(0)
            for a in range(3):
                dtarget[a] = drot[q, 0, a] * n0 + drot[q, 1, a] * n1 + drot[q, 2, a] * n2
                dtarget[3 + a] = (drot[q, 0, a] * mom[0] + drot[q, 1, a] * mom[1] + drot[q, 2, a] * mom[2]
                                  + rot[0, a] * dmom[q, 0] + rot[1, a] * dmom[q, 1] + rot[2, a] * dmom[q, 2])
            if not _solve_factored(d, low, dtarget, dx, y):
                conv = False
            for a in range(3):
                fdp[q, a] = (drot[q, a, 0] * x[0] + drot[q, a, 1] * x[1] + drot[q, a, 2] * x[2]
                             + rot[a, 0] * dx[0] + rot[a, 1] * dx[1] + rot[a, 2] * dx[2])
            for a in range(3):
                fdrot[q, a, 0] = (drot[q, a, 1] * k2 - drot[q, a, 2] * k1) + (rot[a, 1] * dx[5] - rot[a, 2] * dx[4])
                fdrot[q, a, 1] = (drot[q, a, 2] * k0 - drot[q, a, 0] * k2) + (rot[a, 2] * dx[3] - rot[a, 0] * dx[5])
                fdrot[q, a, 2] = (drot[q, a, 0] * k1 - drot[q, a, 1] * k0) + (rot[a, 0] * dx[4] - rot[a, 1] * dx[3])
            fdmom[q, 0] = -(fdp[q, 1] * n2 - fdp[q, 2] * n1)
            fdmom[q, 1] = -(fdp[q, 2] * n0 - fdp[q, 0] * n2)
            fdmom[q, 2] = -(fdp[q, 0] * n1 - fdp[q, 1] * n0)
    return conv, res


@njit(cache=True, error_model="numpy")
def _tendon_wrench(x, rho, drho, tau, sign, out):
    """``out`` (6,) += sign sum_i tau_i (t_i, rho_i x t_i) at the strains ``x``: the tendons' pull on
    the free body beyond the cut, in the body frame (the tendon terms of eqs. W1, W2)."""
    for i in range(tau.shape[0]):
        if tau[i] == 0.0:
            continue
        g0, g1, g2 = _tendon(x[0], x[1], x[2], x[3], x[4], x[5], rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1])
        gn = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        t0, t1, t2 = g0 / gn, g1 / gn, g2 / gn
        ox, oy = rho[i, 0], rho[i, 1]
        ti = sign * tau[i]
        out[0] += ti * t0
        out[1] += ti * t1
        out[2] += ti * t2
        out[3] += ti * oy * t2
        out[4] -= ti * ox * t2
        out[5] += ti * (ox * t1 - oy * t0)


@njit(cache=True, error_model="numpy")
def _jump(x, rot, mom, force, rho, drho, tau_right, kse, kbt, dt):
    """Rucker & Webster's rule at a tendon end (termination ``"rucker_webster"``), in place on the
    totals ``force`` N and ``mom`` M (base frame): only the ending tendons' pull -tau_e t_e is
    applied to the rod there, so its internal wrench jumps by it alone,
    n^+ = n^- + sum_e tau_e t_e^-,  m^+ = m^- + sum_e tau_e (R rho_e) x t_e^-,
    and the strains after the end follow from the constitutive law (eqs. W1, W2 without the ended
    tendons): K_se (nu^+ - e3) = R^T N - sum_c tau_c t_c^-,  K_bt kappa^+ = R^T M - sum_c tau_c rho_c x t_c^-
    over the continuing tendons c.  The totals then become N^+ = R (K_se (nu^+ - e3) + sum_c tau_c t_c^+),
    M^+ likewise: they jump by sum_c tau_c (t_c^+ - t_c^-) (and its moment), the kink forces that the
    consistent equilibrium keeps and this rule drops.  ``x`` (6,): the strains just before the end;
    ``dt`` (6,) workspace."""
    xp = np.empty(6)
    for a in range(6):
        dt[a] = 0.0
    _tendon_wrench(x, rho, drho, tau_right, 1.0, dt)  # sum_c tau_c (t_c, rho_c x t_c) before the end
    for a in range(3):
        nb = rot[0, a] * force[0] + rot[1, a] * force[1] + rot[2, a] * force[2]
        mb = rot[0, a] * mom[0] + rot[1, a] * mom[1] + rot[2, a] * mom[2]
        xp[a] = (nb - dt[a]) / kse[a] + (1.0 if a == 2 else 0.0)
        xp[3 + a] = (mb - dt[3 + a]) / kbt[a]
    _tendon_wrench(xp, rho, drho, tau_right, -1.0, dt)  # minus the same sums after the end
    for a in range(3):  # the totals jump by R (-dt): the kink forces' resultant and moment
        force[a] -= rot[a, 0] * dt[0] + rot[a, 1] * dt[1] + rot[a, 2] * dt[2]
        mom[a] -= rot[a, 0] * dt[3] + rot[a, 1] * dt[4] + rot[a, 2] * dt[5]
    for a in range(6):
        x[a] = xp[a]


@njit(cache=True, error_model="numpy")
def _stage_stretch(x, rho, drho, end, act, out):
    """|g_i| at a stage's strains ``x`` for the tendons that act there (0 for ended ones), (N_t,)."""
    for i in range(out.shape[0]):
        out[i] = _stretch(x, rho[i, 0], rho[i, 1], drho[i, 0], drho[i, 1]) if end[i] > act else 0.0


@njit(cache=True, error_model="numpy")
def _step_act(edges, k):
    """The fraction whose tendons act on the edge ``k``'s first stage (:func:`_active_tensions`):
    its step's midpoint, or at the tip and just before an end (a zero-width step) the previous
    step's, or its own inside a run of zero-width steps."""
    k_steps = edges.shape[0] - 1
    if k < k_steps and edges[k + 1] > edges[k]:
        return 0.5 * (edges[k] + edges[k + 1])
    if k > 0 and edges[k] > edges[k - 1]:
        return 0.5 * (edges[k - 1] + edges[k])
    return edges[k]


@njit(cache=True, error_model="numpy")
def _gained(tau, capstan, wrap, ahead, out):
    """``out`` (N_t,) = ``tau`` (N_t,) exp(capstan_i (theta_i + rate_i ahead)): the tensions ``ahead``
    m past the last edge of :func:`_shoot_pass` (eq. CAP; ``wrap`` as :func:`_edge_with_friction`'s)."""
    for i in range(tau.shape[0]):
        out[i] = tau[i] * _capstan_gain(capstan[i], wrap[0, i] + wrap[2, i] * ahead)


@njit(cache=True, error_model="numpy")
def _edge_with_friction(first, s0, state, x, want_var, rod, capstan, tau_step, force, tols, ws, deriv, wrap, frames,
                        rot_prev, turn, h_prev):
    """:func:`_stage` at an edge of :func:`_shoot_pass` with friction (eq. CAP): into ``tau_step``
    (N_t,) the tensions where they act (``wrap[3]``) times exp(capstan_i theta_i), theta_i predicted
    from the last step's rate, then corrected by the angle the tendons' unit tangents turned since
    the last edge (the frames' relative rotation R_prev^T R) and solved again until the gains move by
    at most ``_WRAP_TOL``.
    Updates ``wrap`` (4, N_t) = (theta, its value at this edge, its rate rad/m; the tensions: read),
    ``frames`` (2, N_t, 3) = (tangents here, at the last edge) and ``rot_prev`` (3, 3).
    Returns (converged, residual) of the last :func:`_stage`."""
    theta, theta_edge, rate, tau_base = wrap[0], wrap[1], wrap[2], wrap[3]
    tangents, tangents_prev = frames[0], frames[1]
    rot = state[1]
    n_t = capstan.shape[0]
    _predict_wraps(theta, rate, h_prev, theta_edge)  # corrected below
    c, r = False, np.inf
    for _ in range(_MAX_WRAP_CORRECTIONS + 1):
        for i in range(n_t):
            tau_step[i] = tau_base[i] * _capstan_gain(capstan[i], theta_edge[i])
        c, r = _stage(s0, state, x, want_var, rod, tau_step, force, tols, ws, deriv)
        _unit_tangents(x, ws[0], ws[1], tangents)
        if first:
            break
        for a in range(3):  # R_prev^T R: the frames' relative rotation
            for b in range(3):
                turn[a, b] = rot_prev[0, a] * rot[0, b] + rot_prev[1, a] * rot[1, b] + rot_prev[2, a] * rot[2, b]
        if _correct_wraps(theta, tangents_prev, tangents, turn, capstan, tau_base, theta_edge) <= _WRAP_TOL:
            break
    _accept_wraps(theta, rate, h_prev, theta_edge)
    tangents_prev[:, :] = tangents
    rot_prev[:, :] = rot
    return c, r


@njit(cache=True, error_model="numpy")
def _shoot_pass(m0, n_start, edges, rod, capstan, f_g, tols, want_var, shortcut, record, jac_out, lengths):
    """One RK4 integration of the :class:`Rod` ``rod`` under the weight per length ``f_g`` (3,) N/m
    from M(0) = ``m0`` and N(0) = ``n_start`` over ``edges`` (fractions of
    L; a tendon end is a zero-width step, :func:`_with_ends`), N' = -f_g between ends and, with
    ``shortcut``, the jump of :func:`_jump` at each.  Writes the tip moment's Jacobian
    dM(L)/dM(0) into ``jac_out`` (3, 3) (if ``want_var``) and, ``record`` = (out_step (n,), pos (n, 3),
    rot (n, 3, 3), x (n, 6), gain (n, N_t)), poses, strains and the tendons' friction gains exp(capstan_i
    theta_i) at the edges ``out_step`` (entries < 0 skipped).

    With friction (``capstan`` (N_t,), eq. CAP) each tendon pulls with tau_i exp(capstan_i theta_i(s))
    in the local equations (W1, W2); the totals N, M are those of rod and tendons together, which
    friction (internal to them) leaves alone.  The wrap angle theta_i is summed edge to edge from the
    angle between the tendon's unit tangents (:func:`_wrap_angle`, the frames' relative rotation
    R_k^T R_k+1 taken from the state; a tendon end's kink is a zero-width step).  An edge's strains
    start from the angle predicted by the last step's rate and are solved again until the corrected
    angle moves the gains by at most ``_WRAP_TOL``; a step's inner stages take the angle on that rate.
    The variational equations hold the gains fixed (a chord Jacobian for the shooting).  With ``lengths`` of
    size N_t (else empty), the tendons' path lengths int |g_i| ds, m, integrated as one more state by the same RK4
    stages.
    Returns (M(L) (3,), N(L) (3,), converged, residual)."""
    length, tau, end, kse, kbt = rod.length, rod.tension, rod.end, rod.kse, rod.kbt
    out_step, pos_out, rot_out, x_out, gain_out = record
    n_t = rod.offset.shape[0]
    friction = has_friction(capstan)
    n_f = n_t if friction else 0  # the friction state's size (none without friction)
    wrap = np.zeros((4, n_f))  # theta (rad), its prediction at the edge, its rate (rad/m), the tensions
    tau_base = wrap[3]  # the tensions where they act, before the gains
    frames = np.zeros((2, n_f, 3))  # the tendons' unit tangents at this edge and the last
    rot_prev, turn = np.eye(3), np.empty((3, 3))
    h_prev = 0.0
    ws = (np.empty((n_t, 2)), np.empty((n_t, 2)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)),
          np.empty(6), np.empty(6), np.empty(6))
    p, rot, mom = np.zeros(3), np.eye(3), m0.copy()
    force = n_start.copy()
    f_stage = np.empty(3)
    tau_step, tau_right = np.empty(n_t), np.empty(n_t)
    dp, drot, dmom = np.zeros((3, 3)), np.zeros((3, 3, 3)), np.zeros((3, 3))
    for q in range(3):
        dmom[q, q] = 1.0
    x = np.zeros(6)
    x[2] = 1.0
    xs = np.empty(6)
    f = [(np.empty(3), np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((3, 3)))
         for _ in range(4)]
    tp, trot, tmom = np.empty(3), np.empty((3, 3)), np.empty(3)
    tdp, tdrot, tdmom = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty((3, 3))
    ok = True
    worst = 0.0
    n_out = out_step.shape[0]
    k_steps = edges.shape[0] - 1
    want_len = lengths.shape[0] > 0
    stretch = np.zeros((4, n_t))
    for i in range(lengths.shape[0]):
        lengths[i] = 0.0
    for k in range(k_steps + 1):
        s0 = edges[k] * length
        # stage 1 (also the strains at the edge, for the outputs)
        if friction:
            _active_tensions(tau, end, _step_act(edges, k), tau_base)
            c, r = _edge_with_friction(k == 0, s0, (p, rot, mom, dp, drot, dmom), x, want_var, rod, capstan, tau_step,
                                       force, tols, ws, f[0], wrap, frames, rot_prev, turn, h_prev)
        else:
            _active_tensions(tau, end, _step_act(edges, k), tau_step)
            c, r = _stage(s0, (p, rot, mom, dp, drot, dmom), x, want_var, rod, tau_step, force, tols, ws, f[0])
        ok = ok and c
        if not (r <= worst):
            worst = r
        if want_len:
            _stage_stretch(x, ws[0], ws[1], end, _step_act(edges, k), stretch[0])
        for j in range(n_out):
            if out_step[j] == k:
                pos_out[j, :] = p
                rot_out[j, :, :] = rot
                x_out[j, :] = x
                if friction:
                    _gained(np.ones(n_t), capstan, wrap, 0.0, gain_out[j])
        if k == k_steps:
            break
        h = (edges[k + 1] - edges[k]) * length
        h_prev = h
        if h == 0.0:  # a tendon end: the totals are continuous, or jump by Rucker & Webster's rule
            if shortcut and k > 0 and edges[k] > edges[k - 1]:
                _active_tensions(tau, end, edges[k], tau_right)
                _jump(x, rot, mom, force, ws[0], ws[1], tau_right, kse, kbt, ws[5])
            continue
        xs[:] = x
        for st in range(1, 4):
            a = 0.5 * h if st < 3 else h
            prev = f[st - 1]
            for i in range(3):
                tp[i] = p[i] + a * prev[0][i]
                tmom[i] = mom[i] + a * prev[2][i]
                f_stage[i] = force[i] - a * f_g[i]
                for j2 in range(3):
                    trot[i, j2] = rot[i, j2] + a * prev[1][i, j2]
            if want_var:
                for q in range(3):
                    for i in range(3):
                        tdp[q, i] = dp[q, i] + a * prev[3][q, i]
                        tdmom[q, i] = dmom[q, i] + a * prev[5][q, i]
                        for j2 in range(3):
                            tdrot[q, i, j2] = drot[q, i, j2] + a * prev[4][q, i, j2]
            cur = f[st]
            if friction:
                _gained(tau_base, capstan, wrap, a, tau_step)
            c, r = _stage(s0 + a, (tp, trot, tmom, tdp, tdrot, tdmom), xs, want_var, rod, tau_step, f_stage, tols,
                          ws, cur)
            ok = ok and c
            if not (r <= worst):
                worst = r
            if want_len:
                _stage_stretch(xs, ws[0], ws[1], end, _step_act(edges, k), stretch[st])
        w6 = h / 6.0
        for i in range(lengths.shape[0]):
            lengths[i] += w6 * (stretch[0, i] + 2.0 * stretch[1, i] + 2.0 * stretch[2, i] + stretch[3, i])
        for i in range(3):
            p[i] += w6 * (f[0][0][i] + 2.0 * f[1][0][i] + 2.0 * f[2][0][i] + f[3][0][i])
            mom[i] += w6 * (f[0][2][i] + 2.0 * f[1][2][i] + 2.0 * f[2][2][i] + f[3][2][i])
            force[i] -= h * f_g[i]
            for j2 in range(3):
                rot[i, j2] += w6 * (f[0][1][i, j2] + 2.0 * f[1][1][i, j2] + 2.0 * f[2][1][i, j2] + f[3][1][i, j2])
        if want_var:
            for q in range(3):
                for i in range(3):
                    dp[q, i] += w6 * (f[0][3][q, i] + 2.0 * f[1][3][q, i] + 2.0 * f[2][3][q, i] + f[3][3][q, i])
                    dmom[q, i] += w6 * (f[0][5][q, i] + 2.0 * f[1][5][q, i] + 2.0 * f[2][5][q, i] + f[3][5][q, i])
                    for j2 in range(3):
                        drot[q, i, j2] += w6 * (f[0][4][q, i, j2] + 2.0 * f[1][4][q, i, j2]
                                                + 2.0 * f[2][4][q, i, j2] + f[3][4][q, i, j2])
    if want_var:
        for i in range(3):
            for q in range(3):
                jac_out[i, q] = dmom[q, i]
    return mom, force, ok, worst


@njit(cache=True, error_model="numpy")
def _solve3(a, b, out):
    """``out`` = a^-1 b for (3, 3) ``a`` by Cramer's rule; returns det(a)."""
    det = (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]) - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
           + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))
    for c in range(3):
        num = a.copy()
        for i in range(3):
            num[i, c] = b[i]
        out[c] = (num[0, 0] * (num[1, 1] * num[2, 2] - num[1, 2] * num[2, 1])
                  - num[0, 1] * (num[1, 0] * num[2, 2] - num[1, 2] * num[2, 0])
                  + num[0, 2] * (num[1, 0] * num[2, 1] - num[1, 1] * num[2, 0])) / det
    return det


@njit(cache=True, error_model="numpy")
def _solve_dense(a, b, out):
    """``out`` = a^-1 b for a small square ``a`` by Gaussian elimination with partial pivoting;
    returns det(a) (0: singular, ``out`` then not finite)."""
    n = b.shape[0]
    m = a.copy()
    v = b.copy()
    det = 1.0
    for c in range(n):
        piv = c
        for i in range(c + 1, n):
            if abs(m[i, c]) > abs(m[piv, c]):
                piv = i
        if piv != c:
            det = -det
            for j in range(n):
                m[c, j], m[piv, j] = m[piv, j], m[c, j]
            v[c], v[piv] = v[piv], v[c]
        det *= m[c, c]
        for i in range(c + 1, n):
            f = m[i, c] / m[c, c]
            for j in range(c, n):
                m[i, j] -= f * m[c, j]
            v[i] -= f * v[c]
    for i in range(n - 1, -1, -1):
        acc = v[i]
        for j in range(i + 1, n):
            acc -= m[i, j] * out[j]
        out[i] = acc / m[i, i]
    return det


@njit(cache=True, error_model="numpy")
def _shoot_residual(y, lam, edges, rod, capstan, load, tols, record, jac, resid):
    """One pass of :func:`_shoot_pass` (``tols.shortcut``: Rucker & Webster's rule) from the unknowns
    ``y`` = (N(0), M(0)) (6,), the :class:`Load` ``load`` scaled by ``lam``: the tip
    conditions' mismatch into ``resid`` (6,) = (L (N(L) - F_tip), M(L) - M_tip), N m.  Without
    ``shortcut`` N(0) is known (F_tip + f_g L, written into ``y``) and ``jac`` receives dM(L)/dM(0)
    from the variational equations.  Returns (converged, largest local residual)."""
    length, f_g, f_tip, m_tip, shortcut = rod.length, load.f_g, load.f_tip, load.m_tip, tols.shortcut
    fg = lam * f_g
    if not shortcut:
        for i in range(3):
            y[i] = lam * (f_tip[i] + f_g[i] * length)
    mom, force, ok, worst = _shoot_pass(y[3:], y[:3], edges, rod, capstan, fg, tols, not shortcut, shortcut, record,
                                        jac, np.empty(0))
    for i in range(3):
        resid[i] = length * (force[i] - lam * f_tip[i])
        resid[3 + i] = mom[i] - lam * m_tip[i]
    return ok, worst


@njit(cache=True, error_model="numpy")
def _shoot(y, lam, edges, rod, capstan, load, tols, scale, record, info, jac, max_passes):
    """Newton on the tip conditions of the :class:`Rod` ``rod`` for the unknowns ``y`` = (N(0), M(0))
    (in place), the :class:`Load` ``load`` scaled by ``lam``, with backtracking when a step does not reduce the
    mismatch.  Consistent termination: N(0) is known, M(0) alone is shot with the variational Jacobian dM(L)/dM(0);
    Rucker & Webster's rule (``shortcut``): the jumps at the ends make N(0) unknown too, and the
    6 x 6 Jacobian comes from one-sided differences (6 more passes).  Every pass
    records the poses and strains into ``record`` (:func:`_shoot_pass`), so on success they are those
    of the result; ``info`` (3,) receives the mismatch (N m), the pass's local flag (1/0) and its
    largest local residual (N), ``jac`` (3, 3) dM(L)/dM(0) of the last pass; at most ``max_passes``
    passes, backtracks included.  Returns (converged, passes, det of the shooting Jacobian)."""
    length, shortcut, shoot_tol, max_shoot = rod.length, tols.shortcut, tols.shooting_tol, max_passes
    out_step, pos, rot, x, gain = record
    first = 0 if shortcut else 3
    step, y_prev = np.zeros(6), y.copy()
    resid, r_q, y_q = np.empty(6), np.empty(6), np.empty(6)
    full = np.empty((6, 6))
    none = np.full(out_step.shape[0], -1, dtype=np.int64)
    err_prev, alpha, det = np.inf, 1.0, np.nan
    passes = 0
    for it in range(max_shoot):
        ok, worst = _shoot_residual(y, lam, edges, rod, capstan, load, tols, record, jac, resid)
        passes += 1
        err = 0.0
        for i in range(first, 6):
            err += resid[i] ** 2
        err = math.sqrt(err)
        info[0], info[1], info[2] = err, 1.0 if ok else 0.0, worst
        if not ok or not (err < err_prev) and it > 0:  # backtrack from the last accepted point
            alpha *= 0.5
            if alpha < 1.0 / 256.0:
                return False, passes, det
            for i in range(first, 6):
                y[i] = y_prev[i] - alpha * step[i]
            continue
        if shortcut:  # the 6 x 6 Jacobian by one-sided differences
            for q in range(6):
                delta = 1e-7 * (scale / length if q < 3 else scale) + 1e-14
                y_q[:] = y
                y_q[q] += delta
                _shoot_residual(y_q, lam, edges, rod, capstan, load, tols, (none, pos, rot, x, gain), jac, r_q)
                for i in range(6):
                    full[i, q] = (r_q[i] - resid[i]) / delta
            passes += 6
            for i in range(3):
                for q in range(3):
                    jac[i, q] = full[3 + i, 3 + q]
            det = _solve_dense(full, resid, step)
        else:
            sub = np.empty(3)
            det = _solve3(jac, resid[3:], sub)
            step[3:] = sub
        if err <= shoot_tol * scale:
            return True, passes, det
        y_prev[:] = y
        err_prev, alpha = err, 1.0
        for i in range(first, 6):
            y[i] -= step[i]
    return False, passes, det


@njit(cache=True, error_model="numpy")
def _loaded_outputs(out_step, rho_out, pos, rot, tendons):
    """Tendon positions at the outputs from the recorded poses, the frames first projected back
    onto SO(3) (two Newton-Schulz steps; RK4 leaves them off by O(h^5))."""
    for j in range(out_step.shape[0]):
        if out_step[j] < 0:
            continue
        for _ in range(2):  # R <- 1.5 R - 0.5 R R^T R
            r = rot[j].copy()
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for c in range(3):
                        rrt = r[a, 0] * r[c, 0] + r[a, 1] * r[c, 1] + r[a, 2] * r[c, 2]
                        acc += rrt * r[c, b]
                    rot[j, a, b] = 1.5 * r[a, b] - 0.5 * acc
    _tendon_positions(pos, rot, rho_out, tendons)


@njit(cache=True, error_model="numpy")
def _masked_richardson(fine, coarse, out_step):
    diff, norm = 0.0, 0.0
    for j in range(fine.shape[0]):
        if out_step[j] < 0:
            continue
        for i in range(fine.shape[1]):
            for a in range(3):
                diff += (fine[j, i, a] - coarse[j, i, a]) ** 2
                norm += fine[j, i, a] ** 2
    return math.sqrt(diff / norm) / 15.0 if norm > 0.0 else math.sqrt(diff) / 15.0


#: a warm start's shooting passes at most; one that needs more is not near and gives way to the cold
#: first guess.  FTDCR v4 (fitted) in gravity: warm solves take 5 passes in all at the median (the
#: coarse grid's estimate included; cold: 7 and the first guess's pass); v6 upright, near buckling:
#: warm starts allowed the full max_shooting made its loaded displacement solves 1.5x slower
LOADED_WARM_PASSES = 5


@njit(cache=True, error_model="numpy")
def solve_loaded_design(rod, capstan, load, grid, tols, view, shoot_jac, m0_start):
    """One design, the :class:`Rod` ``rod`` with its tendons' ``capstan`` (N_t,) (eq. CAP), under its
    :class:`Load` ``load``: distributed weight
    ``f_g`` (N/m, base frame) and tip loads ``f_tip`` (N), ``m_tip`` (N m), on the :class:`Grid` ``grid`` (its edges
    must end at 1: the tip condition) with every tendon end added (:func:`_with_ends`); with ``tols.shortcut`` Rucker &
    Webster's rule at
    the ends (:func:`_jump`).  ``shoot_jac`` (3, 3) receives the shooting Jacobian dM(L)/dM(0) at the
    result (the identity for the unloaded rod; the caller judges several equilibria from it).  With
    ``tols.warm`` the shooting starts from ``m0_start`` (3,) N m where finite (a nearby solve's M(0),
    at most :data:`LOADED_WARM_PASSES` passes), else from the loads' moment about the base on the
    tendon-only shape, with load continuation where that fails.
    Writes backbone, frames, strains, tendons and displacements into the :class:`DesignShapes` ``view``.
    Returns (status, residual N, shooting passes, level, error estimate, M(0) x 3)."""
    length, offset, pitch, angle, tau, end = rod.length, rod.offset, rod.pitch, rod.angle, rod.tension, rod.end
    f_g, f_tip, m_tip = load.f_g, load.f_tip, load.m_tip
    pos_out, rot_out, x_out, tendons_out, displacement_out = (view.backbone, view.rotation, view.strains,
                                                              view.tendons, view.displacement)
    fractions_out = grid.fractions
    edges0, out_step0, end_step = _with_ends(grid.edges, grid.out_step, end)
    step_tol, max_level = tols.step_tol, tols.max_level
    scale = 0.0
    for i in range(offset.shape[0]):
        scale += tau[i] * offset[i]
    scale += (math.sqrt(m_tip[0] ** 2 + m_tip[1] ** 2 + m_tip[2] ** 2)
              + math.sqrt(f_tip[0] ** 2 + f_tip[1] ** 2 + f_tip[2] ** 2) * length
              + math.sqrt(f_g[0] ** 2 + f_g[1] ** 2 + f_g[2] ** 2) * length * length + 1e-12)
    n_out, n_t = fractions_out.shape[0], offset.shape[0]
    # the outputs and, after them, the tendons' ends (their termination points)
    n_ext = n_out + n_t
    steps0 = np.concatenate((out_step0, end_step))
    pos, rot, xo, gain = np.zeros((n_ext, 3)), np.zeros((n_ext, 3, 3)), np.zeros((n_ext, 6)), np.ones((n_ext, n_t))
    rho_out = _output_offsets(fractions_out, length, offset, pitch, angle)
    k0 = edges0.shape[0] - 1
    info, jac, y = np.empty(3), np.empty((3, 3)), np.zeros(6)
    for i in range(3):
        y[i] = f_tip[i] + f_g[i] * length
    ok, passes, det = False, 0, np.nan
    if tols.warm and m0_start[0] == m0_start[0] and m0_start[1] == m0_start[1] and m0_start[2] == m0_start[2]:
        y[3], y[4], y[5] = m0_start[0], m0_start[1], m0_start[2]  # a nearby solve's M(0)
        ok, passes, det = _shoot(y, 1.0, edges0, rod, capstan, load, tols, scale, (steps0, pos, rot, xo, gain), info,
                                 shoot_jac, min(LOADED_WARM_PASSES, tols.max_shooting))
    none = np.full(n_ext, -1, dtype=np.int64)  # continuation steps record nothing
    if not ok:
        # first guess: the loads' moment about the base on the tendon-only shape (its tip from one pass)
        tip_step = np.array([k0], dtype=np.int64)
        tip_p, tip_r, tip_x, tip_g = np.empty((1, 3)), np.empty((1, 3, 3)), np.empty((1, 6)), np.empty((1, n_t))
        zero3 = np.zeros(3)
        # bool(False), not False: numba would compile another _shoot_pass (and its stages) for a literal
        _shoot_pass(zero3.copy(), zero3.copy(), edges0, rod, capstan, zero3, tols, bool(False), bool(False),  # noqa: UP018
                    (tip_step, tip_p, tip_r, tip_x, tip_g), jac, np.empty(0))
        tip, half = tip_p[0], 0.5 * length
        y[3] = tip[1] * f_tip[2] - tip[2] * f_tip[1] + m_tip[0] + half * (tip[1] * f_g[2] - tip[2] * f_g[1])
        y[4] = tip[2] * f_tip[0] - tip[0] * f_tip[2] + m_tip[1] + half * (tip[2] * f_g[0] - tip[0] * f_g[2])
        y[5] = tip[0] * f_tip[1] - tip[1] * f_tip[0] + m_tip[2] + half * (tip[0] * f_g[1] - tip[1] * f_g[0])
        start = y.copy()
        ok, used, det = _shoot(y, 1.0, edges0, rod, capstan, load, tols, scale, (steps0, pos, rot, xo, gain), info,
                               shoot_jac, tols.max_shooting)
        passes += used
        for n_steps in (4, 16):  # load continuation from the tendon-only state when the direct Newton fails
            if ok:
                break
            y[:] = 0.0
            for k in range(1, n_steps + 1):
                for i in range(6):
                    y[i] += start[i] / n_steps  # predictor: the first guess scales with the loads
                ok, used, det = _shoot(y, k / n_steps, edges0, rod, capstan, load, tols, scale,
                                       (steps0 if k == n_steps else none, pos, rot, xo, gain), info, shoot_jac,
                                       tols.max_shooting)
                passes += used
                if not ok:
                    break
    _loaded_outputs(out_step0, rho_out, pos[:n_out], rot[:n_out], tendons_out)
    mismatch, local_ok, worst = info[0], info[1] > 0.0, info[2]
    # the free estimate: the coarse grid joins pairs of equal steps (as the tendon-only kernel)
    c_idx = np.empty(k0 + 1, dtype=np.int64)
    to_coarse = np.full(k0 + 1, -1, dtype=np.int64)
    c_idx[0], to_coarse[0], kc, k = 0, 0, 0, 0
    while k < k0:
        w0 = edges0[k + 1] - edges0[k]
        if k + 1 < k0 and abs((edges0[k + 2] - edges0[k + 1]) - w0) <= 1e-12 * w0:
            k += 2
        else:
            k += 1
        kc += 1
        c_idx[kc], to_coarse[k] = k, kc
    c_edges = edges0[c_idx[:kc + 1]]
    c_out = np.empty(n_out, dtype=np.int64)
    for j in range(n_out):
        c_out[j] = to_coarse[out_step0[j]]
    c_pos, c_rot, c_x, c_gain, coarse = (np.zeros((n_out, 3)), np.zeros((n_out, 3, 3)), np.zeros((n_out, 6)),
                                         np.ones((n_out, n_t)), np.zeros((n_out, n_t, 3)))
    c_y = y.copy()
    c_info = np.empty(3)
    c_ok, used, _ = _shoot(c_y, 1.0, c_edges, rod, capstan, load, tols, scale, (c_out, c_pos, c_rot, c_x, c_gain),
                           c_info, jac, tols.max_shooting)
    passes += used
    _loaded_outputs(c_out, rho_out, c_pos, c_rot, coarse)
    estimate = _masked_richardson(tendons_out, coarse, c_out) if c_ok else np.inf
    level = 0
    edges, steps = edges0, steps0.copy()
    prev = tendons_out.copy()
    while ok and level < max_level and not (estimate <= step_tol):
        level += 1
        finer = np.empty(2 * edges.shape[0] - 1)
        for k in range(edges.shape[0] - 1):
            finer[2 * k] = edges[k]
            finer[2 * k + 1] = 0.5 * (edges[k] + edges[k + 1])
        finer[-1] = edges[-1]
        edges = finer
        steps = np.where(steps >= 0, steps * 2, steps)
        ok, used, det = _shoot(y, 1.0, edges, rod, capstan, load, tols, scale, (steps, pos, rot, xo, gain), info,
                               shoot_jac, tols.max_shooting)
        passes += used
        _loaded_outputs(steps[:n_out], rho_out, pos[:n_out], rot[:n_out], tendons_out)
        mismatch, local_ok, worst = info[0], info[1] > 0.0, info[2]
        estimate = _masked_richardson(tendons_out, prev, steps[:n_out])
        prev[:, :, :] = tendons_out
    pos_out[:, :] = pos[:n_out]
    rot_out[:, :, :] = rot[:n_out]
    x_out[:, :] = xo[:n_out]
    # the path lengths on the final grid: one more pass from the result, recording nothing (bool(): as above)
    _shoot_pass(y[3:].copy(), y[:3].copy(), edges, rod, capstan, f_g, tols, bool(False), tols.shortcut,  # noqa: UP018
                (none, pos, rot, xo, gain), jac, displacement_out)
    for i in range(n_t):
        displacement_out[i] = undeformed_length(length, offset[i], pitch[i], end[i]) - displacement_out[i]
    terminal = np.zeros((n_t, 3))
    _end_points(pos[n_out:], rot[n_out:], length, end_step, end, offset, pitch, angle, terminal)
    _clamp_ended(fractions_out, end, terminal, tendons_out)
    for j in range(n_out):  # each tendon pulls with tau_i exp(capstan_i theta_i) up to its end (eq. CAP)
        for i in range(n_t):
            view.profile[j, i] = tau[i] * gain[j, i] if end[i] >= fractions_out[j] else 0.0
    tip_residual = mismatch / length
    residual = worst if worst > tip_residual else tip_residual
    if not _all_finite(residual, tendons_out):
        status = NOT_FINITE
    elif not ok:
        status = SHOOTING_FAILED
    elif not local_ok:
        status = NEWTON_FAILED
    elif not (estimate <= step_tol):
        status = STEP_TOL_NOT_MET
    else:
        status = OK
    return status, residual, passes, level, estimate, y[3], y[4], y[5]


@njit(cache=True, error_model="numpy", nogil=True)
def solve_loaded_batch(rods, loads, grid, tols, out):
    """:func:`solve_loaded_design` for every design of :class:`Rods` ``rods`` under :class:`Loads`
    ``loads``, without the GIL (:func:`tdcr.physics.cosserat._run_kernel` runs chunks side by side),
    into the :class:`Shapes` ``out`` (``iterations``: passes; ``m0`` read first with ``tols.warm``)."""
    for b in range(rods.length.shape[0]):
        res = solve_loaded_design(_rod(rods, b), rods.capstan[b], _load(loads, b), grid, tols, _design_shapes(out, b),
                                  out.shoot_jac[b], out.m0[b])
        _store_summary(out, b, res)
        m0 = out.m0[b]
        m0[0], m0[1], m0[2] = res[5], res[6], res[7]
