"""The Open Inference Protocol v2 over gRPC (``inference.GRPCInferenceService``), on ``grpc.aio`` in
the event loop of the HTTP server: one process, one :class:`service.v2plane.V2Plane`, one dynamic
batcher per model, one solver pool and one Prometheus registry (``protocol="grpc"``).

Also served: the standard health service ``grpc.health.v1.Health`` (``""``: live;
``inference.GRPCInferenceService``: ready, i.e. every model loaded and the solver pool up) and
server reflection.

Tensors come typed (``InferTensorContents``) or raw (``raw_input_contents``: flat row-major
little-endian bytes, one buffer per input); the answer is raw when the request was, as Triton's
(tritonclient reads outputs only from ``raw_output_contents``), else typed.

Status codes: invalid tensors, and requests over the size limits -> ``INVALID_ARGUMENT``; an
unknown model or version -> ``NOT_FOUND``; the solver saturated -> ``RESOURCE_EXHAUSTED``; the solver
down or failed -> ``UNAVAILABLE``; past /exact's deadline -> ``DEADLINE_EXCEEDED``.  Each message
names the tensor (or limit) and the reason.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import time
from collections.abc import Awaitable, Callable, Mapping

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection
from starlette.concurrency import run_in_threadpool

from service.metrics import GRPC
from service.oip import DATATYPES, InferRequest, OipError, check_input, check_request
from service.state import ServiceState
from service.v2plane import SOLVER_MODELS, VERSION, V2Plane
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc

log = logging.getLogger("tdcr.service")

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["GRPCInferenceService"].full_name
#: OIP error kinds -> gRPC status codes.
STATUS_CODES = {"invalid": grpc.StatusCode.INVALID_ARGUMENT, "too_large": grpc.StatusCode.INVALID_ARGUMENT,
                "not_found": grpc.StatusCode.NOT_FOUND, "saturated": grpc.StatusCode.RESOURCE_EXHAUSTED,
                "unavailable": grpc.StatusCode.UNAVAILABLE, "deadline": grpc.StatusCode.DEADLINE_EXCEEDED}
#: The typed-contents field of each datatype.
CONTENTS = {"BOOL": "bool_contents", "INT32": "int_contents", "INT64": "int64_contents",
            "UINT8": "uint_contents", "FP32": "fp32_contents", "FP64": "fp64_contents"}
#: How often the health service's readiness follows the service's.
HEALTH_PERIOD_S = 0.5


def decode(request: pb.ModelInferRequest, *, inputs: Mapping[str, tuple[str, list[int]]],
           outputs: Mapping[str, tuple[str, list[int]]], required: tuple[str, ...] = ("design",)) -> InferRequest:
    """A ``ModelInferRequest`` as an :class:`InferRequest` (outputs raw iff the inputs were)."""
    raw = request.raw_input_contents
    if raw and len(raw) != len(request.inputs):
        raise OipError("invalid", f"raw_input_contents has {len(raw)} buffers for {len(request.inputs)} inputs")
    arrays: dict[str, np.ndarray] = {}
    for i, tensor in enumerate(request.inputs):
        name, shape = tensor.name, list(tensor.shape)
        dtype, count = check_input(name, tensor.datatype, shape, inputs=inputs, seen=arrays)
        if raw:
            if tensor.HasField("contents"):
                raise OipError("invalid", f"input {name!r}: give raw_input_contents or contents, not both")
            if len(raw[i]) != count * dtype.itemsize:
                raise OipError("invalid", f"input {name!r}: {len(raw[i])} raw bytes do not match its shape "
                                          f"{shape} of {tensor.datatype} ({count * dtype.itemsize} bytes)")
            array = np.frombuffer(raw[i], dtype=dtype, count=count)
        else:
            values = getattr(tensor.contents, CONTENTS[tensor.datatype])
            if len(values) != count:
                raise OipError("invalid", f"input {name!r}: contents.{CONTENTS[tensor.datatype]} holds "
                                          f"{len(values)} values, its shape {shape} needs {count}")
            array = np.array(values, dtype=dtype)
        arrays[name] = array.reshape(shape)
    asked = [(o.name, bool(raw)) for o in request.outputs] or [(n, bool(raw)) for n in outputs]
    wanted = check_request(arrays, asked, outputs=outputs, required=required)
    return InferRequest(inputs=arrays, outputs=wanted, id=request.id[:64] or None)


def encode(model: str, tensors: Mapping[str, tuple[str, np.ndarray]], *, raw: bool,
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


def encode_raw(model: str, tensors: Mapping[str, tuple[str, np.ndarray]], *, request_id: str | None) -> bytes:
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


class InferenceServicer(pb_grpc.GRPCInferenceServiceServicer):
    """``inference.GRPCInferenceService`` over a :class:`V2Plane`; every call is counted in the
    service's metrics with ``protocol="grpc"``."""

    def __init__(self, plane: V2Plane):
        self.plane = plane
        self.metrics = plane.state.metrics

    async def _answer(self, method: str, context: grpc.aio.ServicerContext, work: Callable[[], Awaitable]):
        code = grpc.StatusCode.OK
        try:
            return await work()
        except OipError as exc:
            code = STATUS_CODES[exc.kind]
            self.metrics.errors.labels(GRPC, method, exc.kind).inc()
            await context.abort(code, exc.message)
        except asyncio.CancelledError:  # the client went away or its deadline passed
            code = grpc.StatusCode.CANCELLED
            raise
        except grpc.aio.AbortError:  # already answered with its status
            raise
        except Exception:  # a bug: INTERNAL with no details, logged, counted as such
            code = grpc.StatusCode.INTERNAL
            log.exception("unexpected error in %s", method)
            self.metrics.errors.labels(GRPC, method, "internal").inc()
            await context.abort(code, "internal error")
        finally:
            self.metrics.requests.labels(GRPC, method, code.name).inc()

    async def ServerLive(self, request, context):
        return await self._answer("ServerLive", context, _value(pb.ServerLiveResponse(live=True)))

    async def ServerReady(self, request, context):
        return await self._answer("ServerReady", context,
                                  _value(pb.ServerReadyResponse(ready=self.plane.server_ready())))

    async def ModelReady(self, request, context):
        async def work():
            return pb.ModelReadyResponse(ready=self.plane.model_ready(request.name, request.version))
        return await self._answer("ModelReady", context, work)

    async def ServerMetadata(self, request, context):
        return await self._answer("ServerMetadata", context,
                                  _value(pb.ServerMetadataResponse(**self.plane.server_metadata())))

    async def ModelMetadata(self, request, context):
        async def work():
            meta = self.plane.model_metadata(request.name, request.version)
            # the gRPC message has no parameters field: they travel as trailing metadata
            context.set_trailing_metadata(tuple((f"tdcr-{k}", str(v)) for k, v in meta.pop("parameters").items()))
            return pb.ModelMetadataResponse(**meta)
        return await self._answer("ModelMetadata", context, work)

    async def ModelInfer(self, request, context):
        async def work():
            started = time.perf_counter()
            model = request.model_name
            self.plane.check_model(model, request.model_version)
            if model in SOLVER_MODELS:  # the solver request built off the loop, the solve in the pool
                decoded = self._decode(model, request)
                features, body = await run_in_threadpool(self.plane.solver_body, model, decoded)
                tensors, n = await self.plane.solver(model, decoded, features, body)
                response = encode(model, tensors, raw=bool(request.raw_input_contents), request_id=decoded.id)
            else:  # decode, run and encode in one thread hop
                response, n = await run_in_threadpool(self._surrogate, model, request)
            self.metrics.latency.labels(GRPC, "ModelInfer", model).observe(time.perf_counter() - started)
            self.metrics.designs.labels(GRPC, "ModelInfer", model).inc(n)
            return response
        return await self._answer("ModelInfer", context, work)

    def _decode(self, model: str, request: pb.ModelInferRequest) -> InferRequest:
        inputs, outputs, required = self.plane.tensors(model)
        return decode(request, inputs=inputs, outputs=outputs, required=required)

    def _surrogate(self, model: str, request: pb.ModelInferRequest) -> tuple[pb.ModelInferResponse, int]:
        decoded = self._decode(model, request)
        tensors, n = self.plane.surrogate(model, decoded)
        return encode(model, tensors, raw=bool(request.raw_input_contents), request_id=decoded.id), n


