"""Export trained operators to ONNX and record them in ``models/manifest.json``.

Graph inputs / outputs (float32, SI units):

* DeepONet models: ``design`` (B, 15) and ``s`` (n,) fractions of L  ->  outputs at those s.
* FNO models: ``design`` (B, 15)  ->  outputs on their fixed grid s_j = j / 41 (42 points).
* Tendon models output ``tendons`` (B, n, 4, 3) m; pose models ``backbone`` (B, n, 3) m,
  ``rotation`` (B, n, 3, 3) and ``tendons`` (B, n, 4, 3) m.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from training import design_space
from training.operators.models import DeepONet, count_parameters
from training.operators.train import load_trained

OPSET = 17


class _FixedGrid(torch.nn.Module):
    """FNO wrapper whose only input is the design."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, design):
        return self.model(design)


def io_names(model) -> tuple[list[str], list[str]]:
    inputs = ["design", "s"] if isinstance(model, DeepONet) else ["design"]
    outputs = ["tendons"] if model.kind == "tendons" else ["backbone", "rotation", "tendons"]
    return inputs, outputs


def export_onnx(model, path: str | Path) -> None:
    """Write ``model`` to ``path`` (opset 17, dynamic batch; dynamic n for DeepONet)."""
    inputs, outputs = io_names(model)
    design = torch.as_tensor(design_space.sample_designs(2, seed=0).features(), dtype=torch.float32)
    dyn = {"design": {0: "batch"}}
    args: tuple
    if isinstance(model, DeepONet):
        args = (design, torch.linspace(0.0, 1.0, 42))
        dyn["s"] = {0: "points"}
        point_axis = "points"
        module = model
    else:
        args = (design,)
        point_axis = None
        module = _FixedGrid(model)
    for name in outputs:
        dyn[name] = {0: "batch"} | ({1: point_axis} if point_axis else {})
    tmp = Path(str(path) + ".tmp")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), args, str(tmp), input_names=inputs, output_names=outputs,
                          dynamic_axes=dyn, opset_version=OPSET, dynamo=False)
    os.replace(tmp, path)


def sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def manifest_entry(model, record: dict, onnx_path: Path, *, metrics: dict | None, dataset_meta: dict | None) -> dict:
    inputs, outputs = io_names(model)
    n = "n" if isinstance(model, DeepONet) else model.config.n_points
    shapes = {"design": ["B", 3 + 3 * design_space.N_TENDONS], "s": ["n"],
              "tendons": ["B", n, design_space.N_TENDONS, 3], "backbone": ["B", n, 3], "rotation": ["B", n, 3, 3]}
    return {
        "name": record["name"],
        "file": onnx_path.name,
        "sha256": sha256(onnx_path),
        "architecture": type(model).__name__,
        "kind": model.kind,
        "hyperparameters": record["hyperparameters"],
        "parameters": count_parameters(model),
        "training": {**record["config"], **record["summary"]},
        "dataset": dataset_meta,
        "inputs": {k: shapes[k] for k in inputs},
        "outputs": {k: shapes[k] for k in outputs},
        "units": {"design": "SI [E Pa, r m, L m, offsets m, pitches rad/m, tensions N]", "s": "fraction of L",
                  "tendons": "m", "backbone": "m", "rotation": "1"},
        "feature_names": design_space.feature_names(),
        "grid": None if isinstance(model, DeepONet) else np.linspace(0, 1, model.config.n_points).tolist(),
        "ranges": {k: [v.low, v.high] for k, v in design_space.TABLE_I.items()},
        "metrics": metrics,
        "opset": OPSET,
    }


def export_run(run_dir: str | Path, models_dir: str | Path, *, dataset_meta: dict | None = None) -> dict:
    """Export ``run_dir``/model.pt to ``models_dir``/<name>.onnx and update the manifest entry."""
    model, record = load_trained(Path(run_dir) / "model.pt")
    models_dir = Path(models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    path = models_dir / f"{record['name']}.onnx"
    export_onnx(model, path)
    entry = manifest_entry(model, record, path, metrics=None, dataset_meta=dataset_meta)
    update_manifest(models_dir, entry)
    return entry


def update_manifest(models_dir: Path, entry: dict) -> None:
    path = models_dir / "manifest.json"
    manifest = json.loads(path.read_text()) if path.exists() else {"format_version": 1, "models": {}}
    old = manifest["models"].get(entry["name"], {})
    if entry.get("metrics") is None and old.get("sha256") == entry["sha256"]:
        entry["metrics"] = old.get("metrics")
    manifest["models"][entry["name"]] = entry
    tmp = path.with_name("manifest.json.tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True))
    os.replace(tmp, path)
