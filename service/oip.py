"""The Open Inference Protocol v2 (KServe V2 / Triton): its tensors, its REST codec, and what
every OIP transport shares (:class:`OipCodec`: tensors to a model's task, answers to tensors).

Specification: kserve/open-inference-protocol, ``specification/protocol/inference_rest.md``; the
binary tensor extension: triton-inference-server/server, ``docs/protocol/extension_binary_data.md``.

Models and their tensors:

* every operator (kind ``surrogate``): inputs ``design`` FP64 or FP32 ``[-1, 15]`` (raw SI designs
  in the README's feature order) and optionally ``s`` FP64 ``[-1]`` (arclength fractions of L;
  default the 42-point grid) or ``arclength`` FP64 ``[-1]`` (m, for designs of one length);
  outputs (metres) ``backbone`` FP32 ``[-1, n, 3]``, ``rotation`` FP32 ``[-1, n, 3, 3]``,
  ``tendons`` FP32 ``[-1, n, 4, 3]``, ``in_distribution`` BOOL ``[-1]``, ``error_bound`` FP32
  ``[-1]`` (the calibrated 99 % bound of each answer's relative l2 error; -1: none) and ``source``
  INT32 ``[-1]`` (0: the surrogate answered, 1: the exact solver); the request parameter
  ``tolerance`` (a number, relative l2) sends the designs whose bound exceeds it to the exact solver;
* ``exact`` (the solver): ``design`` ``[-1, 3 + 3 N_t]`` for any N_t, the inputs ``gravity``
  ``[-1, 3]``, ``density`` ``[-1]``, ``tip_force`` ``[-1, 3]``, ``tip_moment`` ``[-1, 3]``, and for
  any robot ``layout`` FP64 ``[-1, N_t, 4..8]`` (per tendon: angle at s = 0 in rad, end in m,
  displacement in m, 1 where the tendon is driven by that displacement, 0 by its tension in
  ``design``; then, each optional, series stiffness N/m (0: rigid), drive zero m, Capstan friction
  and motion 1 pull / -1 release) and ``poisson`` FP64 ``[-1]``; the request parameter ``termination`` (``exact`` or
  ``rucker_webster``); the outputs ``converged`` BOOL, ``residual`` FP64, ``status`` INT32 (an
  index into ``tdcr.physics.STATUS``), ``error_estimate`` FP64 (-1: none), ``tension`` FP64
  ``[-1, N_t]`` N, ``displacement`` FP64 ``[-1, N_t]`` m, ``tension_profile`` FP64 ``[-1, n, N_t]`` N
  and ``slack`` BOOL ``[-1, N_t]``;
* ``inverse`` (inverse kinematics with the exact model): inputs ``design`` ``[1, 15]``,
  ``position`` ``[-1, 3]`` (the targets), optionally ``direction`` ``[-1, 3]`` and ``tension_max``
  ``[1]``; outputs ``tensions`` FP64 ``[-1, 4]`` N, ``position`` (the tips reached), ``error`` (m)
  and ``status`` INT32 (:data:`INVERSE_STATUS`).

Decoded tensors go through the one validation path (:mod:`tdcr.api.validation`); errors are
:class:`service.model.InferenceError` with a message that names the tensor and the reason.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import orjson
from pydantic import BaseModel, Field

from service.model import VERSION, InferenceError, InverseAnswer, ModelSpec, Tensors, TensorSpec
from tdcr.api.validation import (
    INVERSE_DEFAULTS,
    OUTPUTS,
    InvalidRequest,
    check_inverse,
    quote,
    validate_features,
)
from tdcr.clients.client import INFERENCE_HEADER_LENGTH
from tdcr.physics.cosserat import TERMINATIONS
from tdcr.physics.exact import ExactAnswer
from tdcr.robot.design_space import N_FEATURES, N_TENDONS, range_warnings
from tdcr.robot.designs import DesignBatch
from tdcr.robot.fields import LAYOUT_COLUMNS, OWN_TENSORS
from tdcr.surrogates.engine import Prediction

#: OIP datatypes and their little-endian numpy types.
DATATYPES: dict[str, np.dtype] = {
    "BOOL": np.dtype("?"), "UINT8": np.dtype("<u1"), "INT32": np.dtype("<i4"), "INT64": np.dtype("<i8"),
    "FP32": np.dtype("<f4"), "FP64": np.dtype("<f8"),
}
#: The surrogates' tensors; ``n`` (-1) is the number of arclengths.
SURROGATE_INPUTS = {"design": TensorSpec("FP64", (-1, N_FEATURES)), "s": TensorSpec("FP64", (-1,)),
                    "arclength": TensorSpec("FP64", (-1,))}
SURROGATE_OUTPUTS = {"backbone": TensorSpec("FP32", (-1, -1, 3)), "rotation": TensorSpec("FP32", (-1, -1, 3, 3)),
                     "tendons": TensorSpec("FP32", (-1, -1, N_TENDONS, 3)),
                     "in_distribution": TensorSpec("BOOL", (-1,)), "error_bound": TensorSpec("FP32", (-1,)),
                     "source": TensorSpec("INT32", (-1,))}
#: The outputs only a surrogate gives (not the solver).
GUARD_OUTPUTS = ("error_bound", "source")
#: The value of ``error_bound`` for a design without a finite bound (OIP JSON has no infinity).
NO_BOUND = -1.0
#: The solver's extra tensors.
LOAD_INPUTS = {"gravity": TensorSpec("FP64", (-1, 3)), "density": TensorSpec("FP64", (-1,)),
               "tip_force": TensorSpec("FP64", (-1, 3)), "tip_moment": TensorSpec("FP64", (-1, 3))}
#: Any robot's tensors (:data:`tdcr.robot.fields.LAYOUT_COLUMNS`): ``layout`` per tendon (angle rad, end m,
#: displacement m, displacement-driven 0/1), and each design field of its own (``poisson``).
LAYOUT_INPUTS = {"layout": TensorSpec("FP64", (-1, -1, -1))} | {
    name: TensorSpec("FP64", (-1,)) for name in OWN_TENSORS}
EXACT_INPUTS = SURROGATE_INPUTS | {"design": TensorSpec("FP64", (-1, -1))} | LOAD_INPUTS | LAYOUT_INPUTS
EXACT_OUTPUTS = {k: v for k, v in SURROGATE_OUTPUTS.items() if k not in GUARD_OUTPUTS} | {
    "tendons": TensorSpec("FP32", (-1, -1, -1, 3)),
    "converged": TensorSpec("BOOL", (-1,)), "residual": TensorSpec("FP64", (-1,)),
    "status": TensorSpec("INT32", (-1,)), "error_estimate": TensorSpec("FP64", (-1,)),
    "tension": TensorSpec("FP64", (-1, -1)), "displacement": TensorSpec("FP64", (-1, -1)),
    "tension_profile": TensorSpec("FP64", (-1, -1, -1)), "slack": TensorSpec("BOOL", (-1, -1))}
#: The fewest ``layout`` columns (angle, end, displacement, driven); the later ones may be left off.
MIN_LAYOUT_COLUMNS = LAYOUT_COLUMNS.index("driven") + 1
#: Inverse kinematics (/inverse with the exact model): one design, the targets of a path.
INVERSE_INPUTS = {"design": TensorSpec("FP64", (1, N_FEATURES)), "position": TensorSpec("FP64", (-1, 3)),
                  "direction": TensorSpec("FP64", (-1, 3)), "tension_max": TensorSpec("FP64", (1,))}
INVERSE_OUTPUTS = {"tensions": TensorSpec("FP64", (-1, N_TENDONS)), "position": TensorSpec("FP64", (-1, 3)),
                   "error": TensorSpec("FP64", (-1,)), "status": TensorSpec("INT32", (-1,))}
#: The ``status`` output of the inverse model.
INVERSE_STATUS = {"reached": 0, "closest": 1, "failed": 2}
#: Header of the binary tensor extension.
HEADER_LENGTH = INFERENCE_HEADER_LENGTH
#: What the server says of itself (OIP server metadata).
SERVER_NAME = "tdcr-surrogates"
EXTENSIONS = ["binary_tensor_data"]
#: Error kinds and their HTTP statuses over OIP REST (the gRPC binding maps the same kinds to its codes).
HTTP_STATUS = {"invalid": 400, "not_found": 404, "too_large": 413, "saturated": 503, "unavailable": 503,
               "deadline": 504}
#: Output tensors: name -> (datatype, array).
OutputTensors = dict[str, tuple[str, np.ndarray]]


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


@dataclass(frozen=True)
class InferRequest:
    """A decoded inference request: input arrays by name, the outputs wanted (name -> binary/raw),
    the id and the ``tolerance`` parameter (None: none)."""

    inputs: dict[str, np.ndarray]
    outputs: dict[str, bool]
    id: str | None
    tolerance: float | None = None
    termination: str | None = None  #: the exact model's ``termination`` parameter (None: absent)


def tolerance_parameter(value) -> float | None:
    """The request parameter ``tolerance`` (a number; None: absent); :class:`InferenceError` else."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InferenceError("invalid", f"parameter 'tolerance' must be a number (relative l2), got {quote(value)}")
    return float(value)


