"""The FastAPI application: ``create_app()`` builds it; the lifespan handler loads the models.

Run with ``tdcr serve --port 8000`` or ``uvicorn --factory service.app:create_app``.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import time
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

import tdcr
from service.errors import ApiError
from service.grpc_server import GrpcServer
from service.metrics import HTTP, Metrics
from service.model import RETRY_SATURATED_S
from service.oip import InferenceRequest
from service.routers import design_space, exact, health, inverse, models, predict, v2, viewer
from service.settings import Settings
from service.state import ServiceState, start
from tdcr.api.schemas import ExactRequest, InverseRequest, PredictRequest
from tdcr.robot.real import robot_schema

log = logging.getLogger("tdcr.service")


class ExactAdmission:
    """ASGI middleware: /exact answers 503 at once while every solver slot is taken, before
    routing, body or parsing, and closes the connection so the client stops uploading.  Under a
    flood this is the cheapest refusal there is; the router checks again (a slot can go between)."""

    def __init__(self, app, state: ServiceState):
        self.app, self.state = app, state

    async def __call__(self, scope, receive, send):
        exact = self.state.exact
        if scope["type"] == "http" and scope["path"] == "/exact" and exact is not None and exact.saturated:
            self.state.metrics.errors.labels(HTTP, "/exact", "saturated").inc()
            retry = (b"retry-after", str(RETRY_SATURATED_S).encode())
            return await _send_error(send, 503, "the solver is saturated; retry later",
                                     extra=[(b"connection", b"close"), retry])
        return await self.app(scope, receive, send)


class BodyLimit:
    """ASGI middleware: 413 for bodies over ``limit`` bytes (declared or streamed)."""

    def __init__(self, app, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or {}).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            return await _send_error(send, 413, f"request body over {self.limit} bytes")
        seen = 0

        async def limited_receive():
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.limit:
                raise _TooLarge()
            return message

        try:
            await self.app(scope, limited_receive, send)
        except _TooLarge:
            await _send_error(send, 413, f"request body over {self.limit} bytes")


class ApiKeyAuth:
    """ASGI middleware: 401 unless the request carries one of ``keys`` (``Authorization: Bearer KEY``
    or ``X-API-Key: KEY``); health probes are open; /metrics takes ``metrics_key`` when set."""

    OPEN = ("/healthz", "/readyz", "/v2/health/live", "/v2/health/ready")

    def __init__(self, app, keys: set[str], metrics_key: str | None):
        self.app, self.keys, self.metrics_key = app, {k.encode() for k in keys}, metrics_key

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] in self.OPEN:
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        given = headers.get(b"x-api-key") or headers.get(b"authorization", b"").removeprefix(b"Bearer ").strip()
        accepted = {self.metrics_key.encode()} if scope["path"] == "/metrics" and self.metrics_key else self.keys
        if not any(hmac.compare_digest(given, key) for key in accepted):
            return await _send_error(send, 401, "a valid API key is required (Authorization: Bearer KEY)",
                                     extra=[(b"www-authenticate", b"Bearer")])
        return await self.app(scope, receive, send)


class RequestMetrics:
    """ASGI middleware: counts requests by endpoint and status; latency of the endpoints without a model."""

    def __init__(self, app, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = time.perf_counter()
        status = 500

        async def send_status(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            path = _route_label(scope)  # the router has put the matched route into the scope
            self.metrics.requests.labels(HTTP, path, str(status)).inc()
            if path not in ("/predict", "/exact", "/v2/models/{model}/infer",
                            "/v2/models/{model}/versions/{version}/infer"):
                self.metrics.latency.labels(HTTP, path, "").observe(time.perf_counter() - started)


class _TooLarge(Exception):
    pass


async def _send_error(send, status: int, message: str, extra: list[tuple[bytes, bytes]] = ()) -> None:
    body = json.dumps({"message": message, "detail": message}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *extra]})
    await send({"type": "http.response.body", "body": body})


async def _watch_solver(state: ServiceState, starting: asyncio.Task) -> None:
    """Once the service has started, replace solver processes that die (until cancelled)."""
    await asyncio.shield(starting)
    exact = state.exact
    if exact is not None and exact.pool is not None:
        await exact.pool.watch()


def _route_label(scope) -> str:
    """The metric label of a request: its route's path template (a fixed set), or ``other``
    (never the raw path)."""
    return getattr(scope.get("route"), "path", None) or "other"


def _error_response(request: Request, exc: ApiError) -> JSONResponse:
    state: ServiceState = request.app.state.service
    state.metrics.errors.labels(HTTP, _route_label(request.scope), exc.kind).inc()
    return JSONResponse({"message": exc.message, "detail": exc.detail}, status_code=exc.status, headers=exc.headers)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    state = ServiceState.create(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        state.plane.starting = True  # the port answers at once: /healthz 200, /readyz 503 until started
        grpc_server = GrpcServer(state) if settings.grpc_port else None
        if grpc_server is not None:
            try:
                await grpc_server.start()
            except RuntimeError as exc:  # e.g. the port is taken: reported by /readyz
                state.problems.append(f"gRPC server on {grpc_server.address}: {exc}")
                grpc_server = None
        starting = asyncio.create_task(start(state, before_ready=None if grpc_server is None
                                             else grpc_server.set_health))
        watcher = asyncio.create_task(_watch_solver(state, starting))
        yield
        if grpc_server is not None:
            await grpc_server.stop()
        for task in (starting, watcher):
            task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await starting
        state.plane.close()

    docs = {} if settings.docs else {"docs_url": None, "redoc_url": None, "openapi_url": None}
    app = FastAPI(title="tdcr-surrogates", version=tdcr.__version__, lifespan=lifespan, **docs,
                  description="Shapes of tendon-driven continuum robots: neural-operator surrogates (/predict) "
                              "and the Cosserat solver (/exact).  SI units throughout.")
    app.state.service = state
    for router in (predict.router, exact.router, inverse.router, models.router, design_space.router, health.router,
                   v2.router, viewer.router):
        app.include_router(router)
    viewer.mount(app)

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        return _error_response(request, exc)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        items = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", "invalid"), "type": e.get("type", "invalid")}
                 for e in exc.errors()]
        message = "; ".join(f"{'.'.join(map(str, i['loc']))}: {i['msg']}" for i in items)
        return _error_response(request, ApiError(422, message, items, kind="validation"))

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        response = _error_response(request, ApiError(exc.status_code, str(exc.detail)[:200],
                                                     kind=f"http_{exc.status_code}"))
        response.headers.update(exc.headers or {})  # e.g. Allow on a 405
        return response

    @app.exception_handler(ClientDisconnect)
    async def disconnected(request: Request, exc: ClientDisconnect):  # nobody is left to read the answer
        return _error_response(request, ApiError(400, "the client disconnected", kind="disconnected"))

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception):  # pragma: no cover - must never happen
        log.exception("unexpected error on %s", request.url.path)
        return _error_response(request, ApiError(500, "internal error", kind="internal"))

    app.add_middleware(BodyLimit, limit=settings.max_body_bytes)
    app.add_middleware(ExactAdmission, state=state)
    if settings.api_keys or settings.metrics_api_key:
        app.add_middleware(ApiKeyAuth, keys=settings.api_keys, metrics_key=settings.metrics_api_key)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["GET", "POST"],
                           allow_headers=["content-type", "authorization", "x-api-key"])
    app.add_middleware(RequestMetrics, metrics=state.metrics)  # outermost: counts every answer
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app




def _openapi(app: FastAPI) -> dict:
    """FastAPI's document plus the JSON schemas of the request bodies (parsed by tdcr.api.validation)."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    ref_template = "#/components/schemas/{model}"
    for body in (PredictRequest, ExactRequest, InverseRequest, InferenceRequest):
        js = body.model_json_schema(ref_template=ref_template)
        components.update(js.pop("$defs", {}))
        components[body.__name__] = js
    robot = robot_schema(ref_template=ref_template)  # /exact also takes a robot file: its design
    del robot["$schema"], robot["$defs"]
    robot["properties"]["design"] = {"$ref": ref_template.format(model="Design")}  # ExactRequest's, as above
    components["RobotFile"] = robot
    app.openapi_schema = schema
    return schema
