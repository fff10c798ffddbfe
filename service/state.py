"""What the lifespan handler builds and keeps on ``app.state``: the settings, the metrics, the
manifest and the one :class:`service.dataplane.DataPlane` with its model repository."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.batching import Batcher
from service.dataplane import DataPlane
from service.metrics import Metrics
from service.model import ModelRepository
from service.settings import Settings
from service.solver import ExactModel, InverseModel
from service.surrogate import SurrogateModel
from tdcr import design_space
from tdcr.runtime import ManifestError, Surrogate, load_manifest


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
        return cls(settings=settings, metrics=metrics, plane=DataPlane(ModelRepository(), metrics))

    @property
    def repository(self) -> ModelRepository:
        return self.plane.repository

    @property
    def exact(self) -> ExactModel:
        return self.repository.get(None, kind="solver")  # type: ignore[return-value]

    @property
    def default_model(self) -> str | None:
        return self.repository.defaults.get("surrogate")

    @property
    def surrogates(self) -> list[str]:
        return sorted(self.repository.names("surrogate"))


def best_model(manifest: dict) -> str | None:
    """The manifest model with the lowest mean test relative l2 (any model if none has metrics)."""
    models = manifest.get("models", {})

    def score(name):
        m = (models[name].get("metrics") or {}).get("test_relative_l2") or {}
        return m.get("mean", float("inf"))

    return min(models, key=score) if models else None


def load_models(state: ServiceState) -> None:
    """Register the exact solver, its inverse kinematics and every manifest operator (checksum
    verified, warmed up); record problems instead of raising.  The solver's processes start in
    :func:`start_solver`."""
    settings, repository = state.settings, state.repository
    exact = ExactModel(settings)
    repository.register(exact)
    repository.register(InverseModel(exact, lambda name: repository.get(name, kind="surrogate")))
    try:
        state.manifest = load_manifest(settings.models_dir)
    except ManifestError as exc:
        state.problems.append(str(exc))
        return
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
    default = settings.default_model or best_model(state.manifest)
    if default is not None:
        if default not in repository.names("surrogate"):
            state.problems.append(f"default model {default!r} is not loaded")
        repository.defaults["surrogate"] = default


def start_solver(state: ServiceState) -> None:
    """Start the exact model's solver processes (at startup)."""
    state.exact.start()
