"""Prometheus metrics of one app instance (own registry, so several apps can live in one process)."""

from __future__ import annotations

from dataclasses import dataclass

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector

#: The ``protocol`` label: HTTP (the JSON/binary API and OIP v2 REST) or gRPC (OIP v2).
HTTP = "http"
GRPC = "grpc"
_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 30)


@dataclass
class Metrics:
    registry: CollectorRegistry
    requests: Counter
    latency: Histogram
    designs: Counter
    errors: Counter
    batch: Histogram
    guarded: Counter
    fallback: Counter
    solver_slots: Gauge

    @classmethod
    def create(cls) -> Metrics:
        reg = CollectorRegistry()
        ProcessCollector(registry=reg)
        return cls(
            registry=reg,
            requests=Counter("tdcr_requests", "requests by status (HTTP status or gRPC code)",
                             ["protocol", "endpoint", "status"], registry=reg),
            latency=Histogram("tdcr_request_seconds", "request latency, s", ["protocol", "endpoint", "model"],
                              buckets=_LATENCY_BUCKETS, registry=reg),
            designs=Counter("tdcr_designs", "designs answered", ["protocol", "endpoint", "model"], registry=reg),
            errors=Counter("tdcr_errors", "error responses by kind", ["protocol", "endpoint", "kind"], registry=reg),
            guarded=Counter("tdcr_guarded_designs", "surrogate designs asked with a tolerance", ["model"],
                            registry=reg),
            fallback=Counter("tdcr_fallback_designs", "of those, designs the exact solver answered (their error "
                             "bound exceeded the tolerance); the share that fell back is fallback / guarded",
                             ["model"], registry=reg),
            batch=Histogram("tdcr_graph_run_designs", "designs per onnxruntime run (dynamic batching)", ["model"],
                            buckets=(1, 2, 4, 8, 16, 32, 64, 256, 1024, 4096, 16384, 65536), registry=reg),
            solver_slots=Gauge("tdcr_solver_slots_in_use", "solver slots held (of TDCR_EXACT_MAX_PENDING): /exact, "
                               "/inverse and guarded requests waiting for or running in a solver process; "
                               "at the maximum a request that needs one is refused saturated", registry=reg),
        )
