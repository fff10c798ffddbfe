"""A small client for planners (httpx): sync :class:`Client` and async :class:`AsyncClient`.

    with Client("http://localhost:8000") as c:
        shapes = c.predict(features, points=42)          # (B, 15) SI designs -> dict of arrays
        shapes["tendons"]                                 # (B, n, 4, 3) m

``predict`` sends ``.npy`` and receives ``.npz`` (binary), the fast path for large batches;
``predict_json`` and ``exact`` send the JSON request format.  For one design ``predict_json``
answers sooner: reading the ``.npz``'s ten arrays costs the client about 0.8 ms on a 2-core VM
(docs/results.md, "The service's own latency, and the client's").

A 503 that waiting cures (the solver saturated, the service or a solver path still starting) carries
``Retry-After``; with ``retry_for`` (seconds, keyword) a client waits as told and sends the request
again until that much time has passed, then raises the last answer's :class:`TDCRError`.
"""

from __future__ import annotations

import asyncio
import io
import time

import httpx
import numpy as np

from tdcr.robot.design_space import DEFAULT_POINTS

NPY, NPZ = "application/x-npy", "application/x-npz"
#: The Open Inference Protocol's header giving the length of the JSON part of a binary-tensor body.
INFERENCE_HEADER_LENGTH = "inference-header-content-length"


class TDCRError(RuntimeError):
    """A 4xx / 5xx answer; ``status``, the server's ``message`` and its ``Retry-After`` in seconds
    (``retry_after``; None: waiting will not cure it)."""

    def __init__(self, status: int, message: str, *, retry_after: float | None = None):
        super().__init__(f"HTTP {status}: {message}")
        self.status, self.message, self.retry_after = status, message, retry_after


def predict_request(features: np.ndarray, *, model: str | None = None, points: int | None = None, s=None,
                    arclength=None, outputs=None, loads=None, tolerance: float | None = None) -> dict:
    """The ``/predict`` call that :meth:`Client.predict` sends (httpx's ``content``, ``params`` and
    ``headers``: ``.npy`` in, ``.npz`` asked for), for a tool that sends it its own way; after the
    one validation path's checks (nothing is sent for a bad one; the same words as the service's
    422: :class:`tdcr.api.checks.InvalidRequest`, a ``ValueError``).  With ``loads``
    (:class:`tdcr.ExternalLoads`) the body is ``(B, 25)``: each design followed by its loads matrix
    row."""
    from tdcr.api.checks import (
        check_fractions,
        check_loads,
        check_surrogate_features,
        check_tolerance,
        checkable_loads,
        raise_problems,
    )

    problems = check_surrogate_features(features) + check_tolerance(tolerance)
    if s is not None:
        problems += check_fractions(s)[1]
    body = np.asarray(features, dtype=np.float64)
    if loads is not None and not problems:
        problems += check_loads(checkable_loads(loads, len(body)), np.arange(len(body)))
        body = np.concatenate([body, np.nan_to_num(loads.matrix(len(body)))], axis=1)
    raise_problems(problems)
    params = _params(model, points, s, arclength, outputs) + ([] if tolerance is None else [("tolerance",
                                                                                                repr(tolerance))])
    return {"content": _npy(body), "params": params, "headers": {"content-type": NPY, "accept": NPZ}}


def _npy(features: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(features, dtype=np.float64), allow_pickle=False)
    return buf.getvalue()


def _params(model: str | None, points: int | None, s, arclength, outputs=None) -> list[tuple[str, str]]:
    params = [] if model is None else [("model", model)]
    if outputs is not None:
        params.append(("outputs", ",".join(outputs)))
    if s is not None:
        params += [("s", repr(float(v))) for v in s]
    elif arclength is not None:
        params += [("arclength", repr(float(v))) for v in arclength]
    elif points is not None:
        params.append(("points", str(points)))
    return params


def _retry_after(response: httpx.Response) -> float | None:
    """A 503's ``Retry-After`` in seconds (None: none, or not a number of seconds)."""
    if response.status_code != 503:
        return None
    try:
        return max(0.0, float(response.headers["retry-after"]))
    except (KeyError, ValueError):
        return None


def _wait(response: httpx.Response, started: float, retry_for: float) -> float | None:
    """How long to wait before sending again (None: answer with ``response``): its ``Retry-After``
    while that still ends within ``retry_for`` s of ``started`` (``time.monotonic``)."""
    delay = _retry_after(response)
    if delay is None or time.monotonic() + delay > started + retry_for:
        return None
    return delay


