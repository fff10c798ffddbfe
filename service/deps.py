"""Typed FastAPI dependencies: endpoints receive the service state and data plane through these,
never by reading ``request.app.state`` themselves."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.dataplane import DataPlane
from service.state import ServiceState


def get_state(request: Request) -> ServiceState:
    return request.app.state.service


def get_dataplane(request: Request) -> DataPlane:
    return request.app.state.service.dataplane


State = Annotated[ServiceState, Depends(get_state)]
Plane = Annotated[DataPlane, Depends(get_dataplane)]
