"""Batched static Cosserat-rod solver for single-segment TDCRs (Rucker & Webster 2011).

Conventions (identical to ``shared/reference/cosserat_cases.json``): base at the
origin with R(0) = I and the undeformed backbone along +z; tendon i at body-frame
angle 2 pi i / N_t + pitch_i s with its own offset; tendons terminate at the tip;
G = E / (2 (1 + nu)) with nu = POISSON_RATIO = 0.3, A = pi r^2, I = pi r^4 / 4, J = 2 I,
K_se = diag(G A, G A, E A), K_bt = diag(E I, E I, G J), undeformed strains
nu* = e3, kappa* = 0.

Method.  Cut the rod *and* its tendons at s.  The tendons pull the part [s, L]
with -tau_i t_i(s) at p_i(s), so the balance of [s, L] gives, in the body frame,

    K_se (nu - e3) + sum_i tau_i t_i = R^T N(s)                      (eq. W1)
    K_bt kappa + sum_i tau_i rho_i x t_i = R^T M(s)                  (eq. W2)

with t_i = g_i / |g_i|, g_i = nu + kappa x rho_i + rho_i'  (Rucker & Webster eq. 8),
N(s) = F_tip + f_g (L - s) and M(s) the total moment of tip and distributed loads
about p(s).  Without external loads N = M = 0 and (W1, W2) is a 6-unknown algebraic
equation at each s: it is the gradient of the strictly convex potential

    Phi(nu, kappa) = 1/2 (nu-e3)^T K_se (nu-e3) + 1/2 kappa^T K_bt kappa + sum_i tau_i |g_i|   (eq. PHI)

(elastic energy plus the work of the tendons), so its root is unique and Newton
with an Armijo line search on Phi finds it from the undeformed strains.  The
strains at the ends and middle of each step feed a fourth-order Magnus integrator on SE(3)
(eq. MAG), which keeps R(s) in SO(3) to round-off.

With external loads, M(s) depends on the unknown shape: the solver shoots on
M(0) (3 unknowns) with RK4 on (p, R, M), M' = -p' x N (eq. MT), the local
strains again from (W1, W2), the shooting Jacobian from the variational
equations, and load continuation only when the direct Newton fails.

Where each runs.  The compiled kernels (:mod:`tdcr.physics._kernel`, numba) are the solver:
tendon loads and external loads, each with the step chosen per design from a Richardson
estimate (``SolverOptions.step_tol``).  This module adds what the kernels do not do, on a
vectorised numpy path of the tendon-only method: the exact Jacobian to the tensions
(``jacobian=True``: the implicit-function theorem at every node and a tangent carried through the
Magnus steps), the linearised reference robot (``SolverOptions.linearized``) and the warm-started
tip solves of inverse kinematics (:class:`TipSolver`).  It shares the kernels' constants
(:func:`material`), status codes (:class:`tdcr.physics.status.Status`) and post-processing
(:func:`internal_wrench`); tests/test_kernel.py checks that both give the same shapes.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import numpy as np

from tdcr.designs import DEFAULT_POISSON, DesignBatch, ExternalLoads
from tdcr.physics._lie import hat, se3_bracket, se3_exp
from tdcr.physics.status import STATUS, Status

#: The Poisson ratio of a design that gives none (:data:`tdcr.designs.DEFAULT_POISSON`).
POISSON_RATIO = DEFAULT_POISSON
#: How a tendon that ends before the tip loads the rod (``solve(..., termination=)``).
TERMINATIONS = ("exact", "rucker_webster")
_E3 = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class SolverOptions:
    """Numerical settings of :func:`solve`.

    Attributes:
        max_step: largest Magnus step as a fraction of L (tendon-only loads).
        max_step_loads: largest RK4 step as a fraction of L (with external loads).
        newton_tol: Newton stops after a full step whose scaled size |d nu| + r |d kappa| is
            below sqrt(newton_tol), which leaves an error of order newton_tol.
        max_newton: Newton iterations per collocation node.
        shooting_tol: tip-moment tolerance of the shooting method, as a fraction of a
            reference moment (sum of tension x offset + |M_tip| + |F_tip| L + |f_g| L^2).
        max_shooting: shooting iterations per load step.
        residual_tol: a design whose wrench residual (N) exceeds this times its load
            scale is reported as not converged.
        step_tol: per-design step control: the largest accepted estimate of the
            relative l2 error of the tendon positions at the outputs due to the integration step
            (Richardson, see :func:`solve`); a design whose estimate stays above it after
            ``max_level`` halvings of the step is flagged (status ``step_tol_not_met``).
        max_level: how many times the step may be halved per design.
        linearized: replace the local Newton solve by the first-order strains (the roots of
            (W1, W2) with the tendon tangents of the undeformed rod; the neural operators'
            reference robot).  Tendon loads only; ``converged`` then only flags non-finite
            results and ``residual`` says how far from equilibrium the result is.
    """

    max_step: float = 1.0 / 41.0
    max_step_loads: float = 1.0 / 100.0
    newton_tol: float = 1e-13
    max_newton: int = 60
    shooting_tol: float = 1e-11
    max_shooting: int = 20
    residual_tol: float = 1e-8
    step_tol: float = 3e-7
    max_level: int = 4
    linearized: bool = False


@dataclass(frozen=True)
class RodSolution:
    """Equilibria of a batch of ``B`` designs at ``n`` arclengths.

    Attributes:
        s: arclengths, m, ``(B, n)``.
        backbone: backbone positions p(s), m, ``(B, n, 3)``.
        rotation: frames R(s), body axes as columns, ``(B, n, 3, 3)``.
        tendons: tendon positions p + R rho_i, m, ``(B, n, N_t, 3)``.
        force: internal force n(s) of the rod, base frame, N, ``(B, n, 3)``.
        moment: internal moment m(s) of the rod, base frame, N m, ``(B, n, 3)``.
        converged: per-design success flag, ``(B,)``.
        residual: per-design wrench-balance residual, N (moments divided by L), ``(B,)``.
        iterations: per-design Newton (tendon-only) or shooting iterations, ``(B,)``.
        status: per-design outcome ``(B,)``, a :class:`tdcr.physics.status.Status` code (names in
            :data:`STATUS`): 0 converged, 1 Newton failed, 2 not finite, 3 step tolerance not met,
            4 residual above tolerance, 5 shooting failed (loads), 6 several equilibria (loads:
            the shooting Jacobian dM(L)/dM(0), the identity without loads, has a real eigenvalue
            <= 0 at the result, so one crossed zero as the loads grew: a fold or a bifurcation,
            e.g. Euler buckling).
        error_estimate: per-design estimate of the relative l2 error of the tendon positions due
            to the integration step, ``(B,)`` (NaN where not estimated: linearized, tip solves).
        steps: integration steps per design along [0, L], ``(B,)``.
        jacobian: with ``solve(..., jacobian=True)``, the sensitivity of the pose at each
            arclength to the tensions, base frame, ``(B, n, 6, N_t)``: rows 0-2 d p / d tau (m/N),
            rows 3-5 the rotation vector of d R R^T / d tau (rad/N); else ``None``.
        tension: every tendon's tension, N, ``(B, N_t)``: as given, or found for a displacement.
        displacement: every tendon's displacement (length pulled in), m, ``(B, N_t)``: its path
            length on the straight rod minus its path length int_0^end |g_i| ds at the equilibrium.
        slack: ``(B, N_t)``: a displacement-driven tendon that would need a push to reach its
            displacement, so hangs slack at tension 0 (None: no tendon is displacement-driven).
    """

    s: np.ndarray
    backbone: np.ndarray
    rotation: np.ndarray
    tendons: np.ndarray
    force: np.ndarray
    moment: np.ndarray
    converged: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    jacobian: np.ndarray | None = None
    status: np.ndarray | None = None
    error_estimate: np.ndarray | None = None
    steps: np.ndarray | None = None
    tension: np.ndarray | None = None
    displacement: np.ndarray | None = None
    slack: np.ndarray | None = None


__all__ = ["POISSON_RATIO", "STATUS", "TERMINATIONS", "RodSolution", "SolverOptions", "Status", "TipSolver",
           "body_strains",
           "internal_wrench", "material", "solve", "tendon_routing"]


@dataclass(frozen=True)
class _Material:
    kse: np.ndarray  # (B, 3) N
    kbt: np.ndarray  # (B, 3) N m^2
    area: np.ndarray  # (B,) m^2


def material(designs: DesignBatch) -> _Material:
    """Stiffnesses K_se (N) and K_bt (N m^2) as diagonals, ``(B, 3)`` each: the one place of the
    material law, G = E / (2 (1 + nu)) with each design's Poisson ratio nu (default
    :data:`POISSON_RATIO`), for every path (the kernels receive these)."""
    g = designs.E / (2.0 * (1.0 + designs.poissons))
    area = np.pi * designs.r**2
    inertia = np.pi * designs.r**4 / 4.0
    kse = np.stack([g * area, g * area, designs.E * area], axis=-1)
    kbt = np.stack([designs.E * inertia, designs.E * inertia, g * 2.0 * inertia], axis=-1)
    return _Material(kse=kse, kbt=kbt, area=area)


def internal_wrench(rotation: np.ndarray, strains: np.ndarray, mat: _Material) -> tuple[np.ndarray, np.ndarray]:
    """The rod's internal force n = R K_se (nu - e3) (N) and moment m = R K_bt kappa (N m), base
    frame, ``(B, n, 3)`` each, from frames ``(B, n, 3, 3)`` and body strains ``(B, n, 6)``."""
    force = np.einsum("bnij,bnj->bni", rotation, mat.kse[:, None, :] * (strains[..., :3] - _E3))
    moment = np.einsum("bnij,bnj->bni", rotation, mat.kbt[:, None, :] * strains[..., 3:])
    return force, moment


def tendon_routing(
    designs: DesignBatch, fractions: np.ndarray, *, derivative: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Body-frame tendon offsets rho_i(s) and their arclength derivatives.

    rho_i(s) = offset_i [cos(angle_i + pitch_i s), sin(...), 0] (default angle_i = 2 pi i / N_t).

    Args:
        designs: ``B`` designs with ``N_t`` tendons.
        fractions: arclength fractions s / L, ``(M,)``.
        derivative: also return drho / ds (else ``None``).

    Returns:
        ``(rho, drho)``, m and m/m, each ``(B, M, N_t, 3)``.
    """
    s = designs.L[:, None] * fractions[None, :]  # (B, M)
    phi = designs.angles[:, None, :] + designs.pitch[:, None, :] * s[:, :, None]  # (B, M, N_t)
    off = designs.offset[:, None, :]
    cos, sin = np.cos(phi), np.sin(phi)
    zeros = np.zeros_like(phi)
    rho = off[..., None] * np.stack([cos, sin, zeros], axis=-1)
    if not derivative:
        return rho, None
    drho = (off * designs.pitch[:, None, :])[..., None] * np.stack([-sin, cos, zeros], axis=-1)
    return rho, drho


