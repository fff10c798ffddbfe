"""Inverse kinematics: the tensions that put a design's tip on a target.

A target is a tip position p(L) in the base frame (m) and optionally a tip direction R(L) e3.
For each target, in order, warm-started from the previous target's answer (a planner's path), and
with 0 <= tau_i <= tension_max throughout:

1. a bounded Levenberg-Marquardt iteration on the tensions minimises
   |p(tau) - p*|^2 / L^2 + |d(tau) - d*|^2;
2. once on the target (1 % of the tolerance), steps that minimise |tau + dtau|^2 + |J dtau + r|^2 / w
   (w tiny: 1e-10 of the Jacobian's scale) move along the tip's null space: among the tensions
   that reach a target (four tendons leave a one-parameter family for a position) the answer is
   the one with the least sum of squared tensions, i.e. no needless co-contraction.

Each step solves a box-constrained quadratic program exactly (active set; the one batched
Levenberg-Marquardt of :mod:`tdcr.search.lm`, here one problem at a time).  A target not reached
from its start (the tip map of helical routings is not convex) is tried again from all tensions at
tension_max / 2 and from seeded random tensions (:data:`RESTARTS` in all); the best answer is kept.  The Jacobian comes
from :class:`Forward`: exact (the solver's own,
``solve(..., jacobian=True)``) or any model's by central differences.

Status per target: ``reached`` (position error <= tolerance x L, and direction error <= tolerance
when given), ``closest`` (the iteration stopped at the best tip the bounds allow, farther than that),
``failed`` (the forward model failed).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from tdcr.api.validation import InverseProblem
from tdcr.physics import TipSolver, solve
from tdcr.physics.exact import NOT_FINITE_RESIDUAL
from tdcr.robot.designs import DesignBatch
from tdcr.search.lm import Evaluation, box_qp, levenberg_marquardt

#: Relative weight of |tau|^2 (to the Jacobian's scale) in the least-norm steps.
LEAST_NORM_WEIGHT = 1e-10
#: Least-norm steps end below this fraction of tension_max (0.5 mN at 5 N).
LEAST_NORM_STEP = 1e-4
#: Gauss-Newton steps that bring a least-norm step back onto the target before it is judged.
RESTORATION_STEPS = 2
#: Further starts for a target not reached from the warm start: all tensions at tension_max / 2,
#: then seeded uniform draws within the bounds.
RESTARTS = 4
RESTART_SEED = 0
#: Central-difference step of model Jacobians, N.
DIFFERENCE_STEP = 1e-3


@dataclass(frozen=True)
class TipPose:
    """Tip positions ``(T, 3)`` m, tip directions ``(T, 3)``, their Jacobians ``(T, 6, N_t)`` (rows
    0-2 d p / d tau in m/N, rows 3-5 d d / d tau in 1/N), and which of the ``T`` answers are valid."""

    position: np.ndarray
    direction: np.ndarray
    jacobian: np.ndarray
    ok: np.ndarray


#: A forward model of one design: tensions ``(T, N_t)`` -> their :class:`TipPose`.
Forward = Callable[[np.ndarray], TipPose]


def _with_tensions(design: DesignBatch, tensions: np.ndarray) -> DesignBatch:
    """``T`` copies of a one-design batch with the given tensions ``(T, N_t)``."""
    return design.take(np.zeros(tensions.shape[0], dtype=np.int64)).replace(tension=tensions)


def tip_pose_of(position: np.ndarray, frame: np.ndarray, jacobian: np.ndarray, ok: np.ndarray) -> TipPose:
    """A :class:`TipPose` from tip positions, frames and pose Jacobians (rows 3-5 rotation vectors):
    d (R e3) = (dR R^T) R e3 = omega x d for each tension's rotation vector omega."""
    direction = frame[:, :, 2]
    d_direction = np.cross(np.swapaxes(jacobian[:, 3:], 1, 2), direction[:, None, :]).swapaxes(1, 2)
    pose_jacobian = np.concatenate([jacobian[:, :3], d_direction], axis=1)
    ok = ok & np.isfinite(pose_jacobian).all(axis=(1, 2)) & np.isfinite(position).all(axis=1)
    return TipPose(position, direction, pose_jacobian, ok)


