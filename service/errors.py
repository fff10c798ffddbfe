"""Errors with a status code and a clear message; JSON bodies follow ``tdcr.schemas.ErrorResponse``."""

from __future__ import annotations

from collections.abc import Collection

from tdcr.validation import InvalidRequest


class ApiError(Exception):
    """An error answered with ``status`` and ``{"message": ..., "detail": ...}``.

    ``kind`` labels the ``tdcr_errors_total`` metric (a fixed vocabulary, never user input).
    """

    def __init__(self, status: int, message: str, detail=None, kind: str = "client"):
        super().__init__(message)
        self.status = status
        self.message = message
        self.detail = detail if detail is not None else message
        self.kind = kind


def from_invalid(exc: InvalidRequest, *, query: Collection[str] = ()) -> ApiError:
    """422 (or 413 for sizes) naming every field; ``detail[].loc`` starts with where the field
    came from, ``body`` or ``query`` (the names in ``query``), as FastAPI's own errors do."""
    items = [{"loc": ["query" if p.loc and p.loc[0] in query else "body", *p.loc], "msg": p.msg, "type": p.type}
             for p in exc.problems]
    return ApiError(413 if exc.too_large else 422, exc.message, items,
                    kind="too_large" if exc.too_large else "validation")