# --------------------------------------------------------------------------- local equation


@dataclass
class _Nodes:
    """Flattened collocation data for P = B * M nodes."""

    rho: np.ndarray  # (P, N_t, 3)
    drho: np.ndarray  # (P, N_t, 3)
    tau: np.ndarray  # (P, N_t)
    kse: np.ndarray  # (P, 3)
    kbt: np.ndarray  # (P, 3)
    radius: np.ndarray  # (P,)
    target: np.ndarray | None  # (P, 6) body-frame (R^T N, R^T M) or None for zero
    active: np.ndarray | None = None  # (P, N_t): the tendon acts at the node (None: all do)

    def take(self, idx: np.ndarray) -> _Nodes:
        return _Nodes(
            self.rho[idx], self.drho[idx], self.tau[idx], self.kse[idx], self.kbt[idx],
            self.radius[idx], None if self.target is None else self.target[idx],
            None if self.active is None else self.active[idx],
        )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (faster than np.cross for small trailing axes)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _tendon_directions(x: np.ndarray, nodes: _Nodes) -> tuple[np.ndarray, np.ndarray]:
    """Unit tendon tangents t_i (body frame) and |g_i|, ``(P, N_t, 3)`` and ``(P, N_t)``."""
    g = x[:, None, :3] + _cross(x[:, None, 3:], nodes.rho) + nodes.drho
    gn = np.sqrt(np.einsum("pij,pij->pi", g, g))
    return g / gn[..., None], gn


