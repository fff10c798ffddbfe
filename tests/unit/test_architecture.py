"""The three-package layout: tdcr/ is the torch-free, web-free core; training/ and service/ depend on
it and never on each other (docs/architecture.md)."""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

#: package -> the packages of this repository it must not import (tdcr/cli.py does, lazily)
FORBIDDEN = {"tdcr": {"training", "service"}, "service": {"training"}, "training": {"service"}}
LAZY_ALLOWED = {("tdcr", "cli.py")}


def _imports(path) -> list[tuple[int, str, bool]]:
    """``(line, module, at module level)`` of every absolute import in a file."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module, id(node) in top))
    return out


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_import_directions(root, package):
    files = sorted((root / package).rglob("*.py"))
    assert files, f"no files under {package}/"
    offending = []
    for f in files:
        lazy_ok = f.relative_to(root).parts in LAZY_ALLOWED
        for line, module, top_level in _imports(f):
            if module.split(".")[0] in FORBIDDEN[package] and (top_level or not lazy_ok):
                offending.append(f"{f.relative_to(root)}:{line} imports {module}")
    assert not offending, offending


def test_the_rule_catches_an_offending_import(tmp_path):
    """The checker itself: a core module importing the service is reported."""
    bad = tmp_path / "bad.py"
    bad.write_text("import numpy\nfrom service.app import create_app\n\ndef f():\n    import training.dataset\n")
    assert [(m, top) for _, m, top in _imports(bad)] == [("numpy", True), ("service.app", True),
                                                         ("training.dataset", False)]


@pytest.mark.parametrize("module, banned", [
    ("tdcr", ["torch", "fastapi", "uvicorn", "onnxruntime", "pydantic", "grpc"]),
    ("tdcr.cli", ["torch", "fastapi", "uvicorn", "onnxruntime", "grpc"]),
    ("tdcr.clients.loadtest", ["torch", "fastapi", "uvicorn", "onnxruntime", "grpc"]),
    ("tdcr.surrogates.runtime", ["torch", "fastapi", "uvicorn"]),
    ("tdcr.api.validation", ["torch", "fastapi", "uvicorn", "onnxruntime"]),
    ("service.app", ["torch", "training"]),
    ("training.dataset", ["torch", "fastapi", "service"]),
])
def test_importing_loads_nothing_heavy(root, module, banned):
    code = (f"import sys, {module}; loaded = [m for m in {banned!r} if m in sys.modules]; "
            "assert not loaded, loaded")
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


#: The transports: they decode, call the data plane and encode, and name no model.
TRANSPORTS = ("service/grpc_server.py", "service/routers/v2.py", "service/routers/predict.py",
              "service/routers/exact.py", "service/routers/inverse.py", "service/routers/json_route.py")


def test_no_transport_names_a_model(root, tiny_models):
    """No transport mentions a model by name (the solver's, the inverse model's or any operator's),
    nor the constants that hold those names."""
    import json

    from service.solver import INVERSE_MODEL
    from tdcr.api.schemas import EXACT_MODEL

    manifest = json.loads((tiny_models[1] / "manifest.json").read_text())
    names = {EXACT_MODEL, INVERSE_MODEL, *manifest["models"]}
    for path in TRANSPORTS:
        tree = ast.parse((root / path).read_text())
        for node in ast.walk(tree):  # OpenAPI tags name a resource and ``kind`` a kind of model, not a model
            if isinstance(node, ast.Call):
                node.keywords = [k for k in node.keywords if k.arg not in ("tags", "kind")]
        strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
        identifiers = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
            a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        assert not strings & names, f"{path} names {strings & names}"
        assert not identifiers & {"EXACT_MODEL", "INVERSE_MODEL", "SOLVER_MODELS"}, path


def test_the_documented_example_model_is_served_by_every_codec(root):
    """docs/architecture.md's "Adding a model" example, registered with a data plane, answers
    /predict's codec and OIP REST's, with the shapes its docstring promises."""
    import asyncio
    import re

    import numpy as np
    import orjson

    from service.codecs import PredictCodec
    from service.dataplane import DataPlane
    from service.metrics import Metrics
    from service.model import InferenceRequest, ModelRepository
    from service.oip import RestCodec
    from tdcr.api.validation import Limits
    from tdcr.robot.design_space import sample_designs
    from tdcr.surrogates.engine import prepare_json

    text = (root / "docs" / "architecture.md").read_text()
    code = re.search(r"### Adding a model.*?```python\n(.*?)```", text, re.S).group(1)
    namespace: dict = {}
    exec(code.replace("repository.register(StraightRod())", ""), namespace)  # noqa: S102 - our own docs
    plane = DataPlane(ModelRepository(), Metrics.create())
    plane.repository.register(namespace["StraightRod"]())
    designs = sample_designs(3, seed=0)
    request = prepare_json({"model": "straight", "designs": designs.to_dicts()}, limits=Limits())
    answer = asyncio.run(plane.infer("straight", InferenceRequest(request, PredictCodec()), kind="surrogate",
                                     protocol="http", endpoint="/predict"))
    body = orjson.loads(answer.body)
    assert answer.count == 3 and body["model"] == "straight"
    np.testing.assert_allclose(np.array(body["results"][1]["backbone"])[-1], [0, 0, designs.L[1]], rtol=1e-6)
    tensors = orjson.dumps({"inputs": [{"name": "design", "shape": [3, 15], "datatype": "FP64",
                                        "data": designs.features().reshape(-1).tolist()}],
                            "outputs": [{"name": "backbone"}]})
    answer = asyncio.run(plane.infer("straight", InferenceRequest(tensors, RestCodec()), protocol="http",
                                     endpoint="/v2/models/{model}/infer"))
    out = orjson.loads(answer.body[0])["outputs"][0]
    assert out["shape"] == [3, 42, 3]
    assert np.asarray(out["data"]).reshape(3, 42, 3)[2, -1, 2] == pytest.approx(designs.L[2], rel=1e-6)


def test_every_transport_maps_every_error_kind():
    """The data plane's error kinds, each mapped once per transport: REST JSON, OIP REST, gRPC."""
    from service.errors import STATUS
    from service.grpc_server import STATUS_CODES
    from service.model import ERROR_KINDS
    from service.oip import HTTP_STATUS

    for mapping in (STATUS, HTTP_STATUS, STATUS_CODES):
        assert set(mapping) == set(ERROR_KINDS)
