"""Errors with a status code and a clear message; JSON bodies follow ``tdcr.schemas.ErrorResponse``."""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterator
from contextlib import contextmanager

from service.solver_pool import WorkerDied
from tdcr.exact import TooMuchWork
from tdcr.validation import InvalidRequest

log = logging.getLogger("tdcr.service")


class ApiError(Exception):
    """An error answered with ``status`` and ``{"message": ..., "detail": ...}``.

    ``kind`` labels the ``tdcr_errors_total`` metric (a fixed vocabulary, never user input).
    """

    def __init__(self, status: int, message: str, detail=None, kind: str = "client",
                 headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status = status
        self.message = message
        self.detail = detail if detail is not None else message
        self.kind = kind
        self.headers = headers or {}


def from_invalid(exc: InvalidRequest, *, query: Collection[str] = ()) -> ApiError:
    """422 (or 413 for sizes) naming every field; ``detail[].loc`` starts with where the field
    came from, ``body`` or ``query`` (the names in ``query``), as FastAPI's own errors do."""
    items = [{"loc": ["query" if p.loc and p.loc[0] in query else "body", *p.loc], "msg": p.msg, "type": p.type}
             for p in exc.problems]
    return ApiError(413 if exc.too_large else 422, exc.message, items,
                    kind="too_large" if exc.too_large else "validation")


#: Media types of JSON bodies.
JSON_TYPES = ("application/json",)


def require_json(content_type: str) -> None:
    """415 unless the body is declared JSON (``application/json`` or ``application/*+json``): a
    browser sends ``text/plain`` cross-site without a preflight, so nothing else is parsed as JSON."""
    media = content_type.split(";")[0].strip().lower()
    if media not in JSON_TYPES and not (media.startswith("application/") and media.endswith("+json")):
        raise ApiError(415, f"Content-Type must be application/json, got {media[:40] or 'none'!r}",
                       kind="media_type")


@contextmanager
def solver_errors(timeout_s: float) -> Iterator[None]:
    """A solver process's failures as HTTP errors: more work than admitted 413, past the deadline
    ``timeout_s`` 504 (the worker was killed: its work stops with the deadline), a dead or failing
    worker 503."""
    try:
        yield
    except TooMuchWork as exc:
        raise ApiError(413, str(exc), kind="too_much_work") from None
    except TimeoutError:
        raise ApiError(504, f"the solver did not finish within {timeout_s} s", kind="deadline") from None
    except WorkerDied as exc:
        raise ApiError(503, str(exc), kind="unavailable") from None
    except RuntimeError as exc:
        log.error("solver failed: %s", exc)
        raise ApiError(503, "the solver failed on this request", kind="solver") from None
