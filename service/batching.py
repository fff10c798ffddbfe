"""Dynamic batching of /predict: concurrent requests for one model share one onnxruntime run.

A graph run has a fixed cost (a few hundred small nodes, whatever the batch) on top of its
per-design cost, so under load, running the designs of all queued requests together multiplies
throughput.  One worker thread per model takes everything queued when it becomes free (no
waiting window), groups it by (arclengths, pose wanted), runs each group as one batch and hands
every request its rows.  A request that finds the model idle (nothing queued or running) runs at
once in its own thread instead, saving the two thread hand-offs.  Results do not depend on the
batch: the operators treat designs independently.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from tdcr.surrogates.runtime import Surrogate


@dataclass
class _Job:
    features: np.ndarray  # (b, F) raw SI designs
    fractions: np.ndarray  # (n,) fractions of L
    loads: np.ndarray | None  # (b, 10) the loads matrix of a loaded operator
    pose: bool
    future: Future = field(default_factory=Future)


class Batcher:
    """Queue and worker thread of one model.  ``max_designs``: the most designs run together."""

    def __init__(self, model: Surrogate, *, max_designs: int = 4096, on_run: Callable[[int], None] | None = None):
        """``on_run(designs)`` is called after every graph run (e.g. to feed a histogram)."""
        self.model = model
        self.on_run = on_run
        self.max_designs = max_designs
        self._queue: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._active = 0  # runs in progress, inline or on the worker
        self.runs = 0  # graph runs so far (a run may serve several requests)
        self._thread = threading.Thread(target=self._work, name=f"batcher-{model.name}", daemon=True)
        self._thread.start()

    @property
    def queued(self) -> int:
        """Requests waiting for the worker (a request that runs inline never waits)."""
        return self._queue.qsize()

    @property
    def takes_loads(self) -> bool:
        return self.model.takes_loads

    @property
    def load_ranges(self) -> dict | None:
        return self.model.load_ranges

    def predict(self, features: np.ndarray, fractions: np.ndarray, *, loads=None, pose: bool = True,
                check: bool = False) -> dict[str, np.ndarray]:
        """As :meth:`Surrogate.predict`, run together with whatever else is queued (blocks the
        caller).  Its requests are validated already: ``check`` is accepted, and not run."""
        features = np.asarray(features, dtype=np.float64)
        job = _Job(features, np.asarray(fractions, dtype=np.float64), self.model.load_matrix(loads, len(features)),
                   pose)
        with self._lock:
            inline = self._active == 0 and self._queue.empty()
            if inline:
                self._active += 1
        if not inline:
            self._queue.put(job)
            return job.future.result()
        try:
            self._run([job])
        finally:
            with self._lock:
                self._active -= 1
        return job.future.result()

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=10)

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            with self._lock:
                self._active += 1
            try:
                self._run_queued(job)
            finally:
                with self._lock:
                    self._active -= 1

    def _run_queued(self, job: _Job) -> None:
        """``job`` and whatever else is queued now (up to ``max_designs``), grouped by (arclengths, pose)."""
        jobs = [job]
        designs = len(job.features)
        while designs < self.max_designs:
            try:
                nxt = self._queue.get_nowait()
            except queue.Empty:
                break
            if nxt is None:
                self._queue.put(None)  # stop after this round
                break
            jobs.append(nxt)
            designs += len(nxt.features)
        groups: dict[tuple[bytes, bool], list[_Job]] = {}
        for j in jobs:
            groups.setdefault((j.fractions.tobytes(), j.pose), []).append(j)
        for group in groups.values():
            self._run(group)

    def _run(self, jobs: list[_Job]) -> None:
        self.runs += 1
        if self.on_run is not None:
            self.on_run(sum(len(j.features) for j in jobs))
        try:
            if len(jobs) == 1:
                jobs[0].future.set_result(self.model.predict(jobs[0].features, jobs[0].fractions, loads=jobs[0].loads,
                                                             pose=jobs[0].pose, check=False))
                return
            loads = None if jobs[0].loads is None else np.concatenate([j.loads for j in jobs])
            out = self.model.predict(np.concatenate([j.features for j in jobs]), jobs[0].fractions, loads=loads,
                                     pose=jobs[0].pose, check=False)
        except Exception as exc:  # noqa: BLE001 - handed to the waiting requests, which report it
            for j in jobs:
                if not j.future.done():
                    j.future.set_exception(exc)
            return
        start = 0
        for j in jobs:
            stop = start + len(j.features)
            j.future.set_result({k: v[start:stop] for k, v in out.items()})
            start = stop
