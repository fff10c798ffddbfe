"""The Open Inference Protocol v2 (KServe V2 / Triton) over REST: tensors in, tensors out.

Specification: kserve/open-inference-protocol, ``specification/protocol/inference_rest.md``; the
binary tensor extension: triton-inference-server/server, ``docs/protocol/extension_binary_data.md``.

Models (every manifest operator, and the physics solver as ``exact``):

* inputs: ``design`` FP64 or FP32 ``[-1, 15]`` (raw SI designs in the README's feature order) and
  optionally ``s`` FP64 ``[-1]`` (fractions of L; default the 42-point grid); ``exact`` also takes
  ``gravity`` ``[-1, 3]``, ``density`` ``[-1]``, ``tip_force`` ``[-1, 3]``, ``tip_moment`` ``[-1, 3]``;
* outputs (metres): ``backbone`` FP32 ``[-1, n, 3]``, ``rotation`` FP32 ``[-1, n, 3, 3]``, ``tendons``
  FP32 ``[-1, n, 4, 3]``, ``in_distribution`` BOOL ``[-1]``; ``exact`` also ``converged`` BOOL and
  ``residual`` FP64 ``[-1]``.

Decoded tensors go through the one validation path (:mod:`tdcr.validation`); errors are
:class:`OipError` with a status and a message that names the tensor and the reason.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import orjson
from pydantic import BaseModel, Field

from tdcr.client import INFERENCE_HEADER_LENGTH
from tdcr.design_space import N_FEATURES, N_TENDONS
from tdcr.validation import quote

#: OIP datatypes and their little-endian numpy types.
DATATYPES: dict[str, np.dtype] = {
    "BOOL": np.dtype("?"), "UINT8": np.dtype("<u1"), "INT32": np.dtype("<i4"), "INT64": np.dtype("<i8"),
    "FP32": np.dtype("<f4"), "FP64": np.dtype("<f8"),
}
#: The surrogates' tensors: name -> (datatype, shape); ``n`` is the number of arclengths.
SURROGATE_INPUTS = {"design": ("FP64", [-1, N_FEATURES]), "s": ("FP64", [-1])}
SURROGATE_OUTPUTS = {"backbone": ("FP32", [-1, -1, 3]), "rotation": ("FP32", [-1, -1, 3, 3]),
                     "tendons": ("FP32", [-1, -1, N_TENDONS, 3]), "in_distribution": ("BOOL", [-1])}
#: The solver's extra tensors.
LOAD_INPUTS = {"gravity": ("FP64", [-1, 3]), "density": ("FP64", [-1]), "tip_force": ("FP64", [-1, 3]),
               "tip_moment": ("FP64", [-1, 3])}
#: ``status``: an index into ``tdcr.physics.STATUS``; ``error_estimate``: -1 where there is none.
EXACT_OUTPUTS = SURROGATE_OUTPUTS | {"converged": ("BOOL", [-1]), "residual": ("FP64", [-1]),
                                     "status": ("INT32", [-1]), "error_estimate": ("FP64", [-1])}
#: Inverse kinematics (/inverse with the exact model): one design, the targets of a path.
INVERSE_INPUTS = {"design": ("FP64", [1, N_FEATURES]), "position": ("FP64", [-1, 3]), "direction": ("FP64", [-1, 3]),
                  "tension_max": ("FP64", [1])}
INVERSE_OUTPUTS = {"tensions": ("FP64", [-1, N_TENDONS]), "position": ("FP64", [-1, 3]), "error": ("FP64", [-1]),
                   "status": ("INT32", [-1])}
#: The ``status`` output of the inverse model.
INVERSE_STATUS = {"reached": 0, "closest": 1, "failed": 2}
#: Header of the binary tensor extension.
HEADER_LENGTH = INFERENCE_HEADER_LENGTH


class RequestInput(BaseModel):
    """An input tensor: row-major ``data``, or ``parameters.binary_data_size`` bytes after the JSON."""

    name: str
    shape: list[int]
    datatype: str
    parameters: dict | None = None
    data: list | None = None


class RequestOutput(BaseModel):
    name: str
    parameters: dict | None = Field(None, description='{"binary_data": true} for a binary tensor')


class InferenceRequest(BaseModel):
    """The OIP inference request (documentation; bodies are decoded by :func:`decode`)."""

    id: str | None = None
    parameters: dict | None = Field(None, description='{"binary_data_output": true} for binary outputs')
    inputs: list[RequestInput]
    outputs: list[RequestOutput] | None = None


class OipErrorBody(BaseModel):
    error: str


#: Error kinds and their HTTP statuses (the gRPC binding maps the same kinds to its status codes).
HTTP_STATUS = {"invalid": 400, "not_found": 404, "too_large": 413, "saturated": 503, "unavailable": 503,
               "deadline": 504}


class OipError(Exception):
    """A protocol error: its ``kind`` (a key of :data:`HTTP_STATUS`, also the metric label) and a
    message naming the tensor and the reason."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind, self.message = kind, message

    @property
    def status(self) -> int:
        return HTTP_STATUS[self.kind]


