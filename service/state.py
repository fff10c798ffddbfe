"""What the lifespan handler builds and keeps on ``app.state``: the settings, the metrics, the
manifest and the one :class:`service.dataplane.DataPlane` with its model repository."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field

import numpy as np
from starlette.concurrency import run_in_threadpool

from service.batching import Batcher
from service.dataplane import DataPlane
from service.metrics import Metrics
from service.model import ModelRepository, loaded
from service.routed import AUTO_MODEL, RoutedModel
from service.settings import Settings
from service.solver import ExactModel, InverseModel
from service.surrogate import SurrogateModel
from tdcr import design_space
from tdcr.api.schemas import EXACT_MODEL
from tdcr.surrogates.runtime import ManifestError, Surrogate, best_model, load_manifest

log = logging.getLogger("tdcr.service")


@dataclass
class ServiceState:
    settings: Settings
    metrics: Metrics
    plane: DataPlane
    manifest: dict = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @classmethod
    def create(cls, settings: Settings) -> ServiceState:
        metrics = Metrics.create()
        state = cls(settings=settings, metrics=metrics, plane=DataPlane(ModelRepository(), metrics,
                                                                      inline=settings.inline))
        metrics.solver_slots.set_function(state.solver_slots_in_use)
        return state

    def solver_slots_in_use(self) -> int:
        """Requests holding a solver slot now (0 while the solver starts)."""
        exact = self.exact
        return 0 if exact is None else exact.in_flight

    @property
    def repository(self) -> ModelRepository:
        return self.plane.repository

    @property
    def exact(self) -> ExactModel | None:
        """The solver model (None while the service starts)."""
        return self.repository.models.get(EXACT_MODEL)  # type: ignore[return-value]

    @property
    def default_model(self) -> str | None:
        return self.repository.defaults.get("surrogate")

    @property
    def default_loaded_model(self) -> str | None:
        """The default for designs with loads (a loaded operator; None if none is served)."""
        return self.repository.defaults.get(loaded("surrogate"))

    @property
    def surrogates(self) -> list[str]:
        """The operators served (the router ``auto`` is not one)."""
        return sorted(n for n in self.repository.names("surrogate") if isinstance(self.repository.models[n],
                                                                                   SurrogateModel))

    @property
    def default_operator(self) -> str | None:
        """The operator answering designs without loads by default: the router's, or the default model."""
        routed = self.repository.models.get(AUTO_MODEL)
        return routed.operator.name if isinstance(routed, RoutedModel) else self.default_model

    @property
    def default_loaded_operator(self) -> str | None:
        """The operator answering designs with loads by default: the router's, or the loaded default."""
        routed = self.repository.models.get(AUTO_MODEL)
        if isinstance(routed, RoutedModel):
            return None if routed.loaded is None else routed.loaded.name
        return self.default_loaded_model


