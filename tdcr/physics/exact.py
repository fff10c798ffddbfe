"""Exact (physics) answers to validated requests: admission by estimated work, each tendon-count
group solved as one batch, the answer as arrays (:class:`ExactAnswer`) or JSON-ready dicts."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

import numpy as np

from tdcr.api.validation import ShapeRequest
from tdcr.physics import STATUS, RodSolution, SolverOptions, Status, solve
from tdcr.physics.cosserat import loaded_kernel
from tdcr.robot.design_space import DEFAULT_POINTS


@dataclass(frozen=True)
class WorkBudget:
    """Admission by estimated solver time on one process: tendon-only designs cost
    ``seconds_per_design`` at 42 points, loaded designs (shooting) ``seconds_per_loaded_design``,
    both scaling with more points (the step grid holds every requested arclength); a request
    estimated over ``max_seconds`` is refused."""

    seconds_per_design: float
    seconds_per_loaded_design: float
    max_seconds: float

    def estimate(self, request: ShapeRequest) -> float:
        """Estimated seconds of ``request`` (a design with displacement actuation costs
        :data:`DISPLACEMENT_COST` tendon-only solves, and under loads :data:`LOADED_DISPLACEMENT_COST`
        loaded ones)."""
        tendon_only = request.n_designs - request.n_loaded + (DISPLACEMENT_COST - 1) * request.n_displacement
        loaded = request.n_loaded + (LOADED_DISPLACEMENT_COST - 1) * request.n_loaded_displacement
        points = max(request.fractions.size, DEFAULT_POINTS) / DEFAULT_POINTS
        return points * (tendon_only * self.seconds_per_design + loaded * self.seconds_per_loaded_design)


#: Tendon-only solves that a design with displacement actuation costs (Newton on its tensions,
#: measured: 22,000 tendon-only designs/s against 2,800 with displacements on 2 cores).
DISPLACEMENT_COST = 8
#: Loaded solves that a design with displacement actuation under loads costs (its unloaded tensions,
#: then Newton with differences on the loaded solver; measured: 53-70 designs/s against about 700
#: loaded ones on 2 cores, benchmarks/any_robot.py).
LOADED_DISPLACEMENT_COST = 13


class TooMuchWork(ValueError):
    """A request whose estimated solver time exceeds its :class:`WorkBudget`."""

    def __init__(self, estimate: float, max_seconds: float):
        self.estimate, self.max_seconds = estimate, max_seconds
        super().__init__(f"these designs would take the solver about {estimate:.3g} s, more than the {max_seconds:g} s "
                         "it admits; send fewer designs or points")

    def __reduce__(self):
        return (TooMuchWork, (self.estimate, self.max_seconds))


def admit(request: ShapeRequest, budget: WorkBudget | None) -> None:
    """:class:`TooMuchWork` if ``request`` is estimated over ``budget`` (None: no budget)."""
    if budget is not None and (estimate := budget.estimate(request)) > budget.max_seconds:
        raise TooMuchWork(estimate, budget.max_seconds)


#: The residual reported for a design whose residual is not finite (JSON has no inf or NaN).
NOT_FINITE_RESIDUAL = sys.float_info.max


@dataclass(frozen=True)
class SolvedGroup:
    """The designs of one tendon count: their request ``rows`` ``(b,)`` and their answer, numbers
    only (a design with non-finite values is reported not converged, status ``not_finite``, those
    values 0 and the residual :data:`NOT_FINITE_RESIDUAL`).

    ``arclength`` ``(b, n)`` m; ``backbone`` ``(b, n, 3)`` m; ``rotation`` ``(b, n, 3, 3)``; ``tendons``
    ``(b, n, N_t, 3)`` m; ``converged`` ``(b,)``; ``residual`` ``(b,)`` N; ``status`` ``(b,)`` indices
    into :data:`tdcr.physics.STATUS`; ``error_estimate`` ``(b,)`` (NaN: none); ``tension`` ``(b, N_t)`` N;
    ``displacement`` ``(b, N_t)`` m; ``tension_profile`` ``(b, n, N_t)`` N (each tendon's tension at
    the arclengths); ``slack`` ``(b, N_t)`` or None (no displacement actuation); ``tip_jacobian``
    ``(b, 6, N_t)`` or None.
    """

    rows: np.ndarray
    arclength: np.ndarray
    backbone: np.ndarray
    rotation: np.ndarray
    tendons: np.ndarray
    converged: np.ndarray
    residual: np.ndarray
    status: np.ndarray
    error_estimate: np.ndarray
    tension: np.ndarray
    displacement: np.ndarray
    tension_profile: np.ndarray
    slack: np.ndarray | None = None
    tip_jacobian: np.ndarray | None = None

    @classmethod
    def of(cls, rows: np.ndarray, sol: RodSolution, *, points: int, tip_jacobian: np.ndarray | None) -> SolvedGroup:
        """The first ``points`` arclengths of ``sol``, made finite."""
        n = slice(points)
        arrays = {"arclength": sol.s[:, n], "backbone": sol.backbone[:, n], "rotation": sol.rotation[:, n],
                  "tendons": sol.tendons[:, n], "tension": sol.tension, "displacement": sol.displacement,
                  "tension_profile": sol.tension_profile[:, n]}
        finite = np.isfinite(sol.residual)
        # one reduction per array: a sum is finite only if every term is (an overflow to inf only
        # sends the check down the exact per-design path)
        if not (finite.all() and np.isfinite([v.sum() for v in arrays.values()]).all()):  # else all finite
            for v in arrays.values():
                finite &= np.isfinite(v.reshape(len(v), -1)).all(axis=1)
        if not finite.all():
            arrays = {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in arrays.items()}
        status = np.where(finite, sol.status, Status.NOT_FINITE.value).astype(np.int32)
        return cls(rows=rows, **arrays, converged=sol.converged & finite,
                   residual=np.where(finite, sol.residual, NOT_FINITE_RESIDUAL), status=status,
                   error_estimate=np.where(np.isfinite(sol.error_estimate), sol.error_estimate, np.nan),
                   slack=sol.slack, tip_jacobian=tip_jacobian)


@dataclass(frozen=True)
class ExactAnswer:
    """The solver's answer to a :class:`ShapeRequest`: the arclength ``fractions`` of L ``(n,)``, and
    by tendon-count group the shapes (:class:`SolvedGroup`)."""

    fractions: np.ndarray
    groups: tuple[SolvedGroup, ...]

    @property
    def n_designs(self) -> int:
        return sum(len(g.rows) for g in self.groups)

    def results(self, *, lists: bool = True) -> list[dict]:
        """One JSON-ready dict per design, in request order: ``s`` (fractions of L), ``arclength``
        (m), ``backbone``, ``rotation``, ``tendons``, ``converged``, ``residual``, ``status`` (a name
        of :data:`STATUS`), ``error_estimate`` (None: none), ``tension``, ``displacement``,
        ``tension_profile``, ``slack`` (displacement actuation) and, if asked, ``tip_jacobian``; the
        arrays as nested lists, or with ``lists=False`` as C-contiguous numpy rows, for
        ``orjson.OPT_SERIALIZE_NUMPY`` (the same JSON, written at half the cost)."""
        row = (lambda a: a.tolist()) if lists else np.ascontiguousarray  # noqa: E731
        results: list[dict | None] = [None] * self.n_designs
        fractions = row(self.fractions)
        for g in self.groups:
            for j, i in enumerate(g.rows.tolist()):
                out = {"s": fractions, "arclength": row(g.arclength[j]), "backbone": row(g.backbone[j]),
                       "rotation": row(g.rotation[j]), "tendons": row(g.tendons[j]),
                       "converged": bool(g.converged[j]), "residual": float(g.residual[j]),
                       "status": STATUS[int(g.status[j])],
                       "error_estimate": None if np.isnan(g.error_estimate[j]) else float(g.error_estimate[j]),
                       "tension": row(g.tension[j]), "displacement": row(g.displacement[j]),
                       "tension_profile": row(g.tension_profile[j])}
                if g.slack is not None:
                    out["slack"] = row(g.slack[j])
                if g.tip_jacobian is not None:
                    out["tip_jacobian"] = row(g.tip_jacobian[j])
                results[i] = out
        return results  # type: ignore[return-value]

    def arrays(self) -> SolvedGroup:
        """The answer as arrays in request order: every design must share one tendon count."""
        if len(self.groups) != 1:
            raise ValueError("the designs have different tendon counts")
        g = self.groups[0]
        if (g.rows == np.arange(len(g.rows))).all():  # already in request order (one group always is)
            return g
        order = np.argsort(g.rows, kind="stable")
        return SolvedGroup(**{f.name: None if getattr(g, f.name) is None else getattr(g, f.name)[order]
                              for f in dataclasses.fields(SolvedGroup)})


def solve_request(request: ShapeRequest, *, options: SolverOptions | None = None) -> ExactAnswer:
    """Solve every design of ``request`` at its arclength fractions ``(n,)``, each tendon-count
    group as one batch."""
    # the tip Jacobian is that of s = L: solved as one more arclength when it is not asked for
    fractions = request.fractions
    tip = np.nonzero(fractions == 1.0)[0]
    if request.jacobian and tip.size == 0:
        fractions = np.append(fractions, 1.0)
    tip_index = int(tip[0]) if tip.size else fractions.size - 1
    groups = []
    for group in request.groups:
        with np.errstate(all="ignore"):  # overflow of an extreme design is reported in its flags
            sol = solve(group.designs, fractions, loads=group.loads, options=options, jacobian=request.jacobian,
                        termination=request.termination, validated=True)
        tip_jacobian = np.nan_to_num(sol.jacobian[:, tip_index]) if request.jacobian else None
        groups.append(SolvedGroup.of(group.rows, sol, points=request.fractions.size, tip_jacobian=tip_jacobian))
    return ExactAnswer(fractions=request.fractions, groups=tuple(groups))


#: The solver's compiled paths, in the order a start compiles them: the default (tendon loads,
#: with segments and the tip Jacobian) first, then external loads (and the rucker_webster rule, the
#: same kernel), then displacement actuation.
PATHS = ("tendon", "loaded", "displacement")
#: What a service compiles before it says ready; the rest follows in the background.
DEFAULT_PATHS = ("tendon",)


def paths_of(request: ShapeRequest) -> frozenset[str]:
    """The compiled paths (:data:`PATHS`) that solving ``request`` runs: ``loaded`` where :func:`solve`
    runs the loaded kernel (:func:`~tdcr.physics.cosserat.loaded_kernel`), ``displacement`` for
    displacement actuation, else ``tendon``."""
    paths = set()
    for group in request.groups:
        if any(loaded_kernel(group.designs, group.loads, request.termination)):
            paths.add("loaded")
        if group.designs.displacement_driven.any():
            paths.add("displacement")
    return frozenset(paths or {"tendon"})


def warm_up(paths: tuple[str, ...] = PATHS) -> bool:
    """Run the solver once on each of ``paths`` (:data:`PATHS`): compiles the numba kernels into
    their cache on first use (a cold cache: about a minute and a half each on 2 cores), loads them
    from it afterwards."""
    from tdcr.robot.design_space import sample_designs, sample_segmented_designs
    from tdcr.robot.designs import ExternalLoads

    unknown = set(paths) - set(PATHS)
    if unknown:
        raise ValueError(f"unknown solver paths {sorted(unknown)}; they are {list(PATHS)}")
    designs, fraction = sample_designs(2, seed=0), np.linspace(0.0, 1.0, 5)
    if "tendon" in paths:
        solve(designs, fraction)
        solve(sample_segmented_designs(1, seed=0), fraction, jacobian=True)
    if "loaded" in paths:
        solve(designs, fraction, loads=ExternalLoads(tip_force=np.array([[0.0, 0.01, 0.0]] * 2)))
        solve(sample_segmented_designs(1, seed=0), fraction, termination="rucker_webster")
    if "displacement" in paths:
        solve(designs.replace(displacement=np.full(designs.offset.shape, 1e-4)), fraction)
    return True