def termination_parameter(value) -> str | None:
    """The request parameter ``termination`` (None: absent); :class:`InferenceError` else."""
    if value is None:
        return None
    if value not in TERMINATIONS:
        raise InferenceError("invalid", f"parameter 'termination' must be one of {list(TERMINATIONS)}, "
                                        f"got {quote(value)}")
    return str(value)


def check_input(name, datatype, shape, *, inputs: Tensors, seen: Mapping[str, np.ndarray]) -> tuple[np.dtype, int]:
    """The numpy type and element count of an input tensor's declared ``name``, ``datatype`` and
    ``shape`` (any transport); :class:`InferenceError` naming the tensor and the reason else."""
    if name not in inputs:
        raise InferenceError("invalid", f"unexpected input {quote(name)}; this model takes {list(inputs)}")
    if name in seen:
        raise InferenceError("invalid", f"input {name!r} is given twice")
    allowed = ("FP64", "FP32") if inputs[name].datatype == "FP64" else (inputs[name].datatype,)
    if datatype not in allowed:
        raise InferenceError("invalid", f"input {name!r}: datatype must be one of {list(allowed)}, "
                                        f"got {quote(datatype)}")
    expected = list(inputs[name].shape)
    if (not isinstance(shape, list) or len(shape) != len(expected)
            or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
            or any(e != -1 and d != e for d, e in zip(shape, expected, strict=True))):
        raise InferenceError("invalid", f"input {name!r}: shape must be {expected} (-1: any), got {quote(shape)}")
    return DATATYPES[datatype], int(np.prod(shape, dtype=object))


