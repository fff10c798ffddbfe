"""Neural operators: layers against references, tiny end-to-end train -> export -> onnxruntime -> CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from tdcr import design_space  # noqa: E402
from tdcr.physics import solve  # noqa: E402
from tdcr.physics.geometry import cubic_weights, rigid_fit, tendon_offsets  # noqa: E402
from tdcr.surrogates.runtime import MANIFEST_FORMAT_VERSION, ManifestError, Surrogate  # noqa: E402
from training.operators.layers import SpectralConv1d, gram_schmidt  # noqa: E402
from training.operators.models import LOADED, REGISTRY, TENDON_ONLY, build_model, count_parameters  # noqa: E402
from training.operators.train import Schedule, make_config, train  # noqa: E402


@pytest.mark.parametrize("mixing", ["full", "shared"])
def test_truncated_dft_spectral_layer_equals_torch_fft(mixing):
    torch.manual_seed(0)
    layer = SpectralConv1d(6, 5, modes=5, n=42, mixing=mixing)
    x = torch.randn(3, 42, 6)  # (B, n, C)
    spec = torch.fft.rfft(x, dim=1)[:, :5]  # (B, modes, C)
    if mixing == "full":
        w = torch.complex(layer.weight_re, layer.weight_im)
        mixed = torch.einsum("bmi,iom->bmo", spec, w)
        ref = torch.fft.irfft(mixed, n=42, dim=1)
    else:
        ref = layer.linear(torch.fft.irfft(spec, n=42, dim=1))
    torch.testing.assert_close(layer(x), ref, rtol=1e-5, atol=1e-5)


def test_gram_schmidt_gives_rotations():
    a1, a2 = torch.randn(100, 3), torch.randn(100, 3)
    R = gram_schmidt(a1, a2)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3).expand(100, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(100), atol=1e-5, rtol=0)


def test_parameter_counts_against_the_paper():
    counts = {name: count_parameters(build_model(name)) for name in REGISTRY}
    paper = {name: entry[3] for name, entry in REGISTRY.items()}  # Table "params" of the paper
    assert counts["fno"] == paper["fno"] and counts["fno_pose"] == paper["fno_pose"]
    # DeepONet: branch 15-64-64-64-64-12p and trunk 1-128-128-128-128-12p with p = 100 (+12 biases)
    assert counts["deeponet"] == (15 * 64 + 64 + 3 * (64 * 64 + 64) + 64 * 1200 + 1200
                                  + 128 + 128 + 3 * (128 * 128 + 128) + 128 * 1200 + 1200 + 12)


def test_schedule_warms_up_and_anneals():
    s = Schedule()
    assert s(0.0) == pytest.approx(1e-4)
    assert s(0.3 / 4) == pytest.approx(3e-3)
    assert s(0.25 + 0.3 / 4) == pytest.approx(3e-3 * 0.7)
    assert s(1.0) == pytest.approx(5e-6, rel=1e-3)


def test_zero_network_output_is_the_undeformed_robot(tiny_hyperparameters):
    feats = torch.as_tensor(design_space.sample_designs(4, seed=0).features(), dtype=torch.float32)
    fractions = torch.linspace(0, 1, 42)
    for name in TENDON_ONLY:  # (the loaded operators need the linearised reference)
        model = build_model(name, tiny_hyperparameters[name])
        out = torch.zeros(4, 42, model.out_channels)
        heads = model.heads(feats, fractions, out)
        tendons = heads if model.kind == "tendons" else heads[2]
        torch.testing.assert_close(tendons, model.geometry.undeformed_tendons(feats, fractions))
        if model.kind == "pose":
            torch.testing.assert_close(heads[1], torch.eye(3).expand(4, 42, 3, 3), atol=1e-6, rtol=0)


def test_kabsch_recovers_the_solver_pose():
    """The closed-form planar rigid fit: exact on solver data, equal to the SVD optimum on noisy points."""
    d = design_space.sample_designs(5, seed=3)
    fractions = np.linspace(0, 1, 42)
    sol = solve(d, fractions)
    body = tendon_offsets(d.features(), fractions)
    p, R = rigid_fit(body, sol.tendons)
    np.testing.assert_allclose(p, sol.backbone, atol=1e-12)
    np.testing.assert_allclose(R, sol.rotation, atol=1e-9)
    noisy = sol.tendons + np.random.default_rng(0).normal(0, 1e-3, sol.tendons.shape)
    _, R_fit = rigid_fit(body, noisy)
    h = np.einsum("...ti,...tj->...ji", body - body.mean(-2, keepdims=True), noisy - noisy.mean(-2, keepdims=True))
    u, _, vt = np.linalg.svd(h)
    fix = np.ones(u.shape[:-1])
    fix[..., -1] = np.sign(np.linalg.det(u @ vt))
    np.testing.assert_allclose(R_fit, (u * fix[..., None, :]) @ vt, atol=1e-9)


def test_cubic_interpolation_off_the_fno_grid():
    """FNO outputs live on 42 points; other s come from a natural cubic spline: < 1e-4 relative here."""
    d = design_space.sample_designs(50, seed=8)
    grid = np.linspace(0, 1, 42)
    off = np.sort(np.random.default_rng(0).uniform(0, 1, 30))
    on_grid, exact = solve(d, grid), solve(d, off)
    interp = np.einsum("mn,bntk->bmtk", cubic_weights(grid, off), on_grid.tendons)
    diff, ref = (interp - exact.tendons).reshape(50, -1), exact.tendons.reshape(50, -1)
    err = np.linalg.norm(diff, axis=1) / np.linalg.norm(ref, axis=1)
    assert err.max() < 1e-4
    np.testing.assert_allclose(cubic_weights(grid, grid), np.eye(42), atol=1e-12)


def test_training_is_deterministic_on_cpu(tiny_hyperparameters, tiny_data, tmp_path):
    cfg = make_config("deeponet", "tuned", epochs=2, batch_size=40, hyperparameters=tiny_hyperparameters["deeponet"])
    train(cfg, tiny_data, tmp_path / "a", progress=False, monitor_designs=20)
    train(cfg, tiny_data, tmp_path / "b", progress=False, monitor_designs=20)
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["state_dict"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=False)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    lines = (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["epoch"] for x in lines] == [1, 2]
    # resuming a finished run trains no further epochs
    again = train(cfg, tiny_data, tmp_path / "a", progress=False, monitor_designs=20)
    assert again["epochs"] == 2


@pytest.mark.parametrize("name", list(REGISTRY))
def test_onnx_matches_torch(tiny_models, name):
    from training.operators.train import load_trained

    root, models = tiny_models
    model, _ = load_trained(root / name / "model.pt")
    feats = design_space.sample_designs(64, seed=11).features()
    loads = design_space.BENCHMARK_LOADS.sample(64, seed=11).matrix(64) if name in LOADED else None
    surrogate = Surrogate.load(models, name)
    deeponet = model.__class__.__name__ == "DeepONet"
    # DeepONet graphs switch (ONNX If) between the grid and the partial-step branch: test both,
    # including 42 points that are not the grid
    sigmas = [np.linspace(0, 1, 42), np.linspace(0, 0.9, 42), np.array([0.0, 0.33, 1.0])] if deeponet \
        else [np.linspace(0, 1, 42)]
    names = ["tendons"] if model.kind == "tendons" else ["backbone", "rotation", "tendons"]
    # FNO graphs switch between a small-batch and a large-batch layout: 3 and 64 designs test both
    for fractions, batch in [(fractions, batch) for fractions in sigmas for batch in (3, 64)]:
        given = None if loads is None else loads[:batch]
        raw = surrogate.run(feats[:batch], fractions, given)
        with torch.no_grad():
            x = torch.as_tensor(feats[:batch], dtype=torch.float32)
            lx = None if given is None else torch.as_tensor(given, dtype=torch.float32)
            ref = model(x, torch.as_tensor(fractions, dtype=torch.float32), lx) if deeponet else model(x, lx)
        ref = ref if isinstance(ref, tuple) else (ref,)
        for got, want in zip([raw[k] for k in names], ref, strict=True):
            assert got.shape == want.shape
            rel = np.linalg.norm(got - want.numpy()) / np.linalg.norm(want.numpy())
            assert rel <= 1e-5
    manifest = json.loads((models / "manifest.json").read_text())["models"][name]
    assert manifest["parameters"] == count_parameters(model)
    # the manifest records the constructor arguments: they rebuild the same network
    assert manifest["hyperparameters"] == asdict(model.config)
    assert count_parameters(build_model(name, manifest["hyperparameters"])) == manifest["parameters"]
    assert manifest["format_version"] == MANIFEST_FORMAT_VERSION
    out = surrogate.predict(feats[:3], np.array([0.0, 0.33, 1.0]))
    assert out["tendons"].shape == (3, 3, 4, 3) and out["rotation"].shape == (3, 3, 3, 3)
    R = out["rotation"]
    np.testing.assert_allclose(np.einsum("...ji,...jk->...ik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)


def test_tampered_model_is_refused(tiny_models, tmp_path):
    import shutil

    _, models = tiny_models
    copy = tmp_path / "m"
    shutil.copytree(models, copy)
    (copy / "fno.onnx").write_bytes((copy / "fno.onnx").read_bytes() + b"\0")
    with pytest.raises(ManifestError, match="sha256"):
        Surrogate.load(copy, "fno")


def test_a_manifest_of_another_format_is_refused(tiny_models, tmp_path):
    import shutil

    _, models = tiny_models
    copy = tmp_path / "m"
    shutil.copytree(models, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["models"]["fno"]["format_version"] = MANIFEST_FORMAT_VERSION + 1
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ManifestError, match="format"):
        Surrogate.load(copy, "deeponet")


def test_cli_predict_and_evaluate(root, tiny_models, tiny_data):
    _, models = tiny_models
    cmd = [sys.executable, "-m", "tdcr.cli"]
    out = subprocess.run([*cmd, "predict", "examples/request.json", "--model", "deeponet_pose",
                          "--models-dir", str(models)], capture_output=True, text=True, cwd=root, timeout=120)
    assert out.returncode == 0, out.stderr
    body = json.loads(out.stdout)
    assert body["model"] == "deeponet_pose" and np.array(body["results"][1]["tendons"]).shape == (5, 4, 3)
    bad = subprocess.run([*cmd, "predict", "examples/request.json", "--model", "nope", "--models-dir", str(models)],
                         capture_output=True, text=True, cwd=root, timeout=120)
    assert bad.returncode == 2 and "nope" in bad.stderr
    ev = subprocess.run([*cmd, "evaluate", "--data", str(tiny_data), "--models-dir", str(models), "--ood", "20",
                         "--update-manifest"],
                        capture_output=True, text=True, cwd=root, timeout=300)
    assert ev.returncode == 0, ev.stderr
    assert "undeformed baseline" in ev.stdout and "fno_pose" in ev.stdout
    entry = json.loads((models / "manifest.json").read_text())["models"]["fno"]
    assert entry["metrics"]["test_relative_l2"]["n"] == 30
    assert "out of distribution" in ev.stdout and len(entry["metrics"]["ood_mean_relative_l2"]) == 5


@pytest.mark.parametrize("name", list(REGISTRY))
def test_batch_last_network_equals_the_channels_last_one(tiny_hyperparameters, name):
    """The export's fast layouts (DeepONet trunk folded into the branch, FNO channels first) are
    the same function as the networks written the paper's way."""
    torch.manual_seed(0)
    hyper = dict(tiny_hyperparameters[name], inputs="physics", reference="linearized")
    model = build_model(name, hyper).double().eval()
    feats = torch.as_tensor(design_space.sample_designs(5, seed=3).features())
    loads = torch.as_tensor(design_space.BENCHMARK_LOADS.sample(5, seed=3).matrix(5)) if name in LOADED else None
    fractions = torch.linspace(0, 1, 42, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(model.raw_batch_last(feats, fractions, loads),
                                   model.raw(feats, fractions, loads).permute(2, 1, 0), atol=1e-12, rtol=1e-10)
