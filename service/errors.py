"""Errors with a status code and a clear message; JSON bodies follow ``schemas.ErrorResponse``."""

from __future__ import annotations

from pydantic import ValidationError

from training.schemas import format_error_location


class ApiError(Exception):
    """An error answered with ``status`` and ``{"message": ..., "detail": ...}``."""

    def __init__(self, status: int, message: str, detail=None, kind: str = "client"):
        super().__init__(message)
        self.status = status
        self.message = message
        self.detail = detail if detail is not None else message
        self.kind = kind


def unprocessable(items: list[dict]) -> ApiError:
    """422 from items ``{"loc": [...], "msg": ..., "type": ...}``; the message names every field."""
    lines = [f"{format_error_location(tuple(i['loc'])) or 'body'}: {i['msg']}" for i in items]
    return ApiError(422, "; ".join(lines), [{"loc": list(i["loc"]), "msg": i["msg"], "type": i["type"]} for i in items],
                    kind="validation")


def from_validation_error(exc: ValidationError, prefix: tuple = ("body",)) -> ApiError:
    items = [{"loc": [*prefix, *e["loc"]], "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
    return unprocessable(items)
