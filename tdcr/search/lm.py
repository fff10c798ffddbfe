"""One batched, box-constrained Levenberg-Marquardt iteration on tendon tensions.

It serves both searches: inverse kinematics (:mod:`tdcr.search.inverse`: one problem per target,
warm-started along a path) and the design search's inner loop (:mod:`tdcr.search.design`: every
candidate x target x start as one batch).  Each problem ``b`` minimises ``|r_b(tau_b)|^2`` over
``low_b <= tau_b <= high_b``; a step solves the damped Gauss-Newton model

    min_dtau 1/2 dtau^T (J^T J + mu I) dtau + (J^T r)^T dtau,  low - tau <= dtau <= high - tau

exactly (:func:`box_qp`), and is taken where it does not raise the cost (then mu shrinks, else it
grows).  A problem stops when its cost is at most ``close``, after ``max_iterations`` steps, when
a step no longer moves it (a stationary point within the bounds), or when mu reaches
:data:`DAMPING_LIMIT` times its scale (no step lowers the cost: the closest point the bounds allow).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

#: The damping mu starts at this fraction of the problem's scale, trace(J^T J) / n.
INITIAL_DAMPING = 1e-3
#: mu after an accepted step (times, at least :data:`DAMPING_FLOOR` x scale) and after a rejected one.
SHRINK, GROW = 0.2, 10.0
DAMPING_FLOOR = 1e-12
#: A problem whose mu exceeds this times its scale stops: no step lowers its cost.
DAMPING_LIMIT = 1e12
#: A step that moves no tension by more than this fraction of the largest upper bound has stalled.
STALL = 1e-12


class Evaluation(NamedTuple):
    """The residuals ``(k, m)`` of ``k`` problems at trial tensions, their Jacobians ``(k, m, n)``,
    which are valid ``(k,)``, and any other arrays ``(k, ...)`` to keep with the accepted point."""

    residual: np.ndarray
    jacobian: np.ndarray
    ok: np.ndarray
    extra: dict[str, np.ndarray]


#: ``evaluate(tau, rows)``: the :class:`Evaluation` of problems ``rows`` ``(k,)`` at tensions ``(k, n)``.
Evaluate = Callable[[np.ndarray, np.ndarray], Evaluation]


@dataclass(frozen=True)
class Solution:
    """Per problem: the tensions ``(B, n)``, the :class:`Evaluation` there (residual ``(B, m)``,
    Jacobian ``(B, m, n)``, ``ok`` ``(B,)``, extra arrays), the cost |r|^2 ``(B,)`` (inf: invalid),
    the steps taken ``(B,)``, the Jacobian's scale trace(J^T J) / n ``(B,)`` and the problems
    evaluated in all (the start included)."""

    tau: np.ndarray
    at: Evaluation
    cost: np.ndarray
    iterations: np.ndarray
    scale: np.ndarray
    evaluations: int


def box_qp(h: np.ndarray, g: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """argmin 1/2 x^T h x + g^T x subject to low <= x <= high, for ``B`` small SPD problems at once:
    ``h`` ``(B, n, n)``, ``g``, ``low``, ``high`` ``(B, n)`` -> ``x`` ``(B, n)``.

    Active set, exactly: clamp the free variables that leave their bounds, release a clamped one
    whose gradient points inside, until neither (at most 4 n + 4 rounds)."""
    h, g = np.asarray(h, dtype=np.float64), np.asarray(g, dtype=np.float64)
    b, n = g.shape
    at_low, at_high = np.zeros((b, n), dtype=bool), np.zeros((b, n), dtype=bool)
    x = np.zeros((b, n))
    todo = np.ones(b, dtype=bool)
    eye = np.eye(n, dtype=bool)
    for _ in range(4 * n + 4):
        if not todo.any():
            break
        k = np.nonzero(todo)[0]
        lo, hi, fixed_low, fixed_high = low[k], high[k], at_low[k], at_high[k]
        fixed = fixed_low | fixed_high
        clamped = np.where(fixed_low, lo, np.where(fixed_high, hi, 0.0))
        free = ~fixed
        # the free block solves h_ff x_f = -g_f - h_fF x_F; fixed rows are the identity
        both = free[:, :, None] & free[:, None, :]
        a = np.where(both, h[k], np.where(eye & fixed[:, :, None], 1.0, 0.0))
        rhs = np.where(free, -g[k] - np.einsum("bij,bj->bi", h[k], clamped), clamped)
        with np.errstate(all="ignore"):
            xk = np.linalg.solve(a, rhs[..., None])[..., 0]
        below, above = free & (xk < lo - 1e-15), free & (xk > hi + 1e-15)
        moved = (below | above).any(axis=1)
        at_low[k] |= below
        at_high[k] |= above
        grad = np.einsum("bij,bj->bi", h[k], xk) + g[k]
        release = ~moved[:, None] & ((fixed_low & (grad < 0)) | (fixed_high & (grad > 0)))
        x[k] = xk
        settled = ~moved & ~release.any(axis=1)
        worst = np.argmax(np.abs(np.where(release, grad, 0.0)), axis=1)
        released = ~moved & release.any(axis=1)
        rows = k[released]
        at_low[rows, worst[released]] = False
        at_high[rows, worst[released]] = False
        todo[k[settled]] = False
    return np.clip(x, low, high)


def levenberg_marquardt(evaluate: Evaluate, tau: np.ndarray, low: np.ndarray, high: np.ndarray, *,
                        max_iterations: int, close: float = 0.0, start: Evaluation | None = None) -> Solution:
    """Minimise |r_b(tau_b)|^2 within ``low <= tau <= high`` (each ``(B, n)``) for ``B`` problems
    at once, from ``tau`` (clipped to the bounds; ``start``: its evaluation, if already made).
    Problems whose start is not valid stay there (``ok`` false, cost inf)."""
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    tau = np.clip(np.asarray(tau, dtype=np.float64), low, high)
    n_problems, n = tau.shape
    everyone = np.arange(n_problems)
    evaluations = 0
    if start is None:
        start = evaluate(tau, everyone)
        evaluations += n_problems
    r, j, ok = start.residual.copy(), start.jacobian.copy(), start.ok.copy()
    extra = {key: np.array(v) for key, v in start.extra.items()}
    cost = np.where(ok, np.einsum("bm,bm->b", r, r), np.inf)
    scale = np.maximum(np.einsum("bmi,bmi->b", j, j) / n, 1e-300)
    scale = np.where(np.isfinite(scale), scale, 1.0)
    damping = INITIAL_DAMPING * scale
    iterations = np.zeros(n_problems, dtype=np.int64)
    stopped = ~ok
    eye = np.eye(n)
    reach = STALL * high.max(axis=1)
    while True:
        active = np.nonzero(~stopped & (iterations < max_iterations) & (cost > close))[0]
        if active.size == 0:
            break
        ja, ra = j[active], r[active]
        step = box_qp(np.einsum("bmi,bmj->bij", ja, ja) + damping[active, None, None] * eye,
                      np.einsum("bmi,bm->bi", ja, ra), low[active] - tau[active], high[active] - tau[active])
        trial = np.clip(tau[active] + np.nan_to_num(step), low[active], high[active])
        at = evaluate(trial, active)
        evaluations += active.size
        iterations[active] += 1
        with np.errstate(invalid="ignore"):
            trial_cost = np.where(at.ok, np.einsum("bm,bm->b", at.residual, at.residual), np.inf)
        accept = at.ok & (trial_cost <= cost[active])
        stalled = accept & (np.abs(trial - tau[active]).max(axis=1) <= reach[active])
        taken = active[accept]
        tau[taken], r[taken], j[taken], cost[taken] = trial[accept], at.residual[accept], at.jacobian[accept], \
            trial_cost[accept]
        for key, v in at.extra.items():
            extra[key][taken] = v[accept]
        damping[active] = np.where(accept, np.maximum(damping[active] * SHRINK, DAMPING_FLOOR * scale[active]),
                                   damping[active] * GROW)
        stopped[active] |= stalled | (~accept & (damping[active] > DAMPING_LIMIT * scale[active]))
    return Solution(tau=tau, at=Evaluation(r, j, ok, extra), cost=cost, iterations=iterations, scale=scale,
                    evaluations=evaluations)