def exact_forward(design: DesignBatch) -> Forward:
    """The solver with its exact Jacobian (tendon loads only), Newton warm-started from the last
    evaluation (:class:`tdcr.physics.TipSolver`)."""
    tip = TipSolver(design)

    def forward(tensions: np.ndarray) -> TipPose:
        with np.errstate(all="ignore"):
            sol = tip(tensions)
        return tip_pose_of(sol.backbone[:, -1], sol.rotation[:, -1], sol.jacobian[:, -1], sol.converged)
    return forward


#: the tip, s = L, as the only arclength fraction
TIP = np.ones(1)


def model_tip_pose(predict: Callable[..., dict], *, load_row: np.ndarray | None = None,
                   **options) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Any operator's tip as ``tip_pose(features (K, F)) -> (positions (K, 3) m, frames (K, 3, 3))``,
    float64, from its ``predict(features, fractions, pose=True, **options)`` at s = L (a
    :class:`tdcr.surrogates.runtime.Surrogate`'s or a batcher's); ``load_row`` ``(1, 10)``: the same loads for
    every row.  The one tip-pose helper of inverse kinematics, design search and tip Jacobians."""
    def tip_pose(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        loads = None if load_row is None else np.repeat(load_row, len(features), axis=0)
        out = predict(features, TIP, pose=True, **options, **({} if loads is None else {"loads": loads}))
        return out["backbone"][:, -1].astype(np.float64), out["rotation"][:, -1].astype(np.float64)
    return tip_pose


def model_forward(design: DesignBatch, tip_pose: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], *,
                  step: float = DIFFERENCE_STEP) -> Forward:
    """Any model of the tip, ``tip_pose(features (K, F)) -> (positions (K, 3), frames (K, 3, 3))``,
    with its Jacobian by central differences (:func:`tip_by_differences`)."""
    def forward(tensions: np.ndarray) -> TipPose:
        features = _with_tensions(design, tensions).features()
        with np.errstate(all="ignore"):
            position, frame, jacobian = tip_by_differences(features, tip_pose, step=step)
        return tip_pose_of(position, frame, jacobian, np.ones(len(tensions), dtype=bool))
    return forward


@dataclass(frozen=True)
class InverseResult:
    """One target's answer: ``tensions`` (N_t,) N, the tip ``position`` (3,) m and ``direction``
    (3,) they give, the position ``error`` m, the direction error, ``status`` and ``iterations``."""

    tensions: np.ndarray
    position: np.ndarray
    direction: np.ndarray
    error: float
    direction_error: float
    status: str
    iterations: int


def inverse(forward: Forward, length: float, positions: np.ndarray, directions: np.ndarray | None, *,
            start: np.ndarray, tension_max: float, tolerance: float = 1e-4, max_iterations: int = 60,
            warm_start: bool = True) -> list[InverseResult]:
    """Tensions for each target, in order.

    Args:
        forward: the model of the design's tip (:func:`exact_forward`, :func:`model_forward`).
        length: the design's L, m (positions are weighed in units of L).
        positions: target tip positions, base frame, m, ``(T, 3)``.
        directions: target tip directions ``(T, 3)`` (normalised here; NaN rows: none), or ``None``.
        start: first starting tensions ``(N_t,)`` N (clipped to the bounds).
        tension_max: upper bound of every tension, N.
        tolerance: a target is reached within ``tolerance x L`` (and ``tolerance`` in direction).
        warm_start: start each target from the previous answer (else from ``start``).
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if directions is not None:
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        directions = directions / np.abs(directions).max(axis=1, keepdims=True)  # no overflow in the norm
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    n_t = np.asarray(start).size
    low, high = np.zeros(n_t), np.full(n_t, float(tension_max))
    tau0 = np.clip(np.asarray(start, dtype=np.float64), low, high)
    results = []
    rng = np.random.default_rng(RESTART_SEED)
    for k, target in enumerate(positions):
        wanted = None if directions is None or not np.isfinite(directions[k]).all() else directions[k]
        result = _one_target(forward, length, target, wanted, tau0, low, high, tolerance, max_iterations)
        # the tip map of helical routings is not convex: a start can end in a local minimum
        restarts = [0.5 * high] + [rng.uniform(low, high) for _ in range(RESTARTS - 1)]
        for restart in restarts:
            if result.status == "reached":
                break
            again = _one_target(forward, length, target, wanted, restart, low, high, tolerance, max_iterations)
            if again.status != "failed" and (result.status == "failed" or again.error < result.error):
                result = replace(again, iterations=again.iterations + result.iterations)
        results.append(result)
        if warm_start and result.status != "failed":
            tau0 = result.tensions
    return results


