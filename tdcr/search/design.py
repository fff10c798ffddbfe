"""Design search: the robot that reaches a task's targets, found with an operator and proven with
the exact solver (``tdcr design TASK.json``; :func:`search`).

* **Outer search** over the design (E, r, L, 4 offsets, 4 pitches; minus the task's fixed
  parameters, each scaled to [0, 1] over its bounds): CMA-ES (``cma``, Hansen), seeded.  CMA-ES
  because the tip map is smooth but not convex (helical routings), the space is small (<= 11
  dimensions), a generation is one batch for the operator, and it needs no gradient through the
  inner solve; ``cma`` is the reference implementation, with box bounds.
* **Inner inverse kinematics**, one batch per generation for every candidate x target x start:
  box-constrained Levenberg-Marquardt on the tensions, the tip and its tension Jacobian from the
  operator by central differences (:func:`tdcr.search.inverse.tip_by_differences`), or from the exact
  solver with its exact Jacobian (``inner="exact"``, the baseline).
* **Fitness**: a candidate that reaches every target within the tolerance (the operator's word)
  scores its objective (the largest tension over the targets, the sum of tensions, or L); one that
  does not, ``PENALTY`` plus its summed misses over L.
* **Proof**: the best candidates the operator calls feasible are verified and polished with the
  exact inverse kinematics (:func:`tdcr.search.inverse.answer` with :func:`tdcr.search.inverse.exact_forward`,
  started from the operator's tensions); ``overturned`` counts the candidates physics refused.
  Every reported position, error and ``reached`` is the exact solver's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from tdcr.api.schemas import OBJECTIVES, SEARCH_PARAMETERS, DesignTask
from tdcr.api.validation import InvalidRequest, Problem, check_inverse
from tdcr.robot.design_space import LAYOUT, N_TENDONS, TABLE_I
from tdcr.robot.designs import DesignBatch
from tdcr.search.inverse import answer, exact_forward, model_tip_pose, tip_by_differences
from tdcr.search.lm import Evaluation, levenberg_marquardt

#: Fitness of a candidate that misses a target: above every objective value.
PENALTY = 1e3
#: The operator the search runs on by default (the fastest, pose-predicting one).
DEFAULT_OPERATOR = "deeponet_pose"
#: Inner Levenberg-Marquardt iterations per generation, and its starting tensions (fractions of the
#: bound: low, so that the solutions found pull little).
INNER_ITERATIONS = 12
STARTS = (0.1, 0.5)
#: Candidates per generation and verified candidates per generation (at most).
POPULATION = 24
VERIFY_PER_GENERATION = 2
#: Generations without a better verified design before the search stops.
PATIENCE = 25
ONE = np.ones(1)


@dataclass(frozen=True)
class Task:
    """A validated task: ``positions`` ``(T, 3)`` m, ``directions`` ``(T, 3)`` (NaN rows: none),
    per searched parameter its bounds (``free``: name -> (low, high)), the ``fixed`` values, and
    the options of :class:`tdcr.api.schemas.DesignTask`."""

    positions: np.ndarray
    directions: np.ndarray
    free: dict[str, tuple[float, float]]
    fixed: dict[str, float]
    tension_max: float
    tolerance: float
    objective: str
    seed: int
    budget_s: float

    @property
    def n_targets(self) -> int:
        return len(self.positions)


def validate_task(body: bytes | str | dict) -> Task:
    """A JSON ``DesignTask``: structure (pydantic), then the values: bounds inside the admissible
    ones and ``low < high``, fixed values inside the admissible bounds and not also bounded, and no
    target farther from the base than the longest robot allowed.  Raises :class:`InvalidRequest`
    naming each field."""
    from pydantic import ValidationError

    from tdcr.api.checks import _short

    try:
        task = DesignTask.model_validate(body) if isinstance(body, dict) else DesignTask.model_validate_json(body)
    except ValidationError as exc:
        raise InvalidRequest(Problem(tuple(_short(part) for part in e["loc"]), e["msg"], e["type"])
                             for e in exc.errors(include_input=False, include_url=False)) from None
    problems = []
    free = {}
    for name in SEARCH_PARAMETERS:
        parameter = TABLE_I[name]
        low_ok, high_ok = parameter.admissible
        if name in task.fixed:
            value = task.fixed[name]
            if name in task.bounds:
                problems.append(Problem(("bounds", name), "is also fixed: give one", "fixed_and_bounded"))
            if not low_ok <= value <= high_ok or (parameter.exclusive_min and value == low_ok):
                problems.append(Problem(("fixed", name), f"must be in [{low_ok:g}, {high_ok:g}] {parameter.unit}, "
                                        f"got {value:g}", "out_of_range"))
            continue
        low, high = task.bounds.get(name, (parameter.low, parameter.high))
        if not low < high:
            problems.append(Problem(("bounds", name), f"low must be below high, got [{low:g}, {high:g}]", "bounds"))
        elif low < low_ok or high > high_ok or (parameter.exclusive_min and low == low_ok):
            problems.append(Problem(("bounds", name), f"must lie in the admissible [{low_ok:g}, {high_ok:g}] "
                                    f"{parameter.unit}, got [{low:g}, {high:g}]", "out_of_range"))
        free[name] = (float(low), float(high))
    longest = task.fixed.get("L", free.get("L", (0.0, TABLE_I["L"].high))[1])
    positions = np.array([t.position for t in task.targets], dtype=np.float64)
    for k, p in enumerate(positions):
        if np.linalg.norm(p) > longest:
            problems.append(Problem(("targets", k, "position"), f"is {np.linalg.norm(p):.4g} m from the base, farther "
                                    f"than the longest robot allowed (L <= {longest:g} m)", "unreachable"))
    if problems:
        raise InvalidRequest(problems)
    directions = np.array([np.full(3, np.nan) if t.direction is None else np.asarray(t.direction, dtype=float)
                           for t in task.targets])
    with np.errstate(invalid="ignore"):
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return Task(positions=positions, directions=directions, free=free, fixed=dict(task.fixed),
                tension_max=task.tension_max, tolerance=task.tolerance, objective=task.objective, seed=task.seed,
                budget_s=task.budget_s)


# -- the design space of a task -------------------------------------------------------------------


def _columns(name: str) -> np.ndarray:
    """The feature columns of a parameter (one, or one per tendon)."""
    group = LAYOUT.group(name) if name in ("offset", "pitch") else [("E", "r", "L").index(name)]
    return np.arange(LAYOUT.width)[group]


def features_of(task: Task, x: np.ndarray) -> np.ndarray:
    """Designs ``(P, 15)`` (tensions 0) of points ``x`` ``(P, d)`` in [0, 1]^d over the task's
    free parameters (each tendon's offset and pitch its own coordinate), fixed ones as given."""
    x = np.atleast_2d(x)
    out = np.zeros((len(x), LAYOUT.width))
    j = 0
    for name in SEARCH_PARAMETERS:
        cols = _columns(name)
        if name in task.fixed:
            out[:, cols] = task.fixed[name]
            continue
        low, high = task.free[name]
        out[:, cols] = low + (high - low) * x[:, j:j + cols.size]
        j += cols.size
    return out


def dimensions(task: Task) -> int:
    return sum(_columns(n).size for n in SEARCH_PARAMETERS if n not in task.fixed)


# -- the inner inverse kinematics, batched ----------------------------------------------------------


#: A batched tip model: designs ``(B, 15)`` -> tip positions ``(B, 3)`` m, frames ``(B, 3, 3)`` and
#: their tension Jacobian ``(B, 6, 4)`` (rows 3-5: rotation vectors), and which are valid ``(B,)``.
TipModel = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def operator_tip(surrogate) -> TipModel:
    """An operator's tip and its Jacobian by central differences (one batch of 9 B designs)."""
    tip_pose = model_tip_pose(surrogate.predict, check=False)  # the differences may leave Table I

    def model(features: np.ndarray):
        with np.errstate(all="ignore"):
            position, frame, jacobian = tip_by_differences(features, tip_pose)
        ok = np.isfinite(jacobian).all(axis=(1, 2)) & np.isfinite(position).all(axis=1)
        return position, frame, jacobian, ok
    return model


def exact_tip(features: np.ndarray):
    """The exact solver's tip and its exact Jacobian (tendon loads only) -- a :data:`TipModel`."""
    from tdcr.physics import solve

    with np.errstate(all="ignore"):
        sol = solve(DesignBatch.from_features(features), ONE, jacobian=True)
    jacobian = sol.jacobian[:, -1]
    ok = sol.converged & np.isfinite(jacobian).all(axis=(1, 2))
    return sol.backbone[:, -1], sol.rotation[:, -1], jacobian, ok


def _residual(position, frame, jacobian, targets, directions, lengths):
    """Weighted residuals ``(B, 6)`` and their Jacobians ``(B, 6, 4)``: the position miss over L,
    and the direction miss (zero rows where a target has no direction)."""
    direction = frame[:, :, 2]
    d_direction = np.cross(np.swapaxes(jacobian[:, 3:], 1, 2), direction[:, None, :]).swapaxes(1, 2)
    has = np.isfinite(directions).all(axis=1)
    r = np.concatenate([(position - targets) / lengths[:, None],
                        np.where(has[:, None], direction - np.nan_to_num(directions), 0.0)], axis=1)
    j = np.concatenate([jacobian[:, :3] / lengths[:, None, None], np.where(has[:, None, None], d_direction, 0.0)],
                       axis=1)
    return r, j


def inner_ik(tip: TipModel, features: np.ndarray, targets: np.ndarray, directions: np.ndarray,
             tau: np.ndarray, tension_max: float, iterations: int = INNER_ITERATIONS) -> tuple[np.ndarray, ...]:
    """Box-constrained Levenberg-Marquardt (:func:`tdcr.search.lm.levenberg_marquardt`) on the
    tensions of ``B`` problems at once: designs ``(B, 15)``, targets ``(B, 3)``, directions ``(B, 3)``
    (NaN rows: none), starts ``(B, 4)``.  Returns tensions ``(B, 4)``, tip positions ``(B, 3)``,
    position errors ``(B,)`` m and direction errors ``(B,)`` (|d - d_target|; 0 without a direction;
    inf: the model failed), and the designs evaluated (a model's tip by differences counts each of
    its 1 + 2 N_t designs)."""
    lengths = features[:, 2]
    tension = LAYOUT.group("tension")

    def evaluate(t: np.ndarray, rows: np.ndarray) -> Evaluation:
        f = features[rows].copy()
        f[:, tension] = t
        position, frame, jacobian, ok = tip(f)
        r, j = _residual(position, frame, jacobian, targets[rows], directions[rows], lengths[rows])
        return Evaluation(r, j, ok, {"position": position})

    bounds = np.zeros(tau.shape), np.full(tau.shape, float(tension_max))
    solution = levenberg_marquardt(evaluate, tau, *bounds, max_iterations=iterations)
    finite = np.isfinite(solution.cost)
    position = solution.at.extra["position"]
    error = np.where(finite, np.linalg.norm(position - targets, axis=1), np.inf)
    direction_error = np.where(finite, np.linalg.norm(solution.at.residual[:, 3:], axis=1), np.inf)
    return solution.tau, position, error, direction_error, solution.evaluations * (1 + 2 * N_TENDONS)


# -- the search -------------------------------------------------------------------------------


@dataclass
class Candidate:
    """A design the operator called feasible: its features (tensions 0), per-target tensions
    ``(T, 4)`` and its fitness."""

    features: np.ndarray
    tensions: np.ndarray
    fitness: float


@dataclass
class Result:
    """What :func:`search` found (:meth:`as_json` prints it)."""

    status: str
    features: np.ndarray
    targets: list[dict]
    objective: float
    evaluations: dict[str, int]
    seconds: float
    overturned: int
    generations: int
    history: list[float] = field(default_factory=list)

    def as_json(self) -> dict:
        design = DesignBatch.from_features(self.features[None]).to_dicts()[0]
        design["tendons"] = [{k: v for k, v in t.items() if k != "tension"} for t in design["tendons"]]
        return {"status": self.status, "design": design, "targets": self.targets, "objective": self.objective,
                "evaluations": self.evaluations, "seconds": round(self.seconds, 3), "overturned": self.overturned,
                "generations": self.generations}


def objective_of(task: Task, features: np.ndarray, tensions: np.ndarray) -> float:
    """The task's objective of one design ``(15,)`` and its tensions ``(T, 4)``."""
    if task.objective == "length":
        return float(features[2])
    return float(tensions.max() if task.objective == "max_tension" else tensions.sum())


def verify(task: Task, features: np.ndarray, tensions: np.ndarray) -> tuple[list[dict], int]:
    """The exact inverse kinematics of one design ``(15,)`` from the operator's tensions ``(T, 4)``:
    per target the tensions, the exact tip, its error (m) and ``reached``; and the exact forward
    evaluations spent."""
    design = DesignBatch.from_features(features[None])
    length = float(features[2])
    problem = check_inverse(design, task.positions, task.directions, tension_max=task.tension_max, model="exact",
                            tolerance=min(task.tolerance / length, 0.1))
    results = answer(problem, exact_forward(design), starts=tensions)
    out = [{"tensions": r["tensions"], "position": r["position"], "error": r["error"],
            "reached": r["status"] == "reached" and r["error"] <= task.tolerance}
           | ({"direction": r["direction"]} if "direction" in r else {}) for r in results]
    return out, sum(r["iterations"] for r in results)


def search(task: Task, *, surrogate=None, inner: str = "operator", progress: bool = False) -> Result:
    """The design of ``task`` (see the module docstring): ``surrogate`` (a
    :class:`tdcr.surrogates.runtime.Surrogate`; default :data:`DEFAULT_OPERATOR`) drives the inner inverse
    kinematics, or the exact solver with ``inner="exact"``; ``progress``: a tqdm bar on stderr."""
    import cma
    from tqdm import tqdm

    from tdcr.surrogates.runtime import Surrogate

    if task.objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}")
    started = time.perf_counter()
    tip = exact_tip if inner == "exact" else operator_tip(surrogate or Surrogate.shipped(DEFAULT_OPERATOR))
    d, t = dimensions(task), task.n_targets
    rng = np.random.default_rng(task.seed)
    es = cma.CMAEvolutionStrategy(rng.uniform(0.3, 0.7, d) if d else [], 0.3,
                                  {"bounds": [0.0, 1.0], "seed": task.seed + 1, "popsize": POPULATION,
                                   "verbose": -9}) if d else None
    counts = {"surrogate": 0, "exact": 0}
    pool: list[Candidate] = []
    best: tuple[float, np.ndarray, list[dict]] | None = None  # objective, features, exact targets
    closest: tuple[float, np.ndarray, list[dict]] | None = None  # summed exact miss, features, targets
    tried: list[np.ndarray] = []
    overturned = generations = since = 0
    history = []
    bar = tqdm(total=round(task.budget_s), unit="s", disable=not progress, desc="design", leave=False)
    while time.perf_counter() - started < task.budget_s and (es is None or not es.stop()):
        generations += 1
        xs = np.array(es.ask()) if es is not None else np.zeros((1, 0))
        designs = features_of(task, xs)                                            # (P, 15)
        p = len(designs)
        # every candidate x target x start in one batch
        rows = np.repeat(designs, t * len(STARTS), axis=0)
        targets = np.tile(np.repeat(task.positions, len(STARTS), axis=0), (p, 1))
        directions = np.tile(np.repeat(task.directions, len(STARTS), axis=0), (p, 1))
        starts = np.tile(np.repeat(np.array(STARTS)[:, None] * task.tension_max, N_TENDONS, axis=1), (p * t, 1))
        tau, _, error, turn, evaluated = inner_ik(tip, rows, targets, directions, starts, task.tension_max)
        counts["exact" if inner == "exact" else "surrogate"] += evaluated
        # a miss in metres: the position's, and the direction's times L (the exact inverse kinematics
        # asks both within the tolerance, the direction's over L)
        error = np.maximum(error, turn * rows[:, 2]).reshape(p, t, len(STARTS))
        tau = tau.reshape(p, t, len(STARTS), N_TENDONS)
        pick = np.argmin(error, axis=2)                                            # the better start
        err = np.take_along_axis(error, pick[..., None], axis=2)[..., 0]          # (P, T)
        tensions = np.take_along_axis(tau, pick[..., None, None], axis=2)[:, :, 0]  # (P, T, 4)
        fitness = np.empty(p)
        for k in range(p):
            if np.all(err[k] <= task.tolerance):
                fitness[k] = objective_of(task, designs[k], tensions[k])
                pool.append(Candidate(designs[k], tensions[k], float(fitness[k])))
            else:
                fitness[k] = PENALTY + float(np.nan_to_num(np.maximum(err[k] - task.tolerance, 0.0), posinf=1e3)
                                             .sum() / designs[k, 2])
        if es is not None:
            es.tell(list(xs), list(fitness))
        # prove the best untried candidates the operator calls feasible
        pool.sort(key=lambda c: c.fitness)
        improved = False
        checked = 0
        for candidate in list(pool):
            if checked >= VERIFY_PER_GENERATION or (best is not None and candidate.fitness >= best[0]):
                break
            if any(np.allclose(candidate.features, f, rtol=1e-6) for f in tried):
                pool.remove(candidate)
                continue
            tried.append(candidate.features)
            pool.remove(candidate)
            checked += 1
            results, spent = verify(task, candidate.features, candidate.tensions)
            counts["exact"] += spent
            if all(r["reached"] for r in results):
                value = objective_of(task, candidate.features, np.array([r["tensions"] for r in results]))
                if best is None or value < best[0]:
                    best, improved = (value, candidate.features, results), True
            else:
                overturned += 1
                miss = sum(r["error"] for r in results)
                if closest is None or miss < closest[0]:
                    closest = (miss, candidate.features, results)
        since = 0 if improved else since + 1
        history.append(float(fitness.min()))
        bar.n = min(round(time.perf_counter() - started), bar.total)
        bar.set_postfix(best="-" if best is None else f"{best[0]:.4g}", refresh=True)
        if best is not None and since >= PATIENCE or es is None:
            break
    bar.close()
    if best is None and closest is not None:  # best effort: the proven candidate closest to the task
        miss, features, results = closest
        best = (objective_of(task, features, np.array([r["tensions"] for r in results])), features, results)
    if best is None:  # nothing the operator called feasible: its best candidate, checked by physics
        features = pool[0].features if pool else features_of(task, np.array(es.result.xbest if es else []))[0]
        starts = pool[0].tensions if pool else np.full((t, N_TENDONS), STARTS[0] * task.tension_max)
        results, spent = verify(task, features, starts)
        counts["exact"] += spent
        value = objective_of(task, features, np.array([r["tensions"] for r in results]))
        best = (value, features, results)
    value, features, results = best
    status = "solved" if all(r["reached"] for r in results) else "best_effort"
    return Result(status=status, features=features, targets=results, objective=value, evaluations=counts,
                  seconds=time.perf_counter() - started, overturned=overturned, generations=generations,
                  history=history)


