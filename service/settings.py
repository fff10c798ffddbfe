"""All service settings, from environment variables prefixed ``TDCR_`` (pydantic-settings)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from tdcr.api.validation import Limits
from tdcr.physics.exact import WorkBudget
from tdcr.robot.design_space import MAX_POINTS
from tdcr.surrogates.runtime import DEFAULT_MODELS_DIR


class Settings(BaseSettings):
    """Service configuration.  E.g. ``TDCR_MODELS_DIR=/models TDCR_MAX_DESIGNS=5000 tdcr serve``."""

    model_config = SettingsConfigDict(env_prefix="TDCR_", extra="ignore")

    models_dir: Path = Field(DEFAULT_MODELS_DIR, description="directory with manifest.json and the ONNX files")
    default_model: str | None = Field(None, description="model used when a request names none (default: best)")
    max_designs: int = Field(100_000, ge=1, description="designs per /predict request")
    max_points: int = Field(MAX_POINTS, ge=2, le=MAX_POINTS, description="arclengths per request")
    max_design_points: int = Field(
        1_000_000, ge=1, description="designs x arclengths per request: the memory budget of one answer (a JSON "
                                     "answer takes about 330 bytes per design-point, so 1,000,000 is ~330 MB)")
    max_body_bytes: int = Field(64 * 1024 * 1024, ge=1024, description="request body limit, bytes")
    onnx_threads: int = Field(0, ge=0, description="chunks of a large batch run side by side (0: one per core)")
    batch_max_designs: int = Field(4096, ge=1, description="designs of concurrent /predict requests run together")
    inline: bool = Field(True, description="answer a request of a few designs without a tolerance on the event "
                                           "loop when no other inference is in flight (saves two thread hand-offs)")
    onnx_chunk: int = Field(512, ge=1, description="large batches run as chunks of this many designs")
    exact_workers: int = Field(1, ge=1, description="solver processes behind /exact")
    exact_max_designs: int = Field(2000, ge=1, description="designs per /exact request")
    exact_max_pending: int = Field(8, ge=1, description="solver slots: requests (/exact, /inverse, guarded /predict) "
                                   "waiting for or running in a solver process; with all taken, a request that "
                                   "needs one is refused saturated (503, gRPC RESOURCE_EXHAUSTED; /exact at the door)")
    exact_timeout_s: float = Field(30.0, gt=0, description="deadline of one /exact request's work in a solver process "
                                  "before 504 (the process is killed); a request that waits as long for a free "
                                  "process gets 503 with Retry-After")
    exact_seconds_per_design: float = Field(
        2e-4, gt=0, description="admission estimate of one tendon-loaded design at 42 points, s (measured with the "
        "compiled kernel on one core: 0.075 ms)")
    exact_seconds_per_loaded_design: float = Field(
        1e-2, gt=0, description="admission estimate of one design with gravity or tip loads, s (measured with the "
        "compiled kernel on one core: 3.6 ms)")
    exact_admission_factor: float = Field(
        3.0, gt=0, description="/exact refuses (413) work estimated at more than this times its deadline")
    router_costs: dict[str, tuple[float, float]] | None = Field(
        None, description='the router\'s costs instead of timing the paths at startup (JSON: {"exact": [fixed s, s '
        'per design], "exact_loaded": [...], "operator": [...], "loaded_operator": [...]}), e.g. for a deployment '
        'measured once, or tests')
    workers: int = Field(1, ge=1, description="uvicorn worker processes (scale out with replicas instead)")
    api_keys: set[str] = Field(set(), description='keys accepted on every route but /healthz and /readyz, as '
                               '"Authorization: Bearer KEY" or "X-API-Key: KEY" (JSON list; empty: no authentication)')
    metrics_api_key: str | None = Field(None, description="a key of its own for /metrics (else the api_keys)")
    cors_origins: list[str] = Field([], description="origins allowed cross-site (JSON list; empty: CORS off)")
    docs: bool = Field(True, description="serve /docs, /redoc and /openapi.json")
    header_timeout_s: float = Field(10.0, gt=0, description="a client's time to send a request's headers")
    body_timeout_s: float = Field(60.0, gt=0, description="a client's time to send a request's body")
    keep_alive_s: float = Field(5.0, gt=0, description="idle keep-alive connections are closed after this")
    max_connections: int = Field(1000, ge=1, description="open connections and requests before 503 (uvicorn's "
                                                         "limit_concurrency; keep it below the process's file limit)")

    grpc_port: int = Field(8001, ge=0, le=65535, description="port of the OIP v2 gRPC server (0: no gRPC server)")
    grpc_host: str = Field("127.0.0.1", description="address the gRPC server binds (tdcr serve sets it to --host)")
    grpc_max_receive_bytes: int = Field(64 * 1024 * 1024, ge=1024, description="largest gRPC request, bytes")
    grpc_max_send_bytes: int = Field(
        256 * 1024 * 1024, ge=1024, description="largest gRPC answer, bytes (every output of max_design_points "
                                                "design-points as FP32 is 96 MB)")
    grpc_grace_s: float = Field(5.0, ge=0, description="at shutdown, calls in flight get this long to finish")

    def predict_limits(self) -> Limits:
        """Size limits of one /predict request."""
        return Limits(max_designs=self.max_designs, max_points=self.max_points,
                      max_design_points=self.max_design_points)

    def exact_budget(self) -> WorkBudget:
        """The work /exact admits (estimated solver time, at most the factor times the deadline)."""
        return WorkBudget(seconds_per_design=self.exact_seconds_per_design,
                          seconds_per_loaded_design=self.exact_seconds_per_loaded_design,
                          max_seconds=self.exact_admission_factor * self.exact_timeout_s)

    def exact_limits(self) -> Limits:
        """Size limits of one /exact request."""
        return Limits(max_designs=self.exact_max_designs, max_points=self.max_points,
                      max_design_points=self.max_design_points)