def check_request(arrays: Mapping[str, np.ndarray], outputs_asked: list[tuple[object, bool]], *,
                  outputs: Tensors, required: tuple[str, ...] = ("design",)) -> dict[str, bool]:
    """The outputs wanted (name -> binary/raw) from ``outputs_asked`` (name, binary) pairs, empty
    for every output; :class:`InferenceError` for a missing input or an unknown output."""
    missing = [n for n in required if n not in arrays]
    if missing:
        raise InferenceError("invalid", f"missing input(s) {missing}")
    wanted: dict[str, bool] = {}
    for name, binary in outputs_asked:
        if name not in outputs:
            raise InferenceError("invalid", f"unknown output {quote(name)}; this model gives {list(outputs)}")
        wanted[name] = binary
    return wanted


def decode(body: bytes, header_length: str | None, *, inputs: Tensors, outputs: Tensors,
           required: tuple[str, ...] = ("design",)) -> InferRequest:
    """An OIP REST inference request (JSON, or JSON followed by binary tensors)."""
    try:
        json_length = len(body) if header_length is None else int(header_length)
    except ValueError:
        raise InferenceError("invalid", f"{HEADER_LENGTH} must be an integer, got {quote(header_length)}") from None
    if not 0 <= json_length <= len(body):
        raise InferenceError("invalid", f"{HEADER_LENGTH} {json_length} is outside the body of {len(body)} bytes")
    try:
        request = orjson.loads(body[:json_length])
    except orjson.JSONDecodeError as exc:
        raise InferenceError("invalid", f"the request is not valid JSON: {exc}") from None
    if not isinstance(request, dict) or not isinstance(request.get("inputs"), list):
        raise InferenceError("invalid", "the request must be an object with a list of 'inputs'")
    binary = memoryview(body)[json_length:]
    offset = 0
    arrays: dict[str, np.ndarray] = {}
    for spec in request["inputs"]:
        if not isinstance(spec, dict):
            raise InferenceError("invalid", "each input must be an object")
        name, datatype, shape = spec.get("name"), spec.get("datatype"), spec.get("shape")
        dtype, count = check_input(name, datatype, shape, inputs=inputs, seen=arrays)
        size = (spec.get("parameters") or {}).get("binary_data_size")
        if size is not None:
            if not isinstance(size, int) or size != count * dtype.itemsize or offset + size > len(binary):
                raise InferenceError("invalid", f"input {name!r}: binary_data_size {quote(size)} does not match its "
                                          f"shape {shape} of {datatype} or the {len(binary) - offset} bytes left")
            array = np.frombuffer(binary, dtype=dtype, count=count, offset=offset)
            offset += size
        else:
            data = spec.get("data")
            if not isinstance(data, list):
                raise InferenceError("invalid", f"input {name!r}: 'data' must be a list (or use binary_data_size)")
            array = np.asarray(data, dtype=object).reshape(-1) if count else np.zeros(0)
            if array.size != count or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                               for v in array.tolist()):
                raise InferenceError("invalid", f"input {name!r}: 'data' must hold {count} numbers, row-major")
            array = array.astype(dtype)
        arrays[name] = array.reshape(shape)
    if offset != len(binary):
        raise InferenceError("invalid", f"{len(binary) - offset} bytes of binary data are not claimed by any input")
    default_binary = bool((request.get("parameters") or {}).get("binary_data_output", False))
    asked = [(spec.get("name") if isinstance(spec, dict) else None,
              bool(((spec.get("parameters") if isinstance(spec, dict) else None) or {}).get("binary_data",
                                                                                            default_binary)))
             for spec in request.get("outputs") or [{"name": n} for n in outputs]]
    wanted = check_request(arrays, asked, outputs=outputs, required=required)
    request_id = request.get("id")
    parameters = request.get("parameters") or {}
    tolerance = tolerance_parameter(parameters.get("tolerance") if isinstance(parameters, dict) else None)
    termination = termination_parameter(parameters.get("termination") if isinstance(parameters, dict) else None)
    return InferRequest(inputs=arrays, outputs=wanted, id=None if request_id is None else str(request_id)[:64],
                        tolerance=tolerance, termination=termination)


