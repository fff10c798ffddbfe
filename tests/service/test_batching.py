"""Dynamic batching: concurrent requests share graph runs and get exactly their own rows."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from service.batching import Batcher
from tdcr import design_space
from tdcr.surrogates.runtime import Surrogate


@pytest.mark.parametrize("name", ["deeponet", "fno_pose"])
def test_concurrent_requests_get_their_own_rows(tiny_models, name):
    """Requests that arrive while the model is busy are merged into a few runs, whatever the
    scheduler does: the first two runs (one inline, one on the worker) are held until the other 28
    requests are queued, and each request gets exactly its own rows."""
    model = Surrogate.load(tiny_models[1], name)
    batcher = Batcher(model, max_designs=64)
    feats = design_space.sample_designs(40, seed=11).features()
    sigmas = [np.linspace(0, 1, 42), np.array([0.0, 0.3, 1.0])]
    jobs = [(feats[i:i + 1 + i % 3], sigmas[i % 2], i % 4 != 0) for i in range(30)]
    results: dict[int, dict] = {}
    running, release, real_predict = threading.Semaphore(0), threading.Event(), model.predict

    def held(*args, **kwargs):  # the real model, once the queue is full
        running.release()
        release.wait(60)
        return real_predict(*args, **kwargs)

    model.predict = held

    def call(i):
        f, s, pose = jobs[i]
        results[i] = batcher.predict(f, s, pose=pose)

    threads = [threading.Thread(target=call, args=(i,)) for i in range(len(jobs))]
    for t in threads[:2]:  # the first runs inline, the second on the worker: both held
        t.start()
        assert running.acquire(timeout=60)
    for t in threads[2:]:
        t.start()
    for _ in range(600):  # nothing takes from the queue while both runs are held
        if batcher.queued == len(jobs) - 2:
            break
        time.sleep(0.1)
    assert batcher.queued == len(jobs) - 2
    release.set()
    for t in threads:
        t.join(timeout=60)
    batcher.close()
    model.predict = real_predict
    assert len(results) == len(jobs)
    assert batcher.runs <= 2 + 4  # the 28 queued: one run per (arclengths, pose) group
    for i, (f, s, pose) in enumerate(jobs):
        alone = model.predict(f, s, pose=pose)
        assert set(results[i]) == set(alone)
        for k in alone:
            np.testing.assert_allclose(results[i][k], alone[k], rtol=1e-5, atol=2e-6)  # float32 graph, other blocking


def test_a_failing_run_fails_only_its_requests(tiny_models):
    batcher = Batcher(Surrogate.load(tiny_models[1], "deeponet"))
    with pytest.raises(Exception):  # noqa: B017 - whatever onnxruntime raises for a wrong shape
        batcher.predict(np.zeros((2, 7)), np.linspace(0, 1, 5))
    out = batcher.predict(design_space.sample_designs(2, seed=0).features(), np.linspace(0, 1, 5))
    assert out["tendons"].shape == (2, 5, 4, 3)
    batcher.close()


@pytest.mark.parametrize("name", ["deeponet", "fno_pose"])
def test_chunks_side_by_side_equal_one_call(tiny_models, name):
    feats = design_space.sample_designs(50, seed=12).features()
    fractions = np.array([0.0, 0.25, 0.5, 1.0])
    whole = Surrogate.load(tiny_models[1], name, threads=1, chunk=1000).predict(feats, fractions)
    chunked = Surrogate.load(tiny_models[1], name, threads=2, chunk=7).predict(feats, fractions)
    for k in whole:
        np.testing.assert_allclose(chunked[k], whole[k], rtol=1e-5, atol=2e-6)


def test_a_lone_request_runs_in_its_own_thread(tiny_models):
    """No hand-off to the worker when the model is idle; queued requests still go to the worker."""
    threads: list[str] = []
    batcher = Batcher(Surrogate.load(tiny_models[1], "deeponet"),
                      on_run=lambda n: threads.append(threading.current_thread().name))
    feats = design_space.sample_designs(3, seed=0).features()
    out = batcher.predict(feats, np.linspace(0, 1, 5))
    assert out["tendons"].shape == (3, 5, 4, 3)
    assert threads == [threading.current_thread().name]
    batcher.close()
