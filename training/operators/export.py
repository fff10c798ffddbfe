"""Export trained operators to ONNX and record them in ``models/manifest.json``.

Graph inputs / outputs (float32, SI units):

* DeepONet models: ``design`` (B, 15) and ``s`` (n,) fractions of L  ->  outputs at those s.
* FNO models: ``design`` (B, 15)  ->  outputs on their fixed grid s_j = j / 41 (42 points).
* Loaded operators also take ``loads`` (B, 10): gravity (3, m/s^2), density (kg/m^3), tip force
  (3, N), tip moment (3, N m), base frame (:data:`tdcr.robot.designs.LOAD_COLUMNS`).
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
import onnx
import torch

from tdcr import design_space
from tdcr.robot.designs import N_LOAD_COLUMNS
from tdcr.surrogates.runtime import MANIFEST_FORMAT_VERSION, MANIFEST_NAME
from training.operators.models import DeepONet, count_parameters
from training.operators.train import load_trained

OPSET = 17


class _FixedGrid(torch.nn.Module):
    """Wrapper whose only input is the design: an FNO, or a DeepONet on its reference grid.
    ``channels_last``: an FNO computed in its (B, n, W) layout (:meth:`FNO.raw`), faster for a few
    designs than the batch-last one."""

    def __init__(self, model, channels_last: bool = False):
        super().__init__()
        self.model = model
        self.channels_last = channels_last

    def forward(self, design, loads=None):
        if isinstance(self.model, DeepONet):
            return self.model.outputs(design, self.model.reference_grid, loads=loads)
        if self.channels_last:
            return self.model.heads(design, self.model.grid, self.model.raw(design, loads=loads), loads=loads)
        return self.model(design, loads)


class _WithLoads(torch.nn.Module):
    """A loaded DeepONet with its graph inputs in the order ``design``, ``s``, ``loads``."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, design, s, loads):
        return self.model(design, s, loads)


def io_names(model) -> tuple[list[str], list[str]]:
    inputs = ["design", "s"] if isinstance(model, DeepONet) else ["design"]
    if model.config.loads:
        inputs.append("loads")
    outputs = ["tendons"] if model.kind == "tendons" else ["backbone", "rotation", "tendons"]
    return inputs, outputs


def _trace(module, args, path: Path, inputs: list[str], outputs: list[str], dyn: dict) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), args, str(path), input_names=inputs, output_names=outputs,
                          dynamic_axes=dyn, opset_version=OPSET, dynamo=False)


def export_onnx(model, path: str | Path) -> None:
    """Write ``model`` to ``path`` (opset 17, dynamic batch; dynamic n for DeepONet).

    Graphs of the linearised-reference models hold two branches under an ONNX ``If``:

    * DeepONet: when ``s`` is the reference grid (the default 42 points), the reference robot on
      that grid; otherwise the grid plus one partial Magnus step to each requested s
      (:func:`training.operators.kinematics.partial_step`), which costs about as much again.
    * FNO: below :data:`FNO_SMALL_BATCH` designs the network in its channels-last layout (fewer,
      larger MatMuls for a few designs), otherwise batch last (one GEMM per channel map).
    """
    inputs, outputs = io_names(model)
    design = torch.as_tensor(design_space.sample_designs(2, seed=0).features(), dtype=torch.float32)
    path = Path(path)
    tmp = Path(str(path) + ".tmp")
    fixed = {"design": {0: "batch"}} | {name: {0: "batch"} for name in outputs}
    if model.config.loads:  # a loaded operator: the loads ride along with the design
        sample = design_space.TRAINING_LOADS.sample(2, seed=0).matrix(2)
        loads = (torch.as_tensor(sample, dtype=torch.float32),)
        fixed |= {"loads": {0: "batch"}}
        with_s = _WithLoads(model)
    else:
        loads, with_s = (), model
    first, second = Path(str(path) + ".1.tmp"), Path(str(path) + ".2.tmp")
    try:
        if model.config.reference != "linearized":  # the paper preset: one graph
            if isinstance(model, DeepONet):
                _trace(model, (design, torch.linspace(0.0, 1.0, design_space.DEFAULT_POINTS)), tmp, inputs, outputs,
                       {"design": {0: "batch"}, "s": {0: "points"}} | {k: {0: "batch", 1: "points"} for k in outputs})
            else:
                _trace(_FixedGrid(model), (design,), tmp, inputs, outputs, fixed)
        elif isinstance(model, DeepONet):
            dyn = {"design": {0: "batch"}, "s": {0: "points"}} | {k: {0: "batch", 1: "points"} for k in outputs}
            dyn |= {"loads": {0: "batch"}} if loads else {}
            grid_inputs = [n for n in inputs if n != "s"]
            _trace(_FixedGrid(model), (design, *loads), first, grid_inputs, outputs, fixed)
            _trace(with_s, (design, torch.linspace(0.0, 1.0, design_space.DEFAULT_POINTS), *loads), second, inputs,
                   outputs, dyn)
            cond = _grid_condition(model.reference_grid.shape[0])
            onnx.save(_switch(onnx.load(str(first)), onnx.load(str(second)), cond, inputs), str(tmp))
        else:
            _trace(_FixedGrid(model, channels_last=True), (design, *loads), first, inputs, outputs, fixed)
            _trace(_FixedGrid(model), (design, *loads), second, inputs, outputs, fixed)
            cond = _small_batch_condition(FNO_SMALL_BATCH)
            onnx.save(_switch(onnx.load(str(first)), onnx.load(str(second)), cond, inputs), str(tmp))
    finally:
        first.unlink(missing_ok=True)
        second.unlink(missing_ok=True)
    os.replace(tmp, path)