def load_models(state: ServiceState, exact: ExactModel | None = None) -> ModelRepository:
    """A repository of the exact solver (``exact``, or a new one), its inverse kinematics and every
    manifest operator (checksum verified, warmed up); problems are recorded instead of raised.  The
    solver's processes start with :meth:`ExactModel.start`.  Blocking: the lifespan runs it in a
    thread, and serves the finished repository (:func:`start`)."""
    settings, repository = state.settings, ModelRepository()
    exact = ExactModel(settings) if exact is None else exact
    repository.register(exact)
    repository.register(InverseModel(exact, lambda name: repository.get(name, kind="surrogate")))
    try:
        state.manifest = load_manifest(settings.models_dir)
    except ManifestError as exc:
        state.problems.append(str(exc))
        return repository
    warm = design_space.sample_designs(2, seed=0).features()
    limits = settings.predict_limits()
    for name in state.manifest.get("models", {}):
        try:
            surrogate = Surrogate.load(settings.models_dir, name, threads=settings.onnx_threads,
                                       chunk=settings.onnx_chunk, manifest=state.manifest)
            surrogate.predict(warm, np.linspace(0.0, 1.0, design_space.DEFAULT_POINTS))
        except Exception as exc:  # noqa: BLE001 - any failure makes the model unavailable, reported by /readyz
            state.problems.append(f"model {name}: {exc.__class__.__name__}: {exc}")
            continue
        batcher = Batcher(surrogate, max_designs=settings.batch_max_designs,
                          on_run=state.metrics.batch.labels(name).observe)
        repository.register(SurrogateModel(surrogate, limits=limits, batcher=batcher))
    guard(repository, exact, state.problems)
    if settings.default_model is not None:  # a configured default, served as asked
        if settings.default_model not in repository.names("surrogate"):
            state.problems.append(f"default model {settings.default_model!r} is not loaded")
        repository.defaults["surrogate"] = settings.default_model
        with_loads = best_model(state.manifest, loads=True)  # the default for designs with loads
        if with_loads in repository.names("surrogate"):
            repository.defaults[loaded("surrogate")] = with_loads
        return repository
    # the router: the cheaper of the solver and the most accurate operator (its loaded default for loads)
    operator, with_loads = best_model(state.manifest, loads=None), best_model(state.manifest, loads=True)
    if operator in repository.names("surrogate"):
        named = repository.models
        routed = RoutedModel(exact, named[operator], named.get(with_loads))  # type: ignore[arg-type]
        repository.register(routed)
        repository.defaults["surrogate"] = repository.defaults[loaded("surrogate")] = routed.name
    elif operator is not None:
        state.problems.append(f"default model {operator!r} is not loaded")
    return repository


def guard(repository: ModelRepository, exact: ExactModel, problems: list[str]) -> None:
    """Give every operator its error bound (none, so every design goes to the solver under a
    tolerance, for an uncalibrated one) and the exact solver behind its tolerance; an operator
    whose score needs a companion that is not served stays unguarded (a problem)."""
    for model in list(repository):
        if not isinstance(model, SurrogateModel):
            continue
        calibration = model.surrogate.calibration
        name = None if calibration is None else calibration.companion
        companion = None if name is None else repository.models.get(name)
        if name is not None and not isinstance(companion, SurrogateModel):
            problems.append(f"model {model.name}: its error bound needs the operator {name!r}, which is not loaded")
            continue
        model.guard_with(companion, exact.solve_from_thread)


async def start(state: ServiceState, *, before_ready=None) -> None:
    """Start the solver processes and load the models side by side, while the server already
    answers (/healthz 200, /readyz 503 and inference 503 "starting" meanwhile).  The service is
    ready once the operators and the router answer: on a machine's first start the solver's
    processes still compile its kernels then (about a minute on 2 cores), and until they are up
    ``exact`` and ``inverse`` say 503 "starting" (their readiness too, and /readyz lists them under
    ``starting``), and the router answers by its operators.  ``before_ready``: an async callback
    given the readiness just before the service reports it (the gRPC health)."""
    log.warning("starting: loading the models of %s while the solver processes start (the first start on a "
                "machine compiles the solver kernels: about a minute on 2 cores, its default path first)",
                state.settings.models_dir)
    exact = ExactModel(state.settings)
    solver = asyncio.ensure_future(run_in_threadpool(exact.start))
    repository = await run_in_threadpool(load_models, state, exact)
    routed = repository.models.get(AUTO_MODEL)
    if isinstance(routed, RoutedModel):  # the operators' costs now; the solver's once it is up
        await run_in_threadpool(routed.measure, exact=False)
    state.plane.repository = repository
    state.plane.loaded = not state.problems and bool(state.surrogates)
    if before_ready is not None:
        await before_ready(state.plane.models_ready())
    state.plane.starting = False
    log.warning("ready=%s models=%s problems=%s starting=%s", state.plane.server_ready(), sorted(repository.names()),
                state.problems, state.plane.starting_models())
    try:
        await solver
    except Exception as exc:  # noqa: BLE001 - reported by /readyz
        exact.failed = True
        state.problems.append(f"solver pool: {exc}")
        state.plane.loaded = False
        return
    if isinstance(routed, RoutedModel):  # the solver's default kernels are in the cache now: load them here
        await run_in_threadpool(routed.measure)
    log.warning("the solver is up: every model ready")