def encode(model: str, tensors: OutputTensors, binary: Mapping[str, bool],
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
    head = orjson.dumps({"model_name": model, "model_version": VERSION, "outputs": outputs,
                         **({"id": request_id} if request_id is not None else {})}, option=orjson.OPT_SERIALIZE_NUMPY)
    return (head + b"".join(blobs), len(head)) if blobs else (head, None)


# -- what every OIP transport shares: tensors to a model's task, its answer to tensors -------------


@dataclass(frozen=True)
class Decoded:
    """A decoded OIP request for one model: its validated ``task``, the input arrays, the outputs
    wanted (name -> binary/raw) and the request id."""

    task: object
    request: InferRequest
    model: str


class OipCodec:
    """The OIP's meaning, shared by REST (:class:`RestCodec`) and gRPC
    (:class:`service.grpc_codec.GrpcCodec`): subclasses read and write the wire (``wire_decode``,
    ``wire_encode``)."""

    def wire_decode(self, payload, spec: ModelSpec) -> InferRequest:
        raise NotImplementedError

    def wire_encode(self, model: str, tensors: OutputTensors, request: InferRequest):
        raise NotImplementedError

    def decode(self, payload, spec: ModelSpec) -> Decoded:
        request = self.wire_decode(payload, spec)
        inputs = request.inputs
        if request.tolerance is not None and spec.kind != "surrogate":
            raise InferenceError("invalid", f"parameter 'tolerance' applies to the operators, not to {spec.name!r} "
                                            "(the exact solver's error is below 1e-6 already)")
        if request.termination is not None and spec.kind != "solver":
            raise InferenceError("invalid", f"parameter 'termination' applies to the exact model, not to {spec.name!r}")
        try:
            if spec.kind == "inverse":
                task = _inverse_problem(inputs)
            else:
                wanted = [n for n in request.outputs if n in OUTPUTS]
                task = validate_features(inputs["design"], target="surrogate" if spec.kind == "surrogate" else "solver",
                                         model=spec.name, s=inputs.get("s"), arclength=inputs.get("arclength"),
                                         outputs=wanted or ["tendons"], tolerance=request.tolerance,
                                         limits=spec.limits, loads={n: inputs[n] for n in LOAD_INPUTS if n in inputs},
                                         layout=_layout(inputs), termination=request.termination or "exact")
        except InvalidRequest as exc:
            inputs_named = "input 'design' or 's'" if spec.kind == "surrogate" else "inputs"
            if [p.loc for p in exc.problems] == [("tolerance",)]:
                inputs_named = "parameter"
            raise InferenceError("too_large" if exc.too_large else "invalid", f"{inputs_named}: {exc.message}",
                                 tuple(exc.problems)) from None
        return Decoded(task=task, request=request, model=spec.name)

    def encode(self, decoded: Decoded, answer):
        tensors = answer_tensors(decoded, answer)
        return self.wire_encode(decoded.model, {n: tensors[n] for n in decoded.request.outputs}, decoded.request)


def _layout(inputs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
    """The ``layout`` ``[B, N_t, k]`` (:data:`tdcr.robot.fields.LAYOUT_COLUMNS`) and the design fields'
    own ``[B]`` inputs as the general design's arrays by name
    (:func:`tdcr.api.validation.validate_features`'s ``layout``), or None."""
    out = {}
    if "layout" in inputs:
        layout = np.asarray(inputs["layout"], dtype=np.float64)
        if not MIN_LAYOUT_COLUMNS <= layout.shape[-1] <= len(LAYOUT_COLUMNS):
            raise InferenceError("invalid", f"input 'layout' must have {MIN_LAYOUT_COLUMNS} to {len(LAYOUT_COLUMNS)} "
                                            f"columns ({', '.join(LAYOUT_COLUMNS)}; absent ones take their "
                                            f"defaults), got {layout.shape[-1]}")
        for k, name in enumerate(LAYOUT_COLUMNS[:layout.shape[-1]]):
            if name == "driven":
                continue
            out[name] = layout[..., k]
            if name == "stiffness":  # 0: rigid
                out[name] = np.where(out[name] == 0.0, np.inf, out[name])
            if LAYOUT_COLUMNS[k + 1:k + 2] == ("driven",):  # an alternative field: NaN where the other drives
                driven = layout[..., k + 1]
                if not np.isin(driven, (0.0, 1.0)).all():
                    raise InferenceError("invalid", f"input 'layout': its column {k + 1} ({name}-driven) must be 0 "
                                                    "or 1")
                out[name] = np.where(driven == 1.0, out[name], np.nan)
    out |= {name: np.asarray(inputs[name], dtype=np.float64) for name in OWN_TENSORS if name in inputs}
    return out or None


def _inverse_problem(inputs: Mapping[str, np.ndarray]):
    """The inverse problem of the ``inverse`` model's tensors (exact model)."""
    positions = np.asarray(inputs["position"], dtype=np.float64)
    directions = inputs.get("direction")
    if directions is not None and len(directions) != len(positions):
        raise InferenceError("invalid", f"input 'direction' has {len(directions)} rows, "
                                        f"'position' has {len(positions)}")
    design = DesignBatch.from_features(np.asarray(inputs["design"], dtype=np.float64))
    tension_max = inputs.get("tension_max")
    return check_inverse(design, positions, np.full_like(positions, np.nan) if directions is None else directions,
                         tension_max=INVERSE_DEFAULTS["tension_max"] if tension_max is None else float(tension_max[0]))


def answer_tensors(decoded: Decoded, answer) -> OutputTensors:
    """Every output tensor of a model's answer (name -> (datatype, array))."""
    if isinstance(answer, Prediction):
        bounds = answer.bounds
        return {"in_distribution": ("BOOL", np.array([not w for w in answer.warnings])),
                "error_bound": ("FP32", np.where(np.isfinite(bounds), bounds, NO_BOUND)),
                "source": ("INT32", answer.sources)} | {k: ("FP32", v) for k, v in answer.arrays.items()}
    if isinstance(answer, ExactAnswer):
        g = answer.arrays()
        return {"backbone": ("FP32", g.backbone), "rotation": ("FP32", g.rotation), "tendons": ("FP32", g.tendons),
                "in_distribution": ("BOOL", np.array([not w for w in range_warnings(decoded.task.features)])),
                "converged": ("BOOL", g.converged), "residual": ("FP64", g.residual),
                "status": ("INT32", g.status.astype(np.int32)),
                "error_estimate": ("FP64", np.where(np.isnan(g.error_estimate), -1.0, g.error_estimate)),
                "tension": ("FP64", g.tension), "displacement": ("FP64", g.displacement),
                "tension_profile": ("FP64", g.tension_profile),
                "slack": ("BOOL", np.zeros(g.tension.shape, dtype=bool) if g.slack is None else g.slack)}
    if isinstance(answer, InverseAnswer):
        r = answer.results
        return {"tensions": ("FP64", np.array([x["tensions"] for x in r])),
                "position": ("FP64", np.array([x["position"] for x in r])),
                "error": ("FP64", np.array([x["error"] for x in r])),
                "status": ("INT32", np.array([INVERSE_STATUS[x["status"]] for x in r], dtype=np.int32))}
    raise TypeError(f"no tensors for {type(answer).__name__}")


@dataclass(frozen=True)
class RestCodec(OipCodec):
    """OIP over REST: a JSON body, or JSON followed by binary tensors (``header_length``: the
    JSON part's length, from the ``Inference-Header-Content-Length`` header)."""

    header_length: str | None = None

    def wire_decode(self, payload: bytes, spec: ModelSpec) -> InferRequest:
        return decode(payload, self.header_length, inputs=spec.inputs, outputs=spec.outputs, required=spec.required)

    def wire_encode(self, model: str, tensors: OutputTensors, request: InferRequest) -> tuple[bytes, int | None]:
        return encode(model, tensors, request.outputs, request.id)