# -- the reachable workspace ---------------------------------------------------------------------


@dataclass(frozen=True)
class Workspace:
    """Reachable tips of one design: ``tips`` ``(n, 3)`` m at ``tensions`` ``(n, 4)`` N drawn
    uniformly in the tension box (the converged ones), the convex hull's volume (m^3) and the
    bounding box."""

    tips: np.ndarray
    tensions: np.ndarray
    volume: float
    low: np.ndarray
    high: np.ndarray
    model: str

    def as_json(self, *, seconds: float) -> dict:
        return {"model": self.model, "samples": len(self.tips), "tips": np.round(self.tips, 9).tolist(),
                "volume": {"m3": self.volume, "method": "volume of the convex hull of the sampled tips "
                           "(scipy.spatial.ConvexHull): the tips of a rod of fixed length form a thin shell, so "
                           "this is the region the shell encloses with its rim's plane, an upper bound of any "
                           "solid reachable region"},
                "bounding_box": {"min": self.low.tolist(), "max": self.high.tolist()}, "seconds": round(seconds, 3)}


def workspace(features: np.ndarray, *, samples: int = 20_000, tension_max: float = 5.0, seed: int = 0,
              surrogate=None) -> Workspace:
    """Monte-Carlo reachable tips of one design ``(15,)`` (its tensions ignored): ``samples``
    tension vectors uniform in [0, ``tension_max``]^4 (seeded) through the exact solver, or
    ``surrogate`` (a :class:`tdcr.surrogates.runtime.Surrogate`)."""
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng([seed, 0x5A])
    tensions = rng.uniform(0.0, tension_max, size=(samples, N_TENDONS))
    rows = np.repeat(np.asarray(features, dtype=np.float64)[None], samples, axis=0)
    rows[:, LAYOUT.group("tension")] = tensions
    if surrogate is None:
        from tdcr.physics import solve

        sol = solve(DesignBatch.from_features(rows), ONE, workers=0)
        tips, ok, model = sol.backbone[:, -1], sol.converged, "exact"
    else:
        tips = surrogate.predict(rows, ONE, check=False)["backbone"][:, -1].astype(np.float64)
        ok, model = np.isfinite(tips).all(axis=1), surrogate.name
    tips, tensions = tips[ok], tensions[ok]
    return Workspace(tips=tips, tensions=tensions, volume=float(ConvexHull(tips).volume), low=tips.min(axis=0),
                     high=tips.max(axis=0), model=model)


def plot_workspace(space: Workspace, path: str) -> None:
    """A PNG of the tips' three projections (x-y, x-z, y-z), mm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    tips = 1e3 * space.tips
    for ax, (i, j, label) in zip(axes, ((0, 1, "x-y"), (0, 2, "x-z"), (1, 2, "y-z")), strict=True):
        ax.scatter(tips[:, i], tips[:, j], s=1, alpha=0.3, color="tab:blue", rasterized=True)
        ax.set_xlabel(f"{'xyz'[i]} (mm)")
        ax.set_ylabel(f"{'xyz'[j]} (mm)")
        ax.set_title(label)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Reachable tips, {len(tips):,} samples ({space.model}); hull volume "
                 f"{1e6 * space.volume:.4g} cm^3")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
