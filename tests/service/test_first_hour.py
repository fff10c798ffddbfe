"""A roboticist's first hour: each problem a newcomer met (issue 23) as a test, against the real
command line, library and server."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.model import RETRY_STARTING_S
from service.process import ServerProcess, free_port
from tdcr import DesignBatch, Surrogate, design_space, solve
from tdcr.clients import Client
from tdcr.surrogates.runtime import best_model


@pytest.fixture(scope="module")
def server(tiny_models):
    srv = ServerProcess(tiny_models[1], grpc=False, wait_for_paths=("loaded",))
    yield srv
    srv.stop()


def _tdcr(*args, cwd, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tdcr.cli", *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


# -- 1. evaluate never touches the manifest unless asked, and never scores training designs -------


def test_evaluate_leaves_the_manifest_alone_and_leaves_out_training_designs(root, tiny_models, tiny_data, tmp_path):
    from training import dataset

    models = tmp_path / "models"
    shutil.copytree(tiny_models[1], models)
    manifest = json.loads((models / "manifest.json").read_text())
    for entry in manifest["models"].values():  # what `tdcr export --data tiny_data` records
        entry["dataset"] = {"n": 150, "seed": 2, "n_test": 30, "n_train": 120, "points": 42}
    (models / "manifest.json").write_text(json.dumps(manifest))
    before = (models / "manifest.json").read_bytes()
    data = tmp_path / "eval"  # the same seed: its first designs are the training designs' first
    dataset.generate(data, dataset.GenerateConfig(n=60, seed=2, shard_size=60), workers=1, progress=False)
    trained = {row.tobytes() for row in dataset.load(tiny_data, "train")["features"]}  # read, not regenerated
    test = dataset.load(data, "test")["features"]
    seen = sum(row.tobytes() in trained for row in test)
    assert 0 < seen < len(test)

    out = _tdcr("evaluate", "--data", str(data), "--models-dir", str(models), "--models", "deeponet", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (models / "manifest.json").read_bytes() == before
    assert f"left out {seen} of {len(test)} test designs: in the training set of deeponet" in out.stderr
    assert "is unchanged (--update-manifest writes these metrics)" in out.stderr
    assert f"| {len(test) - seen} |" in out.stdout

    out = _tdcr("evaluate", "--data", str(data), "--models-dir", str(models), "--models", "deeponet",
                "--update-manifest", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    metrics = json.loads((models / "manifest.json").read_text())["models"]["deeponet"]["metrics"]
    assert metrics["test_relative_l2"]["n"] == len(test) - seen
    assert metrics["evaluated_on"] == {"n": 60, "seed": 2, "n_test": 12, "n_held_out": len(test) - seen}


def test_a_command_without_its_extra_names_the_extra(root, tmp_path):
    code = ("import sys; sys.modules['onnx'] = None\n"  # an install without the 'train' extra
            "from tdcr.cli import main\n"
            f"sys.exit(main(['evaluate', '--data', {str(tmp_path)!r}]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120)
    assert out.returncode == 2, out.stderr
    assert "tdcr evaluate: needs the 'train' extra (no module named 'onnx'): pip install -e '.[train]'" in out.stderr
    assert "Traceback" not in out.stderr


# -- 3. units that cannot be confused ------------------------------------------------------------


def test_s_is_a_fraction_in_answers_too_and_metres_travel_as_arclength(server, example_request):
    design = example_request["designs"][0]
    length = design["L"]
    for route in ("/predict", "/exact"):
        body = httpx.post(server.url + route, json={"designs": [design], "arclength": [0.0, length / 2, length]},
                          timeout=60).json()
        assert body["format_version"] == 2
        result = body["results"][0]
        assert result["s"] == [0.0, 0.5, 1.0] and result["arclength"] == pytest.approx([0.0, length / 2, length])
    exact = httpx.post(server.url + "/exact", json={"designs": [design], "points": 3}, timeout=60).json()
    np.testing.assert_allclose(exact["results"][0]["backbone"], result["backbone"], rtol=1e-12)  # the same shape
    two = [design, {**design, "L": length / 2}]
    r = httpx.post(server.url + "/predict", json={"designs": two, "arclength": [0.0, 0.1]}, timeout=60)
    assert r.status_code == 422 and "arclength: metres need designs of one length L" in r.json()["message"]
    r = httpx.post(server.url + "/exact", json={"designs": [design], "arclength": [0.0, 2 * length]}, timeout=60)
    assert r.status_code == 422 and f"arclength[1]: must be in [0, L] = [0, {length:g}] m" in r.json()["message"]
    features = design_space.sample_designs(2, seed=0).features()
    features[:, 2] = 0.11  # one length, 110 mm
    with Client(server.url) as client:
        shapes = client.predict(features, arclength=np.linspace(0.0, 0.11, 42))
    assert shapes["s"][0, -1] == 1.0 and shapes["arclength"][0, -1] == pytest.approx(0.11, rel=1e-6)


# -- 4. the Python API is as safe as the service --------------------------------------------------


def test_the_python_api_refuses_what_the_service_refuses_in_the_same_words(tiny_models):
    model = Surrogate.load(tiny_models[1], "deeponet")
    features = design_space.sample_designs(2, seed=0).features()
    fractions = np.linspace(0.0, 1.0, 42)
    bad_tension = features.copy()
    bad_tension[0, 11] = -2.0
    cases = [
        (features[0], fractions, "designs: expected a numeric (B, 15) array"),
        (features[:, :12], fractions, "the operators take 4 tendons (15 columns), got 3 tendons; the exact solver"),
        (bad_tension, fractions, "designs[0].tendons[0].tension: must be in [0, 1000] N, got -2"),
        (features, fractions * 1.01, "fractions[41]: must be a fraction of L in [0, 1], got 1.01"),
    ]
    for f, s, message in cases:
        with pytest.raises(ValueError, match=re.escape(message)):
            model.predict(f, s)
    with Client("http://127.0.0.1:9") as client:  # refused before anything is sent: nobody listens there
        for f, s, message in cases:
            with pytest.raises(ValueError, match=re.escape(message.replace("fractions[", "s["))):
                client.predict(f, s=s)
    with pytest.raises(ValueError, match=re.escape("designs[0].tendons[0].tension: must be in [0, 1000] N, got -2")):
        solve(DesignBatch.from_features(bad_tension), fractions)


# -- 5. errors say what to do ---------------------------------------------------------------------


def test_a_design_an_operator_cannot_take_is_sent_to_the_solver(server, example_request):
    design = example_request["designs"][0]
    three = {**design, "tendons": design["tendons"][:3]}
    loaded = {**design, "gravity": [0, 0, -9.81], "density": 7800.0}
    for other, model in ((three, None), (loaded, "fno")):  # 3 tendons; loads for an operator that takes none
        r = httpx.post(server.url + "/predict", json={"designs": [other], "model": model}, timeout=60)
        assert r.status_code == 422
        assert "the exact solver takes it: tdcr solve, POST /exact or tdcr.solve" in r.json()["message"]
        assert httpx.post(server.url + "/exact", json={"designs": [other]}, timeout=60).status_code == 200
    # with loads and no model named: the router's loaded operator, or the solver where it is cheaper
    r = httpx.post(server.url + "/predict", json={"designs": [loaded]}, timeout=60)
    assert r.status_code == 200
    router = httpx.get(server.url + "/v2/models/auto").json()["parameters"]
    assert r.json()["model"] in (router["loaded_operator"], "exact")


# -- 6. one behaviour ----------------------------------------------------------------------------


def test_tdcr_predict_chooses_like_the_service_and_honours_the_request(server, tiny_models, example_request, tmp_path):
    models = tiny_models[1]
    request = tmp_path / "request.json"
    request.write_text(json.dumps(example_request))
    out = _tdcr("predict", str(request), "--models-dir", str(models), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    # no model named: the router, here and in the service, answers by the solver or the most accurate operator
    assert httpx.get(server.url + "/readyz").json()["default_model"] == "auto"
    best = best_model(json.loads((models / "manifest.json").read_text()), loads=None)
    assert httpx.get(server.url + "/v2/models/auto").json()["parameters"]["operator"] == best
    assert json.loads(out.stdout)["model"] in ("exact", best)
    served = httpx.post(server.url + "/predict", json=example_request, timeout=60).json()
    assert served["model"] in ("exact", best)
    request.write_text(json.dumps(example_request | {"model": "fno"}))
    out = _tdcr("predict", str(request), "--models-dir", str(models), cwd=tmp_path)
    assert out.returncode == 0 and json.loads(out.stdout)["model"] == "fno"


def test_the_shipped_models_are_found_from_any_directory(root, example_request, tmp_path):
    request = tmp_path / "request.json"
    request.write_text(json.dumps(example_request))
    out = _tdcr("predict", str(request), cwd=tmp_path)  # no --models-dir, another working directory
    assert out.returncode == 0, out.stderr
    shipped = json.loads((root / "models" / "manifest.json").read_text())
    assert json.loads(out.stdout)["model"] in ("exact", best_model(shipped, loads=None))  # the router's paths


# -- 7. help and messages ------------------------------------------------------------------------


def test_every_option_has_help_and_openapi_says_what_it_wrote(root, tmp_path):
    from tdcr.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    missing = [f"{name} {'/'.join(action.option_strings) or action.dest}"
               for name, sub in commands.items() for action in sub._actions if not action.help]
    assert not missing, missing
    out = _tdcr("openapi", "--out", str(tmp_path / "openapi.json"), cwd=root)
    assert out.returncode == 0 and f"wrote {tmp_path / 'openapi.json'}: OpenAPI 3.1.0" in out.stderr


# -- readiness as Kubernetes expects --------------------------------------------------------------


def test_the_port_answers_while_the_service_starts(root, tiny_models, tmp_path):
    """A first start compiles the solver (an empty numba cache here): meanwhile /healthz answers
    200, /readyz and inference 503 with the reason and a Retry-After (the service's own API and OIP
    REST), and the log says so; then it is ready.  Once the solver joins, /readyz lists the paths it
    still compiles, and a request on one is refused at once with a Retry-After."""
    port = free_port()
    env = {**os.environ, "TDCR_MODELS_DIR": str(tiny_models[1]), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    log = tempfile.NamedTemporaryFile("w+", suffix=".log", delete=False)
    proc = subprocess.Popen([sys.executable, "-m", "tdcr.cli", "serve", "--port", str(port), "--grpc-port", "0"],
                            cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT)
    url, seen = f"http://127.0.0.1:{port}", []
    try:
        deadline = time.monotonic() + 420  # a first start compiles every kernel (about two minutes)
        while time.monotonic() < deadline:
            try:
                live, ready = httpx.get(url + "/healthz"), httpx.get(url + "/readyz")
            except httpx.TransportError:
                time.sleep(0.05)
                continue
            seen.append((live.status_code, ready.status_code))
            if ready.status_code == 200:
                break
            assert ready.json()["problems"][0].startswith("starting: loading the models")
            predict = httpx.post(url + "/predict", json={"designs": design_space.sample_designs(1, seed=0).to_dicts()})
            if predict.status_code == 200 and httpx.get(url + "/readyz").status_code == 200:
                seen.append((200, 200))  # it became ready between the two calls
                break
            assert predict.status_code == 503 and "starting" in predict.json()["message"]
            assert predict.headers["retry-after"] == str(RETRY_STARTING_S)
            oip = httpx.post(url + "/v2/models/exact/infer", json={"inputs": []})
            if oip.status_code == 503:  # (200 with 400 below: it became ready meanwhile)
                assert "starting" in oip.json()["error"] and oip.headers["retry-after"] == str(RETRY_STARTING_S)
            time.sleep(0.2)
        assert (200, 503) in seen and seen[-1] == (200, 200), seen[:3] + seen[-3:]
        log.seek(0)
        assert "the first start on a machine compiles the solver kernels" in log.read()
        robot = (root / "examples" / "ftdcr_v4_fitted.json").read_bytes()  # displacement: compiled last
        compiling, refused = [], None
        while time.monotonic() < deadline:
            ready = httpx.get(url + "/readyz").json()
            if "exact" in ready["starting"]:  # the solver joins (its default path compiled) ...
                assert ready["compiling"] == {}, ready
            else:  # ... then compiles its other paths
                compiling.append(ready["compiling"].get("exact", []))
                assert compiling[-1], "the solver joins while its last path still compiles (about a minute)"
                answer = httpx.post(url + "/exact", content=robot, headers={"Content-Type": "application/json"})
                refused = None if answer.status_code == 200 else answer  # (200: a process compiled it since)
                break
            time.sleep(0.2)
        assert compiling and set(compiling[0]) <= {"loaded", "displacement"}, compiling
        if refused is not None:
            assert refused.status_code == 503 and "compiles its displacement path" in refused.json()["message"], \
                refused.text
            assert refused.headers["retry-after"] == str(RETRY_STARTING_S)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        Path(log.name).unlink()


# -- the README is a tutorial whose code runs as written ------------------------------------------


def _python_blocks(root: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", (root / "README.md").read_text(), re.S)


def test_every_python_block_of_the_readme_runs_as_written(root, tmp_path):
    """Each block in a fresh interpreter, from another working directory; the blocks that talk to
    the service talk to a real one on the shipped models (its address in for 127.0.0.1:8000)."""
    blocks = _python_blocks(root)
    assert len(blocks) >= 2
    with ServerProcess(root / "models", grpc=False) as srv:
        for block in blocks:
            code = block.replace("http://127.0.0.1:8000", srv.url)
            out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                                 timeout=300)
            assert out.returncode == 0, f"{block}\n{out.stderr[-3000:]}"
            assert out.stdout.strip(), f"the block prints what it promises:\n{block}"
