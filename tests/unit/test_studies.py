"""The paper's studies (`tdcr study NAME`), each in its tiny budget: records, plots, resumption and
reproducibility with the same seed."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("matplotlib")

from tdcr import design_space  # noqa: E402
from tdcr.cli import main  # noqa: E402
from training import studies  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("study")
    return {"data": base / "data", "runs": base / "runs", "out": base / "out"}


def _study(name: str, paths: dict[str, Path], *extra: str) -> int:
    return main(["study", name, "--budget", "tiny", "--data", str(paths["data"]), "--runs", str(paths["runs"]),
                 "--out", str(paths["out"]), "--models-dir", str(ROOT / "models"), "--quiet", *extra])


@pytest.mark.parametrize("name", studies.STUDIES)
def test_every_study_runs_in_its_tiny_budget(name, tiny):
    assert _study(name, tiny) == 0
    recs = studies.records(tiny["out"] / f"{name}.jsonl")
    assert recs, name
    budget = studies.BUDGETS["tiny"]
    for r in recs:
        assert r["study"] == name and r["version"] == studies.RECORD_VERSION
        assert r["budget"]["name"] == "tiny" and r["machine"]["cores"] >= 1
    assert (tiny["out"] / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
    if name == "n-sweep":  # every preset, model, N and seed of the budget, once
        keys = [r["key"] for r in recs]
        assert len(keys) == len(set(keys))
        expected = {(p, m, n, s) for p in studies.PRESET_NAMES for m in studies.MODEL_NAMES
                    for n in budget.n_values for s in budget.seeds_at(m, n)}
        assert {(r["preset"], r["model"], r["n_train"], r["seed"]) for r in recs} == expected
        for r in recs:
            assert r["epochs"] == budget.epochs(r["model"], r["n_train"])
            assert r["test"]["n"] == budget.eval_designs and 0 < r["test"]["mean"] <= r["test"]["max"]
    if name == "dropout":
        assert {r["dropout"] for r in recs} == set(budget.dropouts)
    if name == "ood":
        assert {r["protocol"] for r in recs} == {"paper", "widened"}
        assert {r["model"] for r in recs} >= {"undeformed baseline", "linearized reference", *studies.MODEL_NAMES}
    if name == "timing":
        kinds = {(r["kind"], r["n"]) for r in recs}
        assert {("training", n) for n in budget.timing_n} <= kinds
        assert {("inference", n) for n in budget.inference_sizes} <= kinds
        assert all(r["seconds_per_epoch"] > 0 for r in recs if r["kind"] == "training")
    if name == "worst":
        for r in recs:
            errors = [w["error"] for w in r["worst"]]
            assert len(errors) == studies.N_WORST and errors == sorted(errors, reverse=True)
            assert math.isclose(errors[0], r["error"]["max"])


def test_a_rerun_adds_nothing_and_keeps_the_plot(tiny):
    assert _study("seeds", tiny) == 0
    before = (tiny["out"] / "seeds.jsonl").read_text()
    assert _study("seeds", tiny) == 0
    assert (tiny["out"] / "seeds.jsonl").read_text() == before
    assert _study("seeds", tiny, "--plot-only") == 0


def _ctx(tmp: Path, data: Path, **kw) -> studies.Context:
    return studies.Context(data=data, runs=tmp / "runs", out=tmp / "out", budget=studies.BUDGETS["tiny"],
                           presets=("tuned",), models=("deeponet", "fno"), progress=lambda _m: None, **kw)


def test_same_seed_reproduces_and_an_interrupted_study_resumes_to_the_same_numbers(tmp_path, tiny):
    _study("seeds", tiny)  # makes the dataset if the module's other tests did not
    budget = replace(studies.BUDGETS["tiny"], epochs_at_max={"deeponet": 3, "fno": 2})
    first = _ctx(tmp_path / "a", tiny["data"])
    first = replace(first, budget=budget)
    assert studies.run_study("n-sweep", first)["unfinished"] == 0
    # the same study from scratch, interrupted after every first epoch, then resumed
    again = replace(_ctx(tmp_path / "b", tiny["data"]), budget=budget, stop_at=time.time())
    assert studies.run_study("n-sweep", again)["unfinished"] > 0
    assert studies.run_study("n-sweep", replace(again, stop_at=None))["unfinished"] == 0

    def errors(ctx):
        return {r["key"]: r["test"] for r in studies.records(ctx.out / "n-sweep.jsonl")}

    assert errors(first) == errors(again) and len(errors(first)) == 4 + 3  # deeponet 2 N x 2 seeds, fno 2 + 1


def test_widened_ood_designs_leave_the_box_on_both_sides_within_admissible_bounds():
    low, high = design_space.feature_bounds()
    a_low, a_high, _ = design_space.admissible_bounds()
    x = studies.widened_ood_designs(2000, (0.10, 0.15), seed=3).features()
    width = high - low
    distance = np.maximum(low - x, x - high) / width
    assert np.all(distance >= 0.10 - 1e-12) and np.all(distance <= 0.15 + 1e-12)
    assert np.all(x >= a_low) and np.all(x <= a_high)
    below = x < low
    assert below[:, :3].mean() > 0.4  # E, r, L go below as often as above
    assert not below[:, design_space.LAYOUT.group("tension")].any()  # tensions cannot go below 0 N


def test_bending_angle_is_the_tip_angle_of_the_exact_solver_for_one_straight_tendon():
    """Independent of the formula: one straight tendon pulling bends the rod into a circle, whose tip
    tangent turns by the angle the solver returns; for a small pull it is the linear beam angle."""
    from tdcr.physics import solve
    from tdcr.robot.designs import DesignBatch

    feats = np.array([[20e9, 1e-3, 0.2, 0.008, 0.008, 0.008, 0.008, 0, 0, 0, 0, 0.2, 0, 0, 0]])
    sol = solve(DesignBatch.from_features(feats), np.ones(1))
    tip_angle = math.acos(sol.rotation[0, -1, 2, 2])  # the angle between the tip's tangent R e3 and e3
    # a straight tendon bends the rod into an exact circle of curvature tau rho / (E I)
    assert math.isclose(studies.bending_angle(feats)[0], tip_angle, rel_tol=1e-9)
    assert tip_angle > 0.01  # a bend worth measuring


def test_bad_study_arguments_exit_2(tmp_path, capsys):
    assert main(["study", "nope"]) == 2
    assert "unknown study 'nope'" in capsys.readouterr().err
    assert main(["study", "ood", "--budget", "huge"]) == 2
    assert main(["study", "ood", "--presets", "paper,fast"]) == 2
    assert main(["study", "ood", "--hours", "0"]) == 2
    assert main(["study", "ood", "--models", "unet"]) == 2


def test_the_gpu_schedule_script_records_every_phase_on_whatever_device_it_finds(tmp_path, tiny, monkeypatch):
    """``training.gpu_schedule`` (run on a lent GPU for docs/study/gpu.jsonl) in seconds on this CPU:
    timing at one N, the paper schedule compressed into a second, inference at two batch sizes."""
    from training import gpu_schedule

    _study("seeds", tiny)  # makes the tiny dataset if the module's other tests did not
    out = tmp_path / "gpu.jsonl"
    monkeypatch.setitem(studies.PAPER_EPOCHS, "deeponet", 3)  # --full runs here: 3, not 20,000 epochs
    assert gpu_schedule.main(["--data", str(tiny["data"]), "--runs", str(tmp_path / "runs"), "--out", str(out),
                              "--timing-n", "1", "--train-minutes", "0.01", "--deadline-minutes", "5",
                              "--inference-sizes", "1", "3", "--full", "deeponet"]) == 0
    recs = studies.records(out)
    kinds = [r["kind"] for r in recs]
    n_models = len(studies.MODEL_NAMES)
    assert kinds.count("training") == len(studies.PRESET_NAMES) * n_models
    assert kinds.count("schedule") == n_models + 1 and kinds.count("inference") == 2 * n_models
    full = recs[-1]  # --full deeponet: all of its (patched) schedule
    assert (full["kind"], full["stop"], full["epochs"], full["side_by_side"]) == ("schedule", "epochs", 3, 1)
    for r in recs:
        assert r["study"] == "gpu" and r["machine"]["threads_per_run"] >= 1
        if r["kind"] == "schedule":  # scored on the held-out designs
            assert 0.0 < r["test"]["mean"] < 10.0 and r["test"]["n"] > 0
            if r is not full:  # the paper's epochs (in their own processes: unpatched), cut short
                assert r["stop"] == "time budget" and r["epochs"] >= 1
        else:
            assert (r["seconds_per_epoch"] if r["kind"] == "training" else r["seconds"]) > 0.0
