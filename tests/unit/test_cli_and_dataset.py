"""The tdcr CLI (real subprocesses) and dataset generation (real processes, files and Dask)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tdcr import relative_l2
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch
from training import dataset

TDCR = [sys.executable, "-m", "tdcr.cli"]


@pytest.fixture
def run_tdcr(root):
    """``run_tdcr(*args, stdin=None, cwd=root)``: the CLI in a subprocess."""
    def run(*args, stdin: str | None = None, cwd=None):
        return subprocess.run([*TDCR, *args], input=stdin, capture_output=True, text=True, cwd=cwd or root,
                              timeout=300)

    return run


def test_solve_example_request_matches_the_library(run_tdcr, root, designs_from_json):
    out = run_tdcr("solve", "examples/request.json")
    assert out.returncode == 0, out.stderr
    results = json.loads(out.stdout)["results"]
    request = json.loads((root / "examples/request.json").read_text())
    assert len(results) == 2
    sol = solve(designs_from_json(request["designs"]), np.linspace(0, 1, 5))
    for j, res in enumerate(results):
        assert res["converged"] is True and res["residual"] < 1e-8
        assert np.array(res["tendons"]).shape == (5, 4, 3)
        assert np.array(res["rotation"]).shape == (5, 3, 3)
        assert relative_l2(np.array(res["tendons"])[None], sol.tendons[j][None])[0] < 1e-14
        np.testing.assert_allclose(res["arclength"], sol.s[j])  # m
        np.testing.assert_allclose(res["s"], np.linspace(0, 1, 5))  # fractions of L


def test_solve_with_explicit_s_and_mixed_tendon_counts(run_tdcr, tmp_path):
    request = {
        "designs": [
            {"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": [{"offset": 0.008, "tension": 1.0}]},
            {"E": 3e10, "r": 1e-3, "L": 0.2, "tendons": [{"offset": 0.008, "tension": 1.0}] * 3,
             "tip_force": [0.0, 0.01, 0.0]},
        ],
        "s": [0.0, 0.5, 1.0],
    }
    out = run_tdcr("solve", "-", stdin=json.dumps(request))
    assert out.returncode == 0, out.stderr
    results = json.loads(out.stdout)["results"]
    assert [len(r["tendons"][0]) for r in results] == [1, 3]
    assert all(r["converged"] for r in results)
    np.testing.assert_allclose(results[0]["arclength"], [0.0, 0.1, 0.2])
    assert results[0]["s"] == [0.0, 0.5, 1.0]


@pytest.mark.parametrize(
    "body, message",
    [
        ("{not json", "Invalid JSON"),
        ('{"designs": []}', "designs: List should have at least 1 item"),
        ('{"designs": [{"E": 3e10, "r": 0.001, "L": 0.2, "tendons": [{"offset": 0.01, "tension": 1}]},'
         ' {"E": 3e10, "r": -1, "L": 0.2, "tendons": [{"offset": 0.01, "tension": 1}]}]}',
         "designs[1].r: must be in [0.0001, 0.05] m, got -1"),
        ('{"designs": [{"E": 3e10, "r": 0.001, "L": 0.2, "tendons": [{"offset": 0.01, "tension": -2}]}]}',
         "designs[0].tendons[0].tension: must be in [0, 1000] N, got -2"),
        ('{"designs": [{"E": 3e10, "r": 0.001, "L": 0.2, "tendons": [{"offset": 0.01, "tension": 1}]}],'
         ' "s": [0.5, 1.5]}', "s[1]: must be a fraction of L in [0, 1], got 1.5"),
        ('{"designs": [{"E": 3e10, "r": 0.001, "L": 0.2, "tendons": [{"offset": 0.01, "tension": 1}]}],'
         ' "points": 100000}', "points: must be an integer from 2 to 1000, got 100000"),
    ],
)
def test_bad_requests_exit_2_with_a_message(run_tdcr, body, message):
    out = run_tdcr("solve", "-", stdin=body)
    assert out.returncode == 2
    assert message in out.stderr
    assert "Traceback" not in out.stderr


def test_missing_file_and_bad_flags_exit_2(run_tdcr, tmp_path):
    assert run_tdcr("solve", str(tmp_path / "nope.json")).returncode == 2
    assert run_tdcr("generate", "--n", "0", "--out", str(tmp_path / "d")).returncode == 2
    assert run_tdcr("generate", "--n", "ten", "--out", str(tmp_path / "d")).returncode == 2
    for args, words in [(("openapi", "--out", str(tmp_path / "none" / "o.json")), "no folder"),
                        (("calibrate", "--designs", "0"), "--designs: must be at least 1")]:
        out = run_tdcr(*args)
        assert out.returncode == 2 and words in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_every_help_page_prints(run_tdcr, capsys):
    """``tdcr --help`` lists every command's help line (argparse %-formats those: a literal % once broke
    the top-level page with a TypeError) and every command's own page prints too."""
    from tdcr.cli import build_parser, main

    top = run_tdcr("--help")
    assert top.returncode == 0, top.stderr
    assert "99 % error bounds" in top.stdout  # the calibrate line, with its percent sign
    assert "The tdcr command line" in top.stdout and "``" not in top.stdout  # no rst markup on the page
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert {"solve", "replay", "fit", "serve", "calibrate"} <= set(commands)
    for name in commands:
        with pytest.raises(SystemExit) as exit_:
            main([name, "--help"])
        assert exit_.value.code == 0, name
        assert f"usage: tdcr {name}" in capsys.readouterr().out


