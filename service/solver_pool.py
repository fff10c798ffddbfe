"""The solver processes behind /exact: killable workers, so that a deadline really stops the work.

Each worker is a spawned process that answers one request at a time over a pipe.  A request past
its deadline (or whose client went away, which cancels the awaiting task) has its worker killed
and replaced: the next request does not queue behind abandoned work.  A worker that dies is
detected when its pipe closes and replaced the same way; ``healthy`` is False until it is back, so
``/readyz`` reflects the pool.  Workers die with the server, even after a SIGKILL of the server:
they ask Linux for a parent-death signal (``PR_SET_PDEATHSIG``) and also watch their parent's pid.
Linux sends that signal when the *thread* that started the process ends, so every worker is started
on the pool's own spawner thread, which lives as long as the pool: started from a short-lived
thread-pool thread (anyio ends its idle threads after 10 s), a healthy worker was killed with it.

A worker says ready once the solver's default path is compiled (a machine's first start compiles
it, about a minute on 2 cores) and compiles the others after that; it shares one flag per path with
the server, so that ``/readyz`` lists the paths still compiling (:meth:`SolverPool.compiling`).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection

import anyio
from starlette.concurrency import run_in_threadpool

from tdcr.physics.exact import DEFAULT_PATHS, PATHS

log = logging.getLogger("tdcr.service")

_PR_SET_PDEATHSIG = 1


class WorkerDied(RuntimeError):
    """The worker process died while solving (it has been replaced)."""


class NoFreeWorker(RuntimeError):
    """No worker became free within the deadline (all busy, or being replaced after a deadline's
    kill): the request never started, so it is not a deadline's failure but a refusal to retry."""


