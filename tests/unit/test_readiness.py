"""Readiness while the solver starts (service/dataplane.py, service/solver.py): the service is
ready once its models answer; a model still starting is listed, not a problem, and its calls say
503 "starting" by name."""

from __future__ import annotations

import asyncio

import pytest

from service.dataplane import DataPlane
from service.metrics import Metrics
from service.model import RETRY_STARTING_S, InferenceError, ModelRepository
from service.settings import Settings
from service.solver import STARTING, ExactModel, InverseModel


def _plane() -> tuple[DataPlane, ExactModel]:
    repository = ModelRepository()
    exact = ExactModel(Settings())
    repository.register(exact)
    repository.register(InverseModel(exact, lambda name: None))
    plane = DataPlane(repository, Metrics.create())
    plane.loaded = True
    return plane, exact


def test_a_starting_solver_leaves_the_service_ready_and_says_so():
    plane, exact = _plane()
    assert exact.starting and not exact.ready() and exact.health() == STARTING
    assert plane.server_ready() and plane.problems() == []
    assert plane.starting_models() == {"exact": STARTING, "inverse": STARTING}
    with pytest.raises(InferenceError, match="starting: the solver processes are starting") as err:
        asyncio.run(exact.run(print))
    assert err.value.kind == "unavailable" and err.value.retry_after == RETRY_STARTING_S


def test_a_solver_that_failed_to_start_is_a_problem_and_the_service_not_ready():
    plane, exact = _plane()
    exact.failed = True
    assert not exact.starting and not plane.server_ready()
    assert plane.problems() == ["solver pool: not running", "solver pool: not running"]
    assert plane.starting_models() == {}
    with pytest.raises(InferenceError, match="not running") as err:  # waiting will not cure it: no Retry-After
        asyncio.run(exact.run(print))
    assert err.value.kind == "unavailable" and err.value.retry_after is None


@pytest.mark.parametrize(("status", "header", "retry_for", "delay"),
                         [(503, "1", 10.0, 1.0), (503, "5", 3.0, None), (503, None, 10.0, None),
                          (503, "soon", 10.0, None), (504, "1", 10.0, None), (503, "2", 0.0, None)])
def test_a_client_waits_only_for_a_503_with_retry_after_within_its_budget(status, header, retry_for, delay):
    """``Client(retry_for=)``: a 503 whose Retry-After (seconds) still ends within the budget is
    waited for; any other answer is the client's answer (its TDCRError carries the Retry-After)."""
    import time

    import httpx

    from tdcr.clients.client import TDCRError, _decode, _wait

    response = httpx.Response(status, json={"message": "the solver is saturated; retry later"},
                              headers={} if header is None else {"retry-after": header})
    assert _wait(response, time.monotonic(), retry_for) == delay
    with pytest.raises(TDCRError) as err:
        _decode(response)
    assert err.value.retry_after == (float(header) if status == 503 and header and header.isdigit() else None)
