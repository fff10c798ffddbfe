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

Real tendons (docs/real_robot.md).  A displacement-driven tendon with a series stiffness k_i (of
the tendon and its drive) and a drive zero z_i pulls with

    tau_i = k_i max(0, u_i - z_i - d_i),   d_i = l0_i - l_i                (eq. SE)

(u_i the drive's reading, d_i the length its path shortened; k_i = inf: the rigid u_i - z_i = d_i).
Along a sequence of commands (a replay) a tendon may creep: a dashpot in series with its spring,
which lengthens the tendon by r tau_i / k_i per second (r the creep rate, 1/s; the spring's stretch
relaxes at rate r) and never recovers.  Explicit in time, the pull-in of command b falls short by

    e_i(b) = sum_{j<b} r tau_i(j) (t_{j+1} - t_j) / k_i,   u_i -> u_i - e_i(b)       (eq. CREEP)

Capstan friction between a tendon and its guides makes its tension vary along the path,

    d tau_i / ds = c_i tau_i |d t_i / ds|,  tau_i(s) = tau_i(0) exp(c_i theta_i(s))   (eq. CAP)

with c_i = -mu_i while the tendon is pulled in and +mu_i while it is released, t_i its unit
tangent and theta_i its wrap angle from the base.  Friction is internal to rod and tendons, so
(W1, W2) hold at every s with tau_i(s) in place of tau_i: the cut's total wrench stays continuous.

Where it runs.  The compiled kernels (:mod:`tdcr.physics._kernel`, numba) are the one
implementation of the method: tendon loads and external loads, each with the step chosen per
design from a Richardson estimate (``SolverOptions.step_tol``), the exact Jacobian to the tensions
(``jacobian=True``: the implicit-function theorem at every node and a tangent carried through the
Magnus steps), the linearised reference robot (``SolverOptions.linearized``), the warm-started
tip solves of inverse kinematics (:class:`TipSolver`) and displacement actuation.  This module
holds the material law (:func:`material`), validates and groups the inputs for the kernels and
turns their outputs into a :class:`RodSolution`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from tdcr.physics.status import STATUS, Status
from tdcr.robot.designs import DEFAULT_POISSON, DesignBatch, ExternalLoads

#: The Poisson ratio of a design that gives none (:data:`tdcr.robot.designs.DEFAULT_POISSON`).
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
        displacement_tol: displacement actuation: the largest miss of a driven tendon's pull-in, m
            (the tensions are found on the base grid to a tenth of it, and once more for the
            finer grid's miss where that exceeds it).
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
    displacement_tol: float = 1e-10


@dataclass(frozen=True)
class RodSolution:
    """Equilibria of a batch of ``B`` designs at ``n`` arclengths.

    Attributes:
        s: arclengths, m, ``(B, n)``.
        backbone: backbone positions p(s), m, ``(B, n, 3)``.
        rotation: frames R(s), body axes as columns, ``(B, n, 3, 3)``.
        tendons: tendon positions p + R rho_i, m, ``(B, n, N_t, 3)``.
        force: internal force n(s) of the rod, base frame, N, ``(B, n, 3)`` (computed from
            ``strains`` on first access: :func:`internal_wrench`).
        moment: internal moment m(s) of the rod, base frame, N m, ``(B, n, 3)`` (the same).
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
        strains: body strains (nu (1), kappa (rad/m)) at the arclengths, ``(B, n, 6)``.
        tension_profile: every tendon's tension at the arclengths, N, ``(B, n, N_t)``: ``tension``
            where it acts without friction, tension exp(-/+ mu theta(s)) with friction (eq. CAP),
            0 beyond its end.
        crept: with ``solve(..., creep=)``, how far each tendon had crept when its design was
            solved (eq. CREEP), m, ``(B, N_t)``: its pull-in fell short by this much; else ``None``.
        section: the section stiffnesses the solve used (:func:`material`).
    """

    s: np.ndarray
    backbone: np.ndarray
    rotation: np.ndarray
    tendons: np.ndarray
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
    strains: np.ndarray | None = None
    tension_profile: np.ndarray | None = None
    crept: np.ndarray | None = None
    section: _Material | None = dataclasses.field(default=None, repr=False)

    @functools.cached_property
    def _wrench(self) -> tuple[np.ndarray, np.ndarray]:
        # on first access only: a service's answers never read it (15 us of a one-design solve)
        return internal_wrench(self.rotation, self.strains, self.section)

    @property
    def force(self) -> np.ndarray:
        return self._wrench[0]

    @property
    def moment(self) -> np.ndarray:
        return self._wrench[1]


__all__ = ["POISSON_RATIO", "STATUS", "TERMINATIONS", "RodSolution", "SolverOptions", "Status", "TipSolver",
           "internal_wrench", "material", "section_stiffness", "solve", "tendon_routing"]


@dataclass(frozen=True)
class _Material:
    kse: np.ndarray  # (B, 3) N
    kbt: np.ndarray  # (B, 3) N m^2
    area: np.ndarray  # (B,) m^2


def section_stiffness(E, r, poisson):
    """The one place of the material law: the section stiffnesses ``(G A, E A, E I, G J)`` of a solid
    circular rod, N and N m^2, with G = E / (2 (1 + nu)), A = pi r^2, I = pi r^4 / 4, J = 2 I, from
    Young's modulus ``E`` Pa, radius ``r`` m and Poisson ratio ``poisson`` (each ``(B,)``, or a
    scalar).  Plain arithmetic, so numpy arrays and torch tensors alike (the operators' graphs
    take it from here)."""
    g = E / (2.0 * (1.0 + poisson))
    area = math.pi * r**2
    inertia = (math.pi / 4.0) * r**4
    return g * area, E * area, E * inertia, 2.0 * g * inertia


def material(designs: DesignBatch) -> _Material:
    """Stiffnesses K_se (N) and K_bt (N m^2) as diagonals, ``(B, 3)`` each, of each design's Poisson
    ratio nu (default :data:`POISSON_RATIO`), by :func:`section_stiffness`, for every path (the
    kernels receive these)."""
    ga, ea, ei, gj = section_stiffness(designs.E, designs.r, designs.poissons)
    kse, kbt = np.empty((designs.n_designs, 3)), np.empty((designs.n_designs, 3))  # (np.stack costs more)
    kse[:, 0], kse[:, 1], kse[:, 2] = ga, ga, ea
    kbt[:, 0], kbt[:, 1], kbt[:, 2] = ei, ei, gj
    return _Material(kse=kse, kbt=kbt, area=ea / designs.E)  # A of the material law


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


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (faster than np.cross for small trailing axes)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


# --------------------------------------------------------------------------- grids


def _step_grid(fractions_out: np.ndarray, max_step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integration steps from 0 to max(fractions_out), aligned with the output points.

    Returns ``(edges (K+1,), widths (K,), out_step (n,))`` in fractions of L, where
    ``out_step[j]`` is the index of output point j among the edges (K = 0 when all s are 0).
    """
    breaks = np.unique(np.concatenate([[0.0], fractions_out]))
    widths = np.diff(breaks)
    k = np.maximum(1, np.ceil(widths / max_step - 1e-9)).astype(np.int64)  # steps per output interval
    interval = np.repeat(np.arange(k.size), k)
    last = np.cumsum(k) - 1
    j = np.arange(interval.size) - (last - k + 1)[interval] + 1  # 1..k within each interval
    inner = breaks[:-1][interval] + j * (widths / k)[interval]  # np.linspace's a + j (b - a) / k, bit for bit
    inner[last] = breaks[1:]  # and its exact end point
    edges = np.concatenate([np.zeros(1), inner])
    return edges, np.diff(edges), np.searchsorted(edges, fractions_out)


#: Base grids kept by :func:`_base_edges` (a service asks for the same few point sets again and again).
BASE_GRIDS_KEPT = 64


def _base_edges(fractions_out: np.ndarray, max_step: float) -> np.ndarray:
    """The base grid's edges ``(K+1,)`` from 0 to the tip (the path lengths need s = L) through the
    output points ``fractions_out`` ``(n,)``: :func:`_step_grid`'s, remembered per point set and step
    (it cost 0.1 ms, as much as one design's solve).  A fresh copy each call: callers own it."""
    return _cached_base_edges(np.ascontiguousarray(fractions_out, dtype=np.float64).tobytes(), float(max_step)).copy()


@functools.lru_cache(maxsize=BASE_GRIDS_KEPT)
def _cached_base_edges(fractions_bytes: bytes, max_step: float) -> np.ndarray:
    edges, _, _ = _step_grid(np.append(np.frombuffer(fractions_bytes), 1.0), max_step)
    return edges


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
    sequence: bool = False,
    creep: np.ndarray | None = None,
    validated: bool = False,
    progress: Callable[[int], None] | None = None,
) -> RodSolution:
    """Equilibrium shapes of a batch of designs.

    Args:
        designs: ``B`` designs with ``N_t >= 1`` tendons each.
        fractions: requested arclengths as fractions of L in [0, 1] (within
            ``FRACTION_ROUNDING``, clamped), ``(n,)``, any order.
        loads: optional gravity and tip loads; ``None`` means tendon loads only.
        options: numerical settings.
        workers: threads of the compiled kernels (0: one per core).  Designs are independent,
            so the result equals ``workers=1`` bit for bit.
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
        sequence: the designs are one robot's commands in order (:func:`tdcr.replay`): with
            displacement actuation each design's tensions start from those found for the one
            before (the answers equal those of independent solves to the solver's tolerances).
        creep: with ``sequence`` and displacement actuation, ``(B, N_t)`` m/N: how far each
            displacement-driven tendon lengthens per newton of its tension after its design
            (r (t_{b+1} - t_b) / k_i, eq. CREEP; :meth:`tdcr.robot.real.Robot.creep`).  Each design's
            pull-ins then fall short by the creep of the designs before it, so the designs are solved
            as one chain (on one thread; under loads, sweeps of the whole chain: :func:`crept_by`);
            ``RodSolution.crept`` says by how much.  None or zeros: none.
        validated: the designs, loads and fractions come from the one validation path
            (:mod:`tdcr.api.validation`, as :func:`tdcr.physics.exact.solve_request`'s do): its
            checks are not run a second time.
        progress: called with the number of designs just solved, by the displacement solve under
            loads (the costliest, 50-100x the others per design): a ``sequence``
            :data:`LOADED_CHUNK` designs at a time (the answers do not change), a creeping chain
            every design of each sweep again.  Not called elsewhere.

    Returns:
        A :class:`RodSolution`.  A design that fails is flagged in ``status`` and ``converged``;
        it never fails the batch.
    """
    opts = options or SolverOptions()
    if termination not in TERMINATIONS:
        raise ValueError(f"termination must be one of {list(TERMINATIONS)}, got {termination!r}")
    fractions_out = np.asarray(fractions, dtype=np.float64) if validated else check_inputs(designs, fractions, loads)
    loaded, shortcut = loaded_kernel(designs, loads, termination)
    if (designs.capstan != 0.0).any() and (shortcut or jacobian or opts.linearized):
        raise ValueError("friction covers consistent termination (no Jacobian, not linearized)")
    if creep is not None:
        creep = np.asarray(creep, dtype=np.float64)
        if creep.shape != designs.tension.shape or not (np.isfinite(creep) & (creep >= 0.0)).all():
            raise ValueError(f"creep: must be {designs.tension.shape} (B, N_t) finite m/N >= 0")
        if not creep.any():
            creep = None
        elif not sequence or not designs.displacement_driven.any():
            raise ValueError("creep covers a sequence of displacement commands")
    if designs.displacement_driven.any():
        if shortcut or jacobian or opts.linearized:
            raise ValueError("displacement actuation covers consistent termination (no Jacobian, not linearized)")
        if loaded:
            if creep is not None:
                return _solve_creeping_loaded(designs, fractions_out, loads, opts, workers, creep, progress=progress)
            return _solve_displacement_loaded(designs, fractions_out, loads, opts, workers, sequence=sequence,
                                              progress=progress)
        return _solve_displacement(designs, fractions_out, opts, workers, sequence=sequence, creep=creep)
    if (loaded or shortcut) and opts.linearized:
        raise ValueError("the linearized model covers tendon loads only, with consistent termination")
    if jacobian and (loaded or opts.linearized or shortcut):
        raise ValueError("the Jacobian covers the exact model under tendon loads only, with consistent termination")
    if loaded or shortcut:
        return _solve_loaded_compiled(designs, fractions_out, loads or ExternalLoads(), opts, workers,
                                      shortcut=termination == "rucker_webster")
    return _solve_tendon_only(designs, fractions_out, opts, jacobian=jacobian, threads=workers)


def loaded_kernel(designs: DesignBatch, loads: ExternalLoads | None, termination: str) -> tuple[bool, bool]:
    """Whether :func:`solve` runs the loaded kernel: for external loads that are not zero (``loaded``),
    and for the rucker_webster rule on segmented designs (``shortcut``)."""
    return (loads is not None and not loads.is_zero(),
            termination == "rucker_webster" and bool(designs.segmented.any()))


def check_inputs(designs: DesignBatch, fractions: np.ndarray, loads: ExternalLoads | None) -> np.ndarray:
    """The one validation path's value checks (:mod:`tdcr.api.checks`) for the Python API: every design
    and load inside its admissible bounds, the fractions in [0, 1] (clamped within rounding).
    Returns the fractions ``(n,)``; raises :class:`tdcr.api.checks.InvalidRequest` (a ``ValueError``)
    with the service's words, e.g. ``designs[0].tendons[1].tension: must be in [0, 1000] N, got -2``."""
    from tdcr.api.checks import (
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


@dataclass
class _WarmStart:
    """Level 0's node strains of the last solve ``(B, 2 K0 + 1, 6)`` (:class:`tdcr.physics._kernel.Shapes`
    ``nodes``); the next solve of the same shape starts its Newton there while ``valid``."""

    nodes: np.ndarray | None = None
    valid: bool = False


def _solve_tendon_only(designs: DesignBatch, fractions_out: np.ndarray, opts: SolverOptions, *,
                       jacobian: bool = False, warm: _WarmStart | None = None, threads: int = 1) -> RodSolution:
    """Tendon loads only: the tendon-only kernel, step control per design (``opts.step_tol``) except
    for the linearized model (the base grid); ``warm`` (one design's copies: :class:`TipSolver`)
    starts Newton from the last solve's strains and keeps this one's."""
    edges0 = _base_edges(fractions_out, opts.max_step)
    return _solve_compiled(designs, fractions_out, edges0, opts, threads, jacobian=jacobian, warm=warm)


def _kernel_array(a) -> np.ndarray:
    """``a`` as the compiled kernels take their arrays: float64, C-contiguous and writable.  numba
    compiles a kernel anew for every array type, and a read-only array is another type: designs
    read from a ``.npy`` body (a read-only buffer) would otherwise compile the whole solver again
    where it runs, minutes on a cold cache."""
    if type(a) is np.ndarray and a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a  # already so: np.require's own checks cost as much as a small design's setup
    return np.array(a, dtype=np.float64, order="C")  # a copy, writable


def _kernel_inputs(designs: DesignBatch, mat: _Material, edges0: np.ndarray, fractions_out: np.ndarray,
                   opts: SolverOptions, *, loaded: bool, shortcut: bool = False, jacobian: bool = False,
                   warm: _WarmStart | None = None):
    """The kernels' grouped arguments (:mod:`tdcr.physics._kernel`'s named tuples): the rods, the
    base grid, the tolerances and the preallocated outputs (with ``jacobian`` the pose Jacobian's;
    with ``warm`` level 0's node strains, read back as Newton's starts while ``warm.valid``)."""
    from tdcr.physics._compiled import kernel

    f64 = _kernel_array
    b, n, n_t = designs.n_designs, fractions_out.shape[0], designs.n_tendons
    rods = kernel.Rods(kse=f64(mat.kse), kbt=f64(mat.kbt), radius=f64(designs.r), length=f64(designs.L),
                       offset=f64(designs.offset), pitch=f64(designs.pitch), tension=f64(designs.tension),
                       angle=f64(designs.angles), end=f64(designs.end_fractions),
                       compliance=f64(designs.compliance), capstan=f64(designs.capstan))
    grid = kernel.Grid(edges=f64(edges0), out_step=np.searchsorted(edges0, fractions_out).astype(np.int64),
                       fractions=f64(fractions_out))
    nodes, warm_start = np.empty((b, 0, 6)), False
    if warm is not None and b:  # one design's copies: its grid with the ends
        edges, _, _ = kernel._with_ends(grid.edges, grid.out_step, rods.end[0])
        shape = (b, 2 * edges.shape[0] - 1, 6)
        warm_start = warm.valid and warm.nodes is not None and warm.nodes.shape == shape
        nodes = warm.nodes if warm_start else np.zeros(shape)
    tols = _tolerances(opts, shortcut=bool(shortcut), warm=bool(warm_start))
    per_design = lambda dtype=np.float64: np.empty(b, dtype=dtype)  # noqa: E731
    out = kernel.Shapes(backbone=np.empty((b, n, 3)), rotation=np.empty((b, n, 3, 3)), strains=np.empty((b, n, 6)),
                        tendons=np.empty((b, n, n_t, 3)), status=per_design(np.int64), residual=per_design(),
                        iterations=per_design(np.int64), level=per_design(np.int64), estimate=per_design(),
                        m0=np.empty((b if loaded else 0, 3)), shoot_jac=np.empty((b if loaded else 0, 3, 3)),
                        displacement=np.empty((b, n_t)), jacobian=np.empty((b, n if jacobian else 0, 6, n_t)),
                        nodes=nodes, profile=np.empty((b, n, n_t)))
    return kernel, rods, grid, tols, out


@functools.lru_cache(maxsize=32)
def _tolerances(opts: SolverOptions, *, shortcut: bool, warm: bool):
    """The kernels' :class:`~tdcr.physics._kernel.Tolerances` of ``opts`` (kept: options repeat)."""
    from tdcr.physics._compiled import kernel

    return kernel.Tolerances(newton_tol=float(opts.newton_tol), max_newton=int(opts.max_newton),
                             step_tol=float(opts.step_tol), max_level=int(opts.max_level),
                             shooting_tol=float(opts.shooting_tol), max_shooting=int(opts.max_shooting),
                             shortcut=shortcut, linearized=bool(opts.linearized), warm=warm,
                             displacement_tol=0.1 * float(opts.displacement_tol))


#: Chunks per thread of a batch run side by side (designs differ in cost: smaller chunks balance).
CHUNKS_PER_THREAD = 4
#: Fewer designs than this per thread run on the calling thread (a hand-off costs more than they do).
MIN_DESIGNS_PER_THREAD = 8
_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool of ``threads`` kernel threads, made on first use and kept (a new pool per
    call cost 3 ms, more than a few designs' solve).  Keyed by the process id too: a forked child
    (``training/dataset.py``'s process pool) inherits the parent's pools without their threads."""
    key = (os.getpid(), threads)
    with _POOLS_LOCK:
        if key not in _POOLS:
            _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix="tdcr-kernel")
        return _POOLS[key]


def _run_kernel(entry, threads: int, n_designs: int, *args) -> None:
    """``entry(*args)`` on ``threads`` threads (0: one per core): the designs in contiguous chunks,
    each a call of the compiled ``entry`` (``nogil``) on its rows of the batch-first arguments (the
    :class:`~tdcr.physics._kernel.Rods`, ``Loads`` and ``Shapes`` and the plain arrays; the grid and
    the tolerances are shared).  Designs are independent, so any split gives the same bits."""
    from tdcr.physics._compiled import kernel

    wanted = min(threads or os.cpu_count() or 1, max(n_designs // MIN_DESIGNS_PER_THREAD, 1))
    if wanted <= 1:
        entry(*args)
        return
    batched = (kernel.Rods, kernel.Loads, kernel.Shapes)

    def rows(arg, part: slice):
        if isinstance(arg, batched):
            return type(arg)(*(a[part] if a.shape[0] == n_designs else a for a in arg))
        return arg[part] if isinstance(arg, np.ndarray) else arg

    size = -(-n_designs // (wanted * CHUNKS_PER_THREAD))
    parts = [slice(i, min(i + size, n_designs)) for i in range(0, n_designs, size)]
    for _ in _pool(wanted).map(lambda part: entry(*(rows(a, part) for a in args)), parts):
        pass


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
    return RodSolution(
        s=designs.L[:, None] * fractions_out[None, :], backbone=out.backbone, rotation=out.rotation,
        tendons=out.tendons, section=mat, converged=status == 0, residual=out.residual,
        iterations=out.iterations, status=status, error_estimate=out.estimate,
        steps=(len(edges0) - 1) * 2**out.level, tension=designs.tension.copy(), displacement=out.displacement,
        strains=out.strains, jacobian=out.jacobian if out.jacobian.shape[1] else None, tension_profile=out.profile,
    )


def _solve_loaded_compiled(designs: DesignBatch, fractions_out: np.ndarray, loads: ExternalLoads, opts: SolverOptions,
                           threads: int, *, shortcut: bool = False,
                           base_moment: np.ndarray | None = None) -> RodSolution:
    """The loaded shooting kernel (:func:`tdcr.physics._kernel.solve_loaded_design`) on ``threads``
    threads (0: all): variational shooting Jacobian, load continuation when needed, RK4 with the
    step controlled per design like the tendon-only kernel.  ``base_moment`` ``(B, 3)`` N m (float64,
    C-contiguous): the shooting's M(0) to start each design from where finite (a nearby solve's; NaN:
    the cold first guess), overwritten with each result's M(0)."""
    mat = material(designs)
    f_g, f_tip, m_tip = loads.resolved(designs.n_designs, mat.area)
    edges0 = _base_edges(fractions_out, opts.max_step_loads)
    kernel, rods, grid, tols, out = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=True,
                                                   shortcut=shortcut)
    if base_moment is not None:  # the kernel reads its starts from m0 and writes the results there
        out, tols = out._replace(m0=base_moment), _tolerances(opts, shortcut=bool(shortcut), warm=True)
    _run_kernel(kernel.solve_loaded_batch, threads, designs.n_designs, rods,
                kernel.Loads(f_g=_kernel_array(f_g), f_tip=_kernel_array(f_tip), m_tip=_kernel_array(m_tip)), grid,
                tols, out)
    status = out.status.astype(np.int8)
    status[(status == Status.CONVERGED.value) & several_equilibria(out.shoot_jac)] = Status.MULTIPLE_EQUILIBRIA.value
    return _from_kernel(designs, mat, fractions_out, edges0, out, status)


def _solve_displacement(designs: DesignBatch, fractions_out: np.ndarray, opts: SolverOptions,
                        threads: int, *, sequence: bool = False, creep: np.ndarray | None = None) -> RodSolution:
    """Displacement actuation: the tensions that pull in the displacement-driven tendons' lengths
    (:func:`tdcr.physics._kernel.find_tensions`: Newton with the exact Jacobian of the path
    lengths, tau >= 0, slack tendons flagged), then the tendon-only answer at those tensions, taken on
    from Newton's last shooting where it was at them (:func:`tdcr.physics._kernel.finish_design`: the
    same chain as a solve's level 0, so the same bits as solving again).  A
    tendon's pull-in is its displacement minus its drive's ``zero``; with a series ``stiffness``
    k it pulls with k max(0, pull-in - d) (eq. SE), d the length its path shortened.  With
    ``sequence`` the designs are one robot's commands in order, each started from the tensions
    found for the one before (:func:`tdcr.replay`); with ``creep`` ``(B, N_t)`` m/N they are one chain,
    each pull-in short by what its tendon crept before it (eq. CREEP)."""
    edges0 = _base_edges(fractions_out, opts.max_step)
    mat = material(designs)
    kernel, rods, grid, tols, out = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=False)
    start = np.where(designs.displacement_driven, 0.0, designs.tension)
    rods = rods._replace(tension=_kernel_array(start))  # a new array: the kernel writes the tensions in it
    b, n_t = designs.n_designs, designs.n_tendons
    slack, found = np.zeros((b, n_t), dtype=np.bool_), np.empty(b, dtype=np.int64)
    iterations = np.empty(b, dtype=np.int64)
    wanted = np.where(designs.displacement_driven, designs.displacement - designs.resolved("zero"), np.nan)
    target = _kernel_array(wanted)
    steps = _kernel_array(np.zeros((b, n_t)) if creep is None else creep)
    crept = np.zeros((b, n_t))
    if creep is not None:
        threads = 1  # each design's creep is the designs' before: one chain
    for correction in range(2):
        # the tensions on the base grid and each design's answer at them (from the last shooting there);
        # then, once, again for the target moved by what the answer's finer grid (step control) still
        # misses (the grids' lengths differ by O(h^4))
        _run_kernel(kernel.find_tensions_batch, threads, b, rods, target, grid, tols, slack, found, iterations,
                    sequence, steps, crept, out)
        sol = _tendon_only_answer(designs.replace(tension=rods.tension, displacement=None), mat, fractions_out, edges0,
                                  out, opts)
        miss = np.where(slack, 0.0, wanted - crept - sol.displacement - designs.compliance * rods.tension)
        if correction or not (np.nan_to_num(np.abs(miss)) > opts.displacement_tol).any():
            break
        target = _kernel_array(target + np.nan_to_num(miss))
    status = sol.status.copy()
    status[(status == Status.CONVERGED.value) & (found != 0)] = Status.DISPLACEMENT_NOT_MET.value
    return dataclasses.replace(sol, status=status, converged=status == 0, slack=slack,
                               crept=None if creep is None else crept)


#: Displacement actuation under loads: Newton iterations at most, and step halvings per iteration.
LOADED_DISPLACEMENT_NEWTON, LOADED_DISPLACEMENT_HALVINGS = 30, 6
#: ... the forward difference of the path lengths to a tension: this times max(1 N, the tension), N.
LOADED_DISPLACEMENT_DIFF = 1e-6
#: ... with ``sequence``: one design in this many differences its Jacobian at the start (replays).
LOADED_DISPLACEMENT_SHARED = 8
#: ... with ``sequence`` and ``solve(progress=)``: the designs are solved this many at a time, in order (a
#: multiple of LOADED_DISPLACEMENT_SHARED: every chunk has the whole batch's leaders, so the answers are
#: the same bit for bit), and each chunk is reported as it is done.
LOADED_CHUNK = 32 * LOADED_DISPLACEMENT_SHARED
#: ... Newton goes on to this fraction of ``displacement_tol`` (an answer within the tolerance counts
#: as found): a series spring k turns a miss r into a tension error k r, and the iterations that close
#: the gap are superlinear (at k = 5,000 N/m the tension errors fell from 2e-7 to 3e-13 N).
LOADED_DISPLACEMENT_MARGIN = 0.01


def _solve_displacement_loaded(designs: DesignBatch, fractions_out: np.ndarray, loads: ExternalLoads,
                               opts: SolverOptions, threads: int, *, sequence: bool = False,
                               crept: np.ndarray | None = None, start: np.ndarray | None = None,
                               tension_rate: np.ndarray | None = None,
                               progress: Callable[[int], None] | None = None) -> RodSolution:
    """:func:`_solve_displacement_loaded_batch`, told to ``progress`` as designs are done: a sequence
    :data:`LOADED_CHUNK` designs at a time (the same answers), a batch once, whole."""
    b = designs.n_designs
    if progress is None or not sequence or b <= LOADED_CHUNK:
        sol = _solve_displacement_loaded_batch(designs, fractions_out, loads, opts, threads, sequence=sequence,
                                               crept=crept, start=start, tension_rate=tension_rate)
        if progress is not None:
            progress(b)
        return sol
    parts = []
    for first in range(0, b, LOADED_CHUNK):
        rows = slice(first, min(first + LOADED_CHUNK, b))  # views: tension_rate's rows are filled in place
        parts.append(_solve_displacement_loaded_batch(
            designs.take(rows), fractions_out, loads.take(rows), opts, threads, sequence=True,
            crept=None if crept is None else crept[rows], start=None if start is None else start[rows],
            tension_rate=None if tension_rate is None else tension_rate[rows]))
        progress(rows.stop - first)
    return _concatenate(parts)


def _put(into: RodSolution, rows: np.ndarray, part: RodSolution, which: np.ndarray) -> None:
    """Designs ``rows`` of ``into`` replaced by the designs ``which`` of ``part`` (a solve of the same
    outputs), every per-design field (the section stiffnesses are the design's own in both)."""
    for f in dataclasses.fields(RodSolution):
        target = getattr(into, f.name)
        if isinstance(target, np.ndarray):
            target[rows] = getattr(part, f.name)[which]


def _concatenate(parts: list[RodSolution]) -> RodSolution:
    """One solution of the designs of ``parts``, in order (their batches joined)."""
    def joined(values: list) -> np.ndarray | None:
        return None if values[0] is None else np.concatenate(values)

    out = {f.name: joined([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(RodSolution)
           if f.name != "section"}
    section = None if parts[0].section is None else _Material(
        **{f.name: joined([getattr(p.section, f.name) for p in parts]) for f in dataclasses.fields(_Material)})
    return RodSolution(**out, section=section)


def _solve_displacement_loaded_batch(designs: DesignBatch, fractions_out: np.ndarray, loads: ExternalLoads,
                                     opts: SolverOptions, threads: int, *, sequence: bool = False,
                                     crept: np.ndarray | None = None, start: np.ndarray | None = None,
                                     tension_rate: np.ndarray | None = None) -> RodSolution:
    """Displacement actuation in gravity and under tip loads: the tensions ``tau`` (B, N_t) at which
    every displacement-driven tendon i meets min(s_i tau_i, c_i tau_i + d_i(tau) - w_i) = 0 (eq. SE
    with its slack branch: w_i its pull-in minus its drive's ``zero``, c_i its compliance 1 /
    stiffness, d_i(tau) the shortening of its path under the tensions and the loads, s_i > 0 a scale
    in m/N), then the loaded solve at those tensions (the last accepted one: no shooting again).
    Semismooth Newton on the loaded kernel, started from the unloaded solve's tensions, each loaded
    solve's shooting started from the M(0) of the design's last accepted one; the path lengths'
    Jacobian by forward differences
    (one loaded solve per driven tendon, every design in one batch), then kept up to date by
    Broyden's update along each step, and differenced again where no step along it lowers the miss.
    Each step is capped like the unloaded kernel's (1 N + 50 % of the tension) and halved until the
    worst miss shrinks.  A design from whose tensions no step along a Jacobian differenced there
    lowers the miss stops (the next iteration would repeat the same deterministic solves) and is
    flagged ``displacement_not_met`` unless within the tolerance.  With ``sequence`` (one robot's
    commands in order, :func:`tdcr.replay`) only every :data:`LOADED_DISPLACEMENT_SHARED`-th design
    (a leader) differences its Jacobian at the start, and the designs after it start from its
    Jacobian.  Friction acts as in the unloaded solve (eq. CAP, each tendon's ``motion``): the
    loaded kernel carries it.  ``crept`` ``(B, N_t)`` m: each pull-in falls short by this much (eq.
    CREEP, held); ``start`` ``(B, N_t)`` N: Newton's first tensions (default: the unloaded solve's);
    ``tension_rate`` ``(B, N_t, N_t)`` N/m receives d tau / d w at the answer, the inverse of the last
    Jacobian of the misses over the taut tendons (Broyden's or differenced; zeros where none was
    formed or it is singular)."""
    driven = designs.displacement_driven
    wanted = np.where(driven, designs.displacement - designs.resolved("zero"), 0.0)  # w (B, N_t), m
    if crept is not None:
        wanted = wanted - np.where(driven, crept, 0.0)
    compliance = designs.compliance
    b, n_t = designs.n_designs, designs.n_tendons
    if start is None:
        start = _solve_displacement(designs, fractions_out, opts, threads).tension
    tension = np.maximum(np.nan_to_num(np.where(driven, start, designs.tension)), 0.0)
    scale = np.ones((b, n_t))  # s: the path's own stiffness dd_i/dtau_i, from each Jacobian
    moments = np.full((b, 3), np.nan)  # M(0) of each design's last accepted loaded solve, N m (NaN: none yet)

    def solved_miss(tau: np.ndarray, rows: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, RodSolution]:
        """r = c tau + d(tau) - w (len(rows), N_t), m, of designs ``rows`` at tensions ``tau`` (NaN
        where the loaded solve failed), their shooting started from ``start`` (len(rows), 3), which
        receives the results' M(0); and the loaded solve."""
        sol = _solve_loaded_compiled(designs.take(rows).replace(tension=tau, displacement=None), fractions_out,
                                     loads.take(rows), opts, threads, base_moment=start)
        miss = compliance[rows] * tau + sol.displacement - wanted[rows]
        return np.where((sol.status == Status.CONVERGED.value)[:, None], miss, np.nan), sol

    def phi(tau: np.ndarray, miss: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """min(s tau, r) on the driven tendons, 0 elsewhere (len(rows), N_t), m."""
        return np.where(driven[rows], np.minimum(tau * scale[rows], miss), 0.0)

    def worst(values: np.ndarray) -> np.ndarray:
        return np.where(np.isfinite(values).all(axis=1), np.abs(values).max(axis=1, initial=0.0), np.inf)

    rows = np.arange(b)
    miss, answer = solved_miss(tension, rows, moments)  # the answer: each design's last accepted solve
    found = np.zeros(b, dtype=bool)
    stuck = np.zeros(b, dtype=bool)  # no step from here lowers the miss, along a Jacobian differenced here
    jacobians, refresh = np.zeros((b, n_t, n_t)), np.ones(b, dtype=bool)  # dr/dtau (m/N), and where to difference
    shared = sequence and b > 1
    if shared:  # neighbouring commands are close: one design in LOADED_DISPLACEMENT_SHARED differences
        refresh[:] = np.arange(b) % LOADED_DISPLACEMENT_SHARED == 0
    for iteration in range(LOADED_DISPLACEMENT_NEWTON + 1):
        err = worst(phi(tension[rows], miss, rows))
        found[rows[err <= opts.displacement_tol]] = True
        done = err <= LOADED_DISPLACEMENT_MARGIN * opts.displacement_tol
        rows, miss = rows[~done], miss[~done]
        if iteration == LOADED_DISPLACEMENT_NEWTON:
            break
        solved = np.isfinite(miss).all(axis=1) & ~stuck[rows]  # a failed solve is left to the status
        rows, miss = rows[solved], miss[solved]
        if not rows.size:
            break
        tau = tension[rows]
        followers = np.empty(0, dtype=np.int64)
        if shared:  # the first iteration: a design whose leader is solved takes the leader's Jacobian
            solving = np.zeros(b, dtype=bool)
            solving[rows] = True
            leads = rows // LOADED_DISPLACEMENT_SHARED * LOADED_DISPLACEMENT_SHARED
            refresh[rows[~solving[leads]]] = True  # its leader met the displacements already: its own
            followers, shared = rows[~refresh[rows]], False
        stale = np.nonzero(refresh[rows])[0]  # forward differences where Broyden's updates lost their way
        if stale.size:
            fresh = np.zeros((stale.size, n_t, n_t))
            for j in np.nonzero(driven[rows[stale]].any(axis=0))[0]:
                h = LOADED_DISPLACEMENT_DIFF * np.maximum(1.0, tau[stale, j])
                bumped = tau[stale].copy()
                bumped[:, j] += h
                fresh[:, :, j] = (solved_miss(bumped, rows[stale], moments[rows[stale]])[0] - miss[stale]) / h[:, None]
            jacobians[rows[stale]], refresh[rows[stale]] = fresh, False
        differenced = np.zeros(rows.size, dtype=bool)
        differenced[stale] = True
        jacobians[followers] = jacobians[followers // LOADED_DISPLACEMENT_SHARED * LOADED_DISPLACEMENT_SHARED]
        jac = jacobians[rows]  # dr/dtau, m/N
        scale[rows] = np.maximum(np.abs(np.nan_to_num(np.diagonal(jac, axis1=1, axis2=2))), 1e-9)
        residual = phi(tau, miss, rows)
        on_tension = driven[rows] & (tau * scale[rows] <= miss)  # min() takes s tau: the slack branch
        newton = np.where(on_tension[:, :, None], np.eye(n_t) * scale[rows][:, :, None], jac)
        newton = np.where(driven[rows][:, :, None] & np.isfinite(newton), newton, np.eye(n_t))
        with np.errstate(all="ignore"):
            step = -np.linalg.solve(newton, residual[:, :, None])[:, :, 0]
        cap = 1.0 + 0.5 * tau
        step = np.where(driven[rows], np.clip(np.nan_to_num(step), -cap, cap), 0.0)
        before, old_tau, old_miss = worst(residual), tau.copy(), miss.copy()
        pending = np.arange(rows.size)
        for halving in range(LOADED_DISPLACEMENT_HALVINGS + 1):
            trial = np.maximum(tau[pending] + step[pending] / 2.0**halving, 0.0)
            trial_moments = moments[rows[pending]]  # a copy: kept below where the step is
            trial_miss, trial_answer = solved_miss(trial, rows[pending], trial_moments)
            better = worst(phi(trial, trial_miss, rows[pending])) < before[pending]
            if halving == LOADED_DISPLACEMENT_HALVINGS:
                refresh[rows[pending]] = True  # no step along it lowered the miss: differences next time
                better = np.isfinite(trial_miss).all(axis=1)  # the last halving is kept where it solved
            keep = pending[better]
            tau[keep], miss[keep], moments[rows[keep]] = trial[better], trial_miss[better], trial_moments[better]
            _put(answer, rows[keep], trial_answer, better)
            pending = pending[~better]
            if not pending.size:
                break
        # Broyden's update of dr/dtau along the step taken: J += (dr - J dtau) dtau^T / |dtau|^2
        moved, changed = tau - old_tau, np.nan_to_num(miss - old_miss)
        norm2 = (moved**2).sum(axis=1)
        with np.errstate(all="ignore"):
            unexplained = changed - np.einsum("bij,bj->bi", jac, moved)
            update = unexplained[:, :, None] * moved[:, None, :] / norm2[:, None, None]
        jacobians[rows] = jac + np.where((norm2 > 0.0)[:, None, None], np.nan_to_num(update), 0.0)
        tension[rows] = tau
        # the next iteration would difference the same Jacobian at the same tensions and fail the same
        # steps (every solve is deterministic): such a design is left where it is, to its status
        stuck[rows] = differenced & (moved == 0.0).all(axis=1)
    sol = answer  # the loaded solve at the found tensions (each design's last accepted one: no solve again)
    status = sol.status.copy()
    status[(status == Status.CONVERGED.value) & ~found] = Status.DISPLACEMENT_NOT_MET.value
    slack = driven & (tension == 0.0) & (compliance * tension + sol.displacement - wanted > opts.displacement_tol)
    if tension_rate is not None:
        taut = driven & (tension > 0.0)
        both = taut[:, :, None] & taut[:, None, :]
        block = np.where(both, jacobians, np.eye(n_t))  # the taut tendons' Jacobian, the identity elsewhere
        with np.errstate(all="ignore"):
            formed = np.isfinite(block).all(axis=(1, 2)) & (np.abs(np.linalg.det(block)) > 0.0)
        tension_rate[...] = 0.0
        tension_rate[formed] = np.where(both[formed], np.linalg.inv(block[formed]), 0.0)
    return dataclasses.replace(sol, status=status, converged=status == 0, slack=slack)


def crept_by(creep: np.ndarray, tension: np.ndarray, driven: np.ndarray) -> np.ndarray:
    """Eq. CREEP's sum over a chain of ``B`` designs: how far each tendon had crept by its design,
    e(b) = sum_{j<b} creep_j tau_j, ``(B, N_t)`` m, from ``creep`` ``(B, N_t)`` m/N, the tensions
    ``tension`` ``(B, N_t)`` N and which tendons are ``driven`` ``(B, N_t)`` (the others, and a
    tension that is not finite, add nothing).  The unloaded kernel sums the same as it goes
    (``find_tensions_batch``); the loaded chain's sweeps take it whole."""
    step = np.where(driven & np.isfinite(tension), creep * tension, 0.0)
    return np.concatenate([np.zeros((1, step.shape[1])), np.cumsum(step, axis=0)[:-1]])


#: Creep under loads: sweeps of the whole chain at most (each one loaded displacement solve of every
#: design, its pull-ins short by the creep the last sweep predicts: :func:`_creep_newton`).
CREEP_SWEEPS = 16


def _creep_newton(creep: np.ndarray, tension: np.ndarray, tension_rate: np.ndarray, crept: np.ndarray,
                  driven: np.ndarray) -> np.ndarray:
    """Newton's step for the creep of a chain under loads, ``(B, N_t)`` m: eq. CREEP's sum taken row
    by row with each design's tensions linearised about the last sweep's answer ``tension`` ``(B,
    N_t)`` N, solved at the creep ``crept`` ``(B, N_t)`` m: tau_b(e) = max(0, tau_b - R_b (e -
    crept_b)), R_b = d tau / d w ``tension_rate`` ``(B, N_t, N_t)`` N/m (a pull-in short by e is w -
    e).  A tendon's own relaxation (more creep, less tension, less creep) is then in the step, so the
    sweeps do not overshoot as the plain sum of the last tensions (:func:`crept_by`) does once the
    chain lasts longer than the tendons' relaxation time (r t > 1)."""
    tension = np.where(driven & np.isfinite(tension), tension, 0.0)
    out, so_far = np.empty_like(crept), np.zeros(crept.shape[1])
    for b in range(crept.shape[0]):
        out[b] = so_far
        now = np.maximum(tension[b] - tension_rate[b] @ (so_far - crept[b]), 0.0)
        so_far = so_far + np.where(driven[b], creep[b] * now, 0.0)
    return out


def _solve_creeping_loaded(designs: DesignBatch, fractions_out: np.ndarray, loads: ExternalLoads,
                           opts: SolverOptions, threads: int, creep: np.ndarray, *,
                           progress: Callable[[int], None] | None = None) -> RodSolution:
    """A creeping chain of displacement-driven designs under loads (eq. CREEP with eq. SE under the
    loads): each design's pull-ins short by e(b) = sum_{j<b} creep_j tau_j (:func:`crept_by`) of
    the answer's own tensions.  Newton's sweeps: the unloaded chain gives the first creep, then
    every design is solved under the loads at once (:func:`_solve_displacement_loaded`, started
    from the last sweep's tensions) with its pull-ins short by the creep so far, and the next creep
    is eq. CREEP's sum with each design's tensions linearised about those (:func:`_creep_newton`),
    until the creep of the answer's own tensions (:func:`crept_by`) is the creep it was solved at to
    ``displacement_tol`` (a design whose creep still moves more after :data:`CREEP_SWEEPS` is flagged
    ``displacement_not_met``).
    ``crept`` is the creep its answer was solved at.  ``progress`` hears of every sweep's designs."""
    driven = designs.displacement_driven
    unloaded = _solve_displacement(designs, fractions_out, opts, threads, sequence=True, creep=creep)
    crept, tension = unloaded.crept, unloaded.tension
    rate = np.zeros((*tension.shape, tension.shape[1]))
    for sweep in range(CREEP_SWEEPS):
        sol = _solve_displacement_loaded(designs, fractions_out, loads, opts, threads, sequence=True, crept=crept,
                                         start=np.nan_to_num(tension), tension_rate=rate, progress=progress)
        moved = np.abs(crept_by(creep, sol.tension, driven) - crept).max(axis=1)
        if (moved <= opts.displacement_tol).all() or sweep == CREEP_SWEEPS - 1:
            break
        crept, tension = _creep_newton(creep, sol.tension, rate, crept, driven), sol.tension
    status = sol.status.copy()
    status[(status == Status.CONVERGED.value) & (moved > opts.displacement_tol)] = Status.DISPLACEMENT_NOT_MET.value
    return dataclasses.replace(sol, status=status, converged=status == 0, crept=crept)


def _solve_compiled(designs: DesignBatch, fractions_out: np.ndarray, edges0: np.ndarray, opts: SolverOptions,
                    threads: int, *, jacobian: bool = False, warm: _WarmStart | None = None) -> RodSolution:
    """The tendon-only kernel (:func:`tdcr.physics._kernel.solve_design`) on ``threads`` threads (0: all)."""
    mat = material(designs)
    kernel, rods, grid, tols, out = _kernel_inputs(designs, mat, edges0, fractions_out, opts, loaded=False,
                                                   jacobian=jacobian, warm=warm)
    _run_kernel(kernel.solve_batch, threads, designs.n_designs, rods, grid, tols, out)
    return _tendon_only_answer(designs, mat, fractions_out, edges0, out, opts, warm=warm)


def _tendon_only_answer(designs: DesignBatch, mat: _Material, fractions_out: np.ndarray, edges0: np.ndarray, out,
                        opts: SolverOptions, *, warm: _WarmStart | None = None) -> RodSolution:
    """The :class:`RodSolution` of the tendon-only kernel's outputs ``out`` (:class:`~tdcr.physics._kernel.Shapes`,
    written by ``solve_batch`` or ``find_tensions_batch``): the residual checked against ``opts``,
    collapsed tendons named, ``warm`` kept up."""
    status = out.status.astype(np.int8)
    if not opts.linearized:  # the linearized model reports its residual but is not an equilibrium
        scale = np.maximum(designs.tension.sum(axis=1), 1.0)
        status[(status == Status.CONVERGED.value) & ~(out.residual <= opts.residual_tol * scale)] = \
            Status.RESIDUAL_TOO_LARGE.value
    # Newton stopped (or divided by |g_i| = 0) beside a collapsed tendon
    failed = np.nonzero((status == Status.NEWTON_FAILED.value) | (status == Status.NOT_FINITE.value)
                        & np.isfinite(out.tendons).all(axis=(1, 2, 3)))[0]
    if failed.size:
        status[failed[tendon_collapsed(designs.take(failed), fractions_out, out.strains[failed])]] = \
            Status.TENDON_COLLAPSED.value
    if warm is not None:  # a failed solve is no place to start from
        warm.nodes, warm.valid = out.nodes, bool((status == Status.CONVERGED.value).all())
    return _from_kernel(designs, mat, fractions_out, edges0, out, status)


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
    from tdcr.physics._compiled import kernel

    least = kernel.least_stretch(*(_kernel_array(a) for a in (designs.L, designs.offset, designs.pitch,
                                                               designs.angles, designs.end_fractions, fractions,
                                                               strains)))
    return ~(least >= COLLAPSED_STRETCH)


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