def _die_with_parent(parent: int) -> None:
    """SIGKILL this process when the parent dies: the kernel's parent-death signal where there is
    one (Linux), and a watchdog thread polling the parent pid everywhere."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)

    def watch():
        while os.getppid() == parent:
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, daemon=True).start()


def _serve(conn: Connection, parent: int, preload: tuple[str, ...], warm) -> None:
    """Worker loop: ``(fn, args, kwargs, expected exception types)`` in, ``(ok, result or exception)`` out.
    ``preload``: the modules of the functions it will be sent, imported before it says ready (else
    the first request unpickling its function pays the imports, a quarter second, inside its deadline).
    ``warm``: one shared flag per solver path (:data:`PATHS`), set here as each is compiled."""
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server handles Ctrl-C and stops us
    for module in preload:
        importlib.import_module(module)
    from tdcr.physics.exact import warm_up

    global _WARM
    _WARM = warm
    warm_up(DEFAULT_PATHS)  # ready once the default path answers; the others compile meanwhile
    _mark_warm(DEFAULT_PATHS)
    conn.send((True, "ready"))
    rest = tuple(p for p in PATHS if p not in DEFAULT_PATHS)
    threading.Thread(target=_warm_up_rest, args=(rest,), daemon=True, name="tdcr-warm-up").start()
    while True:
        try:
            fn, args, kwargs, expected = conn.recv()
        except EOFError:
            return
        try:
            conn.send((True, fn(*args, **kwargs)))
        except expected as exc:  # the caller's errors (e.g. invalid requests) go back as they are
            conn.send((False, exc))
        except Exception as exc:  # noqa: BLE001 - reported to the server, which answers 500-free
            conn.send((False, RuntimeError(f"{exc.__class__.__name__}: {exc}")))


#: In a solver process: one flag per solver path (:data:`PATHS`), set once the path is compiled (or
#: loaded from the cache), shared with the server (:meth:`SolverPool.compiling`); None elsewhere (no check).
_WARM = None


def _warm_paths(flags) -> set[str]:
    """The solver paths whose flag in ``flags`` (one per :data:`PATHS`) is set."""
    return {path for path, warm in zip(PATHS, flags, strict=True) if warm}


def _mark_warm(paths) -> None:
    for path in paths:
        _WARM[PATHS.index(path)] = 1


def cold_paths(paths) -> list[str]:
    """Those of ``paths`` that this solver process is still compiling (none outside the solver processes)."""
    return [] if _WARM is None else sorted(set(paths) - _warm_paths(_WARM))


def _warm_up_rest(paths: tuple[str, ...]) -> None:
    """Compile (or load) the solver's other paths, one by one, after the worker said ready.  A request
    on one of them meanwhile would wait for its compilation (numba's compiler lock) until the deadline
    killed the process, and its compilation with it: it is answered "starting" instead
    (:func:`cold_paths`)."""
    from tdcr.physics.exact import warm_up

    for path in paths:
        try:
            warm_up((path,))
        except Exception:  # noqa: BLE001 - a request on that path compiles it itself, and reports what fails
            log.exception("warming up the solver path %s failed", path)
        _mark_warm((path,))


class _Worker:
    def __init__(self, ctx, preload: tuple[str, ...]):
        self.conn, child = ctx.Pipe()
        self.warm = ctx.RawArray("b", len(PATHS))  # the paths it has compiled (set by the process)
        self.process = ctx.Process(target=_serve, args=(child, os.getpid(), preload, self.warm), daemon=True,
                                   name="tdcr-solver")
        self.process.start()
        child.close()

    def wait_ready(self, timeout: float) -> None:
        if not self.conn.poll(timeout):
            self.kill()
            raise RuntimeError("a solver process did not start in time")
        self.conn.recv()

    def kill(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=5)
        self.conn.close()


def _exchange(worker: _Worker, message, timeout: float):
    """Send ``message`` to ``worker`` and wait up to ``timeout`` s for its answer (blocking pipe I/O:
    the fd is made blocking again, since an event loop that polled it may have left it not)."""
    os.set_blocking(worker.conn.fileno(), True)
    worker.conn.send(message)
    if not worker.conn.poll(timeout):
        raise TimeoutError
    return worker.conn.recv()


class SolverPool:
    """``workers`` solver processes; :meth:`run` solves on an idle one within a deadline.  ``preload``:
    the modules whose functions :meth:`run` will send, imported by each process before it is ready."""

    def __init__(self, workers: int, *, preload: tuple[str, ...] = (), start_timeout_s: float = 300.0):
        self._ctx = multiprocessing.get_context("spawn")
        self._preload = tuple(preload)
        self._start_timeout_s = start_timeout_s
        # the one thread that starts workers: their parent-death signal is tied to it (module docstring)
        self._spawner = ThreadPoolExecutor(1, thread_name_prefix="tdcr-solver-spawner")
        self.workers = [self._spawner.submit(self._start).result() for _ in range(workers)]
        self._idle: asyncio.Queue[_Worker] | None = None
        self._tasks: set[asyncio.Task] = set()  # replacements in progress (kept referenced)
        self.down = 0  # workers that died unexpectedly and are being replaced (the pool is unhealthy)

    def _start(self) -> _Worker:
        """A ready worker (on the spawner thread only)."""
        worker = _Worker(self._ctx, self._preload)
        worker.wait_ready(self._start_timeout_s)
        return worker

    def compiling(self) -> list[str]:
        """The solver paths that a process is still compiling (a machine's first start: about two
        minutes on 2 cores; a replaced process loads them from the cache in seconds).  A request on
        one of them may be answered "starting" meanwhile (:func:`cold_paths`)."""
        warm = set(PATHS)
        for worker in self.workers:
            warm &= _warm_paths(worker.warm)
        return sorted(set(PATHS) - warm)

    @property
    def healthy(self) -> bool:
        """No worker is down.  (A worker killed at a deadline is routine and does not count.)"""
        return self.down == 0

    def _idle_queue(self) -> asyncio.Queue:
        if self._idle is None:  # created on the event loop that uses it
            self._idle = asyncio.Queue()
            for w in self.workers:
                self._idle.put_nowait(w)
        return self._idle

    async def run(self, fn, *args, timeout: float, expected: tuple[type[Exception], ...] = (), **kwargs):
        """``fn(*args, **kwargs)`` in a worker; :class:`NoFreeWorker` if none becomes free within
        ``timeout`` s, ``TimeoutError`` if the work then runs ``timeout`` s (the worker is killed and
        replaced), :class:`WorkerDied` if it died; an ``expected`` exception of ``fn`` is raised as it
        is, any other as ``RuntimeError``.  The wait for a worker and the work each have the whole
        ``timeout``: a request that got a worker late (one restarting after a deadline) would otherwise
        have its few milliseconds of work killed for time it spent waiting."""
        idle = self._idle_queue()
        try:  # an idle worker is taken at once, however short the timeout
            worker = idle.get_nowait() if idle.qsize() else await asyncio.wait_for(idle.get(), timeout)
        except TimeoutError:
            raise NoFreeWorker(f"no solver process became free within {timeout} s") from None
        healthy, died = False, False
        try:
            # the blocking pipe I/O runs in a thread; a cancelled request abandons it (the worker is
            # then killed, which ends the thread's wait)
            ok, result = await anyio.to_thread.run_sync(_exchange, worker, (fn, args, kwargs, expected), timeout,
                                                        abandon_on_cancel=True)
            healthy = True
        except TimeoutError:  # a subclass of OSError: re-raised as it is
            raise
        except (EOFError, OSError):
            died = True
            raise WorkerDied("a solver process died; it is being replaced") from None
        finally:
            if healthy:
                idle.put_nowait(worker)
            else:  # past the deadline, cancelled (client gone) or dead: kill it, start another
                self._tasks.add(task := asyncio.get_running_loop().create_task(self._replace(worker, died=died)))
                task.add_done_callback(self._tasks.discard)
        if not ok:
            raise result
        return result

    async def _replace(self, worker: _Worker, *, died: bool = False) -> None:
        """Kill ``worker`` and start another in its place, retrying until one starts.  ``died``: it
        died unexpectedly, so the pool counts as down until the replacement is up."""
        self.down += died
        try:
            await run_in_threadpool(worker.kill)
            while True:
                try:
                    fresh = await asyncio.wrap_future(self._spawner.submit(self._start))
                    break
                except (EOFError, OSError, RuntimeError) as exc:  # e.g. killed while starting
                    log.warning("a solver process failed to start (%s); retrying", exc)
                    await asyncio.sleep(1.0)
            self.workers[self.workers.index(worker)] = fresh
            self._idle_queue().put_nowait(fresh)
        finally:
            self.down -= died

    async def watch(self, interval_s: float = 0.5) -> None:
        """Replace idle workers that died (e.g. killed from outside), until cancelled."""
        while True:
            await asyncio.sleep(interval_s)
            idle = self._idle_queue()
            for _ in range(idle.qsize()):
                worker = idle.get_nowait()
                if worker.process.is_alive():
                    idle.put_nowait(worker)
                else:
                    await self._replace(worker, died=True)

    def close(self) -> None:
        for w in self.workers:
            w.kill()
        self._spawner.shutdown(wait=False)