def _shard_times(out: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted((out / "shards").glob("*.npz"))}


def test_generate_resumes_without_recomputing(run_tdcr, tmp_path):
    out = tmp_path / "data"
    args = ("generate", "--n", "60", "--seed", "4", "--shard-size", "20", "--workers", "2", "--out", str(out),
            "--quiet")
    first = run_tdcr(*args)
    assert first.returncode == 0, first.stderr
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["converged"] == 60 and meta["n_train"] == 48 and meta["n_test"] == 12
    before = _shard_times(out)
    (out / "shards" / "shard-00001.npz").unlink()
    again = run_tdcr(*args)
    assert again.returncode == 0, again.stderr
    after = _shard_times(out)
    assert set(after) == set(before)
    assert after["shard-00000.npz"] == before["shard-00000.npz"]
    assert after["shard-00002.npz"] == before["shard-00002.npz"]
    assert json.loads(again.stdout)["last_run"]["designs_solved"] == 20
    data = dataset.load(out)
    np.testing.assert_array_equal(np.sort(data["index"]), np.arange(60))
    train, test = dataset.load(out, "train"), dataset.load(out, "test")
    assert len(train["index"]) == 48 and len(test["index"]) == 12
    assert not set(train["index"]) & set(test["index"])
    # the data are the solver's answers for the seeded designs
    sol = solve(DesignBatch.from_features(data["features"][:5]), np.linspace(0, 1, 42))
    np.testing.assert_allclose(data["tendons"][:5], sol.tendons, atol=1e-15)
    # other settings in the same directory are refused
    bad = run_tdcr("generate", "--n", "61", "--seed", "4", "--shard-size", "20", "--out", str(out), "--quiet")
    assert bad.returncode == 2 and "other settings" in bad.stderr


