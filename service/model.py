"""The model protocol: every served thing is a :class:`Model`, held by a :class:`ModelRepository`.

As in KServe's model server (``kserve/model.py``, ``model_repository.py``): a model has a name, a
version, its input and output tensor specifications, readiness and metadata, and ``infer``.  The
surrogates (:mod:`service.surrogate`), the exact solver and its inverse kinematics
(:mod:`service.solver`) implement it; a new model is one more class and one
:meth:`ModelRepository.register`.

``infer`` takes an :class:`InferenceRequest`: what a transport received (its ``payload``) and the
transport's :class:`Codec`.  The model asks the codec for the task it needs (a validated
:class:`tdcr.api.validation.ShapeRequest` or :class:`tdcr.api.validation.InverseProblem`) where its work
runs (a worker thread, or a solver process for the exact solver), and has the codec encode its
answer there, so that a transport never names a model and no tensor makes a round trip through
another transport's format.  Errors are :class:`InferenceError` with a ``kind``; each transport
maps kinds to its own statuses in one place.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal, NamedTuple, Protocol

from tdcr.api.validation import Limits, Problem, quote

#: The one version of every model.
VERSION = "1"
#: What a model answers: surrogate shapes, exact shapes, or inverse kinematics.
Kind = Literal["surrogate", "solver", "inverse"]
#: The most designs a request may have for a model to answer it on the event loop
#: (:meth:`Model.answers_inline`): one to a few designs take well under a millisecond.
INLINE_DESIGNS = 4
#: Error kinds (the ``tdcr_errors`` metric's label too).
ERROR_KINDS = ("invalid", "not_found", "too_large", "saturated", "unavailable", "deadline")
#: Seconds a client is asked to wait (HTTP ``Retry-After``) before it retries a saturated service.
RETRY_SATURATED_S = 1
#: ... and one that is starting (a first start compiles the solver for a minute or two).
RETRY_STARTING_S = 5


class InferenceError(Exception):
    """A request the data plane cannot answer: ``kind`` (one of :data:`ERROR_KINDS`), a message
    naming the field or tensor and the reason, and for ``invalid`` / ``too_large`` the ``problems``
    (:class:`tdcr.api.validation.Problem`) when they came from the validation path; ``retry_after``:
    the seconds after which the same request may succeed (HTTP ``Retry-After``; None: not by waiting)."""

    def __init__(self, kind: str, message: str, problems: tuple[Problem, ...] = (), *,
                 retry_after: int | None = None):
        super().__init__(message)
        self.kind, self.message, self.problems, self.retry_after = kind, message, tuple(problems), retry_after

    def __reduce__(self):  # picklable: it crosses the solver processes' pipes (the keyword as state)
        return (InferenceError, (self.kind, self.message, self.problems), {"retry_after": self.retry_after})


@dataclass(frozen=True)
class TensorSpec:
    """An OIP tensor: its datatype and shape (``-1``: any size)."""

    datatype: str
    shape: tuple[int, ...]


Tensors = dict[str, TensorSpec]


@dataclass(frozen=True)
class ModelSpec:
    """What a codec needs to know of a model to decode for it (picklable: it travels to the solver
    processes): name, kind, tensors (``required``: inputs that must be given) and size limits."""

    name: str
    kind: Kind
    inputs: Tensors
    outputs: Tensors
    required: tuple[str, ...]
    limits: Limits


class Codec(Protocol):
    """A transport's decoding and encoding, run by a model where its work runs (so it must be
    picklable: a module-level class).  ``decode`` returns the decoded request (with ``.task``, the
    validated :class:`ShapeRequest` or :class:`InverseProblem`, and whatever ``encode`` needs);
    ``encode`` turns the model's answer (:class:`tdcr.surrogates.engine.Prediction`,
    :class:`tdcr.physics.exact.ExactAnswer` or :class:`InverseAnswer`) into what the transport sends."""

    def decode(self, payload: Any, spec: ModelSpec) -> Any: ...

    def encode(self, decoded: Any, answer: Any) -> Any: ...


class Peek(NamedTuple):
    """What a codec can tell of a request without decoding it: its ``designs`` (the first dimension
    of its design tensor), and whether it asks a ``tolerance`` or gives ``loads``."""

    designs: int
    tolerance: bool
    loads: bool


@dataclass(frozen=True)
class InferenceRequest:
    """What a transport hands the data plane: its ``payload`` and the ``codec`` that reads it."""

    payload: Any
    codec: Codec

    def peek(self) -> Peek | None:
        """The codec's :class:`Peek` of the payload (None: a codec that cannot tell, or a payload it
        will refuse)."""
        peek = getattr(self.codec, "peek", None)
        return None if peek is None else peek(self.payload)


@dataclass(frozen=True)
class InferenceResponse:
    """What a model answers: the codec's encoding of its answer, the designs (or targets) answered,
    and of a surrogate's designs those asked with a tolerance (``guarded``) and those of them the
    exact solver answered (``exact``)."""

    body: Any
    count: int
    guarded: int = 0
    exact: int = 0


@dataclass(frozen=True)
class InverseAnswer:
    """Inverse kinematics' answer: the forward ``model`` used and one JSON-ready dict per target
    (``tensions``, ``position``, ``error``, ``status``, ``iterations``, ``direction`` if asked)."""

    model: str
    results: list[dict]


class Model(ABC):
    """A served model.  Subclasses set ``name``, ``kind``, ``platform`` and their tensors."""

    name: str
    kind: Kind
    platform: str
    version: str = VERSION
    inputs: Tensors
    outputs: Tensors
    required: tuple[str, ...] = ("design",)
    limits: Limits = Limits()

    @cached_property
    def spec(self) -> ModelSpec:
        """What a codec needs of this model (built once: name, tensors and limits do not change)."""
        return ModelSpec(name=self.name, kind=self.kind, inputs=self.inputs, outputs=self.outputs,
                         required=self.required, limits=self.limits)

    def health(self) -> str | None:
        """Why the model cannot answer now, or None."""
        return None

    @property
    def starting(self) -> bool:
        """The model is still starting after the service became ready (the solver compiling)."""
        return False

    def starting_note(self) -> str:
        """What /readyz says of the model while it is :attr:`starting`."""
        return self.health() or "starting"

    def compiling(self) -> list[str]:
        """The solver paths the model is still compiling once started (a request on one: 503
        "starting", with Retry-After); none but the solver's."""
        return []

    def ready(self) -> bool:
        """Whether the model can answer now."""
        return self.health() is None

    def parameters(self) -> dict:
        """Metadata beyond name, versions, platform and tensors (OIP ``parameters``)."""
        return {}

    def metadata(self) -> dict:
        """OIP model metadata."""
        return {"name": self.name, "versions": [self.version], "platform": self.platform,
                "inputs": [{"name": n, "datatype": t.datatype, "shape": list(t.shape)} for n, t in self.inputs.items()],
                "outputs": [{"name": n, "datatype": t.datatype, "shape": list(t.shape)}
                            for n, t in self.outputs.items()],
                "parameters": self.parameters()}

    @property
    def saturated(self) -> bool:
        """Whether a request now would be refused for want of capacity (checked before a body is read)."""
        return False

    @abstractmethod
    async def infer(self, request: InferenceRequest) -> InferenceResponse:
        """Decode, run and encode ``request``; raises :class:`InferenceError` or the validation
        path's :class:`tdcr.api.validation.InvalidRequest` (the data plane maps both)."""

    #: Whether :meth:`infer_blocking` answers on the calling thread (a transport already in a
    #: worker thread then saves a thread hop).
    blocking = False

    def infer_blocking(self, request: InferenceRequest) -> InferenceResponse:
        """As :meth:`infer`, on the calling (worker) thread; models with ``blocking`` only."""
        raise NotImplementedError(f"model {self.name!r} answers asynchronously only")

    def answers_inline(self, request: InferenceRequest) -> bool:
        """Whether :meth:`infer_blocking` of ``request`` is short and bounded (a few designs, no path
        that waits on another process), so that the data plane may run it on the event loop when
        nothing else is in flight, saving the hand-off to a worker thread and back."""
        return False

    def close(self) -> None:  # noqa: B027 - most models hold nothing to release
        """Release threads and processes (at shutdown)."""


