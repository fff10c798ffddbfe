"""Typed FastAPI dependencies: endpoints receive the service state (and through it the one data
plane) through these, never by reading ``request.app.state`` themselves."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.state import ServiceState


async def get_state(request: Request) -> ServiceState:
    """Async, so FastAPI calls it on the event loop: a sync dependency is handed to a worker thread
    on every request (a round trip that cost about as much as ``GET /healthz`` itself)."""
    return request.app.state.service


State = Annotated[ServiceState, Depends(get_state)]
