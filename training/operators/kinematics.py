"""Rod kinematics and the linearised-strain reference robot, inside the graph.

Layout: component axes first and the batch last, e.g. vectors ``(3, n, B)`` and rotations
``(3, 3, n, B)``.  onnxruntime then runs every product as a broadcast over small leading axes
with long contiguous inner loops; batched 3 x 3 MatMuls or reductions over 3-long trailing axes
are an order of magnitude slower there.

The reference robot (:func:`linearized_pose`) integrates the strains of the local equilibrium
(W1, W2) evaluated with the tendon tangents of the undeformed rod (:func:`strain_prior`), with
the solver's own 4th-order Magnus scheme on the 42-point grid.  Without any network it is within
a mean relative l2 of about 4e-3 of the exact solution over Table I; the operators learn the rest.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from tdcr.physics.cosserat import POISSON_RATIO, section_stiffness
from tdcr.robot.designs import LOAD_COLUMNS


def cross3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the leading axis, ``(3, ...) x (3, ...) -> (3, ...)``."""
    a0, a1, a2 = a.split(1, dim=0)  # Split + Concat: no per-component Gather / Unsqueeze nodes
    b0, b1, b2 = b.split(1, dim=0)
    return torch.cat([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def matmul3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for 3 x 3 matrices on the two leading axes, ``(3, 3, ...)``: three broadcast products
    (one Split per operand in the exported graph)."""
    a0, a1, a2 = a.split(1, dim=1)
    b0, b1, b2 = b.split(1, dim=0)
    return a0 * b0 + a1 * b1 + a2 * b2


def matvec3(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``a @ v`` for ``(3, 3, ...)`` and ``(3, ...)``."""
    return matmul3(a, v[:, None])[:, 0]


def se3_exp(v: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exponential of twists ``(v, w)`` ``(3, ...)`` on SE(3): ``(R (3, 3, ...), p (3, ...))``.

    Rodrigues: R = (1 - B t^2) I + A hat(w) + B w w^T and p = v + B (w x v) + C w x (w x v), with
    A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, t = |w|; below t = 0.1 their
    Taylor series (truncation < 1e-9) replace the float32-unstable quotients.
    """
    w0, w1, w2 = w.split(1, dim=0)  # (1, ...) each
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    small = t2 < 0.01
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2s)
    sin_t = torch.sin(t)
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, sin_t / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - torch.cos(t)) / t2s)
    c = torch.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - sin_t) / (t2s * t))
    d = 1.0 - b * t2
    aw0, aw1, aw2 = a * w0, a * w1, a * w2
    bw0, bw1, bw2 = b * w0, b * w1, b * w2
    rot = torch.cat([d + bw0 * w0, bw0 * w1 - aw2, bw0 * w2 + aw1,
                     bw1 * w0 + aw2, d + bw1 * w1, bw1 * w2 - aw0,
                     bw2 * w0 - aw1, bw2 * w1 + aw0, d + bw2 * w2])  # (9, ...), row-major
    wxv = cross3(w, v)
    return rot.reshape((3, 3) + tuple(w.shape[1:])), v + b * wxv + c * cross3(w, wxv)


def _magnus_step(xa: torch.Tensor, xm: torch.Tensor, xb: torch.Tensor, step: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """One 4th-order Magnus step (eq. MAG) from body twists ``(6, ...)`` at its start, middle and
    end over length ``step`` (m, broadcast against ``...``): ``(R (3, 3, ...), p (3, ...))``."""
    va, wa = xa.split(3, dim=0)
    vb, wb = xb.split(3, dim=0)
    mean_v, mean_w = ((xa + 4.0 * xm + xb) * (step / 6.0)).split(3, dim=0)
    h2 = step * step / 12.0
    return se3_exp(mean_v + h2 * (cross3(wa, vb) - cross3(wb, va)), mean_w + h2 * cross3(wa, wb))


def magnus_kinematics(xi_nodes: torch.Tensor, xi_mid: torch.Tensor, step: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Integrate g' = g hat(xi) from g(0) = I over K equal steps (the solver's scheme, eq. MAG).

    4th-order Magnus with Simpson nodes, per step
    Omega = h/6 (xi_0 + 4 xi_1/2 + xi_1) + h^2/12 [xi_0, xi_1],  g_{k+1} = g_k exp(Omega),
    with [xi_a, xi_b] = (w_a x v_b - w_b x v_a, w_a x w_b) for xi = (v, w).

    Args:
        xi_nodes: body twists (nu (1), kappa (rad/m)) at the K + 1 step ends, ``(6, K + 1, B)``.
        xi_mid: body twists at the K step midpoints, ``(6, K, B)``.
        step: step length h, m, ``(B,)``.

    Returns:
        ``(backbone (3, K + 1, B) m, rotation (3, 3, K + 1, B))``.
    """
    rot_k, pos_k = _magnus_step(xi_nodes[:, :-1], xi_mid, xi_nodes[:, 1:], step)
    rotation = _prefix_products(rot_k)  # (3, 3, K + 1, B)
    # p_{k+1} = p_k + R_k p_step_k, all steps at once
    moves = matvec3(rotation[:, :, :-1], pos_k)  # (3, K, B)
    backbone = torch.cat([torch.zeros_like(moves[:, :1]), torch.cumsum(moves, dim=1)], dim=1)
    return backbone, rotation


def _prefix_products(steps: torch.Tensor, block: int = 6) -> torch.Tensor:
    """R_0 = I, R_{k+1} = R_k S_k for steps S ``(3, 3, K, B)``; returns ``(3, 3, K + 1, B)``.

    Blocked scan: products inside blocks of ``block`` steps for all blocks at once, then the
    block prefixes one after another, then one product of both.  That is about block + K / block
    sequential 3 x 3 products instead of K (13 instead of 41 for the 42-point grid), so fewer and
    larger graph nodes.
    """
    k = int(steps.shape[2])  # a fixed grid: a constant in the exported graph
    blocks = math.ceil(k / block)
    eye = torch.eye(3, dtype=steps.dtype, device=steps.device)[:, :, None, None]
    ones = torch.zeros_like(steps[:, :, :1]) + eye  # identities (3, 3, 1, B), broadcast (exports cleanly)
    pad = blocks * block - k
    if pad:
        steps = torch.cat([steps] + [ones] * pad, dim=2)
    steps = steps.reshape(3, 3, blocks, block, -1)
    inner = [steps[:, :, :, 0]]  # prefix products inside each block, (3, 3, blocks, B) each
    for j in range(1, block):
        inner.append(matmul3(inner[-1], steps[:, :, :, j]))
    outer = [ones[:, :, 0]]  # product of all earlier blocks, (3, 3, B) each
    for i in range(1, blocks):
        outer.append(matmul3(outer[-1], inner[-1][:, :, i - 1]))
    full = matmul3(torch.stack(outer, dim=2)[:, :, :, None], torch.stack(inner, dim=3))  # (3, 3, blocks, block, B)
    full = full.reshape(3, 3, blocks * block, -1)[:, :, :k]
    return torch.cat([ones, full], dim=2)


class ReferenceRobot(NamedTuple):
    """Pose and tendon offsets of the reference robot, batch last."""

    backbone: torch.Tensor  #: ``(3, n, B)`` m
    rotation: torch.Tensor  #: ``(3, 3, n, B)``
    rho_x: torch.Tensor  #: body-frame tendon offsets, x, ``(N_t, n, B)`` m
    rho_y: torch.Tensor  #: and y (z is 0)

    def tendons(self) -> torch.Tensor:
        """p + R rho_i, m, ``(N_t, 3, n, B)``."""
        return tendon_positions(self.backbone, self.rotation, (self.rho_x, self.rho_y))


def _grid_prior(features: torch.Tensor, grid: torch.Tensor, base_angle: torch.Tensor):
    """On the uniform ``grid`` ``(K + 1,)``: the tendon angles' sines and cosines at the nodes
    ``(N_t, K + 1, B)`` each and at the step midpoints ``(N_t, K, B)`` each (by angle addition:
    phi(s + h/2) = phi(s) + q h / 2), and the first-order strains there (:func:`strain_prior`),
    ``(6, K + 1, B)`` and ``(6, K, B)``."""
    t = base_angle.shape[0]
    sin, cos = _grid_trig(features, grid, base_angle)
    half_turn = features.T[3 + t:3 + 2 * t, None, :] * (0.5 * features[:, 2] * (grid[1] - grid[0]))  # (N_t, 1, B)
    sin_h, cos_h = torch.sin(half_turn), torch.cos(half_turn)
    mid_trig = (sin[:, :-1] * cos_h + cos[:, :-1] * sin_h, cos[:, :-1] * cos_h - sin[:, :-1] * sin_h)
    return ((sin, cos), mid_trig, strain_prior(features, grid, base_angle, (sin, cos)),
            strain_prior(features, grid[:-1], base_angle, mid_trig))


def linearized_reference(features: torch.Tensor, grid: torch.Tensor, base_angle: torch.Tensor,
                         fractions: torch.Tensor | None = None) -> ReferenceRobot:
    """The reference robot on the uniform ``grid`` ``(K + 1,)``, or at any ``fractions`` ``(m,)`` by one
    partial Magnus step from the grid point below (:func:`partial_step`).

    The sines and cosines of the tendon angles at the grid nodes give the strains there, at the
    midpoints (by angle addition) and the tendon offsets.
    """
    (sin, cos), _, xi_nodes, xi_mid = _grid_prior(features, grid, base_angle)
    backbone, rotation = magnus_kinematics(xi_nodes, xi_mid, features[:, 2] * (grid[1] - grid[0]))
    if fractions is None:
        return ReferenceRobot(backbone, rotation, *_offsets(features, (sin, cos)))
    trig_end = tendon_trig(features, fractions, base_angle)
    backbone, rotation = _partial_step(backbone, rotation, xi_nodes, features, fractions, base_angle, trig_end)
    return ReferenceRobot(backbone, rotation, *_offsets(features, trig_end))


def partial_step(backbone: torch.Tensor, rotation: torch.Tensor, features: torch.Tensor, fractions: torch.Tensor,
                 base_angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses at any ``fractions`` ``(m,)`` from poses on the uniform grid of ``n`` points: from the grid
    point s_k just below, one 4th-order Magnus step with the prior strains at s_k, (s_k + s) / 2, s.

    Args:
        backbone: ``(3, n, B)`` m; rotation: ``(3, 3, n, B)`` on the grid j / (n - 1).
        features: raw SI designs ``(B, F)``; fractions: arclength fractions of L ``(m,)``.

    Returns:
        ``(backbone (3, m, B) m, rotation (3, 3, m, B))``.
    """
    grid = torch.linspace(0.0, 1.0, backbone.shape[1], dtype=fractions.dtype, device=fractions.device)
    xi_nodes = strain_prior(features, grid, base_angle)
    return _partial_step(backbone, rotation, xi_nodes, features, fractions, base_angle,
                         tendon_trig(features, fractions, base_angle))


def _partial_step(backbone: torch.Tensor, rotation: torch.Tensor, xi_nodes: torch.Tensor, features: torch.Tensor,
                  fractions: torch.Tensor, base_angle: torch.Tensor, trig_end: tuple[torch.Tensor, torch.Tensor],
                  *, extra: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`partial_step` given the grid strains ``xi_nodes`` ``(6, n, B)`` and the trig at ``fractions``;
    ``extra`` ``(6, n, B)``: strains added on the grid (the loads'), linear between grid points."""
    intervals = backbone.shape[1] - 1
    k = torch.clamp(torch.floor(fractions * intervals), 0, intervals - 1).long()  # (m,)
    s_k = k.to(fractions.dtype) / intervals
    xa = xi_nodes[:, k]
    xm = strain_prior(features, 0.5 * (s_k + fractions), base_angle)
    xb = strain_prior(features, fractions, base_angle, trig_end)
    if extra is not None:
        below, above = extra[:, k], extra[:, k + 1]
        u = ((fractions - s_k) * intervals)[:, None]  # position inside the interval, (m, 1)
        xa = xa + below
        xm = xm + below + (0.5 * u) * (above - below)
        xb = xb + below + u * (above - below)
    rot_s, pos_s = _magnus_step(xa, xm, xb, (fractions - s_k)[:, None] * features[:, 2])  # step (m, B) m
    rot_k, pos_k = rotation[:, :, k], backbone[:, k]
    return pos_k + matvec3(rot_k, pos_s), matmul3(rot_k, rot_s)


def tendon_trig(features: torch.Tensor, fractions: torch.Tensor, base_angle: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """sin and cos of the tendon angles phi_i(s) = 2 pi i / N_t + q_i s, each ``(N_t, n, B)``, for
    ``fractions`` ``(n,)`` or ``(n, B)`` fractions of L (shared by the strains and the tendon offsets)."""
    t = base_angle.shape[0]
    f = features.T  # (F, B)
    s = (fractions[:, None] if fractions.dim() == 1 else fractions) * f[2]  # (n, B) m
    phi = base_angle[:, None, None] + f[3 + t:3 + 2 * t, None, :] * s  # (N_t, n, B) rad
    return torch.sin(phi), torch.cos(phi)


def _grid_trig(features: torch.Tensor, grid: torch.Tensor, base_angle: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`tendon_trig` on a uniform grid of n points with about 2 sqrt(n) sines and cosines per
    tendon instead of n: with j = a m + b (m = ceil(sqrt n)), phi_j = phi_b + a m q h, and
    sin / cos of the sum by angle addition (one complex product, round-off of a few ulp)."""
    n = int(grid.shape[0])  # a fixed grid: constants in the exported graph
    block = math.ceil(math.sqrt(n))
    blocks = math.ceil(n / block)
    t = base_angle.shape[0]
    pitch_length = features.T[3 + t:3 + 2 * t, None, :] * features[:, 2]  # q_i L, (N_t, 1, B) rad
    h = grid[1] - grid[0]
    counts = torch.arange(max(block, blocks), dtype=grid.dtype, device=grid.device)
    inner = base_angle[:, None, None] + pitch_length * (grid[0] + h * counts[:block])[:, None]
    outer = pitch_length * ((h * block) * counts[:blocks])[:, None]  # (N_t, blocks, B)
    s_in, c_in = torch.sin(inner)[:, None], torch.cos(inner)[:, None]  # (N_t, 1, block, B)
    s_out, c_out = torch.sin(outer)[:, :, None], torch.cos(outer)[:, :, None]  # (N_t, blocks, 1, B)
    sin = (s_in * c_out + c_in * s_out).reshape(t, blocks * block, -1)
    cos = (c_in * c_out - s_in * s_out).reshape(t, blocks * block, -1)
    if blocks * block != n:
        sin, cos = sin[:, :n], cos[:, :n]
    return sin, cos


def _tendon_sum(x: torch.Tensor) -> torch.Tensor:
    """Sum over the leading tendon axis, ``(N_t, ...) -> (...)``, as one MatMul with a row of ones
    (onnxruntime's ReduceSum over a short leading axis is about 4x slower)."""
    t = x.shape[0]
    total = torch.matmul(torch.ones(1, t, dtype=x.dtype, device=x.device), x.reshape(t, -1))
    return total.reshape(x.shape[1:])


def strain_prior(features: torch.Tensor, fractions: torch.Tensor, base_angle: torch.Tensor,
                 trig: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Body strains of the local equilibrium (W1, W2) with the tendon tangents of the undeformed rod.

    From K_se (nu - e3) + sum_i tau_i t_i = 0 and K_bt kappa + sum_i tau_i rho_i x t_i = 0 with
    t_i = (e3 + rho_i') / |e3 + rho_i'| = (-o_i q_i sin phi_i, o_i q_i cos phi_i, 1) / c_i,
    c_i = sqrt(1 + (o_i q_i)^2) (offset o_i, pitch q_i), so rho_i x t_i = (o_i sin, -o_i cos, o_i^2 q_i) / c_i.
    Exact for parallel tendons at vanishing load; over Table I the median error of kappa L is 7e-4.

    Args:
        features: raw SI designs ``(B, 3 + 3 N_t)``.
        fractions: arclength fractions ``(n,)`` or ``(n, B)``.
        base_angle: tendon angles 2 pi i / N_t, rad, ``(N_t,)``.
        trig: :func:`tendon_trig` at ``fractions`` when already computed.

    Returns:
        ``(6, n, B)``: nu (1) and kappa (rad/m).
    """
    t = base_angle.shape[0]
    sin, cos = tendon_trig(features, fractions, base_angle) if trig is None else trig
    f = features.T  # (F, B)
    offset, pitch, tension = f[3:3 + t, None, :], f[3 + t:3 + 2 * t, None, :], f[3 + 2 * t:, None, :]  # (N_t, 1, B)
    oq = offset * pitch
    w = tension / torch.sqrt(1.0 + oq * oq)  # tau_i / c_i
    ga, ea, ei, gj = Stiffness.of(features)  # (B,) each
    coef = torch.stack([oq * w / ga, -offset * w / ei], dim=1)  # (N_t, 2, 1, B): nu_x, kappa_x per sin phi_i
    nu_x, kappa_x = _tendon_sum(coef * sin[:, None]).split(1, dim=0)  # (1, n, B) each
    nu_y, kappa_y = _tendon_sum(-coef * cos[:, None]).split(1, dim=0)
    nu_z = 1.0 - w.sum(0) / ea + torch.zeros_like(nu_x)  # (1, n, B)
    kappa_z = -(offset * oq * w).sum(0) / gj + torch.zeros_like(nu_x)
    return torch.cat([nu_x, nu_y, nu_z, kappa_x, kappa_y, kappa_z])


def tendon_offsets(features: torch.Tensor, fractions: torch.Tensor, base_angle: torch.Tensor) -> torch.Tensor:
    """Body-frame tendon offsets rho_i(s), m, ``(2, N_t, n, B)`` (x and y; z is 0)."""
    return torch.stack(_offsets(features, tendon_trig(features, fractions, base_angle)))


def _offsets(features: torch.Tensor, trig: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """rho_i x and y, m, ``(N_t, n, B)`` each, from :func:`tendon_trig`."""
    sin, cos = trig
    offset = features.T[3:3 + sin.shape[0], None, :]  # (N_t, 1, B) m
    return offset * cos, offset * sin


def tendon_positions(backbone: torch.Tensor, rotation: torch.Tensor, rho) -> torch.Tensor:
    """p + R rho_i (paper eq. tend-path), m: ``(3, n, B)``, ``(3, 3, n, B)`` and rho ``(2, N_t, n, B)``
    (or its x and y parts) -> ``(N_t, 3, n, B)`` (rho has no z component)."""
    rho_x, rho_y = rho[0], rho[1]
    return backbone[None] + rotation[:, 0][None] * rho_x[:, None] + rotation[:, 1][None] * rho_y[:, None]


def gram_schmidt(a1: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
    """Rotations with columns b1 = a1 / |a1|, b2 = the normalised part of a2 orthogonal to b1, b1 x b2.
    ``(3, ...)`` each -> ``(3, 3, ...)``."""
    b1 = a1 / torch.sqrt(a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2]).clamp_min(1e-12)
    u2 = a2 - (b1[0] * a2[0] + b1[1] * a2[1] + b1[2] * a2[2]) * b1
    b2 = u2 / torch.sqrt(u2[0] * u2[0] + u2[1] * u2[1] + u2[2] * u2[2]).clamp_min(1e-12)
    return torch.stack([b1, b2, cross3(b1, b2)], dim=1)


def linearized_pose(features: torch.Tensor, grid: torch.Tensor, base_angle: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference robot on the uniform ``grid`` ``(n,)``: the prior strains integrated by
    :func:`magnus_kinematics`.  Returns ``(backbone (3, n, B) m, rotation (3, 3, n, B))``."""
    ref = linearized_reference(features, grid, base_angle)
    return ref.backbone, ref.rotation


def batch_first(x: torch.Tensor) -> torch.Tensor:
    """Batch-last ``(D..., n, B)`` -> batch-first ``(B, n, D...)``.  The n axis moves to the front
    with B kept innermost (rows of B move as blocks), then one 2-D transpose: in onnxruntime about
    6x faster than the equivalent single N-D Transpose."""
    d = x.dim()
    lead = x.permute(d - 2, *range(d - 2), d - 1)  # (n, D..., B)
    return lead.reshape(-1, x.shape[-1]).T.reshape(-1, *lead.shape[:-1])


_GRAVITY, _DENSITY, _FORCE, _MOMENT = (LOAD_COLUMNS[k] for k in ("gravity", "density", "tip_force", "tip_moment"))


class Stiffness(NamedTuple):
    """Section stiffnesses of the designs, ``(B,)`` each: G A and E A (N), E I and G J (N m^2)."""

    ga: torch.Tensor
    ea: torch.Tensor
    ei: torch.Tensor
    gj: torch.Tensor

    @classmethod
    def of(cls, features: torch.Tensor, poisson: torch.Tensor | float = POISSON_RATIO) -> Stiffness:
        """From raw SI designs ``(B, F)`` and their Poisson ratios ``(B,)`` (default the core's
        :data:`tdcr.physics.POISSON_RATIO`, the operators' training value): the core's material
        law, :func:`tdcr.physics.cosserat.section_stiffness`."""
        return cls(*section_stiffness(features[:, 0], features[:, 1], poisson))


def external_wrench(features: torch.Tensor, loads: torch.Tensor, backbone: torch.Tensor, grid: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Internal force and moment that gravity and the tip wrench cause along a given shape.

    Static equilibrium of the piece [s, L] (Rucker & Webster 2011, eqs. 3-4 integrated), base frame:
    n(s) = f (L - s) + F and m(s) = int_s^L (p(t) - p(s)) dt x f + (p(L) - p(s)) x F + M, with
    the weight per length f = rho A g.  The integral is the trapezoid rule on ``grid``.

    Args:
        features: raw SI designs ``(B, F)``; loads: ``(B, 10)`` (:data:`tdcr.robot.designs.LOAD_COLUMNS`).
        backbone: the shape p(s), m, ``(3, n, B)``, on the uniform ``grid`` ``(n,)`` of fractions of L.

    Returns:
        ``(n (3, n, B) N, m (3, n, B) N m)``.
    """
    loads_t = loads.T  # (10, B)
    length, r = features[:, 2], features[:, 1]
    weight = loads_t[_GRAVITY] * (loads_t[_DENSITY] * (math.pi * r * r))  # (3, B) N/m
    force, moment = loads_t[_FORCE][:, None], loads_t[_MOMENT][:, None]  # (3, 1, B)
    remaining = (1.0 - grid)[:, None] * length  # L - s, (n, B) m
    h = (grid[1] - grid[0]) * length  # (B,)
    pieces = (0.5 * h) * (backbone[:, 1:] + backbone[:, :-1])  # (3, K, B)
    done = torch.cumsum(pieces, dim=1)
    total = done[:, -1:]
    tail = torch.cat([total, total - done], dim=1)  # int_s^L p dt, (3, n, B)
    lever = tail - remaining * backbone  # int_s^L (p(t) - p(s)) dt
    force_s = weight[:, None] * remaining + force
    moment_s = cross3(lever, weight[:, None].expand_as(lever)) + cross3(backbone[:, -1:] - backbone,
                                                                      force.expand_as(backbone)) + moment
    return force_s, moment_s


def load_strains(features: torch.Tensor, loads: torch.Tensor, backbone: torch.Tensor, rotation: torch.Tensor,
                 grid: torch.Tensor) -> torch.Tensor:
    """Body strains that the loads add to the tendons' along a given pose (the linear constitutive
    law, eq. 5: nu - e3 = K_se^-1 R^T n, kappa = K_bt^-1 R^T m), ``(6, n, B)``.

    ``backbone`` ``(3, n, B)`` m and ``rotation`` ``(3, 3, n, B)`` on the uniform ``grid`` ``(n,)``.
    """
    force, moment = external_wrench(features, loads, backbone, grid)
    rt = rotation.transpose(0, 1)
    force_b, moment_b = matvec3(rt, force), matvec3(rt, moment)  # body frame
    k = Stiffness.of(features)
    shear = torch.stack([k.ga, k.ga, k.ea])[:, None]  # (3, 1, B)
    bend = torch.stack([k.ei, k.ei, k.gj])[:, None]
    return torch.cat([force_b / shear, moment_b / bend])


def tendon_strains(features: torch.Tensor, trig: tuple[torch.Tensor, torch.Tensor], strains: torch.Tensor
                   ) -> torch.Tensor:
    """Body strains of the local equilibrium (W1, W2) with the tendon tangents of given strains.

    K_se (nu - e3) + sum_i tau_i t_i = 0 and K_bt kappa + sum_i tau_i rho_i x t_i = 0, with the tangents
    t_i = d_i / |d_i| of the tendon paths of ``strains``: d_i = nu + kappa x rho_i + rho_i' (Rucker &
    Webster 2011, eq. 13), rho_i = o_i (cos phi_i, sin phi_i, 0), rho_i' = o_i q_i (-sin phi_i, cos phi_i, 0).
    At ``strains`` = (e3, 0) this is :func:`strain_prior`; its fixed point is the exact tendon-only solution.

    Args:
        features: raw SI designs ``(B, 3 + 3 N_t)``; trig: sin and cos of phi_i, ``(N_t, n, B)`` each.
        strains: nu (1) and kappa (rad/m), ``(6, n, B)``.

    Returns:
        ``(6, n, B)``.
    """
    sin, cos = trig
    t = sin.shape[0]
    f = features.T  # (F, B)
    offset, pitch, tension = f[3:3 + t, None, :], f[3 + t:3 + 2 * t, None, :], f[3 + 2 * t:, None, :]  # (N_t, 1, B)
    nu_x, nu_y, nu_z, k_x, k_y, k_z = strains[:, None]  # (1, n, B) each
    o_sin, o_cos = offset * sin, offset * cos
    d_x = nu_x - (k_z + pitch) * o_sin
    d_y = nu_y + (k_z + pitch) * o_cos
    d_z = nu_z + k_x * o_sin - k_y * o_cos
    w = tension / torch.sqrt(d_x * d_x + d_y * d_y + d_z * d_z)  # tau_i / |d_i|
    f_x, f_y, f_z = w * d_x, w * d_y, w * d_z  # tau_i t_i, (N_t, n, B)
    parts = torch.stack([f_x, f_y, f_z, o_sin * f_z, -o_cos * f_z, o_cos * f_y - o_sin * f_x])  # (6, N_t, n, B)
    total = _tendon_sum(parts.transpose(0, 1))  # (6, n, B): sum_i tau_i t_i and sum_i tau_i rho_i x t_i
    ga, ea, ei, gj = Stiffness.of(features)
    compliance = torch.stack([ga, ga, ea, ei, ei, gj])[:, None]  # (6, 1, B)
    e3 = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=strains.dtype, device=strains.device)[:, None, None]
    return e3 - total / compliance


def _stiffening(features: torch.Tensor, t: int) -> torch.Tensor:
    """1 + the tendons' share of the bending and torsion stiffness, sum_i tau_i o_i^2 / (2 E I) and
    sum_i tau_i o_i^2 / (G J) (evenly spaced tendons), ``(6, 1, B)``: the under-relaxation of the
    fixed-point iteration of :func:`loaded_reference` (its iteration map has these negative
    eigenvalues; dividing the step by them makes it contract)."""
    f = features.T
    share = (f[3 + 2 * t:] * f[3:3 + t] ** 2).sum(0)  # sum_i tau_i o_i^2, (B,) N m^2
    _, _, ei, gj = Stiffness.of(features)
    zero = torch.zeros_like(share)
    return 1.0 + torch.stack([zero, zero, zero, share / (2.0 * ei), share / (2.0 * ei), share / gj])[:, None]


def loaded_reference(features: torch.Tensor, loads: torch.Tensor, grid: torch.Tensor, base_angle: torch.Tensor,
                     fractions: torch.Tensor | None = None, *, iterations: int = 4) -> ReferenceRobot:
    """The reference robot of the loaded operators: ``iterations`` under-relaxed fixed-point passes
    of the local equilibrium under tendons, gravity and a tip wrench, from the first-order strains.

    Each pass takes the tendon tangents from the current strains (:func:`tendon_strains`) and the
    loads' lever arms from the current shape (:func:`load_strains`, the small-deflection response
    along it), and integrates the strains by :func:`magnus_kinematics`.  ``iterations=0`` is
    :func:`linearized_reference`.  Over the loaded benchmark space 4 passes leave a mean relative
    l2 of about 1e-4 (docs/operators.md); the operators learn the rest.

    On the uniform ``grid`` ``(K + 1,)``, or at any ``fractions`` ``(m,)`` by one partial Magnus
    step from the grid point below, with the iterations' strain corrections interpolated linearly.
    """
    (sin, cos), mid_trig, prior_nodes, xi_mid = _grid_prior(features, grid, base_angle)
    xi_nodes = prior_nodes
    step = features[:, 2] * (grid[1] - grid[0])
    backbone, rotation = magnus_kinematics(xi_nodes, xi_mid, step)
    relax = _stiffening(features, base_angle.shape[0])
    for _ in range(iterations):
        extra = load_strains(features, loads, backbone, rotation, grid)
        xi_nodes = xi_nodes + (tendon_strains(features, (sin, cos), xi_nodes) + extra - xi_nodes) / relax
        xi_mid = xi_mid + (tendon_strains(features, mid_trig, xi_mid) + 0.5 * (extra[:, 1:] + extra[:, :-1])
                           - xi_mid) / relax
        backbone, rotation = magnus_kinematics(xi_nodes, xi_mid, step)
    if fractions is None:
        return ReferenceRobot(backbone, rotation, *_offsets(features, (sin, cos)))
    trig_end = tendon_trig(features, fractions, base_angle)
    backbone, rotation = _partial_step(backbone, rotation, prior_nodes, features, fractions, base_angle, trig_end,
                                       extra=xi_nodes - prior_nodes)
    return ReferenceRobot(backbone, rotation, *_offsets(features, trig_end))
