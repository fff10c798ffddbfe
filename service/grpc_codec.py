"""The Open Inference Protocol v2's gRPC wire (``inference.ModelInferRequest`` and
``ModelInferResponse``): :class:`GrpcCodec`.  Only protobuf and numpy: a solver process that runs
this codec imports no gRPC server.

Tensors come typed (``InferTensorContents``) or raw (``raw_input_contents``: flat row-major
little-endian bytes, one buffer per input); the answer is raw when the request was, as Triton's
(tritonclient reads outputs only from ``raw_output_contents``), else typed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.model import VERSION, InferenceError, ModelSpec, Peek, Tensors
from service.oip import (
    DATATYPES,
    LOAD_INPUTS,
    InferRequest,
    OipCodec,
    OutputTensors,
    check_input,
    check_request,
    termination_parameter,
    tolerance_parameter,
)
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb

#: The ``InferParameter`` fields that hold a number.
NUMBER_PARAMETERS = ("double_param", "int64_param", "uint64_param")
#: The typed-contents field of each datatype.
CONTENTS = {"BOOL": "bool_contents", "INT32": "int_contents", "INT64": "int64_contents",
            "UINT8": "uint_contents", "FP32": "fp32_contents", "FP64": "fp64_contents"}


def decode(request: pb.ModelInferRequest, *, inputs: Tensors, outputs: Tensors,
           required: tuple[str, ...] = ("design",)) -> InferRequest:
    """A ``ModelInferRequest`` as an :class:`InferRequest` (outputs raw iff the inputs were)."""
    raw = request.raw_input_contents
    if raw and len(raw) != len(request.inputs):
        raise InferenceError("invalid", f"raw_input_contents has {len(raw)} buffers for {len(request.inputs)} inputs")
    arrays: dict[str, np.ndarray] = {}
    for i, tensor in enumerate(request.inputs):
        name, shape = tensor.name, list(tensor.shape)
        dtype, count = check_input(name, tensor.datatype, shape, inputs=inputs, seen=arrays)
        if raw:
            if tensor.HasField("contents"):
                raise InferenceError("invalid", f"input {name!r}: give raw_input_contents or contents, not both")
            if len(raw[i]) != count * dtype.itemsize:
                raise InferenceError("invalid", f"input {name!r}: {len(raw[i])} raw bytes do not match its shape "
                                          f"{shape} of {tensor.datatype} ({count * dtype.itemsize} bytes)")
            array = np.frombuffer(raw[i], dtype=dtype, count=count)
        else:
            values = getattr(tensor.contents, CONTENTS[tensor.datatype])
            if len(values) != count:
                raise InferenceError("invalid", f"input {name!r}: contents.{CONTENTS[tensor.datatype]} holds "
                                          f"{len(values)} values, its shape {shape} needs {count}")
            array = np.array(values, dtype=dtype)
        arrays[name] = array.reshape(shape)
    asked = [(o.name, bool(raw)) for o in request.outputs] or [(n, bool(raw)) for n in outputs]
    wanted = check_request(arrays, asked, outputs=outputs, required=required)
    tolerance = None
    if "tolerance" in request.parameters:
        parameter = request.parameters["tolerance"]
        choice = parameter.WhichOneof("parameter_choice")
        value = getattr(parameter, choice) if choice in NUMBER_PARAMETERS else str(getattr(parameter, choice or "",
                                                                                            "no value"))
        tolerance = tolerance_parameter(value)
    termination = None
    if "termination" in request.parameters:
        parameter = request.parameters["termination"]
        choice = parameter.WhichOneof("parameter_choice")
        termination = termination_parameter(getattr(parameter, choice) if choice == "string_param" else
                                            f"a {choice or 'parameter with no value'}")
    return InferRequest(inputs=arrays, outputs=wanted, id=request.id[:64] or None, tolerance=tolerance,
                        termination=termination)


def encode(model: str, tensors: OutputTensors, *, raw: bool,
           request_id: str | None) -> pb.ModelInferResponse | bytes:
    """A ``ModelInferResponse`` of ``tensors`` (name -> (datatype, array)): typed, as a message, or
    raw, already serialised (:func:`encode_raw`)."""
    if raw:
        return encode_raw(model, tensors, request_id=request_id)
    response = pb.ModelInferResponse(model_name=model, model_version=VERSION, id=request_id or "")
    for name, (datatype, array) in tensors.items():
        array = np.ascontiguousarray(array, dtype=DATATYPES[datatype])
        tensor = response.outputs.add(name=name, datatype=datatype, shape=array.shape)
        getattr(tensor.contents, CONTENTS[datatype]).extend(array.reshape(-1).tolist())
    return response


#: The key of ``ModelInferResponse.raw_output_contents`` on the wire: field 6, length-delimited.
RAW_OUTPUT_KEY = bytes([pb.ModelInferResponse.RAW_OUTPUT_CONTENTS_FIELD_NUMBER << 3 | 2])


def _varint(value: int) -> bytes:
    """A protobuf base-128 varint."""
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def encode_raw(model: str, tensors: OutputTensors, *, request_id: str | None) -> bytes:
    """The serialised ``ModelInferResponse`` with raw output contents, written straight from the
    arrays: the message without the contents through protobuf, then each buffer as a
    ``raw_output_contents`` field (key, varint length, bytes).  The bytes are those protobuf writes
    for the same message (fields in number order; tested), with one copy of each array instead of
    three (``tobytes``, the message's own, serialisation): 8,192 designs' tendons are 16.5 MB."""
    head = pb.ModelInferResponse(model_name=model, model_version=VERSION, id=request_id or "")
    parts = [b""]
    for name, (datatype, array) in tensors.items():
        array = np.ascontiguousarray(array, dtype=DATATYPES[datatype])
        head.outputs.add(name=name, datatype=datatype, shape=array.shape)
        parts += [RAW_OUTPUT_KEY, _varint(array.nbytes), memoryview(array.reshape(-1)).cast("B")]
    parts[0] = head.SerializeToString()
    return b"".join(parts)


@dataclass(frozen=True)
class GrpcCodec(OipCodec):
    """OIP over gRPC: a ``ModelInferRequest`` in; a ``ModelInferResponse``, or its serialised bytes
    with raw contents when the request was raw, out."""

    def peek(self, payload: pb.ModelInferRequest) -> Peek | None:
        """The designs (the ``design`` tensor's first dimension), tolerance and loads of ``payload``,
        read from its tensors' headers (None without a ``design`` tensor of two dimensions)."""
        designs = [t.shape for t in payload.inputs if t.name == "design"]
        if len(designs) != 1 or len(designs[0]) != 2:
            return None
        return Peek(designs=int(designs[0][0]), tolerance="tolerance" in payload.parameters,
                    loads=any(t.name in LOAD_INPUTS for t in payload.inputs))

    def wire_decode(self, payload: pb.ModelInferRequest, spec: ModelSpec) -> InferRequest:
        return decode(payload, inputs=spec.inputs, outputs=spec.outputs, required=spec.required)

    def wire_encode(self, model: str, tensors: OutputTensors, request: InferRequest) -> pb.ModelInferResponse | bytes:
        return encode(model, tensors, raw=any(request.outputs.values()), request_id=request.id)  # raw iff asked raw