#: ``s`` within this of the reference grid (fractions of L) takes the grid branch
GRID_TOLERANCE = 1e-6
#: FNO graphs run batches smaller than this in the channels-last layout (measured crossover)
FNO_SMALL_BATCH = 16


def _const(name: str, value, dtype):
    from onnx import helper

    dims = [len(value)] if isinstance(value, list) else []
    return helper.make_node("Constant", [], [name], value=helper.make_tensor(name, dtype, dims, value))


def _grid_condition(points: int) -> list:
    """Nodes computing ``switch/cond``: ``s`` has ``points`` values, each within
    :data:`GRID_TOLERANCE` of j / (points - 1)."""
    from onnx import TensorProto, helper

    return [
        _const("switch/points", [points], TensorProto.INT64),
        _const("switch/zero", 0, TensorProto.INT64),
        _const("switch/one", 1, TensorProto.INT64),
        _const("switch/intervals", float(points - 1), TensorProto.FLOAT),
        _const("switch/tolerance", GRID_TOLERANCE, TensorProto.FLOAT),
        _const("switch/pad", [0.0], TensorProto.FLOAT),
        helper.make_node("Shape", ["s"], ["switch/n"]),
        helper.make_node("Equal", ["switch/n", "switch/points"], ["switch/n_ok_1"]),
        helper.make_node("Squeeze", ["switch/n_ok_1"], ["switch/n_ok"]),
        helper.make_node("Squeeze", ["switch/n"], ["switch/n_scalar"]),
        helper.make_node("Range", ["switch/zero", "switch/n_scalar", "switch/one"], ["switch/j"]),
        helper.make_node("Cast", ["switch/j"], ["switch/j_float"], to=TensorProto.FLOAT),
        helper.make_node("Div", ["switch/j_float", "switch/intervals"], ["switch/grid"]),
        helper.make_node("Sub", ["s", "switch/grid"], ["switch/diff"]),
        helper.make_node("Abs", ["switch/diff"], ["switch/abs"]),
        helper.make_node("Concat", ["switch/abs", "switch/pad"], ["switch/abs_padded"], axis=0),
        helper.make_node("ReduceMax", ["switch/abs_padded"], ["switch/max"], keepdims=0),
        helper.make_node("Less", ["switch/max", "switch/tolerance"], ["switch/values_ok"]),
        helper.make_node("And", ["switch/n_ok", "switch/values_ok"], ["switch/cond"]),
    ]


def _small_batch_condition(limit: int) -> list:
    """Nodes computing ``switch/cond``: fewer than ``limit`` designs."""
    from onnx import TensorProto, helper

    return [
        _const("switch/limit", [limit], TensorProto.INT64),
        _const("switch/start", [0], TensorProto.INT64),
        _const("switch/stop", [1], TensorProto.INT64),
        helper.make_node("Shape", ["design"], ["switch/shape"]),
        helper.make_node("Slice", ["switch/shape", "switch/start", "switch/stop"], ["switch/batch"]),
        helper.make_node("Less", ["switch/batch", "switch/limit"], ["switch/cond_1"]),
        helper.make_node("Squeeze", ["switch/cond_1"], ["switch/cond"]),
    ]