def _potential(x: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """Phi of eq. (PHI) minus target . x, ``(P,)``."""
    _, gn = _tendon_directions(x, nodes)
    d_nu = x[:, :3] - _E3
    phi = 0.5 * np.einsum("pi,pi->p", nodes.kse * d_nu, d_nu)
    phi += 0.5 * np.einsum("pi,pi->p", nodes.kbt * x[:, 3:], x[:, 3:])
    phi += np.einsum("pi,pi->p", nodes.tau, gn)
    if nodes.target is not None:
        phi -= np.einsum("pi,pi->p", nodes.target, x)
    return phi


def _residual_parts(x: np.ndarray, nodes: _Nodes):
    t, gn = _tendon_directions(x, nodes)
    tau_t = nodes.tau[..., None] * t
    c = _cross(nodes.rho, t)  # rho_i x t_i, (P, N_t, 3)
    f1 = nodes.kse * (x[:, :3] - _E3) + tau_t.sum(axis=1)
    f2 = nodes.kbt * x[:, 3:] + (nodes.tau[..., None] * c).sum(axis=1)
    res = np.concatenate([f1, f2], axis=1)
    if nodes.target is not None:
        res = res - nodes.target
    return res, t, gn, c


def _residual(x: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """Left-hand side minus right-hand side of (W1, W2), N and N m, ``(P, 6)``."""
    return _residual_parts(x, nodes)[0]


def _residual_and_jacobian(x: np.ndarray, nodes: _Nodes) -> tuple[np.ndarray, np.ndarray]:
    """Residual of (W1, W2) ``(P, 6)`` and its Jacobian, the Hessian of Phi ``(P, 6, 6)``."""
    res, jac, _ = _jacobian_parts(x, nodes)
    return res, jac


def _jacobian_parts(x: np.ndarray, nodes: _Nodes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual ``(P, 6)``, Jacobian ``(P, 6, 6)`` and a_i = d residual / d tau_i ``(P, N_t, 6)``.

    With w_i = tau_i / |g_i|, A_i = [I, -hat(rho_i)] and a_i = A_i^T t_i = (t_i, rho_i x t_i):
    J = diag(K_se, K_bt) + sum_i w_i (A_i^T A_i - a_i a_i^T), symmetric positive definite
    because A_i^T (I - t_i t_i^T) A_i is positive semi-definite.
    """
    res, t, gn, c = _residual_parts(x, nodes)
    w = nodes.tau / gn  # (P, N_t)
    a = np.concatenate([t, c], axis=-1)  # (P, N_t, 6)
    jac = -np.matmul(np.swapaxes(w[..., None] * a, 1, 2), a)
    sw = w.sum(axis=1)  # (P,)
    wr = np.einsum("pi,pij->pj", w, nodes.rho)  # sum_i w_i rho_i
    wrr = np.matmul(np.swapaxes(w[..., None] * nodes.rho, 1, 2), nodes.rho)  # sum_i w_i rho_i rho_i^T
    wr2 = np.einsum("pi,pij,pij->p", w, nodes.rho, nodes.rho)  # sum_i w_i |rho_i|^2
    diag = np.arange(3)
    jac[:, diag, diag] += (sw[:, None] + nodes.kse)
    hw = hat(wr)
    jac[:, :3, 3:] -= hw
    jac[:, 3:, :3] += hw
    jac[:, 3:, 3:] -= wrr
    jac[:, diag + 3, diag + 3] += wr2[:, None] + nodes.kbt
    return res, jac, a


def _solve_batched(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``a @ x = b`` for ``(P, k, k)`` systems and ``(P, k)`` or ``(P, k, m)`` right-hand
    sides; NaN rows where a system is not finite or singular, so that one bad design never fails
    the batch."""
    out = np.full(b.shape, np.nan)
    good = np.isfinite(a).all(axis=(1, 2)) & np.isfinite(b.reshape(b.shape[0], -1)).all(axis=1)
    if not good.any():
        return out
    try:
        out[good] = (np.linalg.solve(a[good], b[good]) if b.ndim == 3
                     else np.linalg.solve(a[good], b[good][..., None])[..., 0])
    except np.linalg.LinAlgError:  # a singular system among them: solve one by one (rare)
        for i in np.nonzero(good)[0]:
            try:
                out[i] = np.linalg.solve(a[i], b[i])
            except np.linalg.LinAlgError:
                pass
    return out


def _solve_spd(jac: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``jac @ x = rhs`` for SPD ``(P, 6, 6)`` systems and ``(P, 6)`` or ``(P, 6, m)``
    right-hand sides after symmetric Jacobi scaling (NaN rows where a system is not positive on
    its diagonal, not finite, or singular)."""
    diag = np.einsum("pii->pi", jac)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(diag > 0, 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), np.nan)
    scaled = jac * d[:, :, None] * d[:, None, :]
    dd = d if rhs.ndim == 2 else d[:, :, None]
    return dd * _solve_batched(scaled, dd * rhs)


def _newton(x: np.ndarray, nodes: _Nodes, opts: SolverOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Damped Newton on (W1, W2) for every node, in place on ``x`` ``(P, 6)``.

    Returns ``(x, converged (P,), iterations (P,))``.
    """
    n = x.shape[0]
    iterations = np.zeros(n, dtype=np.int64)
    converged = np.zeros(n, dtype=bool)
    active = np.arange(n)
    sub = nodes
    for _ in range(opts.max_newton):
        xa = x[active]
        res, jac = _residual_and_jacobian(xa, sub)
        step = -_solve_spd(jac, res)
        alpha = np.ones(xa.shape[0])
        big = np.linalg.norm(step[:, :3], axis=1) + sub.radius * np.linalg.norm(step[:, 3:], axis=1) > 1e-3
        if big.any():  # globalise only far from the root; small steps are in Newton's quadratic basin
            alpha[big] = _line_search(xa[big], step[big], res[big], sub.take(big))
        x[active] = xa + alpha[:, None] * step
        iterations[active] += 1
        size = np.linalg.norm(step[:, :3], axis=1) + sub.radius * np.linalg.norm(step[:, 3:], axis=1)
        # a full Newton step of size e leaves an error of order e^2 (quadratic convergence)
        done = (alpha == 1.0) & (size < np.sqrt(opts.newton_tol)) | ~np.isfinite(size)
        converged[active[done]] = np.isfinite(size[done])
        keep = ~done
        if not keep.any():
            break
        active = active[keep]
        sub = sub.take(keep)
    return x, converged, iterations


def _continue_along_s(x: np.ndarray, ok: np.ndarray, iters: np.ndarray, nodes: _Nodes, node_fractions: np.ndarray,
                      x_base: np.ndarray, opts: SolverOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve again, by continuation in s, every design with a node whose Newton failed from the
    base strains: its nodes in order of arclength, each started from the last converged node's
    strains (the compiled kernel's strategy).  Strongly bent designs with helical tendons need it:
    their strains drift far from those at s = 0, where Newton on (W1, W2) is slow to converge.

    ``x`` ``(B m, 6)``, ``ok`` and ``iters`` ``(B m,)`` design-major; ``x_base`` ``(B, 6)``.
    """
    m = node_fractions.shape[0]
    x, ok, iters = x.reshape(-1, m, 6).copy(), ok.reshape(-1, m).copy(), iters.reshape(-1, m).copy()
    redo = np.nonzero(~ok.all(axis=1))[0]
    last = x_base[redo].copy()  # (R, 6): the strains to start the next node from
    for j in np.argsort(node_fractions, kind="stable"):
        xj, okj, itj = _newton(last.copy(), nodes.take(redo * m + j), opts)
        x[redo, j], ok[redo, j] = xj, okj
        iters[redo, j] += itj
        last[okj] = xj[okj]
    return x.reshape(-1, 6), ok.reshape(-1), iters.reshape(-1)


def _first_order_strains(nodes: _Nodes) -> np.ndarray:
    """Strains ``(P, 6)`` solving (W1, W2) with the tendon tangents t_i of the undeformed rod:
    nu = e3 - K_se^-1 sum_i tau_i t_i, kappa = -K_bt^-1 sum_i tau_i rho_i x t_i.  Exact to first
    order in the tensions."""
    x0 = _undeformed(nodes.rho.shape[0])
    # (W1, W2) are K (x - x0) + tendon terms; with the tendon terms frozen at x0: x = x0 - K^-1 res(x0)
    return x0 - _residual(x0, nodes) / np.concatenate([nodes.kse, nodes.kbt], axis=1)


def _line_search(x: np.ndarray, step: np.ndarray, grad: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """Backtracking (Armijo) step lengths on Phi, ``(P,)``; 1 where the full step is accepted."""
    alpha = np.ones(x.shape[0])
    phi0 = _potential(x, nodes)
    slope = np.einsum("pi,pi->p", grad, step)  # < 0: Newton direction of an SPD Hessian
    slack = 1e-13 * (np.abs(phi0) + 1.0)  # round-off allowance near the minimum
    pending = np.arange(x.shape[0])
    for _ in range(40):
        trial = x[pending] + alpha[pending, None] * step[pending]
        phi = _potential(trial, nodes.take(pending))
        ok = phi <= phi0[pending] + 1e-4 * alpha[pending] * slope[pending] + slack[pending]
        pending = pending[~ok]
        if pending.size == 0:
            break
        alpha[pending] *= 0.5
    return alpha


# --------------------------------------------------------------------------- grids


def _step_grid(fractions_out: np.ndarray, max_step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integration steps from 0 to max(fractions_out), aligned with the output points.

    Returns ``(edges (K+1,), widths (K,), out_step (n,))`` in fractions of L, where
    ``out_step[j]`` is the index of output point j among the edges (K = 0 when all s are 0).
    """
    breaks = np.unique(np.concatenate([[0.0], fractions_out]))
    edges = [np.zeros(1)]
    for a, b in zip(breaks[:-1], breaks[1:], strict=True):
        k = max(1, int(np.ceil((b - a) / max_step - 1e-9)))
        edges.append(np.linspace(a, b, k + 1)[1:])
    edges = np.concatenate(edges)
    return edges, np.diff(edges), np.searchsorted(edges, fractions_out)


def _make_nodes(designs: DesignBatch, mat: _Material, fractions: np.ndarray,
                act: np.ndarray | None = None) -> _Nodes:
    """Nodes at ``fractions`` ``(M,)`` of every design; ``act`` ``(M,)``: the fraction whose tendons
    act at each node (:func:`_node_activity`; None: every tendon, as at s < every end)."""
    rho, drho = tendon_routing(designs, fractions)
    b, m = designs.n_designs, fractions.shape[0]
    rep = lambda a: np.repeat(a, m, axis=0)  # noqa: E731  (B, ...) -> (B*M, ...)
    tau, active = rep(designs.tension), None
    if act is not None and designs.segmented.any():
        active = (designs.end_fractions[:, None, :] > act[None, :, None]).reshape(b * m, -1)
        tau = tau * active
    return _Nodes(
        rho=rho.reshape(b * m, -1, 3), drho=drho.reshape(b * m, -1, 3),
        tau=tau, kse=rep(mat.kse), kbt=rep(mat.kbt), radius=rep(designs.r), target=None, active=active,
    )


def _node_activity(edges: np.ndarray) -> np.ndarray:
    """The fraction whose tendons act at each node ``(2K+1,)`` of the layout of :func:`_solve_on_grid`
    (K+1 edges, then K midpoints): a step's midpoint; an edge takes its left step's (just before an
    end: a zero-width step, :func:`_grid_with_ends`), or its right step's after a zero-width step,
    or its own inside a run of them (the kernel's rule, ``_kernel._node_activity``)."""
    widths = np.diff(edges)
    mids = edges[:-1] + 0.5 * widths
    act = edges.copy()
    right = np.append(widths > 0, False)
    left = np.insert(widths > 0, 0, False)
    act[right] = mids[right[:-1]]
    act[left] = mids[left[1:]]  # the left step wins (the kernel's order)
    return np.concatenate([act, mids])


def _grid_with_ends(edges0: np.ndarray, out_step0: np.ndarray, end_fractions: np.ndarray):
    """The step grid of designs that share the tendon ends ``end_fractions`` ``(N_t,)``: every end
    below the tip inserted twice (a zero-width step; an end within 1e-9 of an edge on it).  Returns
    ``(edges, out_step, end_step (N_t,))`` as the kernel's ``_with_ends`` (-1: ends at the tip)."""
    from tdcr.physics._compiled import kernel

    return kernel._with_ends(np.ascontiguousarray(edges0, dtype=np.float64), out_step0.astype(np.int64),
                             np.ascontiguousarray(end_fractions, dtype=np.float64))


def _undeformed(p: int) -> np.ndarray:
    x = np.zeros((p, 6))
    x[:, 2] = 1.0
    return x


# --------------------------------------------------------------------------- public entry


def solve(
    designs: DesignBatch,
    fractions: np.ndarray,
    *,
    loads: ExternalLoads | None = None,
    options: SolverOptions | None = None,
    workers: int = 1,
    jacobian: bool = False,
    termination: str = "exact",
) -> RodSolution:
    """Equilibrium shapes of a batch of designs.

    Args:
        designs: ``B`` designs with ``N_t >= 1`` tendons each.
        fractions: requested arclengths as fractions of L in [0, 1] (within
            ``FRACTION_ROUNDING``, clamped), ``(n,)``, any order.
        loads: optional gravity and tip loads; ``None`` means tendon loads only.
        options: numerical settings.
        workers: threads of the compiled kernels (0: one per core).  Designs are independent,
            so the result equals ``workers=1`` bit for bit.  The numpy path (``jacobian``,
            ``linearized``) runs on the calling thread.
        jacobian: also the pose's sensitivity to the tensions (``RodSolution.jacobian``), exact
            by the implicit-function theorem at every node and a tangent carried through the
            Magnus steps (no finite differences).  Tendon loads only.
        termination: how a tendon that ends before the tip loads the rod (:data:`TERMINATIONS`).
            ``"exact"``: the consistent equilibrium, in which the total wrench across any cut
            through rod and tendons is continuous (an ending tendon's pull and the kink forces of
            the tendons that continue past the end).  ``"rucker_webster"``: the common shortcut of
            integrating Rucker & Webster's ODE segment by segment with only the ending tendon's
            pull applied at its end (e.g. tdcr-modeling); it shoots on N(0) and M(0) for such
            designs.  Both agree for designs whose tendons all end at the tip.

    Returns:
        A :class:`RodSolution`.  A design that fails is flagged in ``status`` and ``converged``;
        it never fails the batch.
    """
    opts = options or SolverOptions()
    if termination not in TERMINATIONS:
        raise ValueError(f"termination must be one of {list(TERMINATIONS)}, got {termination!r}")
    fractions_out = check_inputs(designs, fractions, loads)
    loaded = loads is not None and not loads.is_zero()
    shortcut = termination == "rucker_webster" and bool(designs.segmented.any())
    if designs.displacement_driven.any():
        if loaded or shortcut or jacobian or opts.linearized:
            raise ValueError("displacement actuation covers tendon loads with consistent termination (no Jacobian, "
                             "not linearized)")
        return _solve_displacement(designs, fractions_out, opts, workers)
    if (loaded or shortcut) and opts.linearized:
        raise ValueError("the linearized model covers tendon loads only, with consistent termination")
    if jacobian and (loaded or opts.linearized or shortcut):
        raise ValueError("the Jacobian covers the exact model under tendon loads only, with consistent termination")
    if loaded or shortcut:
        return _solve_loaded_compiled(designs, fractions_out, loads or ExternalLoads(), opts, workers,
                                      shortcut=termination == "rucker_webster")
    return _solve_tendon_only(designs, fractions_out, opts, jacobian=jacobian, threads=workers)


def check_inputs(designs: DesignBatch, fractions: np.ndarray, loads: ExternalLoads | None) -> np.ndarray:
    """The one validation path's value checks (:mod:`tdcr.checks`) for the Python API: every design
    and load inside its admissible bounds, the fractions in [0, 1] (clamped within rounding).
    Returns the fractions ``(n,)``; raises :class:`tdcr.checks.InvalidRequest` (a ``ValueError``)
    with the service's words, e.g. ``designs[0].tendons[1].tension: must be in [0, 1000] N, got -2``."""
    from tdcr.checks import (
        Problem,
        check_features,
        check_fractions,
        check_layout,
        check_loads,
        checkable_loads,
        raise_problems,
    )

    problems = check_features(designs.features()) + check_layout(designs)
    clamped, more = check_fractions(fractions, name="fractions")
    problems += more
    if loads is not None:
        rows = np.arange(designs.n_designs)
        if loads.gravity is not None and loads.density is None:
            problems.append(Problem(("designs", 0, "gravity"), "needs a density (kg/m^3): give "
                                    "ExternalLoads(density=...)", "missing_density"))
        else:
            problems += check_loads(checkable_loads(loads, designs.n_designs), rows)
    raise_problems(problems)
    return clamped


def body_strains(designs: DesignBatch, fractions: np.ndarray, *, options: SolverOptions | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Equilibrium body strains under tendon loads only: the roots of (W1, W2) at each arclength.

    Args:
        designs: ``B`` designs.
        fractions: arclengths as fractions of L, ``(M,)``.
        options: numerical settings.

    Returns:
        ``(strains (B, M, 6), converged (B,))`` with strains = (nu (1), kappa (rad/m)) in the body frame.
    """
    opts = options or SolverOptions()
    fractions = np.asarray(fractions, dtype=np.float64).reshape(-1)
    b, m = designs.n_designs, fractions.shape[0]
    mat = material(designs)
    x_base, _, _ = _newton(_undeformed(b), _make_nodes(designs, mat, np.zeros(1)), opts)
    x, ok, _ = _newton(np.repeat(x_base, m, axis=0), _make_nodes(designs, mat, fractions), opts)
    return x.reshape(b, m, 6), ok.reshape(b, m).all(axis=1)


@dataclass
class _WarmStart:
    """Strains of the last solve ``(P, 6)``: the next solve of the same shape starts its Newton there."""

    strains: np.ndarray | None = None


def _solve_tendon_only(designs: DesignBatch, fractions_out: np.ndarray, opts: SolverOptions, *,
                       jacobian: bool = False, warm: _WarmStart | None = None, threads: int = 1) -> RodSolution:
    """Tendon loads only.  Step control per design (``opts.step_tol``) except for the linearized
    model and warm-started tip solves (:class:`TipSolver`), which use the base grid.  The
    vectorised path (Jacobian, linearized, tip solves) runs designs with the same tendon ends
    together, on their grid."""
    edges0, _, out0 = _step_grid(np.append(fractions_out, 1.0), opts.max_step)  # to the tip: the path lengths
    out0 = out0[:-1]
    if not (jacobian or opts.linearized or warm is not None):
        return _solve_compiled(designs, fractions_out, edges0, opts, threads)
    ends = designs.end_fractions
    groups = np.unique(ends, axis=0, return_inverse=True)[1].reshape(-1) if designs.segmented.any() else None
    if groups is not None and groups.max() > 0:
        parts = [np.nonzero(groups == g)[0] for g in range(groups.max() + 1)]
        sols = [_solve_tendon_only(designs.take(rows), fractions_out, opts, jacobian=jacobian, warm=None)
                for rows in parts]
        order = np.argsort(np.concatenate(parts), kind="stable")
        return RodSolution(**{f.name: None if getattr(sols[0], f.name) is None
                              else np.concatenate([getattr(x, f.name) for x in sols])[order]
                              for f in dataclasses.fields(RodSolution)})
    end_step = None
    if designs.segmented.any():
        edges0, out0, end_step = _grid_with_ends(edges0, out0, ends[0])
    if opts.linearized or warm is not None:
        sol, _ = _solve_on_grid(designs, fractions_out, edges0, out0, opts, jacobian=jacobian, warm=warm,
                                end_step=end_step)
        return _finish_status(sol, np.full(designs.n_designs, np.nan), len(edges0) - 1, opts, estimated=False)
    return _solve_adaptive(designs, fractions_out, edges0, out0, opts, jacobian, end_step=end_step)


def _refine(edges: np.ndarray) -> np.ndarray:
    """Every step split in two at its midpoint 0.5 (a + b) (the kernel's arithmetic exactly)."""
    out = np.empty(2 * edges.size - 1)
    out[0::2] = edges
    out[1::2] = 0.5 * (edges[:-1] + edges[1:])
    return out


def _coarse_grid(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The coarse grid of the free error estimate: each two consecutive steps of equal width joined
    into one, whose midpoint is their shared edge; a step without an equal neighbour kept.

    Returns ``(coarse edges as indices into edges (Kc+1,), coarse midpoints as node indices (Kc,))``
    with the node layout of :func:`_solve_on_grid` (K+1 edges, then K midpoints)."""
    k_steps = edges.size - 1
    widths = np.diff(edges)
    c_edges, c_mids, k = [0], [], 0
    while k < k_steps:
        if k + 1 < k_steps and abs(widths[k + 1] - widths[k]) <= 1e-12 * widths[k]:
            c_mids.append(k + 1)
            k += 2
        else:
            c_mids.append(k_steps + 1 + k)
            k += 1
        c_edges.append(k)
    return np.array(c_edges), np.array(c_mids, dtype=np.int64)


def _magnus_steps(xi0: np.ndarray, xi1: np.ndarray, xim: np.ndarray, h: np.ndarray):
    """eq. (MAG): 4th-order Magnus step on SE(3) for g' = g xi^ with body twists xi = (nu, kappa)
    at both ends and the middle of each step (Simpson / Lobatto nodes):
      Omega = h/6 (xi_0 + 4 xi_1/2 + xi_1) + h^2/12 [xi_0, xi_1],   g_{k+1} = g_k exp(Omega).
    Twists ``(B, K, 6)``, h ``(B, K, 1)`` m.  Returns ``(rot (B, K+1, 3, 3), pos (B, K+1, 3), parts)``
    with ``parts = ((cv, cw), mean, step_r, step_p)`` for the tangent of :func:`_magnus_tangent`."""
    b, k = xi0.shape[0], xi0.shape[1]
    cv, cw = se3_bracket(xi0[..., :3], xi0[..., 3:], xi1[..., :3], xi1[..., 3:])
    mean = (xi0 + 4.0 * xim + xi1) / 6.0
    step_r, step_p = se3_exp(h * mean[..., :3] + h**2 / 12.0 * cv, h * mean[..., 3:] + h**2 / 12.0 * cw)
    rot = np.empty((b, k + 1, 3, 3))
    pos = np.empty((b, k + 1, 3))
    rot[:, 0] = np.eye(3)
    pos[:, 0] = 0.0
    for j in range(k):
        pos[:, j + 1] = pos[:, j] + np.einsum("bij,bj->bi", rot[:, j], step_p[:, j])
        rot[:, j + 1] = rot[:, j] @ step_r[:, j]
    return rot, pos, ((cv, cw), mean, step_r, step_p)


def _richardson(fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """Error estimate of ``fine`` from a solution with twice its step, 4th-order method:
    ||T_fine - T_coarse|| / (15 ||T_fine||) per design (relative l2, tdcr.metrics), ``(B,)``."""
    axes = tuple(range(1, fine.ndim))
    diff = np.sqrt(((fine - coarse) ** 2).sum(axis=axes))
    norm = np.sqrt((fine**2).sum(axis=axes))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, diff / np.where(norm > 0, norm, 1.0), diff) / 15.0


def _coarse_estimate(designs: DesignBatch, x: np.ndarray, edges: np.ndarray, out_step: np.ndarray,
                     rho_out: np.ndarray, tendons: np.ndarray) -> np.ndarray:
    """The free Richardson estimate of a grid solution (no new Newton solve), ``(B,)``: against the
    coarse grid of :func:`_coarse_grid`, at the outputs on coarse edges.  ``x`` node strains
    ``(B, 2K+1, 6)``, ``tendons`` the grid solution's ``(B, n, N_t, 3)``."""
    c_edges, c_mids = _coarse_grid(edges)
    h = np.diff(edges[c_edges])[None, :, None] * designs.L[:, None, None]
    rot, pos, _ = _magnus_steps(x[:, c_edges[:-1]], x[:, c_edges[1:]], x[:, c_mids], h)
    on_coarse = np.isin(out_step, c_edges)
    where = np.searchsorted(c_edges, out_step[on_coarse])
    R, p = rot[:, where], pos[:, where]
    coarse = p[:, :, None, :] + np.einsum("bnij,bntj->bnti", R, rho_out[:, on_coarse])
    return _richardson(tendons[:, on_coarse], coarse)


def _solve_adaptive(designs: DesignBatch, fractions_out: np.ndarray, edges0: np.ndarray, out0: np.ndarray,
                    opts: SolverOptions, jacobian: bool, *, end_step: np.ndarray | None = None) -> RodSolution:
    """The vectorised path (for the Jacobian) with the kernel's step control: the base grid with the
    free estimate, then, for the designs above ``step_tol``, the grid halved (Richardson against the
    last level)."""
    sol, x = _solve_on_grid(designs, fractions_out, edges0, out0, opts, jacobian=jacobian, end_step=end_step)
    rho_out, _ = tendon_routing(designs, fractions_out, derivative=False)
    estimate = _coarse_estimate(designs, x, edges0, out0, rho_out, sol.tendons)
    fields = {f.name: getattr(sol, f.name) for f in dataclasses.fields(RodSolution)
              if getattr(sol, f.name) is not None}
    fields = {k: v.copy() for k, v in fields.items()}
    steps = np.full(designs.n_designs, len(edges0) - 1)
    edges, out_step = edges0, out0
    active = np.nonzero(estimate > opts.step_tol)[0]
    for _level in range(opts.max_level):
        if active.size == 0:
            break
        edges, out_step = _refine(edges), 2 * out_step
        end_step = None if end_step is None else np.where(end_step >= 0, 2 * end_step, end_step)
        finer, _ = _solve_on_grid(designs.take(active), fractions_out, edges, out_step, opts, jacobian=jacobian,
                                  end_step=end_step)
        estimate[active] = _richardson(finer.tendons, fields["tendons"][active])
        for name in fields:
            fields[name][active] = getattr(finer, name)
        steps[active] = len(edges) - 1
        active = active[estimate[active] > opts.step_tol]
    return _finish_status(RodSolution(**fields), estimate, steps, opts, estimated=True)


def _kernel_inputs(designs: DesignBatch, mat: _Material, edges0: np.ndarray, fractions_out: np.ndarray,
                   opts: SolverOptions, *, loaded: bool, shortcut: bool = False):
    """The kernels' grouped arguments (:mod:`tdcr.physics._kernel`'s named tuples): the rods, the
    base grid, the tolerances and the preallocated outputs."""
    from tdcr.physics._compiled import kernel

    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    b, n, n_t = designs.n_designs, fractions_out.shape[0], designs.n_tendons
    rods = kernel.Rods(kse=f64(mat.kse), kbt=f64(mat.kbt), radius=f64(designs.r), length=f64(designs.L),
                       offset=f64(designs.offset), pitch=f64(designs.pitch), tension=f64(designs.tension),
                       angle=f64(designs.angles), end=f64(designs.end_fractions))
    grid = kernel.Grid(edges=f64(edges0), out_step=np.searchsorted(edges0, fractions_out).astype(np.int64),
                       fractions=f64(fractions_out))
    tols = kernel.Tolerances(newton_tol=float(opts.newton_tol), max_newton=int(opts.max_newton),
                             step_tol=float(opts.step_tol), max_level=int(opts.max_level),
                             shooting_tol=float(opts.shooting_tol), max_shooting=int(opts.max_shooting),
                             shortcut=bool(shortcut))
    per_design = lambda dtype=np.float64: np.empty(b, dtype=dtype)  # noqa: E731
    out = kernel.Shapes(backbone=np.empty((b, n, 3)), rotation=np.empty((b, n, 3, 3)), strains=np.empty((b, n, 6)),
                        tendons=np.empty((b, n, n_t, 3)), status=per_design(np.int64), residual=per_design(),
                        iterations=per_design(np.int64), level=per_design(np.int64), estimate=per_design(),
                        m0=np.empty((b if loaded else 0, 3)), shoot_jac=np.empty((b if loaded else 0, 3, 3)),
                        displacement=np.empty((b, n_t)))
    return kernel, rods, grid, tols, out


def _run_kernel(entry, threads: int, n_designs: int, *args) -> None:
    """``entry(*args)`` on ``threads`` numba threads (0: all), restoring numba's setting after."""
    import numba

    wanted = min(threads or os.cpu_count() or 1, numba.config.NUMBA_NUM_THREADS, max(n_designs, 1))
    previous = numba.get_num_threads()
    numba.set_num_threads(wanted)
    try:
        entry(*args)
    finally:
        numba.set_num_threads(previous)


def several_equilibria(shoot_jac: np.ndarray) -> np.ndarray:
    """Per design ``(B,)``: whether the shooting Jacobian dM(L)/dM(0) ``(B, 3, 3)`` at the result
    says the equilibrium is one of several.  It is the identity without loads; a real eigenvalue
    <= 0 means one crossed zero as the loads grew: a fold or a bifurcation (e.g. Euler buckling).
    A Jacobian that is not finite is flagged too."""
    with np.errstate(all="ignore"):
        finite = np.isfinite(shoot_jac).all(axis=(1, 2))
        eig = np.linalg.eigvals(np.where(finite[:, None, None], shoot_jac, np.eye(3)))
    real = np.abs(eig.imag) <= 1e-12 * np.abs(eig).max(axis=1, keepdims=True)
    return (real & (eig.real <= 0)).any(axis=1) | ~finite


def _from_kernel(designs: DesignBatch, mat: _Material, fractions_out: np.ndarray, edges0: np.ndarray,
                 out, status: np.ndarray) -> RodSolution:
    """A :class:`RodSolution` of the kernels' outputs ``out`` with the final ``status``."""
    force, moment = internal_wrench(out.rotation, out.strains, mat)
    return RodSolution(
        s=designs.L[:, None] * fractions_out[None, :], backbone=out.backbone, rotation=out.rotation,
        tendons=out.tendons, force=force, moment=moment, converged=status == 0, residual=out.residual,
        iterations=out.iterations, status=status, error_estimate=out.estimate,
        steps=(len(edges0) - 1) * 2**out.level, tension=designs.tension.copy(), displacement=out.displacement,
    )


def _solve_loaded_compiled(designs: DesignBatch, fractions_out: np.ndarray, loads: ExternalLoads, opts: SolverOptions,
                           threads: int, *, shortcut: bool = False) -> RodSolution:
    """The loaded shooting kernel (:func:`tdcr.physics._kernel.solve_loaded_design`) on ``threads``
    threads (0: all): variational shooting Jacobian, load continuation when needed, RK4 with the
    step controlled per design like the tendon-only kernel."""
    mat = material(designs)
    f_g, f_tip, m_tip = loads.resolved(designs.n_designs, mat.area)
    edges0, _, _ = _step_grid(np.append(fractions_out, 1.0), opts.max_step_loads)
    kernel, rods, grid, tols, out = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=True,
                                                   shortcut=shortcut)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    _run_kernel(kernel.solve_loaded_batch, threads, designs.n_designs, rods,
                kernel.Loads(f_g=f64(f_g), f_tip=f64(f_tip), m_tip=f64(m_tip)), grid, tols, out)
    status = out.status.astype(np.int8)
    status[(status == Status.CONVERGED) & several_equilibria(out.shoot_jac)] = Status.MULTIPLE_EQUILIBRIA
    return _from_kernel(designs, mat, fractions_out, edges0, out, status)


def _solve_displacement(designs: DesignBatch, fractions_out: np.ndarray, opts: SolverOptions,
                        threads: int) -> RodSolution:
    """Displacement actuation: the tensions that pull in the displacement-driven tendons' lengths
    (:func:`tdcr.physics._kernel.find_tensions`: Newton with the exact Jacobian of the path
    lengths, tau >= 0, slack tendons flagged), then the tendon-only solve at those tensions."""
    edges0, _, _ = _step_grid(np.append(fractions_out, 1.0), opts.max_step)
    mat = material(designs)
    kernel, rods, grid, tols, _ = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=False)
    start = np.where(designs.displacement_driven, 0.0, designs.tension)
    rods = rods._replace(tension=np.ascontiguousarray(start, dtype=np.float64).copy())
    b, n_t = designs.n_designs, designs.n_tendons
    slack, found = np.zeros((b, n_t), dtype=np.bool_), np.empty(b, dtype=np.int64)
    iterations = np.empty(b, dtype=np.int64)
    wanted = np.where(designs.displacement_driven, designs.displacement, np.nan)
    target = np.ascontiguousarray(wanted)
    for correction in range(2):
        # the tensions on the base grid; then, once, again for the target moved by what the solve's
        # finer grid (step control) still misses (the grids' lengths differ by O(h^4))
        _run_kernel(kernel.find_tensions_batch, threads, b, rods, target, grid, tols, slack, found, iterations)
        sol = _solve_compiled(designs.replace(tension=rods.tension, displacement=None), fractions_out, edges0, opts,
                              threads)
        miss = np.where(slack, 0.0, wanted - sol.displacement)
        if correction or not (np.nan_to_num(np.abs(miss)) > DISPLACEMENT_TOL).any():
            break
        target = np.ascontiguousarray(target + np.nan_to_num(miss))
    status = sol.status.copy()
    status[(status == Status.CONVERGED) & (found != 0)] = Status.DISPLACEMENT_NOT_MET
    return dataclasses.replace(sol, status=status, converged=status == 0, slack=slack)


def _finish_status(sol: RodSolution, estimate: np.ndarray, steps, opts: SolverOptions, *,
                   estimated: bool) -> RodSolution:
    """Add the step control's verdict to a grid solution's ``status``; ``converged`` = status 0."""
    status = sol.status.copy()
    if estimated:
        status[(status == 0) & ~(estimate <= opts.step_tol)] = Status.STEP_TOL_NOT_MET
    b = status.shape[0]
    return dataclasses.replace(sol, converged=status == 0, status=status, error_estimate=estimate,
                               steps=np.broadcast_to(np.asarray(steps), (b,)).copy())


def _solve_on_grid(designs: DesignBatch, fractions_out: np.ndarray, edges: np.ndarray, out_step: np.ndarray,
                   opts: SolverOptions, *, jacobian: bool = False, warm: _WarmStart | None = None,
                   end_step: np.ndarray | None = None) -> tuple[RodSolution, np.ndarray]:
    """Tendon-only solve on one step grid (``edges`` fractions of L, outputs at edges ``out_step``;
    designs with tendon ends share them, at the edges ``end_step`` (:func:`_grid_with_ends`));
    returns the solution and the node strains ``(B, 2K+1, 6)`` (K+1 edges, then K midpoints)."""
    b, _n = designs.n_designs, fractions_out.shape[0]
    mat = material(designs)
    widths = np.diff(edges)
    k = widths.shape[0]
    starts = edges[:-1]
    node_fractions = np.concatenate([edges, starts + 0.5 * widths])  # (2K+1,), the outputs among the edges
    m = node_fractions.shape[0]
    nodes = _make_nodes(designs, mat, node_fractions, _node_activity(edges))
    if opts.linearized:
        x = _first_order_strains(nodes)
        ok, iters = np.ones(x.shape[0], dtype=bool), np.zeros(x.shape[0], dtype=np.int64)
    elif warm is not None and warm.strains is not None and warm.strains.shape == (b * m, 6):
        x, ok, iters = _newton(warm.strains.copy(), nodes, opts)  # from the last solve's strains
    else:
        # start every node from the base strains (exact for parallel tendons, close otherwise)
        x_base, _, _ = _newton(_undeformed(b), _make_nodes(designs, mat, np.zeros(1)), opts)
        x, ok, iters = _newton(np.repeat(x_base, m, axis=0), nodes, opts)
        if not ok.all():
            x, ok, iters = _continue_along_s(x, ok, iters, nodes, node_fractions, x_base, opts)
    if warm is not None:
        warm.strains = x.copy() if ok.all() else None  # a failed solve is no place to start from
    dx = _strain_sensitivities(x, nodes).reshape(b, m, 6, -1) if jacobian else None
    res = _residual(x, nodes).reshape(b, m, 6)
    x = x.reshape(b, m, 6)
    ok = ok.reshape(b, m).all(axis=1)
    iters = iters.reshape(b, m).max(axis=1)

    h = widths[None, :, None] * designs.L[:, None, None]  # (B, K, 1) m
    rot, pos, parts = _magnus_steps(x[:, :k], x[:, 1:k + 1], x[:, k + 1:], h)
    R = rot[:, out_step]
    p = pos[:, out_step]
    pose_jacobian = None
    if dx is not None:
        bracket, mean, step_r, step_p = parts
        eta = _magnus_tangent(x, dx, k, h, bracket, mean, step_r, step_p)[:, out_step]  # (B, n, 6, N_t) body
        pose_jacobian = np.concatenate([R @ eta[:, :, :3], R @ eta[:, :, 3:]], axis=2)

    x_out = x[:, out_step]
    rho_out, _ = tendon_routing(designs, fractions_out)
    tendons = p[:, :, None, :] + np.einsum("bnij,bntj->bnti", R, rho_out)
    if end_step is not None:  # beyond its end a tendon holds its termination point
        ends = designs.end_fractions[0]
        for i in np.nonzero(end_step >= 0)[0]:
            rho_end, _ = tendon_routing(designs, ends[i:i + 1], derivative=False)
            terminal = pos[:, end_step[i]] + np.einsum("bij,bj->bi", rot[:, end_step[i]], rho_end[:, 0, i])
            beyond = fractions_out > ends[i]
            tendons[:, beyond, i] = terminal[:, None, :]
    force, moment = internal_wrench(R, x_out, mat)
    displacement = _displacements(designs, edges, x)
    residual = _wrench_norm(res, designs.L[:, None]).max(axis=1)
    scale = np.maximum(designs.tension.sum(axis=1), 1.0)
    status = np.zeros(b, dtype=np.int8)
    status[~ok] = Status.NEWTON_FAILED
    if not opts.linearized:  # the linearized model reports its residual but is not an equilibrium
        status[(status == 0) & ~(residual <= opts.residual_tol * scale)] = Status.RESIDUAL_TOO_LARGE
    status[~(np.isfinite(tendons).all(axis=(1, 2, 3)) & np.isfinite(residual))] = Status.NOT_FINITE
    return RodSolution(
        s=designs.L[:, None] * fractions_out[None, :], backbone=p, rotation=R, tendons=tendons,
        force=force, moment=moment, converged=status == 0, residual=residual, iterations=iters,
        jacobian=pose_jacobian, status=status, tension=designs.tension.copy(), displacement=displacement,
    ), x


def _displacements(designs: DesignBatch, edges: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each tendon's displacement, m, ``(B, N_t)``, from the node strains ``x`` ``(B, 2K+1, 6)`` (K+1
    edges, then K midpoints) by the kernel's quadrature (``_kernel._path_lengths``)."""
    from tdcr.physics._compiled import kernel

    k = edges.size - 1
    sig = np.empty(2 * k + 1)
    sig[0::2], sig[1::2] = edges, edges[:-1] + 0.5 * np.diff(edges)
    inter = np.empty_like(x)
    inter[:, 0::2], inter[:, 1::2] = x[:, :k + 1], x[:, k + 1:]
    act = kernel._node_activity(sig)
    ends, angles = designs.end_fractions, np.ascontiguousarray(designs.angles)
    out = np.empty((designs.n_designs, designs.n_tendons))
    lengths, no_sens, no_dlen = np.empty(designs.n_tendons), np.empty((0, 6, designs.n_tendons)), np.empty((1, 1))
    for b in range(designs.n_designs):
        kernel._path_lengths(sig, act, np.ascontiguousarray(inter[b]), float(designs.L[b]), designs.offset[b],
                             designs.pitch[b], angles[b], np.ascontiguousarray(ends[b]), no_sens, lengths, no_dlen)
        for i in range(designs.n_tendons):
            out[b, i] = kernel.undeformed_length(float(designs.L[b]), designs.offset[b, i], designs.pitch[b, i],
                                                 ends[b, i]) - lengths[i]
    return out


def _solve_compiled(designs: DesignBatch, fractions_out: np.ndarray, edges0: np.ndarray, opts: SolverOptions,
                    threads: int) -> RodSolution:
    """The tendon-only kernel (:func:`tdcr.physics._kernel.solve_design`) on ``threads`` threads (0: all)."""
    mat = material(designs)
    kernel, rods, grid, tols, out = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=False)
    _run_kernel(kernel.solve_batch, threads, designs.n_designs, rods, grid, tols, out)
    status = out.status.astype(np.int8)
    scale = np.maximum(designs.tension.sum(axis=1), 1.0)
    status[(status == Status.CONVERGED) & ~(out.residual <= opts.residual_tol * scale)] = Status.RESIDUAL_TOO_LARGE
    # Newton stopped (or divided by |g_i| = 0) beside a collapsed tendon
    failed = np.nonzero((status == Status.NEWTON_FAILED) | (status == Status.NOT_FINITE)
                        & np.isfinite(out.tendons).all(axis=(1, 2, 3)))[0]
    status[failed[tendon_collapsed(designs.take(failed), fractions_out, out.strains[failed])]] = \
        Status.TENDON_COLLAPSED
    return _from_kernel(designs, mat, fractions_out, edges0, out, status)


#: Displacement actuation: the largest miss of a tendon's displacement, m.
DISPLACEMENT_TOL = 1e-10
#: |g_i| (the tendon's path length per unit s) below which a tendon has collapsed.
COLLAPSED_STRETCH = 1e-2


def tendon_collapsed(designs: DesignBatch, fractions: np.ndarray, strains: np.ndarray) -> np.ndarray:
    """Per design ``(B,)``: some tendon's path length per unit arclength |g_i| = |nu + kappa x rho_i +
    rho_i'| falls below :data:`COLLAPSED_STRETCH` (or is not finite: 0 / 0 in its direction) at the
    strains ``(B, n, 6)`` where Newton stopped.
    The potential (eq. PHI) then has its minimum at the kink g_i = 0: the tension bends the rod
    until the tendon would pass its centre of curvature (to first order tau o^2 / (E I) >= 1 for
    one tendon), and no equilibrium with a taut tendon exists -- more continuation would not help."""
    if len(designs) == 0:
        return np.zeros(0, dtype=bool)
    rho, drho = tendon_routing(designs, fractions)
    g = strains[:, :, None, :3] + _cross(strains[:, :, None, 3:], rho) + drho
    acting = designs.end_fractions[:, None, :] >= fractions[None, :, None]
    with np.errstate(invalid="ignore"):
        stretch = np.where(acting, np.linalg.norm(g, axis=-1), np.inf)
        return ~(stretch.min(axis=(1, 2)) >= COLLAPSED_STRETCH)


def _strain_sensitivities(x: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """d x / d tau at every node, ``(P, 6, N_t)``, by the implicit-function theorem on (W1, W2):
    J dx = -dF/dtau_i, with J the Hessian of Phi (already Newton's) and dF/dtau_i = a_i =
    (t_i, rho_i x t_i) (the tendon tangents do not depend on the tensions).  NaN where J is not
    positive definite or not finite."""
    _, jac, a = _jacobian_parts(x, nodes)
    if nodes.active is not None:  # an ended tendon's tension does not act at the node
        a = a * nodes.active[..., None]
    return _solve_spd(jac, -np.swapaxes(a, 1, 2))


def _ad(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The adjoint matrix of the twist (v, w): ad @ xi2 == [xi, xi2], ``(..., 6, 6)``."""
    out = np.zeros(v.shape[:-1] + (6, 6))
    out[..., :3, :3] = hat(w)
    out[..., :3, 3:] = hat(v)
    out[..., 3:, 3:] = hat(w)
    return out


def _dexp_right(ad: np.ndarray) -> np.ndarray:
    """The right Jacobian of exp on SE(3), dexp_{-Omega} = sum_k (-ad_Omega)^k / (k+1)!, by its
    series (exact to round-off: summed until a term is below 1e-17 of the identity), ``(..., 6, 6)``."""
    total = np.broadcast_to(np.eye(6), ad.shape).copy()
    term = total.copy()
    for k in range(1, 80):
        term = -(term @ ad) / (k + 1)
        total += term
        if not np.isfinite(term).all() or np.abs(term).max() < 1e-17:
            break
    return total


def _magnus_tangent(x, dx, k, h, bracket, mean, step_r, step_p) -> np.ndarray:
    """The body-frame pose tangents eta_j = (g_j^-1 dg_j / dtau)^v at every step edge, ``(B, K+1, 6, N_t)``.

    Differentiating eq. (MAG), Omega = h mean + h^2/12 [xi_0, xi_1] and g_{j+1} = g_j exp(Omega):
      d Omega = h (dxi_0 + 4 dxi_1/2 + dxi_1) / 6 + h^2/12 (ad_{xi_0} dxi_1 - ad_{xi_1} dxi_0),
      eta_{j+1} = Ad_{exp(-Omega)} eta_j + dexp_{-Omega} d Omega,   eta_0 = 0 (the base is clamped).
    """
    b, n_t = x.shape[0], dx.shape[-1]
    xi0, xi1 = x[:, :k], x[:, 1:k + 1]
    dxi0, dxi1, dxim = dx[:, :k], dx[:, 1:k + 1], dx[:, k + 1:]
    hh = h[..., None]  # (B, K, 1, 1)
    d_omega = hh * (dxi0 + 4.0 * dxim + dxi1) / 6.0 + hh**2 / 12.0 * (
        _ad(xi0[..., :3], xi0[..., 3:]) @ dxi1 - _ad(xi1[..., :3], xi1[..., 3:]) @ dxi0)
    cv, cw = bracket
    omega_v, omega_w = h * mean[..., :3] + h**2 / 12.0 * cv, h * mean[..., 3:] + h**2 / 12.0 * cw
    carry = _dexp_right(_ad(omega_v, omega_w)) @ d_omega  # (B, K, 6, N_t)
    rt = np.swapaxes(step_r, -1, -2)  # Ad of exp(-Omega) = (R^T, -R^T p): [[R^T, -R^T hat(p)], [0, R^T]]
    ad_inverse = np.zeros(step_r.shape[:-2] + (6, 6))
    ad_inverse[..., :3, :3] = rt
    ad_inverse[..., :3, 3:] = -rt @ hat(step_p)
    ad_inverse[..., 3:, 3:] = rt
    eta = np.zeros((b, k + 1, 6, n_t))
    for j in range(k):
        eta[:, j + 1] = ad_inverse[:, j] @ eta[:, j] + carry[:, j]
    return eta


class TipSolver:
    """Repeated tendon-only solves of one design's tip (s = L) with its exact Jacobian, for new
    tensions each time: each Newton starts from the last solve's strains (inverse kinematics asks
    for many nearby tensions).  ``solver(tensions (T, N_t))`` -> :class:`RodSolution` at s = L with
    ``jacobian``; the answers equal :func:`solve`'s to Newton's tolerance."""

    def __init__(self, design: DesignBatch, *, options: SolverOptions | None = None):
        if design.n_designs != 1:
            raise ValueError("TipSolver takes one design")
        self.design = design
        self.options = options or SolverOptions()
        self._warm = _WarmStart()

    def __call__(self, tensions: np.ndarray) -> RodSolution:
        tensions = np.asarray(tensions, dtype=np.float64)
        designs = self.design.take(np.zeros(tensions.shape[0], dtype=np.int64)).replace(tension=tensions)
        return _solve_tendon_only(designs, np.ones(1), self.options, jacobian=True, warm=self._warm)


def _wrench_norm(res: np.ndarray, length: np.ndarray) -> np.ndarray:
    """sqrt(|force|^2 + |moment / L|^2) of ``(..., 6)`` residuals, N."""
    return np.sqrt((res[..., :3] ** 2).sum(-1) + (res[..., 3:] ** 2).sum(-1) / length**2)