@dataclass(frozen=True)
class InferRequest:
    """A decoded inference request: input arrays by name, the outputs wanted (name -> binary/raw)."""

    inputs: dict[str, np.ndarray]
    outputs: dict[str, bool]
    id: str | None


def tensor_metadata(tensors: Mapping[str, tuple[str, list[int]]]) -> list[dict]:
    return [{"name": name, "datatype": dtype, "shape": shape} for name, (dtype, shape) in tensors.items()]


def check_input(name, datatype, shape, *, inputs: Mapping[str, tuple[str, list[int]]],
                seen: Mapping[str, np.ndarray]) -> tuple[np.dtype, int]:
    """The numpy type and element count of an input tensor's declared ``name``, ``datatype`` and
    ``shape`` (any transport); :class:`OipError` naming the tensor and the reason else."""
    if name not in inputs:
        raise OipError("invalid", f"unexpected input {quote(name)}; this model takes {list(inputs)}")
    if name in seen:
        raise OipError("invalid", f"input {name!r} is given twice")
    allowed = ("FP64", "FP32") if inputs[name][0] == "FP64" else (inputs[name][0],)
    if datatype not in allowed:
        raise OipError("invalid", f"input {name!r}: datatype must be one of {list(allowed)}, got {quote(datatype)}")
    expected = inputs[name][1]
    if (not isinstance(shape, list) or len(shape) != len(expected)
            or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
            or any(e != -1 and d != e for d, e in zip(shape, expected, strict=True))):
        raise OipError("invalid", f"input {name!r}: shape must be {expected} (-1: any), got {quote(shape)}")
    return DATATYPES[datatype], int(np.prod(shape, dtype=object))


def check_request(arrays: Mapping[str, np.ndarray], outputs_asked: list[tuple[object, bool]], *,
                  outputs: Mapping[str, tuple[str, list[int]]], required: tuple[str, ...] = ("design",)
                  ) -> dict[str, bool]:
    """The outputs wanted (name -> binary/raw) from ``outputs_asked`` (name, binary) pairs, empty
    for every output; :class:`OipError` for a missing input or an unknown output."""
    missing = [n for n in required if n not in arrays]
    if missing:
        raise OipError("invalid", f"missing input(s) {missing}")
    wanted: dict[str, bool] = {}
    for name, binary in outputs_asked:
        if name not in outputs:
            raise OipError("invalid", f"unknown output {quote(name)}; this model gives {list(outputs)}")
        wanted[name] = binary
    return wanted


