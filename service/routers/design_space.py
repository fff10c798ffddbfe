"""GET /design-space: Table I, the admissible bounds and the feature order (for clients and the viewer)."""

from __future__ import annotations

from fastapi import APIRouter

from tdcr import design_space

router = APIRouter(tags=["design space"])


@router.get("/design-space", summary="Table I ranges, admissible bounds (SI units) and the feature order")
async def describe() -> dict:
    return design_space.describe()
