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
    ("tdcr.loadtest", ["torch", "fastapi", "uvicorn", "onnxruntime", "grpc"]),
    ("tdcr.runtime", ["torch", "fastapi", "uvicorn"]),
    ("tdcr.validation", ["torch", "fastapi", "uvicorn", "onnxruntime"]),
    ("service.app", ["torch", "training"]),
    ("training.dataset", ["torch", "fastapi", "service"]),
])
def test_importing_loads_nothing_heavy(root, module, banned):
    code = (f"import sys, {module}; loaded = [m for m in {banned!r} if m in sys.modules]; "
            "assert not loaded, loaded")
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
