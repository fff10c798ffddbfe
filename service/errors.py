"""Errors with a status code and a clear message; JSON bodies follow ``tdcr.api.schemas.ErrorResponse``."""

from __future__ import annotations

from collections.abc import Collection

from service.model import InferenceError
from tdcr.api.validation import InvalidRequest


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


#: The data plane's error kinds -> the HTTP statuses of the service's own API (OIP REST: service.oip.HTTP_STATUS).
STATUS = {"invalid": 422, "too_large": 413, "not_found": 404, "saturated": 503, "unavailable": 503, "deadline": 504}
#: Metric labels of the kinds whose label differs.
LABELS = {"invalid": "validation"}


def from_inference(exc: InferenceError, *, query: Collection[str] = ()) -> ApiError:
    """The HTTP error of a data-plane error: 422 / 413 naming every field (as :func:`from_invalid`),
    404, 503 (with ``Retry-After`` when saturated or starting: the error's ``retry_after``) or 504."""
    if exc.problems:
        return from_invalid(InvalidRequest(exc.problems, too_large=exc.kind == "too_large"), query=query)
    return ApiError(STATUS[exc.kind], exc.message, kind=LABELS.get(exc.kind, exc.kind), headers=retry_headers(exc))


def retry_headers(exc: InferenceError) -> dict[str, str] | None:
    """The HTTP headers of a data-plane error that waiting may cure: ``Retry-After`` (every HTTP API)."""
    return None if exc.retry_after is None else {"retry-after": str(exc.retry_after)}