def _decode(response: httpx.Response) -> dict:
    if response.status_code >= 400:
        try:
            message = response.json().get("message", response.text)
        except ValueError:
            message = response.text
        raise TDCRError(response.status_code, message, retry_after=_retry_after(response))
    if response.headers.get("content-type", "").startswith(NPZ):
        with np.load(io.BytesIO(response.content)) as z:
            out = {k: z[k] for k in z.files}
        out["model"] = response.headers.get("x-tdcr-model")
        return out
    return response.json()


#: A request's default timeout, s: above twice the service's default /exact deadline (30 s to wait for
#: a free solver process, then 30 s for the work).
TIMEOUT_S = 90.0


class Client:
    """``timeout``: each request's, s; ``retry_for``: how long a request may wait on 503s with
    ``Retry-After`` in all, s (0: raise at the first); the rest goes to ``httpx.Client``."""

    def __init__(self, base_url: str, *, timeout: float = TIMEOUT_S, retry_for: float = 0.0, **kwargs):
        self._http = httpx.Client(base_url=base_url, timeout=timeout, **kwargs)
        self.retry_for = retry_for

    def _send(self, method: str, url: str, **kwargs) -> dict:
        started = time.monotonic()
        while True:
            response = self._http.request(method, url, **kwargs)
            delay = _wait(response, started, self.retry_for)
            if delay is None:
                return _decode(response)
            time.sleep(delay)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        self._http.close()

    def predict(self, features: np.ndarray, *, loads=None, model: str | None = None,
                points: int | None = DEFAULT_POINTS, s=None, arclength=None, outputs=None,
                tolerance: float | None = None) -> dict:
        """Binary request: SI designs ``(B, 15)`` -> arrays ``s`` ``(B, n)`` (fractions of L),
        ``arclength`` ``(B, n)`` m, backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)``, tendons
        ``(B, n, 4, 3)`` m, in_distribution, finite, error_bound (the calibrated 99 % bound of
        each answer's relative l2 error, inf: none) and source (0: surrogate, 1: exact) ``(B,)``.
        ``tolerance``: the designs whose bound exceeds it are answered by the exact solver.

        The arclengths: ``points`` equispaced on [0, L], or ``s`` (fractions of L), or ``arclength``
        (m, for designs of one length).  ``outputs``: e.g. ``["tendons"]`` to receive (and compute)
        only those arrays.  ``loads``: gravity and tip wrench per design (:class:`tdcr.ExternalLoads`,
        base frame), for a loaded operator (the default one when ``model`` is None).  Bad designs
        raise ``ValueError`` before anything is sent.
        """
        call = predict_request(features, model=model, points=points, s=s, arclength=arclength, outputs=outputs,
                               loads=loads, tolerance=tolerance)
        return self._send("POST", "/predict", **call)

    def predict_json(self, request: dict) -> dict:
        return self._send("POST", "/predict", json=request)

    def exact(self, request: dict) -> dict:
        return self._send("POST", "/exact", json=request)

    def models(self) -> dict:
        return self._send("GET", "/models")


class AsyncClient:
    """As :class:`Client`, on ``httpx.AsyncClient``."""

    def __init__(self, base_url: str, *, timeout: float = TIMEOUT_S, retry_for: float = 0.0, **kwargs):
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout, **kwargs)
        self.retry_for = retry_for

    async def _send(self, method: str, url: str, **kwargs) -> dict:
        started = time.monotonic()
        while True:
            response = await self._http.request(method, url, **kwargs)
            delay = _wait(response, started, self.retry_for)
            if delay is None:
                return _decode(response)
            await asyncio.sleep(delay)

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def predict(self, features: np.ndarray, *, loads=None, model: str | None = None,
                      points: int | None = DEFAULT_POINTS, s=None, arclength=None, outputs=None,
                      tolerance: float | None = None) -> dict:
        """As :meth:`Client.predict`."""
        call = predict_request(features, model=model, points=points, s=s, arclength=arclength, outputs=outputs,
                               loads=loads, tolerance=tolerance)
        return await self._send("POST", "/predict", **call)

    async def predict_json(self, request: dict) -> dict:
        return await self._send("POST", "/predict", json=request)

    async def exact(self, request: dict) -> dict:
        return await self._send("POST", "/exact", json=request)
