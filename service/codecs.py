"""The codecs of the service's own JSON / binary API: ``/predict``, ``/exact``, ``/inverse``.

A codec is what a transport hands the data plane with its payload (:class:`service.model.Codec`):
the model runs ``decode`` and ``encode`` where its work runs (a worker thread, or a solver
process), so each is a small picklable class.  The OIP codecs are :class:`service.oip.RestCodec`
and :class:`service.grpc_codec.GrpcCodec`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import orjson

from service.model import InverseAnswer, ModelSpec, Peek
from tdcr.api.schemas import RESPONSE_FORMAT_VERSION
from tdcr.api.validation import InverseProblem, ShapeRequest, validate_inverse, validate_json
from tdcr.physics.exact import ExactAnswer
from tdcr.surrogates.engine import Prediction, encode_json, encode_npz


@dataclass(frozen=True)
class Decoded:
    """A decoded request: the model's validated ``task``."""

    task: ShapeRequest | InverseProblem


@dataclass(frozen=True)
class PredictCodec:
    """``/predict``: the payload is the already validated :class:`ShapeRequest` (the route reads
    the JSON or ``.npy`` body first: it names the model); the answer is ``PredictResponse`` JSON,
    or ``.npz`` bytes with ``npz``."""

    npz: bool = False

    def peek(self, payload: ShapeRequest) -> Peek:
        return Peek(designs=payload.n_designs, tolerance=payload.tolerance is not None, loads=payload.n_loaded > 0)

    def decode(self, payload: ShapeRequest, spec: ModelSpec) -> Decoded:
        return Decoded(payload)

    def encode(self, decoded: Decoded, answer: Prediction) -> bytes | NpzAnswer:
        return NpzAnswer(encode_npz(answer), answer.model) if self.npz else encode_json(answer)


class NpzAnswer(NamedTuple):
    """A ``.npz`` answer and the model that gave it (the ``X-TDCR-Model`` header: JSON says it in the body)."""

    content: bytes
    model: str


@dataclass(frozen=True)
class ExactCodec:
    """``/exact``: a JSON ``SolveRequest`` body (validated where the solver runs: parsing a large
    body never costs the server's interpreter); the answer is ``ExactResponse`` JSON."""

    def decode(self, payload: bytes, spec: ModelSpec) -> Decoded:
        return Decoded(validate_json(payload, target="solver", limits=spec.limits))

    def encode(self, decoded: Decoded, answer: ExactAnswer) -> bytes:
        return orjson.dumps({"format_version": RESPONSE_FORMAT_VERSION, "results": answer.results(lists=False)},
                            option=orjson.OPT_SERIALIZE_NUMPY)


@dataclass(frozen=True)
class InverseCodec:
    """``/inverse``: a JSON ``InverseRequest`` body; the answer is ``InverseResponse`` JSON."""

    def decode(self, payload: bytes, spec: ModelSpec) -> Decoded:
        return Decoded(validate_inverse(payload))

    def encode(self, decoded: Decoded, answer: InverseAnswer) -> bytes:
        return orjson.dumps({"model": answer.model, "results": answer.results})