def _residual(pose: TipPose, i: int, target, wanted, length) -> tuple[np.ndarray, np.ndarray]:
    """The weighted residual and its Jacobian for answer ``i`` of ``pose``."""
    r = (pose.position[i] - target) / length
    j = pose.jacobian[i, :3] / length
    if wanted is not None:
        r = np.concatenate([r, pose.direction[i] - wanted])
        j = np.concatenate([j, pose.jacobian[i, 3:]])
    return r, j


def _box_step(h: np.ndarray, g: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """:func:`tdcr.search.lm.box_qp` of one problem ``(n, n)``, ``(n,)``."""
    return box_qp(h[None], g[None], low[None], high[None])[0]


def _one_target(forward, length, target, wanted, tau, low, high, tolerance, max_iterations) -> InverseResult:
    """Levenberg-Marquardt onto the target (:func:`tdcr.search.lm.levenberg_marquardt`), then
    least-norm steps along the tip's null space."""
    pose = forward(tau[None])
    if not pose.ok[0]:
        return _result(tau, pose, target, wanted, "failed", 0)

    def evaluate(trial: np.ndarray, rows: np.ndarray) -> Evaluation:
        at = forward(trial)
        if not at.ok[0]:
            return Evaluation(np.full((1, 3 + 3 * (wanted is not None)), np.nan),
                              np.full((1, 3 + 3 * (wanted is not None), tau.size), np.nan), at.ok, _pose_arrays(at))
        r, j = _residual(at, 0, target, wanted, length)
        return Evaluation(r[None], j[None], at.ok, _pose_arrays(at))

    r, j = _residual(pose, 0, target, wanted, length)
    close = (0.01 * tolerance) ** 2  # |r|^2 that ends the first phase
    solution = levenberg_marquardt(evaluate, tau[None], low[None], high[None], max_iterations=max_iterations,
                                   close=close, start=Evaluation(r[None], j[None], pose.ok, _pose_arrays(pose)))
    tau, r, j = solution.tau[0], solution.at.residual[0], solution.at.jacobian[0]
    pose = TipPose(**solution.at.extra)
    iteration = int(solution.iterations[0])
    scale = float(solution.scale[0])
    if r @ r <= close:  # on the target: the least sum of squared tensions that stays there
        weight = LEAST_NORM_WEIGHT * scale
        on_target = (0.5 * tolerance) ** 2  # what a least-norm step may leave (the next one corrects it)
        while iteration < max_iterations:
            step = _box_step(j.T @ j + weight * np.eye(tau.size), j.T @ r + weight * tau, low - tau, high - tau)
            accepted = False
            for _ in range(8):  # halve a step that leaves the target (the null space is curved)
                if np.abs(step).max() <= LEAST_NORM_STEP * high.max():
                    break
                trial = np.clip(tau + step, low, high)
                for _ in range(RESTORATION_STEPS + 1):  # back onto the target by least-change steps
                    iteration += 1
                    trial_pose = forward(trial[None])
                    if not trial_pose.ok[0]:
                        break
                    tr, tj = _residual(trial_pose, 0, target, wanted, length)
                    if tr @ tr <= close:
                        break
                    trial = np.clip(trial + _box_step(tj.T @ tj + weight * np.eye(tau.size), tj.T @ tr,
                                                      low - trial, high - trial), low, high)
                if trial_pose.ok[0] and tr @ tr <= on_target and trial @ trial < tau @ tau:
                    tau, pose, r, j, accepted = trial, trial_pose, tr, tj, True
                    break
                step = 0.5 * step
            if not accepted:
                break
    return _result(tau, pose, target, wanted, _status(r, wanted, tolerance), iteration)


def _pose_arrays(pose: TipPose) -> dict[str, np.ndarray]:
    return {"position": pose.position, "direction": pose.direction, "jacobian": pose.jacobian, "ok": pose.ok}


def _status(r: np.ndarray, wanted, tolerance: float) -> str:
    position_ok = np.linalg.norm(r[:3]) <= tolerance
    direction_ok = wanted is None or np.linalg.norm(r[3:]) <= tolerance
    return "reached" if position_ok and direction_ok else "closest"


def _result(tau, pose: TipPose, target, wanted, status: str, iterations: int) -> InverseResult:
    error = float(np.linalg.norm(pose.position[0] - target))
    direction_error = 0.0 if wanted is None else float(np.linalg.norm(pose.direction[0] - wanted))
    return InverseResult(tensions=np.asarray(tau, dtype=np.float64), position=pose.position[0],
                         direction=pose.direction[0], error=error, direction_error=direction_error, status=status,
                         iterations=iterations)


def tip_by_differences(features: np.ndarray, tip_pose: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], *,
                       step: float = DIFFERENCE_STEP) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A model's tip pose and its tip Jacobian by central differences in the tensions, in one batch.

    Args:
        features: raw SI designs ``(B, 3 + 3 N_t)``.
        tip_pose: the model, ``features (K, F) -> (tip positions (K, 3) m, tip frames (K, 3, 3))``.
        step: the tension step, N (one-sided where a tension is within a step of 0).

    Returns:
        ``(positions (B, 3), frames (B, 3, 3), jacobian (B, 6, N_t))``: rows 0-2 d p / d tau (m/N),
        rows 3-5 the rotation vector of d R R^T / d tau (rad/N), base frame, as the solver's.
    """
    b, n_t = features.shape[0], (features.shape[1] - 3) // 3
    tension = slice(3 + 2 * n_t, 3 + 3 * n_t)
    eye = np.eye(n_t) * step
    lower = np.repeat(features[:, None, :], n_t, axis=1)
    upper = lower.copy()
    lower[..., tension] = np.maximum(lower[..., tension] - eye[None], 0.0)
    upper[..., tension] += eye[None]
    batch = np.concatenate([features, lower.reshape(-1, features.shape[1]), upper.reshape(-1, features.shape[1])])
    position, frame = tip_pose(batch)
    p_low, p_high = position[b:b + b * n_t].reshape(b, n_t, 3), position[b + b * n_t:].reshape(b, n_t, 3)
    r_low, r_high = frame[b:b + b * n_t].reshape(b, n_t, 3, 3), frame[b + b * n_t:].reshape(b, n_t, 3, 3)
    width = (upper - lower)[..., tension][:, np.arange(n_t), np.arange(n_t)][..., None]  # (B, N_t, 1)
    d_position = (p_high - p_low) / width
    spin = (r_high - r_low) / width[..., None] @ np.swapaxes(frame[:b, None], -1, -2)  # d R R^T
    d_rotation = np.stack([spin[..., 2, 1] - spin[..., 1, 2], spin[..., 0, 2] - spin[..., 2, 0],
                           spin[..., 1, 0] - spin[..., 0, 1]], axis=-1) / 2  # its skew part's vector
    return position[:b], frame[:b], np.swapaxes(np.concatenate([d_position, d_rotation], axis=-1), 1, 2)


def answer(problem: InverseProblem, forward: Forward, *, starts: np.ndarray | None = None,
           max_iterations: int = 60) -> list[dict]:
    """JSON-ready answers of a validated request with ``forward`` (one per target, in order).

    ``starts``: one start per target ``(T, N_t)`` (e.g. a surrogate's answers to polish), without
    warm starts; default: the design's tensions, then each answer warm-starts the next target.
    """
    length = float(problem.design.L[0])
    if starts is None:
        results = inverse(forward, length, problem.positions, problem.directions, start=problem.design.tension[0],
                          tension_max=problem.tension_max, tolerance=problem.tolerance, max_iterations=max_iterations)
    else:
        results = [inverse(forward, length, problem.positions[k:k + 1], problem.directions[k:k + 1], start=start,
                           tension_max=problem.tension_max, tolerance=problem.tolerance,
                           max_iterations=max_iterations)[0] for k, start in enumerate(starts)]
    out = []
    for k, res in enumerate(results):
        finite = np.isfinite(res.position).all() and np.isfinite(res.error)
        item = {"tensions": res.tensions.tolist(),
                "position": res.position.tolist() if finite else [0.0, 0.0, 0.0],
                "error": res.error if finite else NOT_FINITE_RESIDUAL, "status": res.status if finite else "failed",
                "iterations": res.iterations}
        if np.isfinite(problem.directions[k]).all():
            item["direction"] = np.nan_to_num(res.direction).tolist()
        out.append(item)
    return out


#: Estimated forward evaluations per target, for admission (a cold target takes 5-15, restarts more).
EVALUATIONS_PER_TARGET = 20


def _admit(problem: InverseProblem, max_seconds: float | None, seconds_per_design: float, *,
           evaluations: int = EVALUATIONS_PER_TARGET) -> None:
    """:class:`tdcr.physics.exact.TooMuchWork` if ``evaluations`` exact evaluations per target would take
    over ``max_seconds``."""
    from tdcr.physics.exact import TooMuchWork

    estimate = problem.n_targets * evaluations * 4 * seconds_per_design  # ~4 ms per evaluation
    if max_seconds is not None and estimate > max_seconds:
        raise TooMuchWork(estimate, max_seconds)


def answer_exact(problem: InverseProblem, *, starts: np.ndarray | None = None, max_seconds: float | None = None,
                 seconds_per_design: float = 1e-3) -> list[dict]:
    """A validated inverse problem with the exact model, admitted by its estimated work (run in a
    solver process); ``starts`` ``(T, N_t)``: polish these answers (of an operator).  Every answer's
    ``source`` is ``"exact"``.  Raises :class:`tdcr.physics.exact.TooMuchWork`."""
    _admit(problem, max_seconds, seconds_per_design)
    results = answer(problem, exact_forward(problem.design), starts=None if starts is None else np.asarray(starts))
    return [r | {"source": "exact"} for r in results]


def checked(problem: InverseProblem, results: list[dict], *, max_seconds: float | None = None,
            seconds_per_design: float = 1e-3) -> list[dict]:
    """An operator's answers kept to the request's tolerance in exact physics (run in a solver
    process, admitted by one exact evaluation per target; the deadline bounds the rest): the tip at
    each answer's tensions is the exact
    solver's (with the design's loads), and so are the reported ``position``, ``direction``,
    ``error`` and ``status`` (``source`` ``"surrogate"``: the operator's tensions); a target they
    miss (not within ``tolerance x L``) is finished by exact steps from them when the design carries
    tendon loads only (``source`` ``"exact"``; the exact Jacobian covers tendon loads only)."""
    _admit(problem, max_seconds, seconds_per_design, evaluations=1)
    tensions = np.array([r["tensions"] for r in results], dtype=np.float64)
    designs = _with_tensions(problem.design, tensions)
    loads = None
    if problem.loads is not None:
        matrix = np.repeat(problem.loads.matrix(1), len(tensions), axis=0)
        loads = None if not np.any(matrix) else type(problem.loads).from_matrix(matrix)
    with np.errstate(all="ignore"):
        sol = solve(designs, np.ones(1), loads=loads)
    length = float(problem.design.L[0])
    out, missed = [], []
    for k, result in enumerate(results):
        pose = TipPose(position=sol.backbone[k:k + 1, -1], direction=sol.rotation[k:k + 1, -1, :, 2],
                       jacobian=np.zeros((1, 6, tensions.shape[1])), ok=sol.converged[k:k + 1])
        wanted = problem.directions[k] if np.isfinite(problem.directions[k]).all() else None
        target = problem.positions[k]
        verdict = _status(_residual(pose, 0, target, wanted, length)[0], wanted, problem.tolerance) \
            if pose.ok[0] and np.isfinite(pose.position).all() else "failed"
        exact = _result(tensions[k], pose, target, wanted, verdict, result["iterations"])
        item = result | {"position": np.nan_to_num(exact.position).tolist(),
                         "error": exact.error if np.isfinite(exact.error) else NOT_FINITE_RESIDUAL,
                         "status": verdict, "source": "surrogate"}
        if wanted is not None:
            item["direction"] = np.nan_to_num(exact.direction).tolist()
        out.append(item)
        if verdict != "reached" and loads is None:
            missed.append(k)
    if missed:
        sub = replace(problem, positions=problem.positions[missed], directions=problem.directions[missed])
        finished = answer(sub, exact_forward(problem.design), starts=tensions[missed])
        for k, item in zip(missed, finished, strict=True):
            out[k] = item | {"iterations": item["iterations"] + out[k]["iterations"], "source": "exact"}
    return out


def finish(problem: InverseProblem, results: list[dict], *, max_seconds: float | None = None,
           seconds_per_design: float = 1e-3) -> list[dict]:
    """An operator's ``results`` finished in exact physics: every target polished by exact steps
    (``problem.polish``), else :func:`checked`."""
    if problem.polish:
        return answer_exact(problem, starts=np.array([r["tensions"] for r in results]), max_seconds=max_seconds,
                            seconds_per_design=seconds_per_design)
    return checked(problem, results, max_seconds=max_seconds, seconds_per_design=seconds_per_design)
