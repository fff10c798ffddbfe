"""Cost-aware answers: each batch by the cheapest path that still meets its tolerance.

Two paths answer a batch of ``B`` designs:

* **exact**: the solver (:func:`tdcr.physics.solve`), within :data:`tdcr.surrogates.bounds.EXACT_TOLERANCE`
  of the truth, so it meets every admissible tolerance; it costs about ``B`` times a design's solve
  (50x more under gravity or tip loads);
* **operator**: a neural operator (the most accurate of the manifest, its loaded default for designs
  with loads): a graph call whose cost grows slowly with ``B``, its calibrated error bound (the
  bending-angle bins: a lookup, known before the graph runs) and, under a ``tolerance``, the exact
  solves of the ``m`` designs whose bound exceeds it.

:func:`choose` compares the two estimates, ``exact(B)`` against ``operator(B) + exact(m)``,
from :class:`Costs` measured on this machine (:meth:`Costs.measure`), and takes the cheaper.  A
request that names a model is served by that model as asked (the router is not consulted).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from tdcr.api.checks import loaded_rows
from tdcr.surrogates.bounds import EXACT, EXACT_TOLERANCE, SURROGATE, fallback_rows
from tdcr.surrogates.runtime import (
    DEFAULT_MODELS_DIR,
    Surrogate,
    best_model,
    check_inputs,
    load_manifest,
    solve_rows,
)

#: Batches timed by :meth:`Costs.measure` (designs): a path's cost per design falls with the batch
#: (an operator's graph call, the solver's threads), so a line through two small batches overrates
#: a large one.
MEASURED_BATCHES = (1, 16, 128, 1024)


@dataclass(frozen=True)
class Cost:
    """Seconds a path takes for ``B`` designs, measured at ``designs`` (increasing) as ``seconds``:
    linear between them, and beyond the largest on the last segment's slope."""

    designs: tuple[float, ...]
    seconds: tuple[float, ...]

    def __call__(self, n_designs: int) -> float:
        d, t = self.designs, self.seconds
        if n_designs <= d[-1]:
            return float(np.interp(n_designs, d, t))
        slope = max((t[-1] - t[-2]) / (d[-1] - d[-2]), 0.0) if len(d) > 1 else 0.0
        return t[-1] + slope * (n_designs - d[-1])

    @classmethod
    def line(cls, fixed: float, per_design: float) -> Cost:
        """``fixed + per_design * B`` seconds."""
        return cls((0.0, 1.0), (fixed, fixed + per_design))

    def describe(self) -> str:
        """E.g. ``"1: 0.0003 s, 1024: 0.05 s"``."""
        return ", ".join(f"{d:g}: {t:.3g} s" for d, t in zip(self.designs, self.seconds, strict=True))


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


#: The cost of a path that cannot answer (never the cheaper one).
UNAVAILABLE = Cost((0.0,), (math.inf,))


