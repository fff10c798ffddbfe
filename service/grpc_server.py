"""The Open Inference Protocol v2 over gRPC (``inference.GRPCInferenceService``), on ``grpc.aio`` in
the event loop of the HTTP server: one process, the one :class:`service.dataplane.DataPlane` (its
models, their batchers and solver pool) and one Prometheus registry (``protocol="grpc"``).
A thin codec: :class:`service.grpc_codec.GrpcCodec` reads and writes the wire.

Also served: the standard health service ``grpc.health.v1.Health`` (``""``: live;
``inference.GRPCInferenceService``: ready, i.e. every model loaded and the solver pool up) and
server reflection.

Status codes: invalid tensors, and requests over the size limits -> ``INVALID_ARGUMENT``; an
unknown model or version -> ``NOT_FOUND``; the solver saturated -> ``RESOURCE_EXHAUSTED``; the solver
down or failed -> ``UNAVAILABLE``; past /exact's deadline -> ``DEADLINE_EXCEEDED``.  Each message
names the tensor (or limit) and the reason.  An error that waiting cures (saturated, starting)
carries gRPC's server pushback, the trailing metadata ``grpc-retry-pushback-ms`` (HTTP's
``Retry-After``), which a channel's retry policy honours.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
from collections.abc import Awaitable, Callable

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from service.dataplane import DataPlane
from service.grpc_codec import GrpcCodec, decode, encode, encode_raw  # noqa: F401 - the wire, re-exported
from service.metrics import GRPC
from service.model import InferenceError, InferenceRequest
from service.state import ServiceState
from tdcr.oip_grpc import open_inference_grpc_pb2 as pb
from tdcr.oip_grpc import open_inference_grpc_pb2_grpc as pb_grpc

log = logging.getLogger("tdcr.service")

SERVICE_NAME = pb.DESCRIPTOR.services_by_name["GRPCInferenceService"].full_name
#: OIP error kinds -> gRPC status codes.
STATUS_CODES = {"invalid": grpc.StatusCode.INVALID_ARGUMENT, "too_large": grpc.StatusCode.INVALID_ARGUMENT,
                "not_found": grpc.StatusCode.NOT_FOUND, "saturated": grpc.StatusCode.RESOURCE_EXHAUSTED,
                "unavailable": grpc.StatusCode.UNAVAILABLE, "deadline": grpc.StatusCode.DEADLINE_EXCEEDED}
#: gRPC's server pushback: how long a client's retry policy waits before the next attempt.
PUSHBACK = "grpc-retry-pushback-ms"
#: The codec of every ModelInfer call.
CODEC = GrpcCodec()
#: How often the health service's readiness follows the service's.
HEALTH_PERIOD_S = 0.5


class InferenceServicer(pb_grpc.GRPCInferenceServiceServicer):
    """``inference.GRPCInferenceService`` over the :class:`DataPlane`; every call is counted in the
    service's metrics with ``protocol="grpc"``."""

    def __init__(self, plane: DataPlane):
        self.plane = plane
        self.metrics = plane.metrics

    async def _answer(self, method: str, context: grpc.aio.ServicerContext, work: Callable[[], Awaitable]):
        """``work()``'s answer; the one mapping of data-plane errors to gRPC statuses."""
        code = grpc.StatusCode.OK
        try:
            return await work()
        except InferenceError as exc:
            code = STATUS_CODES[exc.kind]
            self.metrics.errors.labels(GRPC, method, exc.kind).inc()
            pushback = () if exc.retry_after is None else ((PUSHBACK, str(round(exc.retry_after * 1000))),)
            await context.abort(code, exc.message, trailing_metadata=pushback)
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
            answer = await self.plane.infer(request.model_name, InferenceRequest(request, CODEC),
                                            version=request.model_version, protocol=GRPC, endpoint="ModelInfer")
            return answer.body
        return await self._answer("ModelInfer", context, work)


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
        self.plane = state.plane
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

    async def set_health(self, ready: bool) -> None:
        """The health service's status of ``inference.GRPCInferenceService``."""
        status = health_pb2.HealthCheckResponse
        await self.health.set(SERVICE_NAME, status.SERVING if ready else status.NOT_SERVING)

    async def _follow_readiness(self) -> None:
        while True:
            await self.set_health(self.plane.server_ready())
            await asyncio.sleep(HEALTH_PERIOD_S)

    async def stop(self) -> None:
        """Stop taking calls; calls in flight get ``grpc_grace_s`` to finish."""
        if self._health_task is not None:
            self._health_task.cancel()
        await self.health.enter_graceful_shutdown()
        await self.server.stop(self.state.settings.grpc_grace_s)