def _serialize(response: pb.ModelInferResponse | bytes | object) -> bytes:
    """Answers are messages, or already serialised (:func:`encode_raw`)."""
    return response if isinstance(response, bytes) else response.SerializeToString()


def _handlers(servicer: InferenceServicer) -> grpc.GenericRpcHandler:
    """The service's method handlers, as the generated ``add_..._to_server`` makes them, but with
    :func:`_serialize` for the answers."""
    methods = pb.DESCRIPTOR.services_by_name["GRPCInferenceService"].methods
    return grpc.method_handlers_generic_handler(SERVICE_NAME, {
        m.name: grpc.unary_unary_rpc_method_handler(getattr(servicer, m.name),
                                                    request_deserializer=getattr(pb, m.input_type.name).FromString,
                                                    response_serializer=_serialize)
        for m in methods})


def _value(response):
    async def work():
        return response
    return work


class ApiKeyInterceptor(grpc.aio.ServerInterceptor):
    """``UNAUTHENTICATED`` unless a call carries one of ``keys`` (metadata ``authorization: Bearer
    KEY`` or ``x-api-key: KEY``), as the HTTP server's ``TDCR_API_KEYS``; health, reflection and the
    liveness / readiness calls are open, as ``/v2/health/*`` are."""

    OPEN = {f"/{SERVICE_NAME}/ServerLive", f"/{SERVICE_NAME}/ServerReady"}

    def __init__(self, keys: set[str]):
        self.keys = {k.encode() for k in keys}

    async def intercept_service(self, continuation, details):
        if not details.method.startswith(f"/{SERVICE_NAME}/") or details.method in self.OPEN:
            return await continuation(details)
        metadata = dict(details.invocation_metadata or ())
        given = metadata.get("x-api-key") or metadata.get("authorization", "").removeprefix("Bearer ").strip()
        given = given.encode() if isinstance(given, str) else given
        if any(hmac.compare_digest(given, key) for key in self.keys):
            return await continuation(details)
        return grpc.unary_unary_rpc_method_handler(_unauthenticated)