@dataclass(frozen=True)
class Costs:
    """What each path costs on this machine: the ``exact`` solver for tendon-only designs and
    ``exact_loaded`` for designs under gravity or tip loads, the ``operator`` (tendon-only designs)
    and the ``loaded_operator`` (designs with loads; None: none is served)."""

    exact: Cost
    exact_loaded: Cost
    operator: Cost
    loaded_operator: Cost | None = None

    @classmethod
    def measure(cls, operator, loaded_operator=None, *, exact=None, exact_loaded: Cost | None = None,
                repeats: int = 5) -> Costs:
        """Time each path at :data:`MEASURED_BATCHES` designs (Table I, seeded, 42 points; median of
        ``repeats``).  ``operator``, ``loaded_operator``: predictors with ``predict(features, fractions,
        loads=)``; ``exact(features, fractions, loads)``: the exact path (default :func:`solve_rows`
        here, on every core; False: none, :data:`UNAVAILABLE`); ``exact_loaded``: the loaded solver's
        cost where it runs elsewhere (None: timed here, which compiles its kernel on first use).
        About two seconds on 2 cores."""
        from tdcr.robot.design_space import BENCHMARK_LOADS, sample_designs

        timed = {"exact": exact is not False, "exact_loaded": exact is not False and exact_loaded is None}
        exact = solve_rows if exact is None else exact  # solve_rows: every core
        fractions = np.linspace(0.0, 1.0, 42)
        points = {}
        for n in MEASURED_BATCHES:
            features = sample_designs(n, seed=0).features()
            loads = BENCHMARK_LOADS.sample(n, seed=0).matrix(n)
            exact_loaded_n = min(n, 4)  # a loaded solve takes milliseconds: a few designs give its rate
            repeats_n = repeats if n <= 128 else 2
            row = {"operator": _median_seconds(lambda f=features: operator.predict(f, fractions, check=False),
                                               repeats_n)}
            if timed["exact"]:
                row["exact"] = _median_seconds(lambda f=features: exact(f, fractions, None), repeats_n)
            if timed["exact_loaded"]:
                row["exact_loaded"] = _median_seconds(
                    lambda f=features[:exact_loaded_n], m=loads[:exact_loaded_n]: exact(f, fractions, m),
                    repeats_n) * n / exact_loaded_n
            if loaded_operator is not None:
                row["loaded_operator"] = _median_seconds(
                    lambda f=features, m=loads: loaded_operator.predict(f, fractions, loads=m, check=False), repeats_n)
            points[n] = row
        measured = {k: Cost(tuple(map(float, MEASURED_BATCHES)), tuple(points[n][k] for n in MEASURED_BATCHES))
                    for k in points[MEASURED_BATCHES[0]]}
        given = {"exact": UNAVAILABLE, "exact_loaded": UNAVAILABLE if exact is False else exact_loaded}
        return cls(**({k: v for k, v in given.items() if not timed[k]} | measured))


def known_bound(calibration, features: np.ndarray, loads: np.ndarray | None, *,
                tolerance: float | None) -> np.ndarray:
    """The operator's error bound of each design ``(B,)`` as far as it is known before its graph
    runs, for :func:`choose`: the bins' bound (:meth:`tdcr.surrogates.bounds.Calibration.bound`;
    ``loads`` ``(B, 10)`` for a loaded operator, else None); a score that needs the answer (a
    companion's) counts as no fallback; without a ``calibration`` every design falls back under a
    tolerance.  Without a tolerance nothing falls back (:func:`~tdcr.surrogates.bounds.fallback_rows`),
    so the bound is not computed: zeros."""
    if tolerance is None or (calibration is not None and calibration.companion is not None):
        return np.zeros(len(features))
    if calibration is None:
        return np.full(len(features), np.inf)
    return calibration.bound(features, None, loads)


@dataclass(frozen=True)
class Choice:
    """A batch's path (``"exact"`` or ``"operator"``), the estimated seconds of each, and the
    operator's error bound ``(B,)`` that it was weighed with."""

    path: str
    exact_seconds: float
    operator_seconds: float
    error_bound: np.ndarray


def choose(costs: Costs, error_bound: np.ndarray, *, loaded: np.ndarray, tolerance: float | None,
           operator_ready: bool = True, exact_ready: bool = True) -> Choice:
    """The cheaper path for a batch: ``error_bound`` ``(B,)`` the operator's bound of each design,
    ``loaded`` ``(B,)`` the designs under gravity or tip loads.  The operator's estimate adds the
    exact solves of the designs whose bound exceeds ``tolerance``.  A path that is not ready (the
    solver still compiling) is not taken while the other is."""
    n = len(error_bound)
    n_loaded = int(np.count_nonzero(loaded))

    def exact_cost(rows: np.ndarray) -> float:
        heavy = int(np.count_nonzero(loaded[rows]))
        return costs.exact(rows.size - heavy) + (costs.exact_loaded(heavy) if heavy else 0.0)

    operator = costs.loaded_operator if n_loaded and costs.loaded_operator is not None else costs.operator
    fallback = fallback_rows(error_bound, tolerance)
    exact_seconds = exact_cost(np.arange(n))
    operator_seconds = operator(n) + (exact_cost(fallback) if fallback.size else 0.0)
    path = "exact" if exact_seconds <= operator_seconds else "operator"
    if not exact_ready and operator_ready:
        path = "operator"
    elif not operator_ready:
        path = "exact"
    return Choice(path=path, exact_seconds=exact_seconds, operator_seconds=operator_seconds,
                  error_bound=error_bound)