def decode(body: bytes, header_length: str | None, *, inputs: Mapping[str, tuple[str, list[int]]],
           outputs: Mapping[str, tuple[str, list[int]]], required: tuple[str, ...] = ("design",)) -> InferRequest:
    """An OIP REST inference request (JSON, or JSON followed by binary tensors)."""
    try:
        json_length = len(body) if header_length is None else int(header_length)
    except ValueError:
        raise OipError("invalid", f"{HEADER_LENGTH} must be an integer, got {quote(header_length)}") from None
    if not 0 <= json_length <= len(body):
        raise OipError("invalid", f"{HEADER_LENGTH} {json_length} is outside the body of {len(body)} bytes")
    try:
        request = orjson.loads(body[:json_length])
    except orjson.JSONDecodeError as exc:
        raise OipError("invalid", f"the request is not valid JSON: {exc}") from None
    if not isinstance(request, dict) or not isinstance(request.get("inputs"), list):
        raise OipError("invalid", "the request must be an object with a list of 'inputs'")
    binary = memoryview(body)[json_length:]
    offset = 0
    arrays: dict[str, np.ndarray] = {}
    for spec in request["inputs"]:
        if not isinstance(spec, dict):
            raise OipError("invalid", "each input must be an object")
        name, datatype, shape = spec.get("name"), spec.get("datatype"), spec.get("shape")
        dtype, count = check_input(name, datatype, shape, inputs=inputs, seen=arrays)
        size = (spec.get("parameters") or {}).get("binary_data_size")
        if size is not None:
            if not isinstance(size, int) or size != count * dtype.itemsize or offset + size > len(binary):
                raise OipError("invalid", f"input {name!r}: binary_data_size {quote(size)} does not match its "
                                          f"shape {shape} of {datatype} or the {len(binary) - offset} bytes left")
            array = np.frombuffer(binary, dtype=dtype, count=count, offset=offset)
            offset += size
        else:
            data = spec.get("data")
            if not isinstance(data, list):
                raise OipError("invalid", f"input {name!r}: 'data' must be a list (or use binary_data_size)")
            array = np.asarray(data, dtype=object).reshape(-1) if count else np.zeros(0)
            if array.size != count or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                               for v in array.tolist()):
                raise OipError("invalid", f"input {name!r}: 'data' must hold {count} numbers, row-major")
            array = array.astype(dtype)
        arrays[name] = array.reshape(shape)
    if offset != len(binary):
        raise OipError("invalid", f"{len(binary) - offset} bytes of binary data are not claimed by any input")
    default_binary = bool((request.get("parameters") or {}).get("binary_data_output", False))
    asked = [(spec.get("name") if isinstance(spec, dict) else None,
              bool(((spec.get("parameters") if isinstance(spec, dict) else None) or {}).get("binary_data",
                                                                                            default_binary)))
             for spec in request.get("outputs") or [{"name": n} for n in outputs]]
    wanted = check_request(arrays, asked, outputs=outputs, required=required)
    request_id = request.get("id")
    return InferRequest(inputs=arrays, outputs=wanted, id=None if request_id is None else str(request_id)[:64])


def encode(model: str, tensors: Mapping[str, tuple[str, np.ndarray]], binary: Mapping[str, bool],
           request_id: str | None) -> tuple[bytes, int | None]:
    """The response body and, when any output is binary, the length of its JSON part."""
    outputs, blobs = [], []
    for name, (datatype, array) in tensors.items():
        array = np.ascontiguousarray(array, dtype=DATATYPES[datatype])
        out = {"name": name, "datatype": datatype, "shape": list(array.shape)}
        if binary[name]:
            blob = array.tobytes()
            out["parameters"] = {"binary_data_size": len(blob)}
            blobs.append(blob)
        else:
            out["data"] = array.reshape(-1)
        outputs.append(out)
    head = orjson.dumps({"model_name": model, "model_version": "1", "outputs": outputs,
                         **({"id": request_id} if request_id is not None else {})}, option=orjson.OPT_SERIALIZE_NUMPY)
    return (head + b"".join(blobs), len(head)) if blobs else (head, None)