def _switch(then_model, else_model, condition: list, inputs: list[str]):
    """One model ``If(switch/cond, then_model, else_model)`` from two traced graphs with the same
    outputs and inputs among ``inputs``; ``condition``: the nodes computing ``switch/cond``.

    Each branch keeps its own initializers (its names prefixed): weights referenced from the outer
    scope become implicit inputs of the ``If``, which onnxruntime binds on every run (about
    0.2 ms per call for a hundred of them, measured); the duplicated weights about double the
    file (a DeepONet: 1.3 -> 2.6 MB)."""
    from onnx import helper

    def copied(items, cls) -> list:
        out = []
        for item in items:
            out.append(cls())
            out[-1].CopyFrom(item)
        return out

    def branch(graph, prefix: str):
        def name(x: str) -> str:
            return x if x == "" or x in inputs else prefix + x
        nodes = copied(graph.node, onnx.NodeProto)
        for node in nodes:
            node.name = prefix + node.name
            node.input[:] = [name(x) for x in node.input]
            node.output[:] = [name(x) for x in node.output]
        inits, outs = copied(graph.initializer, onnx.TensorProto), copied(graph.output, onnx.ValueInfoProto)
        for item in inits + outs:
            item.name = name(item.name)
        return helper.make_graph(nodes, prefix.rstrip("/"), [], outs, initializer=inits)

    main = else_model.graph
    nodes = condition + [helper.make_node("If", ["switch/cond"], [o.name for o in main.output],
                                          then_branch=branch(then_model.graph, "then/"),
                                          else_branch=branch(main, "else/"))]
    graph = helper.make_graph(nodes, main.name or "tdcr", list(main.input), list(main.output))
    merged = helper.make_model(graph, opset_imports=list(else_model.opset_import), producer_name="tdcr-surrogates")
    merged.ir_version = else_model.ir_version
    onnx.checker.check_model(merged)
    return merged


def sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def manifest_entry(model, record: dict, onnx_path: Path, *, metrics: dict | None, dataset_meta: dict | None) -> dict:
    inputs, outputs = io_names(model)
    n = "n" if isinstance(model, DeepONet) else model.config.n_points
    shapes = {"design": ["B", design_space.N_FEATURES], "s": ["n"], "loads": ["B", N_LOAD_COLUMNS],
              "tendons": ["B", n, design_space.N_TENDONS, 3], "backbone": ["B", n, 3], "rotation": ["B", n, 3, 3]}
    return {
        "format_version": MANIFEST_FORMAT_VERSION,
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
                  "tendons": "m", "backbone": "m", "rotation": "1"} | (
                      {"loads": "SI, base frame [gravity (3) m/s^2, density kg/m^3, tip force (3) N, "
                                "tip moment (3) N m]"} if model.config.loads else {}),
        "feature_names": design_space.feature_names(),
        "grid": None if isinstance(model, DeepONet) else np.linspace(0, 1, model.config.n_points).tolist(),
        "ranges": {k: [v.low, v.high] for k, v in design_space.TABLE_I.items()},
        "metrics": metrics,
        "opset": OPSET,
    } | ({"load_ranges": _load_ranges(dataset_meta)} if model.config.loads else {})


def _load_ranges(dataset_meta: dict | None) -> dict[str, list[float]]:
    """The loads of a loaded operator's training data (``dataset_meta["loads"]``, a
    :class:`~tdcr.robot.design_space.LoadSpace`; :data:`~tdcr.robot.design_space.TRAINING_LOADS` if unrecorded)."""
    recorded = (dataset_meta or {}).get("loads")
    space = design_space.LoadSpace.from_record(recorded) if recorded else design_space.TRAINING_LOADS
    return space.ranges()


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
    path = models_dir / MANIFEST_NAME
    empty = {"format_version": MANIFEST_FORMAT_VERSION, "models": {}}
    manifest = json.loads(path.read_text()) if path.exists() else empty
    old = manifest["models"].get(entry["name"], {})
    if old.get("sha256") == entry["sha256"]:  # the same graph: its metrics and calibration still hold
        for key in ("metrics", "calibration"):
            if entry.get(key) is None and old.get(key) is not None:
                entry[key] = old[key]
    manifest["models"][entry["name"]] = entry
    tmp = path.with_name("manifest.json.tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True))
    os.replace(tmp, path)
