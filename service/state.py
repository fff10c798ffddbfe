"""What the lifespan handler builds and keeps on ``app.state``."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import numpy as np

from service.batching import Batcher
from service.dataplane import DataPlane
from service.metrics import Metrics
from service.settings import Settings
from service.solver_pool import SolverPool, exact_response
from tdcr import design_space
from tdcr.exact import TooMuchWork, answer_json
from tdcr.inverse import answer_exact_json
from tdcr.runtime import ManifestError, Surrogate, load_manifest
from tdcr.validation import InvalidRequest


@dataclass
class ServiceState:
    settings: Settings
    metrics: Metrics
    manifest: dict = field(default_factory=dict)
    models: dict[str, Surrogate] = field(default_factory=dict)
    batchers: dict[str, Batcher] = field(default_factory=dict)
    default_model: str | None = None
    dataplane: DataPlane | None = None
    pool: SolverPool | None = None
    exact_slots: asyncio.Semaphore | None = None
    ready: bool = False
    problems: list[str] = field(default_factory=list)

    @property
    def pool_healthy(self) -> bool:
        return self.pool is not None and self.pool.healthy

    async def solve_json(self, body: bytes) -> list[dict]:
        """/exact's whole work for a JSON ``SolveRequest``: validation, admission and the solve, in a
        solver process within the deadline.  Raises ``InvalidRequest``, ``TooMuchWork``,
        ``TimeoutError``, ``WorkerDied`` or ``RuntimeError`` (the solver failed)."""
        settings = self.settings
        return await self.pool.run(answer_json, body, limits=settings.exact_limits(), budget=settings.exact_budget(),
                                   timeout=settings.exact_timeout_s, expected=(InvalidRequest, TooMuchWork))


    async def exact_response(self, body: bytes) -> tuple[int, bytes]:
        """As :meth:`solve_json`, the answer JSON-encoded in the solver process: ``(designs, body)``."""
        settings = self.settings
        return await self.pool.run(exact_response, body, limits=settings.exact_limits(),
                                   budget=settings.exact_budget(), timeout=settings.exact_timeout_s,
                                   expected=(InvalidRequest, TooMuchWork))

    async def inverse_json(self, body: bytes, starts: list | None = None) -> list[dict]:
        """/inverse with the exact model (or the exact polish of ``starts``) in a solver process
        within /exact's deadline and admission.  Raises as :meth:`solve_json`."""
        settings = self.settings
        return await self.pool.run(answer_exact_json, body, starts=starts,
                                   max_seconds=settings.exact_budget().max_seconds,
                                   seconds_per_design=settings.exact_seconds_per_design,
                                   timeout=settings.exact_timeout_s, expected=(InvalidRequest, TooMuchWork))


def best_model(manifest: dict) -> str | None:
    """The manifest model with the lowest mean test relative l2 (any model if none has metrics)."""
    models = manifest.get("models", {})

    def score(name):
        m = (models[name].get("metrics") or {}).get("test_relative_l2") or {}
        return m.get("mean", float("inf"))

    return min(models, key=score) if models else None


def load_models(state: ServiceState) -> None:
    """Load every manifest model (checksum verified) and warm it up; record problems instead of raising."""
    settings = state.settings
    try:
        state.manifest = load_manifest(settings.models_dir)
    except ManifestError as exc:
        state.problems.append(str(exc))
        state.dataplane = DataPlane({}, default_model=None, limits=settings.predict_limits())
        return
    warm = design_space.sample_designs(2, seed=0).features()
    for name in state.manifest.get("models", {}):
        try:
            model = Surrogate.load(settings.models_dir, name, threads=settings.onnx_threads,
                                   chunk=settings.onnx_chunk, manifest=state.manifest)
            model.predict(warm, np.linspace(0.0, 1.0, design_space.DEFAULT_POINTS))
        except Exception as exc:  # noqa: BLE001 - any failure makes the model unavailable, reported by /readyz
            state.problems.append(f"model {name}: {exc.__class__.__name__}: {exc}")
            continue
        state.models[name] = model
        state.batchers[name] = Batcher(model, max_designs=state.settings.batch_max_designs,
                                       on_run=state.metrics.batch.labels(name).observe)
    default = settings.default_model or best_model(state.manifest)
    if default is not None and default not in state.models:
        state.problems.append(f"default model {default!r} is not loaded")
    state.default_model = default
    state.dataplane = DataPlane(state.batchers, default_model=default, limits=settings.predict_limits())


def start_pool(state: ServiceState) -> None:
    """Start the solver processes and the /exact admission slots (at startup; blocks for the
    processes' start, about a second each)."""
    state.pool = SolverPool(state.settings.exact_workers)
    state.exact_slots = asyncio.Semaphore(state.settings.exact_max_pending)
