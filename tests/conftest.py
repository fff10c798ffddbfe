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


TINY = {
    "deeponet": {"branch_width": 16, "trunk_width": 16, "p": 8},
    "deeponet_pose": {"branch_width": 16, "trunk_width": 16, "p": 8},
    "fno": {"width": 16},
    "fno_pose": {"width": 16},
}


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """A 150-design solver dataset on disk."""
    from training import dataset

    out = tmp_path_factory.mktemp("data") / "tiny"
    dataset.generate(out, dataset.GenerateConfig(n=150, seed=2, shard_size=50), workers=1, progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_models(tiny_data, tmp_path_factory):
    """All four operators, tiny, trained for 2 epochs and exported: ``(runs dir, models dir)``."""
    pytest.importorskip("torch")
    from training.operators.export import export_run
    from training.operators.models import REGISTRY
    from training.operators.train import make_config, train

    root = tmp_path_factory.mktemp("runs")
    models = root / "models"
    for name in REGISTRY:
        cfg = make_config(name, "tuned", epochs=2, batch_size=40, hyperparameters=TINY[name])
        train(cfg, tiny_data, root / name, progress=False, monitor_designs=20)
        export_run(root / name, models)
    return root, models
