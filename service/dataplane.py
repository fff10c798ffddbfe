"""The one data plane: every transport (``/predict``, ``/exact``, ``/inverse``, OIP v2 over REST and
gRPC) calls :meth:`DataPlane.infer`, as KServe's REST and gRPC servers call its ``DataPlane``.

It looks the model up in the :class:`service.model.ModelRepository` (a request names a model, or
the default of the kind its transport serves), answers readiness and metadata, runs the model's
``infer`` and records latency and designs in the metrics.  Errors leave it as
:class:`service.model.InferenceError` only; each transport maps their kinds to its statuses in
one place.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import tdcr
from service.metrics import Metrics
from service.model import (
    RETRY_STARTING_S,
    InferenceError,
    InferenceRequest,
    InferenceResponse,
    Kind,
    Model,
    ModelRepository,
)
from service.oip import EXTENSIONS, SERVER_NAME
from tdcr.api.validation import InvalidRequest

#: What /readyz and every inference say while the service starts.
STARTING = "starting: loading the models and starting the solver processes (the first start compiles the solver)"


class DataPlane:
    """Inference, readiness and metadata of the models of ``repository``; ``loaded``: the models
    loaded as configured (no problem at startup); ``inline``: short requests may be answered on the
    event loop (:meth:`infer`)."""

    def __init__(self, repository: ModelRepository, metrics: Metrics, *, inline: bool = True):
        self.repository = repository
        self.inline = inline
        self.metrics = metrics
        self.loaded = False
        self.starting = False  # the models are being loaded and the solver started (service.state.start)
        self.in_flight = 0  # inferences awaiting a worker thread or a solver process (event-loop thread only)

    # -- health and metadata ----------------------------------------------------------------------

    def server_ready(self) -> bool:
        """Started, and :meth:`models_ready`."""
        return not self.starting and self.models_ready()

    def models_ready(self) -> bool:
        """Every model loaded and ready, but for those still starting (:meth:`starting_models`)."""
        return self.loaded and all(m.ready() or m.starting for m in self.repository)

    def problems(self) -> list[str]:
        """Why a model cannot answer now (e.g. a solver process being replaced)."""
        if self.starting:
            return [STARTING]
        return [p for m in self.repository if not m.starting and (p := m.health()) is not None]

    def starting_models(self) -> dict[str, str]:
        """The models still starting after the service became ready, and what they say."""
        return {m.name: m.starting_note() for m in self.repository if m.starting}

    def compiling(self) -> dict[str, list[str]]:
        """The solver paths each model is still compiling (:meth:`Model.compiling`)."""
        return {m.name: paths for m in self.repository if (paths := m.compiling())}

    @staticmethod
    def server_metadata() -> dict:
        return {"name": SERVER_NAME, "version": tdcr.__version__, "extensions": EXTENSIONS}

    def model(self, name: str | None, *, kind: Kind | None = None, version: str | None = None,
              loads: bool = False) -> Model:
        """The model ``name`` (None: the default of ``kind``, for designs with ``loads`` its loaded
        default); :class:`InferenceError` ``not_found`` else (``unavailable`` while the service starts)."""
        if self.starting:
            raise InferenceError("unavailable", f"{STARTING}; retry shortly", retry_after=RETRY_STARTING_S)
        return self.repository.get(name, kind=kind, version=version, loads=loads)

    def model_ready(self, name: str, version: str | None = None) -> bool:
        return self.model(name, version=version).ready()

    def model_metadata(self, name: str, version: str | None = None) -> dict:
        return self.model(name, version=version).metadata()

    # -- inference ------------------------------------------------------------------------------

    async def infer(self, name: str | None, request: InferenceRequest, *, kind: Kind | None = None,
                    version: str | None = None, loads: bool = False, protocol: str,
                    endpoint: str) -> InferenceResponse:
        """``request`` on the model ``name`` (None: the default of ``kind``; given ``kind``, only a
        model of that kind), with its latency and count under ``protocol`` and ``endpoint``.

        A request the model :meth:`~service.model.Model.answers_inline` (a few designs on a bounded
        path) is answered right here on the event loop when no other inference is in flight: the
        hand-off to a worker thread and back would cost more than its work.  Under concurrency every
        request goes to the workers, where the operators' batchers group them.  ``loads``: the
        designs have loads (without a name: the kind's default for loads)."""
        model = self.model(name, kind=kind, version=version, loads=loads)
        started = time.perf_counter()
        with _validation_errors():
            if self.idle and model.answers_inline(request):
                response = model.infer_blocking(request)
            else:
                self.in_flight += 1
                try:
                    response = await model.infer(request)
                finally:
                    self.in_flight -= 1
        return self._record(model, response, started, protocol, endpoint)

    @property
    def idle(self) -> bool:
        """Whether a short request may be answered on the event loop now (:meth:`infer`)."""
        return self.inline and not self.in_flight

    def infer_blocking(self, name: str | None, request: InferenceRequest, *, kind: Kind | None = None,
                       version: str | None = None, loads: bool = False, protocol: str,
                       endpoint: str) -> InferenceResponse:
        """As :meth:`infer`, on the calling worker thread, for a transport that is already on one
        (``/predict`` validates its body there, which names the model, and says whether it has
        ``loads``); a model that answers only asynchronously is ``not_found`` here."""
        model = self.model(name, kind=kind, version=version, loads=loads)
        if not model.blocking:
            raise InferenceError("not_found", f"model {model.name!r} is not served on this route")
        started = time.perf_counter()
        with _validation_errors():
            response = model.infer_blocking(request)
        return self._record(model, response, started, protocol, endpoint)

    def _record(self, model: Model, response: InferenceResponse, started: float, protocol: str,
                endpoint: str) -> InferenceResponse:
        self.metrics.latency.labels(protocol, endpoint, model.name).observe(time.perf_counter() - started)
        self.metrics.designs.labels(protocol, endpoint, model.name).inc(response.count)
        if response.guarded:
            self.metrics.guarded.labels(model.name).inc(response.guarded)
            self.metrics.fallback.labels(model.name).inc(response.exact)
        return response

    def close(self) -> None:
        for model in self.repository:
            model.close()


@contextmanager
def _validation_errors() -> Iterator[None]:
    """The validation path's :class:`InvalidRequest` as :class:`InferenceError`, its problems kept."""
    try:
        yield
    except InvalidRequest as exc:
        raise InferenceError("too_large" if exc.too_large else "invalid", exc.message, tuple(exc.problems)) from None