class Router:
    """The cheapest answer of each batch (the module docstring): the exact solver or ``operator``
    (designs without loads) / ``loaded_operator`` (designs with loads; None: the solver answers
    them), with the :class:`Costs` ``costs`` (None: measured on first use).

    >>> router = Router.shipped()
    >>> out = router.predict(sample_designs(1, seed=0).features(), np.linspace(0, 1, 42), tolerance=1e-3)
    >>> out["source"], out["path"]       # (1,) 1: the solver answered, "exact"
    """

    def __init__(self, operator: Surrogate, loaded_operator: Surrogate | None = None, *, costs: Costs | None = None):
        self.operator, self.loaded_operator = operator, loaded_operator
        self._costs = costs

    @classmethod
    def shipped(cls, **options) -> Router:
        """The shipped models' router: the most accurate operator for load-free designs (any
        operator, a loaded one answering with zero loads) and the best loaded one."""
        manifest = load_manifest(DEFAULT_MODELS_DIR)
        name, loaded = best_model(manifest, loads=None), best_model(manifest, loads=True)
        load = lambda n: Surrogate.load(DEFAULT_MODELS_DIR, n, manifest=manifest)  # noqa: E731
        operator = load(name)
        return cls(operator, operator if loaded == name else (load(loaded) if loaded else None), **options)

    @property
    def costs(self) -> Costs:
        if self._costs is None:
            self._costs = Costs.measure(self.operator, self.loaded_operator)
        return self._costs

    def operator_for(self, loaded: bool) -> Surrogate | None:
        """The operator of designs with (``loaded``) or without loads (None: only the solver)."""
        return self.loaded_operator if loaded else self.operator

    def predict(self, features: np.ndarray, fractions: np.ndarray, *, loads=None, tolerance: float | None = None,
                pose: bool = True) -> dict[str, np.ndarray | str]:
        """Backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m of raw
        SI designs ``(B, 15)`` at arclength ``fractions`` ``(n,)``, with ``error_bound`` and ``source``
        ``(B,)`` (0: an operator, 1: the solver) and ``path`` (``"exact"`` or the operator's name)
        by the cheaper path (:func:`choose`); ``loads`` as :meth:`Surrogate.predict`'s, ``tolerance``
        relative l2 kept by every answer.  Validated like :meth:`Surrogate.predict`."""
        fractions, matrix = check_inputs(features, fractions, loads=loads, tolerance=tolerance)  # loads (B, 10)
        features = np.asarray(features, dtype=np.float64)
        fractions = np.asarray(fractions, dtype=np.float64)
        loaded = np.zeros(len(features), dtype=bool) if matrix is None else loaded_rows(matrix)
        operator = self.operator_for(bool(loaded.any()))
        bound = np.full(len(features), np.inf) if operator is None else known_bound(
            operator.calibration, features, operator.load_matrix(matrix, len(features)), tolerance=tolerance)
        choice = choose(self.costs, bound, loaded=loaded, tolerance=tolerance, operator_ready=operator is not None)
        if choice.path == "operator":
            out = operator.predict(features, fractions, loads=matrix, pose=pose, tolerance=tolerance, bound=True,
                                   check=False)
            source = out.get("source", np.full(len(features), SURROGATE, dtype=np.int32))
            return out | {"source": source, "path": operator.name}
        solved = solve_rows(features, fractions, matrix, pose=pose)
        converged = solved.pop("converged")
        return solved | {"error_bound": np.where(converged, EXACT_TOLERANCE, np.inf),
                         "source": np.full(len(features), EXACT, dtype=np.int32), "path": "exact"}