async def _unauthenticated(request, context):
    await context.abort(grpc.StatusCode.UNAUTHENTICATED, "a valid API key is required (authorization: Bearer KEY)")


class GrpcServer:
    """The gRPC server of one service ``state``: ``await start()`` in the HTTP server's lifespan,
    ``await stop()`` at its end."""

    def __init__(self, state: ServiceState):
        settings = state.settings
        self.state = state
        self.plane = V2Plane(state)
        self.server = grpc.aio.server(
            interceptors=[ApiKeyInterceptor(settings.api_keys)] if settings.api_keys else [],
            options=[("grpc.max_receive_message_length", settings.grpc_max_receive_bytes),
                     ("grpc.max_send_message_length", settings.grpc_max_send_bytes)],
            maximum_concurrent_rpcs=settings.max_connections)
        self.server.add_generic_rpc_handlers((_handlers(InferenceServicer(self.plane)),))
        self.health = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        reflection.enable_server_reflection(
            (SERVICE_NAME, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME),
            self.server)
        self.address = f"{settings.grpc_host}:{settings.grpc_port}"
        self._health_task: asyncio.Task | None = None

    async def start(self) -> None:
        """Bind and serve (``RuntimeError`` if the port cannot be bound)."""
        self.server.add_insecure_port(self.address)
        await self.server.start()
        self._health_task = asyncio.get_running_loop().create_task(self._follow_readiness())
        log.info("gRPC (OIP v2) on %s", self.address)

    async def _follow_readiness(self) -> None:
        serving, not_serving = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING
        while True:
            await self.health.set(SERVICE_NAME, serving if self.plane.server_ready() else not_serving)
            await asyncio.sleep(HEALTH_PERIOD_S)

    async def stop(self) -> None:
        """Stop taking calls; calls in flight get ``grpc_grace_s`` to finish."""
        if self._health_task is not None:
            self._health_task.cancel()
        await self.health.enter_graceful_shutdown()
        await self.server.stop(self.state.settings.grpc_grace_s)
