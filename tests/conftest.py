"""Shared fixtures: the independent C++ reference solutions and small design batches."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from training.designs import DesignBatch

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = Path(os.environ.get("TDCR_SHARED", ROOT.parent / "shared")) / "reference" / "cosserat_cases.json"


def designs_from_json(designs: list[dict]) -> DesignBatch:
    def col(key):
        return [[t[key] for t in d["tendons"]] for d in designs]

    return DesignBatch(
        E=[d["E"] for d in designs], r=[d["r"] for d in designs], L=[d["L"] for d in designs],
        offset=col("offset"), pitch=col("pitch"), tension=col("tension"),
    )


@pytest.fixture(scope="session")
def reference_cases() -> list[dict]:
    if not REFERENCE.exists():
        pytest.fail(f"reference solutions not found at {REFERENCE} (set TDCR_SHARED)")
    return json.loads(REFERENCE.read_text())["cases"]


def relative_l2(pred: np.ndarray, truth: np.ndarray) -> float:
    """Relative l2 error ||pred - truth|| / ||truth|| over all entries (paper eq. l2Error)."""
    return float(np.linalg.norm(pred - truth) / np.linalg.norm(truth))