def test_killed_generation_resumes_to_the_same_dataset(root, tmp_path):
    out = tmp_path / "killed"
    args = [*TDCR, "generate", "--n", "400", "--seed", "9", "--shard-size", "10", "--workers", "1",
            "--out", str(out), "--quiet"]
    proc = subprocess.Popen(args, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((out / "shards").glob("*.npz"))) < 3:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    partial = _shard_times(out)
    assert 3 <= len(partial) < 40, "the run should have been killed part-way"
    assert not (out / "metadata.json").exists()
    done = subprocess.run(args, cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    after = _shard_times(out)
    assert all(after[name] == t for name, t in partial.items())  # nothing recomputed
    data = dataset.load(out)
    np.testing.assert_array_equal(np.sort(data["index"]), np.arange(400))  # nothing lost or duplicated
    assert not list((out / "shards").glob("*.tmp-*"))


def test_generate_on_a_local_dask_cluster(tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        meta = dataset.generate(tmp_path / "dask", dataset.GenerateConfig(n=30, seed=1, shard_size=10),
                                scheduler=c.scheduler_address, progress=False)
    assert meta["converged"] == 30
    local = dataset.generate(tmp_path / "local", dataset.GenerateConfig(n=30, seed=1, shard_size=10),
                             workers=1, progress=False)
    assert local["converged"] == 30
    a, b = dataset.load(tmp_path / "dask"), dataset.load(tmp_path / "local")
    np.testing.assert_array_equal(a["tendons"], b["tendons"])


def test_a_resumed_generation_removes_half_written_shards(tmp_path):
    """A run killed while writing a shard leaves its temporary file; the next run removes it."""
    cfg = dataset.GenerateConfig(n=20, seed=3, shard_size=10)
    dataset.generate(tmp_path / "d", cfg, workers=1, progress=False)
    stale = tmp_path / "d" / "shards" / "shard-00001.npz.tmp-99999"
    stale.write_bytes(b"half a shard")
    dataset.shard_path(tmp_path / "d", 1).unlink()
    dataset.generate(tmp_path / "d", cfg, workers=1, progress=False)
    assert not stale.exists() and dataset.shard_path(tmp_path / "d", 1).exists()


def test_generate_with_loads_records_them_and_solves_them(tmp_path):
    """The loaded design space: gravity of 9.81 m/s^2 in any direction, density 6,450-8,000
    kg/m^3, tip force <= 0.02 N and tip moment <= 0.002 N m; shards hold the loads, and each
    design equals a direct solve with its loads."""
    from tdcr.cli import main
    from tdcr.physics import solve
    from tdcr.robot.designs import DesignBatch, ExternalLoads
    from training import dataset

    out = tmp_path / "loaded"
    args = ["generate", "--n", "24", "--seed", "5", "--out", str(out), "--points", "12", "--shard-size", "10",
            "--workers", "1", "--quiet", "--gravity", "sphere", "--density", "6450,8000", "--tip-force", "0.02",
            "--tip-moment", "0.002"]
    assert main(args) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["convergence_rate"] == 1.0 and meta["status_counts"] == {"converged": 24}
    assert meta["loads"]["gravity"] == "sphere" and meta["loads"]["density"] == [6450.0, 8000.0]
    data = dataset.load(out)
    np.testing.assert_allclose(np.linalg.norm(data["gravity"], axis=1), 9.81)
    assert ((6450 <= data["density"]) & (data["density"] <= 8000)).all()
    assert (np.linalg.norm(data["tip_force"], axis=1) <= 0.02).all() and (data["error_estimate"] <= 3e-7).all()
    loads = ExternalLoads(gravity=data["gravity"], density=data["density"], tip_force=data["tip_force"],
                          tip_moment=data["tip_moment"])
    direct = solve(DesignBatch.from_features(data["features"]), np.linspace(0, 1, 12), loads=loads)
    np.testing.assert_allclose(direct.tendons, data["tendons"], rtol=0, atol=1e-15)
    assert main(args) == 0  # resumes: nothing to do, same plan
    assert main([*args[:-2], "--tip-moment", "0.003"]) == 2  # another plan in the same directory


@pytest.mark.parametrize("bad", [["--gravity", "sphere"], ["--gravity", "1,2"], ["--tip-force", "1000"],
                                 ["--gravity", "0,0,-9.81", "--density", "8000,10"]])
def test_generate_refuses_bad_load_options(tmp_path, bad, capsys):
    from tdcr.cli import main

    assert main(["generate", "--n", "2", "--out", str(tmp_path / "x"), "--quiet", *bad]) == 2
    assert capsys.readouterr().err.strip()
