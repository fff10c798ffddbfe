"""What the lifespan handler builds and keeps on ``app.state``."""

from __future__ import annotations

import asyncio
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from service.batching import Batcher
from service.dataplane import DataPlane
from service.metrics import Metrics
from service.settings import Settings
from tdcr import design_space
from tdcr.runtime import ManifestError, Surrogate, load_manifest


@dataclass
class ServiceState:
    settings: Settings
    metrics: Metrics
    manifest: dict = field(default_factory=dict)
    models: dict[str, Surrogate] = field(default_factory=dict)
    batchers: dict[str, Batcher] = field(default_factory=dict)
    default_model: str | None = None
    dataplane: DataPlane | None = None
    pool: ProcessPoolExecutor | None = None
    exact_slots: asyncio.Semaphore | None = None
    ready: bool = False
    problems: list[str] = field(default_factory=list)


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


def new_pool(settings: Settings) -> ProcessPoolExecutor:
    """Solver processes behind /exact, started and warmed up (blocking: call outside the event loop)."""
    from tdcr.exact import warm_up

    pool = ProcessPoolExecutor(max_workers=settings.exact_workers, mp_context=multiprocessing.get_context("spawn"))
    for f in [pool.submit(warm_up) for _ in range(settings.exact_workers)]:
        f.result(timeout=120)
    return pool


def start_pool(state: ServiceState) -> None:
    """Start the solver pool and the /exact admission slots (at startup)."""
    state.pool = new_pool(state.settings)
    state.exact_slots = asyncio.Semaphore(state.settings.exact_max_pending)


def stop_pool(pool: ProcessPoolExecutor, grace_s: float = 5.0) -> None:
    """Stop the solver processes: cancel queued work, give running work ``grace_s`` seconds, then
    terminate whatever is left (a plain ``shutdown(wait=False)`` leaves them running after the
    server exits)."""
    processes = list(getattr(pool, "_processes", {}).values())  # no public handle on the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        proc.join(timeout=grace_s)
        if proc.is_alive():
            proc.terminate()