def loaded(kind: Kind) -> str:
    """The key of a kind's default for designs with loads in :attr:`ModelRepository.defaults`."""
    return f"{kind}+loads"


@dataclass
class ModelRepository:
    """The served models by name, and the default model of each kind (``/predict`` names none);
    ``defaults[loaded(kind)]``: the default for designs with loads (a loaded operator)."""

    models: dict[str, Model] = field(default_factory=dict)
    defaults: dict[str, str] = field(default_factory=dict)

    def register(self, model: Model, *, default: bool = False) -> None:
        """Serve ``model``; ``default``: the default of its kind (else the first of its kind is)."""
        self.models[model.name] = model
        if default or model.kind not in self.defaults:
            self.defaults[model.kind] = model.name

    def get(self, name: str | None, *, kind: Kind | None = None, version: str | None = None,
            loads: bool = False) -> Model:
        """The model ``name`` (None: the default of ``kind``, or with ``loads`` its default for designs
        with loads), of ``kind`` when given, and of ``version`` when given; :class:`InferenceError`
        ``not_found`` else."""
        if name is None and kind is not None:
            name = self.defaults.get(loaded(kind)) if loads else None
            name = name or self.defaults.get(kind)
        model = self.models.get(name) if name is not None else None
        if model is None or kind is not None and model.kind != kind:
            available = sorted(self.names(kind))
            raise InferenceError("not_found", f"unknown model {quote(str(name)) if name else 'none'}; "
                                              f"available: {available}")
        if version not in (None, "", model.version):
            raise InferenceError("not_found", f"model {model.name!r} has only version {model.version}, "
                                              f"not {version[:16]!r}")
        return model

    def names(self, kind: Kind | None = None) -> list[str]:
        return [n for n, m in self.models.items() if kind is None or m.kind == kind]

    def __iter__(self) -> Iterator[Model]:
        return iter(self.models.values())
