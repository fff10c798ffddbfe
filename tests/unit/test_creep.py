"""Tendons that creep (eq. CREEP, tdcr/physics/cosserat.py): a dashpot in series with each tendon's
spring lengthens it by r tau / k per second, so along a replay each pull-in falls short by what its
tendon crept under its tension in the rows before."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tdcr.physics.cosserat import crept_by, solve
from tdcr.physics.replay import replay
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.robot.real import RobotFileError, load_robot, read_recording

pytestmark = pytest.mark.unit
ROOT = Path(__file__).resolve().parents[2]
#: A robot with series-elastic tendons (stiffness 1e4 N/m: they can creep) and its recording's first rows.
FITTED = ROOT / "examples" / "ftdcr_v4_fitted.json"
SAMPLE = ROOT / "tests" / "data" / "ftdcr_v4_sample.csv"
#: Creep rates, 1/s: large, so that the sample's 17 s show them.
RATE = 0.05


def _held(rows: int, *, rate: float, interval: float = 1.0):
    """``rows`` designs that hold one tendon's pull-in of 3 mm (the others released) against a
    series spring of 2,000 N/m: the designs and their creep (B, N_t) m/N."""
    u = np.tile([0.003, -0.002, -0.002, -0.002], (rows, 1))
    k = np.full((rows, 4), 2000.0)
    designs = DesignBatch(E=np.full(rows, 30e9), r=np.full(rows, 0.001), L=np.full(rows, 0.2),
                          offset=np.full((rows, 4), 0.008), pitch=np.zeros((rows, 4)), tension=np.zeros((rows, 4)),
                          displacement=u, stiffness=k)
    return designs, np.full((rows, 4), rate * interval) / k


def test_a_held_tendon_falls_short_by_what_it_crept_and_its_tension_relaxes():
    """eq. CREEP from the answer's own tensions: crept(b) = sum_{j<b} r dt tau_j / k (to round-off),
    each row meets eq. SE at the crept pull-in, tau = k (u - crept - d), to 1e-9 of k, and a held
    pull-in loses tension at every row."""
    designs, creep = _held(12, rate=RATE)
    sol = solve(designs, np.ones(1), sequence=True, creep=creep)
    assert sol.converged.all()
    expected = np.vstack([np.zeros((1, 4)), np.cumsum(creep * sol.tension, axis=0)[:-1]])
    np.testing.assert_allclose(sol.crept, expected, rtol=0, atol=1e-15)
    assert sol.crept[-1, 0] > 5e-5  # m: the tendon crept 50 um or more
    taut = sol.tension[:, 0]
    np.testing.assert_allclose(taut, 2000.0 * (0.003 - sol.crept[:, 0] - sol.displacement[:, 0]), rtol=0,
                               atol=1e-9 * 2000.0)
    assert (np.diff(taut) < 0).all() and (sol.tension[:, 1:] == 0).all()


def test_no_creep_is_todays_answer_bit_for_bit_and_bad_creep_is_named():
    designs, creep = _held(5, rate=RATE)
    today = solve(designs, np.ones(1), sequence=True)
    none = solve(designs, np.ones(1), sequence=True, creep=np.zeros_like(creep))
    for name in ("backbone", "rotation", "tension", "displacement"):
        np.testing.assert_array_equal(getattr(none, name), getattr(today, name))
    assert today.crept is None
    for bad, words in [(creep[:, :2], "creep: must be"), (-creep, "creep: must be"), (creep * np.nan, "creep: must")]:
        with pytest.raises(ValueError, match=words):
            solve(designs, np.ones(1), sequence=True, creep=bad)
    with pytest.raises(ValueError, match="creep covers a sequence of displacement commands"):
        solve(designs, np.ones(1), creep=creep)


def _creeping(rate: float = RATE, *, memory: bool = True) -> dict:
    """The fitted FTDCR v4 robot file with ``creep_rate`` ``rate``; without ``memory``, without its
    friction and lag too (then only the creep carries a replay's history: a replay started later is
    the whole one's rows there, given the creep so far)."""
    data = json.loads(FITTED.read_text())
    data["actuation"]["creep_rate"] = rate
    if not memory:
        data["measurement"]["time_constant"] = 0.0
        for tendon in data["design"]["tendons"]:
            tendon["friction"] = 0.0
    return data


def test_a_robot_file_creeps_in_a_replay_with_times_and_names_a_bad_rate(tmp_path):
    robot = load_robot(_creeping())
    rec = read_recording(SAMPLE, robot)
    crept = replay(robot, rec.commands, time=rec.time)
    still = replay(robot, rec.commands)  # no clock: each row's equilibrium, no creep
    plain = replay(load_robot(_creeping(0.0)), rec.commands, time=rec.time)
    assert crept.converged.all() and (crept.crept[-1] > 1e-6).any() and not still.crept.any()
    np.testing.assert_array_equal(still.tip_position, plain.tip_position)
    assert np.abs(crept.tip_position - plain.tip_position).max() > 1e-4  # m
    robot.save(tmp_path / "r.json")
    assert load_robot(tmp_path / "r.json").actuation.creep_rate == RATE
    for rate in (-1.0, "fast", float("inf")):
        with pytest.raises(RobotFileError, match=r"actuation\.creep_rate: must be a number >= 0"):
            load_robot(_creeping(rate))
    loaded = _creeping() | {}
    loaded["design"] = loaded["design"] | {"gravity": [0.0, 0.0, -9.81], "density": 7800.0}
    assert load_robot(loaded).creeps and load_robot(loaded).loads is not None  # creep in gravity: below
    pulled = _creeping() | {}
    pulled["actuation"] = pulled["actuation"] | {"kind": "tension", "unit": "N"}
    with pytest.raises(RobotFileError, match=r"actuation\.creep_rate: creep moves a displacement-driven"):
        load_robot(pulled)


def _row_by_row(designs: DesignBatch, creep: np.ndarray, loads: ExternalLoads):
    """The reference for a creeping chain under loads: each design solved alone under its loads, in
    order, its pull-ins short by e(b) = sum_{j<b} creep_j tau_j of the tensions found before it
    (eq. CREEP, as its drive zeros moved by e(b)).  Returns (the tensions (B, N_t), the creep
    (B, N_t), the tips (B, 3))."""
    so_far, tension, crept, tips = np.zeros(designs.n_tendons), [], [], []
    for b in range(designs.n_designs):
        row = designs.take(np.array([b]))
        row = row.replace(zero=row.resolved("zero") + so_far)
        sol = solve(row, np.ones(1), loads=loads.take(np.array([b])))
        assert sol.converged.all()
        crept.append(so_far.copy())
        tension.append(sol.tension[0])
        tips.append(sol.backbone[0, -1])
        so_far = so_far + creep[b] * sol.tension[0]
    return np.array(tension), np.array(crept), np.array(tips)


@pytest.mark.parametrize(("rows", "rate"), [(8, RATE), (24, 0.5)], ids=["r t = 0.4", "r t = 12"])
def test_under_loads_a_creeping_chain_is_its_rows_solved_one_by_one_in_order(rows, rate):
    """eq. CREEP in gravity: the chain's answer (sweeps of the whole chain, each every row's loaded
    solve at once) is each row solved alone, in order, its pull-ins short by the creep of the tensions
    found before it (to the displacement tolerance's effect: 1e-9 m of creep, 1e-6 N); its creep is
    the sum of its own tensions and every row meets eq. SE at the crept pull-in.  The weight moves
    the tips and the creep against the unloaded chain.  Also where the chain lasts far longer than
    the tendon's relaxation time (r t = 12: its tension relaxes to a fraction of its start), where
    sweeps of the plain sum overshoot and did not settle in 16."""
    designs, creep = _held(rows, rate=rate)
    loads = ExternalLoads(gravity=np.tile([9.81, 0.0, 0.0], (rows, 1)), density=np.full(rows, 7800.0))
    sol = solve(designs, np.ones(1), sequence=True, creep=creep, loads=loads)
    tension, crept, tips = _row_by_row(designs, creep, loads)
    assert sol.converged.all() and crept[-1, 0] > 3e-5  # m
    np.testing.assert_allclose(sol.crept, crept, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.tension, tension, rtol=0, atol=1e-6)
    np.testing.assert_allclose(sol.backbone[:, -1], tips, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.crept, crept_by(creep, sol.tension, designs.displacement_driven), rtol=0,
                               atol=1e-10)
    np.testing.assert_allclose(sol.tension[:, 0], 2000.0 * (0.003 - sol.crept[:, 0] - sol.displacement[:, 0]),
                               rtol=0, atol=1e-9 * 2000.0)
    unloaded = solve(designs, np.ones(1), sequence=True, creep=creep)
    assert np.abs(unloaded.backbone[:, -1] - tips).max() > 1e-3 and np.abs(unloaded.crept - crept).max() > 1e-6
    if rate * rows > 1.0:
        assert sol.tension[-1, 0] < 0.1 * sol.tension[0, 0]  # relaxed


def test_the_kernels_running_creep_is_the_chains_sum():
    """The unloaded kernel sums eq. CREEP as it goes; :func:`crept_by` takes the same sum whole."""
    designs, creep = _held(6, rate=RATE)
    sol = solve(designs, np.ones(1), sequence=True, creep=creep)
    np.testing.assert_allclose(sol.crept, crept_by(creep, sol.tension, designs.displacement_driven), rtol=0,
                               atol=1e-15)
    assert not crept_by(creep, sol.tension, np.zeros_like(designs.displacement_driven)).any()


def test_a_creeping_robot_file_replays_and_fits_in_gravity():
    """A robot file with both a creep rate and loads: its replay with times is the chain under the
    loads (the creep falls short of the unloaded chain's by what the weight changed in the tensions),
    and the fit under the loads finds a known creep rate again when ``creep`` is named (it is not a
    default group under loads)."""
    from tdcr.search.fit import check_groups, default_groups, fit

    data = _creeping(memory=False)
    data["design"] = data["design"] | {"gravity": [9.81, 0.0, 0.0], "density": 40_000.0}  # lying on its side
    truth = load_robot(data)
    assert "creep" not in default_groups(truth) and check_groups(("E", "creep"), truth) is None
    assert "creep" in default_groups(replace(truth, loads=None))
    rec = read_recording(SAMPLE, truth)
    rec = rec.take(np.arange(len(rec.time)) < 12)
    made = replay(truth, rec.commands, time=rec.time)
    unloaded = replay(replace(truth, loads=None), rec.commands, time=rec.time)
    assert made.converged.all() and (made.crept[-1] > 1e-6).any()
    assert np.abs(made.tip_position - unloaded.tip_position).max() > 1e-3  # m: the weight acts
    start = load_robot(_creeping(RATE / 4, memory=False) | {"design": data["design"]})
    result = fit(start, replace(rec, measured=made.points), groups=("creep",), prior=None, max_iterations=15,
                 budget=300, workers=2)
    (found,) = result.parameters
    assert result.train_replay.converged.all() and found.value == pytest.approx(RATE, rel=0.03)
    assert result.initial.rmse > 0.05 and result.train.rmse < 0.01  # mm


def test_fit_finds_a_known_creep_rate_and_the_fitted_file_goes_on_from_trains_end(tmp_path):
    """A recording made by a creeping robot: its first 20 rows fitted from a robot that does not creep
    (group ``creep``, the Jacobian's columns side by side) give the rate again; the fitted file's zeros
    are the drives' as train left them, so its replay of the last 10 rows (recorded after train) is the
    creeping robot's, and the same rows replayed from the start's zeros are not.  A replay of a
    recording that starts before train's end says that it starts crept (the API and ``tdcr replay``)."""
    from tdcr.search.fit import at_start, fit, starts_crept

    truth = load_robot(_creeping(memory=False))
    rec = read_recording(SAMPLE, truth)
    made = replace(rec, measured=replay(truth, rec.commands, time=rec.time).points)
    train, later = made.take(np.arange(len(rec.time)) < 20), made.take(np.arange(len(rec.time)) >= 20)
    start = load_robot(_creeping(0.0, memory=False))
    result = fit(start, train, validate=later, groups=("creep",), prior=None, max_iterations=15, budget=300,
                 workers=2)
    (found,) = result.parameters
    assert found.name == "creep" and found.unit == "1/s" and found.value == pytest.approx(RATE, rel=0.03)
    assert result.initial.rmse > 0.1 and result.train.rmse < 0.01  # mm
    assert result.validate.rmse < 0.05  # mm: the last train row's own creep is after the recording
    fitted = result.robot
    assert fitted.actuation.creep_rate == pytest.approx(found.value)
    np.testing.assert_allclose(fitted.design.resolved("zero") - start.design.resolved("zero"),
                               result.train_replay.crept[-1:], rtol=0, atol=1e-15)
    crept = np.array(fitted.extra["fitted"]["crept_m"])  # the report says by how much, and when
    assert (crept > 0.0).any() and fitted.extra["fitted"]["crept_at_s"] == train.time[-1]
    assert "this replay starts crept" in starts_crept(fitted, train.time)
    assert starts_crept(fitted, later.time) is None and starts_crept(start, train.time) is None
    np.testing.assert_allclose(fitted.design.resolved("zero")[0] - start.design.resolved("zero")[0], crept,
                               rtol=0, atol=1e-15)
    fitted.save(tmp_path / "fitted.json")
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "replay", str(tmp_path / "fitted.json"), str(SAMPLE),
                          "--out", str(tmp_path / "pred.csv"), "--quiet"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and json.loads(run.stdout)["note"] == starts_crept(fitted, rec.time), run.stderr
    again = replay(load_robot(tmp_path / "fitted.json"), later.commands, time=later.time)
    np.testing.assert_allclose(again.points, result.validate_replay.points, rtol=0, atol=1e-12)
    afresh = replay(replace(fitted, design=start.design), later.commands, time=later.time)
    assert np.linalg.norm(afresh.points - later.measured, axis=1).max() > 4 * result.validate.max * 1e-3
    # the fit's values applied to its start: the robot as train found it, whose replay of train is the fit's
    found_it = at_start(start, result)
    np.testing.assert_array_equal(found_it.design.resolved("zero"), start.design.resolved("zero"))
    assert found_it.actuation.creep_rate == fitted.actuation.creep_rate
    np.testing.assert_allclose(replay(found_it, train.commands, time=train.time).points, result.train_replay.points,
                               rtol=0, atol=1e-12)
    slower = at_start(start, result, [replace(found, value=RATE / 2)])
    assert slower.actuation.creep_rate == pytest.approx(RATE / 2)
    with pytest.raises(ValueError, match=r"parameters: must be \['creep'\]"):
        at_start(start, result, [replace(found, name="E")])
