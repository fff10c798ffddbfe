"""A real robot: series-elastic tendons (eq. SE), Capstan friction along the path (eq. CAP), robot
files and recordings, replay and the fit's pieces, against closed forms and the answers' own geometry."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from tdcr.metrics import relative_l2
from tdcr.physics.cosserat import SolverOptions, solve
from tdcr.physics.replay import REPLAY_OPTIONS, replay
from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.robot.real import RobotFileError, load_robot, motions, read_recording

pytestmark = pytest.mark.unit
ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "ftdcr_v4.json"
FITTED = ROOT / "examples" / "ftdcr_v4_fitted.json"
#: The header and first 30 rows of the shared recording's validation file (tests/data/README.md).
SAMPLE = ROOT / "tests" / "data" / "ftdcr_v4_sample.csv"
#: The drive zeros of the known robots the fits must find again, m, (1, 9).
KNOWN_ZEROS = np.linspace(-3e-4, 3e-4, 9)[None]


def _design(n: int = 1, *, tension=(3.0, 0.0, 0.0, 0.0), **fields) -> DesignBatch:
    d = DesignBatch(E=np.full(n, 30e9), r=np.full(n, 0.001), L=np.full(n, 0.2), offset=np.full((n, 4), 0.008),
                    pitch=np.zeros((n, 4)), tension=np.tile(np.asarray(tension, float), (n, 1)))
    return d.replace(**fields) if fields else d


FRACTIONS = np.linspace(0.0, 1.0, 41)


def test_friction_zero_and_rigid_tendons_give_todays_answers():
    """friction 0 (either motion) and infinite stiffness, zero 0: today's answers to 1e-12."""
    designs = _design(3, tension=(3.0, 0.5, 0.0, 1.0), pitch=np.array([[0, 5, -5, 2]] * 3, float))
    base = solve(designs, FRACTIONS)
    same = solve(designs.replace(friction=np.zeros((3, 4)), motion=np.array([[1, -1, 1, -1]] * 3, float),
                                 stiffness=np.full((3, 4), np.inf), zero=np.zeros((3, 4))), FRACTIONS)
    assert base.converged.all() and same.converged.all()
    np.testing.assert_allclose(same.tendons, base.tendons, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(base.tension_profile[:, :, 0], 3.0)  # constant without friction


#: Gravity across the rod and a tip force (the loaded kernel), for the tests of friction under loads.
LOADS = ExternalLoads(gravity=np.array([[0.0, 9.81, -9.81]]), density=np.array([7800.0]),
                      tip_force=np.array([[0.0, 0.0, -0.05]]))


def test_friction_zero_under_loads_gives_todays_loaded_answers():
    """In gravity and under a tip force, friction 0 (either motion) is the loaded kernel's answer to
    1e-12; and under a vanishing load the loaded kernel with friction gives the tendon-only
    kernel's friction answer (two integrators: the loaded one's RK4 steps against the node chain) to
    the solvers' tolerances."""
    designs = _design(2, tension=(3.0, 0.5, 0.0, 1.0), pitch=np.array([[0, 5, -5, 2]] * 2, float))
    loads = LOADS.take(np.zeros(2, dtype=np.int64))
    base = solve(designs, FRACTIONS, loads=loads)
    same = solve(designs.replace(friction=np.zeros((2, 4)), motion=np.array([[1, -1, 1, -1]] * 2, float)), FRACTIONS,
                 loads=loads)
    assert base.converged.all() and same.converged.all()
    np.testing.assert_allclose(same.tendons, base.tendons, rtol=0, atol=1e-12)
    rubbing = designs.replace(friction=np.full((2, 4), 0.3), motion=np.array([[1.0] * 4, [-1.0] * 4]))
    vanishing = ExternalLoads(tip_force=np.full((2, 3), 1e-12))
    loaded, free = solve(rubbing, FRACTIONS, loads=vanishing), solve(rubbing, FRACTIONS)
    assert loaded.converged.all() and free.converged.all()
    tolerance = 2 * SolverOptions().step_tol  # each within its step control's relative l2 error
    assert (relative_l2(loaded.tendons, free.tendons) < tolerance).all()
    assert (relative_l2(loaded.tension_profile, free.tension_profile) < tolerance).all()
    assert np.abs(free.tension_profile[:, -1, 0] - 3.0).min() > 0.1  # friction acted
    # two segments: the continuing tendons' kinks where three tendons end count in both kernels
    segments = DesignBatch(E=np.full(2, 30e9), r=np.full(2, 0.001), L=np.full(2, 0.2), offset=np.full((2, 6), 0.008),
                           pitch=np.tile([0, 3, -3, 0, 2, -2.0], (2, 1)),
                           tension=np.tile([2.0, 0.3, 0.0, 1.5, 0.0, 0.4], (2, 1)),
                           angle=np.tile(np.arange(6) * np.pi / 3, (2, 1)), end=np.tile([0.1] * 3 + [0.2] * 3, (2, 1)),
                           friction=np.full((2, 6), 0.3), motion=np.array([[1.0] * 6, [-1.0] * 6]))
    loaded, free = solve(segments, FRACTIONS, loads=vanishing), solve(segments, FRACTIONS)
    assert loaded.converged.all() and free.converged.all()
    assert (relative_l2(loaded.tendons, free.tendons) < tolerance).all()
    assert (relative_l2(loaded.tension_profile, free.tension_profile) < tolerance).all()


@pytest.mark.parametrize("loads", [None, LOADS], ids=["tendon loads", "gravity and a tip force"])
@pytest.mark.parametrize("motion", [1.0, -1.0], ids=["pull", "release"])
def test_the_tension_profile_is_the_capstan_law_of_the_answers_own_geometry(motion, loads):
    """tau(s) = tau(0) exp(-/+ mu int |dt/ds| ds), the wrap angle measured on the answer's own tendon
    path (its tangents by finite differences of the returned positions, a fine output grid)."""
    mu = 0.3
    fractions = np.linspace(0.0, 1.0, 801)
    sol = solve(_design(friction=np.full((1, 4), mu), motion=np.full((1, 4), motion),
                        pitch=np.full((1, 4), 4.0)), fractions, loads=loads)
    assert sol.converged.all()
    path = sol.tendons[0, :, 0]  # (n, 3) the pulled tendon, helical
    tangent = np.diff(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    turn = np.arccos(np.clip((tangent[1:] * tangent[:-1]).sum(axis=1), -1.0, 1.0))
    wrap = np.concatenate([[0.0], np.cumsum(turn)])  # from the first chord's midpoint to each chord's
    got = 0.5 * (sol.tension_profile[0, 1:, 0] + sol.tension_profile[0, :-1, 0])  # at the chords' midpoints
    assert wrap[-1] > 0.1 and abs(sol.tension_profile[0, 0, 0] - 3.0) < 1e-15
    np.testing.assert_allclose(got / got[0], np.exp(-motion * mu * wrap), rtol=2e-6)
    assert (np.diff(sol.tension_profile[0, :, 0]) * motion <= 0).all()  # falls when pulling, grows releasing


def test_a_planar_bend_wraps_as_far_as_the_tip_turns():
    """A straight tendon bending the rod in a plane: its wrap angle is the tip frame's angle."""
    sol = solve(_design(friction=np.full((1, 4), 0.2)), FRACTIONS)
    tip_angle = np.arctan2(sol.rotation[0, -1, 0, 2], sol.rotation[0, -1, 2, 2])
    wrap = -np.log(sol.tension_profile[0, -1, 0] / 3.0) / 0.2
    np.testing.assert_allclose(wrap, abs(tip_angle), rtol=1e-7)


@pytest.mark.parametrize("loads", [None, LOADS], ids=["tendon loads", "gravity and a tip force"])
def test_friction_is_internal_the_rod_and_tendons_carry_only_the_external_load(loads):
    """Friction only moves load between tendon and rod: the total force across every cut, rod plus
    tendons (tau_i(s) t_i, from the answer's profile and tendon path), is the external load beyond
    the cut, F_tip + rho A g (L - s) (zero under tendon loads alone), to the solver's tolerance."""
    fractions = np.linspace(0, 1, 401)
    design = _design(friction=np.full((1, 4), 0.4), tension=(3.0, 1.0, 0.0, 0.0))
    sol = solve(design, fractions, loads=loads)
    assert sol.converged.all()
    path = sol.tendons[0]  # (n, N_t, 3)
    t = np.gradient(path, axis=0)
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    total = sol.force[0] + np.einsum("ni,nij->nj", sol.tension_profile[0], t)
    beyond = np.zeros((len(fractions), 3))
    if loads is not None:
        weight = loads.density[0] * np.pi * design.r[0] ** 2 * loads.gravity[0]  # N/m
        beyond = loads.tip_force[0] + np.outer(design.L[0] * (1.0 - fractions), weight)
        assert np.abs(beyond).max() > 0.05  # the loads are not small beside the 1e-4 tolerance
    assert np.abs((total - beyond)[5:-5]).max() < 1e-4 * 4.0  # central differences of the path: O(h^2)


def test_a_series_spring_pulls_with_k_times_the_pull_in_it_takes_up():
    """tau = k (u - zero - d) to 1e-9, d the path's shortening in the answer (eq. SE); slack below."""
    k, zero = np.array([[800.0, 2000.0, 1e5, 500.0]]), np.array([[0.001, 0.0, -0.0005, 0.0]])
    u = np.array([[0.004, 0.0005, 0.0, -0.002]])
    sol = solve(_design(tension=(0, 0, 0, 0), displacement=u, stiffness=k, zero=zero), np.ones(1))
    assert sol.converged.all()
    expected = np.maximum(k * (u - zero - sol.displacement), 0.0)
    np.testing.assert_allclose(sol.tension, expected, rtol=0, atol=1e-9 * k.max())
    assert sol.tension[0, 0] > 0.5 and sol.slack[0, 3]
    stiff = solve(_design(tension=(0, 0, 0, 0), displacement=u, stiffness=np.full((1, 4), 1e11), zero=zero),
                  np.ones(1))
    rigid = solve(_design(tension=(0, 0, 0, 0), displacement=u - zero), np.ones(1))
    np.testing.assert_allclose(stiff.tension, rigid.tension, rtol=1e-4, atol=1e-6)  # k -> inf: rigid


def _loop(mu: float, cycles: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A pull/release loop of one tendon against a series spring, ``cycles`` times: its commands
    and the tip's x, m."""
    up = np.linspace(0.0, 0.004, 9)
    u = np.concatenate([up, up[::-1][1:]] * cycles)[:, None]
    commands = np.concatenate([u, np.zeros((len(u), 3))], axis=1)
    designs = _design(len(u), tension=(0, 0, 0, 0), displacement=commands, stiffness=np.full((len(u), 4), 1500.0),
                      friction=np.full((len(u), 4), mu), motion=motions(commands))
    sol = solve(designs, np.ones(1), sequence=True)
    assert sol.converged.all()
    return u[:, 0], sol.backbone[:, -1, 0]


def test_a_pull_release_loop_widens_with_friction_and_repeats_without_drift():
    widths = []
    for mu in (0.0, 0.1, 0.3):
        u, x = _loop(mu)
        half = len(u) // 2
        pull, release = x[:9], x[8:17][::-1]  # the same commands, up and down
        widths.append(np.abs(pull - release).max())
        np.testing.assert_allclose(x[half:], x[:half], rtol=0, atol=1e-9)  # the second cycle repeats the first (1 nm)
    assert widths[0] < 1e-12 < widths[1] < widths[2]


def test_motions_follow_the_command_history_and_a_hold_keeps_the_last():
    commands = np.array([[0.0], [1.0], [2.0], [2.0], [1.0], [1.0], [1.02], [3.0]])
    np.testing.assert_array_equal(motions(commands, deadband=0.05)[:, 0], [1, 1, 1, 1, -1, -1, -1, 1])


def test_replay_in_sequence_equals_independent_solves():
    robot = load_robot(EXAMPLE)
    rec = read_recording(SAMPLE, robot)
    together = replay(robot, rec.commands)
    alone = [replay(robot, rec.commands[t:t + 1], motion=together.motion[t:t + 1]) for t in (0, 7, len(rec.time) - 1)]
    for t, a in zip((0, 7, len(rec.time) - 1), alone, strict=True):
        np.testing.assert_allclose(a.points[0], together.points[t], rtol=0, atol=1e-8)
    assert together.converged.all()
    keep = np.arange(len(rec.time)) % 3 == 1  # a fold of the replay is the fold's rows of every field
    fold = together.take(keep)
    for field in fields(fold):
        np.testing.assert_array_equal(getattr(fold, field.name), getattr(together, field.name)[keep])


def test_a_row_like_the_one_before_but_for_its_motion_or_a_tension_is_not_taken_for_it():
    """In a sequence a row whose robot and motions are the row before's starts from that row's last
    shooting (its path lengths at the tensions it ended with; ``find_tensions``), without shooting
    again.  A row that differs in a motion or in a tension-driven tendon's tension must not: the
    same pull-in reversed (friction) or beside another tension is another equilibrium.  Rows: a
    pull; the same row again (its answer the row before's); the same pull-in releasing; and then with
    the tension-driven tendon at 1 N instead of 0.5.  Each must be its row solved alone."""
    n = 4
    displacement = np.tile([0.003, np.nan, 0.0, 0.0], (n, 1))  # tendon 1 is tension-driven
    motion = np.array([[1, 1, 1, 1], [1, 1, 1, 1], [-1, 1, 1, 1], [-1, 1, 1, 1]])
    designs = _design(n, tension=(0.0, 0.5, 0.0, 0.0), displacement=displacement, motion=motion,
                      stiffness=np.full((n, 4), 1500.0), friction=np.full((n, 4), 0.3))
    designs = designs.replace(tension=designs.tension * np.array([[1.0], [1.0], [1.0], [2.0]]))
    together = solve(designs, np.ones(1), sequence=True)
    alone = solve(designs, np.ones(1))
    assert together.converged.all() and alone.converged.all()
    np.testing.assert_allclose(together.tension, alone.tension, rtol=0, atol=1e-6)
    np.testing.assert_allclose(together.backbone[:, -1], alone.backbone[:, -1], rtol=0, atol=1e-9)
    tips = alone.backbone[:, -1]
    assert np.linalg.norm(tips[2] - tips[1]) > 1e-5 and np.linalg.norm(tips[3] - tips[2]) > 1e-5  # others indeed
    np.testing.assert_array_equal(together.tension[1], together.tension[0])  # the repeat: nothing moved


@pytest.mark.parametrize(("sequence", "friction"), [(False, 0.2), (True, 0.2), (True, 0.0)])
def test_the_answer_at_the_found_tensions_is_the_solve_at_them_bit_for_bit(sequence, friction):
    """A displacement answer is taken on from Newton's last shooting where it was at the found
    tensions (for a held row, the row before's; ``finish_design``) instead of solving again.  It must
    be what a tension solve at those tensions gives, every field to the bit: pulls, a hold, a
    release (friction), a tension-driven tendon, and two tendons that end halfway; without friction
    a row of the sequence takes one shooting."""
    n = 7
    pull = np.array([0.0, 0.001, 0.002, 0.002, 0.0015, 0.001, 0.003])  # row 3 holds, rows 4-5 release
    displacement = np.stack([pull, np.full(n, np.nan), -0.5 * pull, np.zeros(n)], axis=1)
    designs = _design(n, tension=(0.0, 0.4, 0.0, 0.0), displacement=displacement, motion=motions(displacement),
                      stiffness=np.full((n, 4), 2000.0), friction=np.full((n, 4), friction),
                      end=np.tile([0.2, 0.2, 0.1, 0.1], (n, 1)))
    fractions = np.linspace(0.0, 1.0, 9)
    sol = solve(designs, fractions, sequence=sequence)
    again = solve(designs.replace(tension=sol.tension, displacement=None), fractions)
    assert sol.converged.all()
    for field in ("backbone", "rotation", "tendons", "strains", "tension_profile", "displacement", "residual",
                  "iterations", "error_estimate", "steps", "status"):
        np.testing.assert_array_equal(getattr(sol, field), getattr(again, field), err_msg=field)


def test_a_warm_start_lost_at_a_release_is_tried_again_from_the_rows_own_start():
    """A replay starts each row's tensions from the row before.  From a bend at up to 8 mm of pull
    to a release near 0 (the shared train.csv, ``rep1_pair12_same_dir0`` and its hold, with a robot
    fitted on half of that file), Newton from those tensions lost its way and the row failed
    (``newton_failed``).  Now the row is tried once more from its own start, and it converges to
    the row solved alone."""
    robot = load_robot(ROOT / "tests" / "data" / "ftdcr_v4_half_fitted.json")
    commands = 1e-3 * np.array([[4.801361, -2.485049, -2.500389, 7.823303, -8.145439, -0.01534, 4.801361, -8.344857,
                                 4.770681],
                                [0.0, -0.092039, -0.092039, 0.690291, -0.84369, -0.01534, -0.01534, -1.963496, 0.0]])
    together = replay(robot, commands)
    assert together.converged.all(), together.status
    alone = replay(robot, commands[1:], motion=together.motion[1:])
    np.testing.assert_allclose(together.tip_position[1], alone.tip_position[0], rtol=0, atol=1e-7)


def _write(tmp_path, text: str, name: str = "c.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


HEADER = "timestamp,pattern_label," + ",".join(f"servo_{s}_mm" for s in (4, 3, 9, 5, 2, 8, 6, 1, 7)) + \
    ",tip_x,tip_y,tip_z\n"


def test_a_recording_takes_its_rows_in_order_and_keeps_their_csv_numbers():
    robot = load_robot(EXAMPLE)
    rec = read_recording(SAMPLE, robot)
    keep = np.arange(len(rec.time)) % 3 == 1
    fold = rec.take(keep)
    assert fold.rows.tolist() == (np.nonzero(keep)[0] + 1).tolist() and fold.header == rec.header
    for name in ("time", "labels", "commands", "measured"):
        np.testing.assert_array_equal(getattr(fold, name), getattr(rec, name)[keep])
    assert len(rec.take(np.zeros(len(rec.time), dtype=bool)).time) == 0


def test_bad_recordings_name_the_column_and_row(tmp_path):
    robot = load_robot(EXAMPLE)
    row = lambda t, x="0": f"{t},p,{x},0,0,0,0,0,0,0,0,1,2,180\n"  # noqa: E731
    with pytest.raises(RobotFileError, match="missing column servo_7_mm"):
        read_recording(_write(tmp_path, HEADER.replace(",servo_7_mm", "") + "1,p,0,0,0,0,0,0,0,0,1,2,180\n"), robot)
    with pytest.raises(RobotFileError, match="column servo_4_mm, row 2: not a finite number"):
        read_recording(_write(tmp_path, HEADER + row(1) + row(2, "nan")), robot)
    with pytest.raises(RobotFileError, match="column timestamp, row 3: timestamps must increase"):
        read_recording(_write(tmp_path, HEADER + row(1) + row(2) + row(2)), robot)
    rec = read_recording(_write(tmp_path, HEADER + row(1) + "2,p,0,0,0,0,0,0,0,0,0,,,\n" + row(3)), robot)
    assert rec.skipped == 1 and rec.has_measurement.tolist() == [True, False, True]
    for text, words in [("", "empty"), (HEADER, "no data rows"), (HEADER + row(1) + "2,p,0,0\n",
                                                                 "column servo_9_mm, row 2: not a finite number ('')")]:
        with pytest.raises(RobotFileError, match=re.escape(words)):
            read_recording(_write(tmp_path, text), robot)
    (tmp_path / "b.csv").write_bytes(b"\x00\xff\xfe")
    with pytest.raises(RobotFileError, match="not a UTF-8 CSV"):
        read_recording(tmp_path / "b.csv", robot)


def test_replay_names_bad_commands_times_and_motions():
    """The Python API refuses what the CSV reader refuses: a NaN command once replayed silently as a
    tension-driven tendon at 0 N (NaN marks a field "not given" inside a design)."""
    robot = load_robot(EXAMPLE)
    good = np.zeros((3, robot.n_tendons))
    nan = good.copy()
    nan[2, 4] = np.nan
    for kwargs, words in [({"commands": np.zeros(robot.n_tendons)}, "got shape (9,)"),
                          ({"commands": np.zeros((3, 5))}, "got shape (3, 5)"),
                          ({"commands": np.zeros((0, robot.n_tendons))}, "got shape (0, 9)"),
                          ({"commands": nan}, "commands[2, 4] (row, tendon): not a finite number"),
                          ({"time": np.array([0.0, 1.0, 1.0])}, "time: must be (3,) finite seconds that increase"),
                          ({"time": np.array([0.0, 1.0])}, "time: must be (3,)"),
                          ({"motion": np.zeros_like(good)}, "motion: must be (3, 9)")]:
        with pytest.raises(ValueError, match=re.escape(words)):
            replay(robot, **({"commands": good} | kwargs))
    motion = np.ones_like(good)
    motion[1:, 0] = -1.0
    assert (replay(robot, good, time=np.arange(3.0), motion=motion).motion == motion).all()


def test_a_spreadsheets_csv_reads_as_the_plain_one(tmp_path):
    """A byte-order mark, Windows line ends and blank lines (a spreadsheet's export) change nothing but
    the rows' CSV numbers, which count the blank lines."""
    robot = load_robot(EXAMPLE)
    row = lambda t, x: f"{t},p,{x},0,0,0,0,0,0,0,0,1,2,180\n"  # noqa: E731
    plain = read_recording(_write(tmp_path, HEADER + row(1, 0.5) + row(2, 1.0)), robot)
    (tmp_path / "s.csv").write_bytes(b"\xef\xbb\xbf" + (HEADER + "\n" + row(1, 0.5) + " , \n" + row(2, 1.0) + "\n")
                                     .replace("\n", "\r\n").encode())
    sheet = read_recording(tmp_path / "s.csv", robot)
    for name in ("time", "labels", "commands", "measured"):
        np.testing.assert_array_equal(getattr(sheet, name), getattr(plain, name))
    assert plain.rows.tolist() == [1, 2] and sheet.rows.tolist() == [2, 4]


def test_bad_robot_files_name_the_key(tmp_path):
    good = json.loads(EXAMPLE.read_text())
    for change, words in [(lambda d: d["actuation"].update(unit="inch"), "actuation.unit: must be one of"),
                          (lambda d: d["actuation"].update(columns=["a"]), "actuation.columns: must be a list of 9"),
                          (lambda d: d["design"]["tendons"][2].update(friction=-1), "design.tendons[2].friction"),
                          (lambda d: d["design"]["tendons"][0].update(motion="push"), "design.tendons[0].motion"),
                          (lambda d: d["measurement"].update(marker=[0, 0]), "measurement.marker"),
                          (lambda d: d["measurement"].update(marker=[0, 0, "1"]), "measurement.marker: must be a list"),
                          (lambda d: d["measurement"].update(base_position=[[0], 0, 0]), "measurement.base_position"),
                          (lambda d: d["actuation"].update(kind=["tension"]), "actuation.kind: must be one of"),
                          (lambda d: d["measurement"].update(time_constant=-0.1), "measurement.time_constant: must"),
                          (lambda d: d.update(time_column=7), "time_column: must be a column's name"),
                          (lambda d: d.update(time_column=None), "time_column: must be a column's name"),
                          (lambda d: d.update(label_column=""), "label_column: must be a column's name"),
                          (lambda d: d.pop("measurement"), "measurement: missing")]:
        data = json.loads(json.dumps(good))
        change(data)
        with pytest.raises(RobotFileError, match=words.replace("[", r"\[").replace("]", r"\]")):
            load_robot(data)


def test_the_cli_replays_and_exits_2_on_bad_input(tmp_path):
    out = tmp_path / "pred.csv"
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "replay", str(EXAMPLE), str(SAMPLE), "--out", str(out),
                          "--quiet"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["rows"] == len(out.read_text().splitlines()) - 1 and summary["errors"]["rows"] == summary["rows"]
    # the rate is the replay's own: the first call's load of the compiled kernel is reported apart
    assert summary["startup_seconds"] > 0 and summary["rows_per_second"] == summary["rows"] / summary["seconds"]
    assert out.read_text().splitlines()[0] == "timestamp,pattern_label,tip_x,tip_y,tip_z,status"
    bad = _write(tmp_path, HEADER + "1,p,0,0,0,0,0,0,0,0,0,1,2,180\n0.5,p,0,0,0,0,0,0,0,0,0,1,2,180\n")
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "replay", str(EXAMPLE), str(bad), "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and "column timestamp, row 2" in run.stderr and "Traceback" not in run.stderr


def _in_gravity(data: dict) -> dict:
    """The example robot file without friction, in gravity along the base's -z (standing upright, tilted)."""
    data = json.loads(json.dumps(data))
    for tendon in data["design"]["tendons"]:
        tendon["friction"] = 0.0
    data["design"] |= {"gravity": [0.0, 3.0, -9.81], "density": 7800.0}
    return data


def _recorded_by(truth, rows: int | None = None):
    """The sample's commands and times (its first ``rows``; None: all) with the tips the robot
    ``truth`` replays (under its loads, if any) as the measurement: (that recording, the replay)."""
    rec = read_recording(SAMPLE, truth)
    rec = rec if rows is None else rec.take(np.arange(len(rec.time)) < rows)
    answer = replay(truth, rec.commands, time=rec.time)
    return replace(rec, measured=answer.points), answer


def _replay_in_gravity(robot, rows: int = 6):
    """The first ``rows`` rows of the shared sample replayed by a robot with loads, checked against
    each row's own loaded solve (the replay's Newton starts from shared Jacobians, a sequence: the
    same equilibria to its tolerances).  Returns (the replay, the commands, the times)."""
    assert robot.loads is not None
    recording = read_recording(SAMPLE, robot)
    commands, time = recording.commands[:rows], recording.time[:rows]
    answer = replay(robot, commands, time=time)
    direct = solve(robot.designs(commands), np.ones(1), loads=robot.row_loads(rows), options=REPLAY_OPTIONS)
    assert answer.converged.all() and direct.converged.all()
    assert robot.row_loads(rows).gravity[0, 2] == -9.81  # the file's loads, row by row
    np.testing.assert_allclose(answer.tip_position, direct.backbone[:, -1], rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(answer.tension, direct.tension, rtol=0.0, atol=1e-6)
    return answer, commands, time


def test_a_robot_file_with_gravity_replays_every_row_in_gravity(tmp_path):
    """The design's loads reach every command row: the replay equals each row's loaded solve, differs
    from the replay without them, and the robot file written keeps them."""

    data = _in_gravity(json.loads(EXAMPLE.read_text()))
    robot = load_robot(data)
    answer, commands, _ = _replay_in_gravity(robot)
    unloaded = replay(load_robot(data | {"design": {k: v for k, v in data["design"].items()
                                                    if k not in ("gravity", "density")}}), commands)
    assert np.abs(answer.tip_position - unloaded.tip_position).max() > 1e-4  # the weight moved the tips
    robot.save(tmp_path / "robot.json")
    again = load_robot(tmp_path / "robot.json")
    np.testing.assert_array_equal(again.loads.gravity, robot.loads.gravity)
    np.testing.assert_array_equal(again.loads.density, robot.loads.density)
    pushed = data | {"design": {k: v for k, v in data["design"].items() if k not in ("gravity", "density")}
                     | {"tip_force": [0.0, 0.01, 0.0]}}  # a tip force alone: no weight written
    load_robot(pushed).save(tmp_path / "pushed.json")
    written = json.loads((tmp_path / "pushed.json").read_text())["design"]
    assert written["tip_force"] == [0.0, 0.01, 0.0] and "density" not in written and "gravity" not in written
    np.testing.assert_array_equal(load_robot(tmp_path / "pushed.json").loads.tip_force, [[0.0, 0.01, 0.0]])


def test_an_effective_density_with_disks_is_taken_and_the_bound_is_named():
    """A robot's density is its mass per length over the rod's cross-section, disks included:
    opencr-mujoco's FTDCR files give 37,708 kg/m^3, above any metal's, and load; beyond the bound
    the message names the field."""
    data = _in_gravity(json.loads(EXAMPLE.read_text()))
    data["design"]["density"] = 37_708.0
    assert load_robot(data).loads.density[0] == 37_708.0
    data["design"]["density"] = 100_001.0
    with pytest.raises(RobotFileError, match=r"design\.density: must be in \(0, 100000\] kg/m\^3, got 100001"):
        load_robot(data)


def test_a_fitted_robot_with_friction_replays_in_gravity():
    """The shipped fitted robot (friction on its tendons) in gravity: every row converges, each row's
    answer is its own loaded solve with friction, and friction still moves the tips there."""
    fitted = json.loads((ROOT / "examples" / "ftdcr_v4_fitted.json").read_text())
    fitted["design"] |= {"gravity": [0.0, 3.0, -9.81], "density": 7800.0}
    fitted["actuation"]["creep_rate"] = 0.0  # each row its own loaded solve (creep in gravity: test_creep.py)
    robot = load_robot(fitted)
    assert (robot.design.resolved("friction") > 0).any()
    answer, commands, time = _replay_in_gravity(robot)
    frictionless = replay(replace(robot, design=robot.design.replace(friction=np.zeros_like(robot.design.offset))),
                          commands, time=time)
    assert np.abs(answer.tip_position - frictionless.tip_position).max() > 2e-5  # 90 um on these rows


@pytest.mark.parametrize("rate", [0.0, 0.05], ids=["rows", "a creeping chain"])
def test_a_progress_bar_under_loads_changes_no_answer(monkeypatch, capsys, rate):
    """With a progress bar a replay under loads solves its rows a chunk at a time (here 8, so that
    the chunks keep the batch's Jacobian leaders) and tells the bar of each; its answers are those of
    the whole batch bit for bit, and the bar counts every row once (a creeping chain: once per sweep,
    at least two)."""
    from tdcr.physics import cosserat

    fitted = json.loads((ROOT / "examples" / "ftdcr_v4_fitted.json").read_text())
    fitted["design"] |= {"gravity": [0.0, 3.0, -9.81], "density": 7800.0}
    fitted["actuation"]["creep_rate"] = rate
    robot = load_robot(fitted)
    recording = read_recording(SAMPLE, robot)
    commands, time = recording.commands[:20], recording.time[:20]
    whole = replay(robot, commands, time=time)
    assert capsys.readouterr().err == ""  # no bar unless asked
    monkeypatch.setattr(cosserat, "LOADED_CHUNK", 8)
    told: list[int] = []
    problem = {"designs": robot.designs(commands), "fractions": np.linspace(0.0, 1.0, 5),
               "loads": robot.row_loads(20), "options": REPLAY_OPTIONS, "sequence": True,
               "creep": robot.creep(time) if robot.creeps else None}
    in_chunks, at_once = solve(**problem, progress=told.append), solve(**problem)
    sweeps = len(told) // 3
    assert told == [8, 8, 4] * sweeps and sweeps >= (2 if rate else 1)
    for f in fields(at_once):  # every field of the chunks' answers joined
        if isinstance(getattr(at_once, f.name), np.ndarray):
            np.testing.assert_array_equal(getattr(in_chunks, f.name), getattr(at_once, f.name), err_msg=f.name)
    chunked = replay(robot, commands, time=time, progress=True)
    for f in fields(chunked):
        np.testing.assert_array_equal(getattr(chunked, f.name), getattr(whole, f.name), err_msg=f.name)
    assert whole.converged.all() and ("replay, sweep 1" if rate else "replay") in capsys.readouterr().err


def test_a_fit_under_loads_recovers_a_known_robot_in_gravity(tmp_path):
    """A recording made by the loaded solver from a known robot lying in gravity (its tips sag by
    about 5 mm): the fit under the robot file's loads (a first round without them, then rounds of
    least squares, each with the loads' shift held) finds E and the drive zeros again, each kept
    round lowers the loaded replay's error, and it ends far below the same fit without the loads;
    the CLI writes the loads back."""
    from tdcr.search.fit import errors, fit

    data = _in_gravity(json.loads(EXAMPLE.read_text()))
    data["design"] |= {"gravity": [9.81, 0.0, 0.0], "density": 40_000.0}  # lying on its side, heavy
    truth = load_robot(data)
    truth = replace(truth, design=truth.design.replace(zero=KNOWN_ZEROS))
    made, _ = _recorded_by(truth)
    start = replace(truth, design=truth.design.replace(E=np.array([40e9]), zero=np.zeros((1, 9))))
    options = {"groups": ("E", "zero"), "loss": "linear", "prior": None, "max_iterations": 20, "budget": 300}
    result = fit(start, made, **options)
    assert result.robot.loads is not None and result.train_replay.converged.all()
    rmse = [e.rmse for e in result.load_rounds]  # mm: after the first round (fitted without the loads), ...
    assert len(rmse) >= 3 and all(b < a for a, b in zip(rmse, rmse[1:], strict=False))
    assert rmse[-1] == pytest.approx(result.train.rmse)
    assert result.initial.rmse > 3.0 and result.train.rmse < 0.1  # 0.034 mm
    values = {p.name: p.value for p in result.parameters}
    assert values["E"] == pytest.approx(50e9, rel=2e-3)
    taut = replay(truth, made.commands).tension.max(axis=0) > 0.0  # a tendon slack throughout shows no zero
    zeros = np.array([values[f"zero[{i}]"] for i in range(9)])
    np.testing.assert_allclose(zeros[taut], truth.design.resolved("zero")[0, taut], atol=3e-5)  # 21 um
    spent = fit(start, made, **(options | {"budget": 0.0}))  # no time to search: the start, replayed under loads
    loaded_start = errors(replay(start, made.commands, time=made.time), made)
    assert len(spent.load_rounds) == 1 and spent.train.rmse == pytest.approx(loaded_start.rmse, rel=1e-9)
    without = fit(replace(start, loads=None), made, **options)
    assert without.train.rmse > 3.0 * result.train.rmse  # 0.87 mm: the weight is not a matter of E and zeros

    path = tmp_path / "robot.json"  # the sample's own measurements, the robot upright in gravity
    load_robot(_in_gravity(json.loads(EXAMPLE.read_text()))).save(path)
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "fit", str(path), str(SAMPLE), "--fit", "E,zero",
                          "--quiet", "--out", str(tmp_path / "fitted.json")], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert report["train"]["rmse_mm"] == pytest.approx(report["load_rounds"][-1]["rmse_mm"])
    assert report["train"]["rmse_mm"] < report["initial_train"]["rmse_mm"]
    assert load_robot(tmp_path / "fitted.json").loads.gravity.tolist() == [[0.0, 3.0, -9.81]]


def test_a_fit_under_loads_starts_again_from_the_start_when_the_first_rounds_values_buckle():
    """A soft robot standing upright in gravity near its buckling load (E 15 GPa at 90,000 kg/m^3: the
    heavy column's critical E is about 11.8 GPa), on the sample's first 20 rows.  The fit without the
    loads lowers E far below that, to bend as far as the weight does, and under the weight those
    values buckle: every row fails.  The fit under the loads must then go on from the start replayed
    under them (its first round's errors are the start's), never from the buckled values, and find E
    again."""
    from tdcr.search.fit import errors, fit

    data = _in_gravity(json.loads(EXAMPLE.read_text()))
    data["design"] |= {"E": 15e9, "gravity": [0.0, 0.0, -9.81], "density": 90_000.0}
    truth = load_robot(data)
    truth = replace(truth, design=truth.design.replace(zero=KNOWN_ZEROS))
    made, measured = _recorded_by(truth, rows=20)
    assert measured.converged.all()
    start = replace(truth, design=truth.design.replace(zero=np.zeros((1, 9))))
    options = {"groups": ("E", "zero"), "loss": "linear", "prior": None, "max_iterations": 20, "budget": 300}

    without = fit(replace(start, loads=None), made, **options)  # what the first round finds
    assert without.robot.design.E[0] < 8e9  # 5.4 GPa
    buckled = replay(replace(without.robot, loads=truth.loads), made.commands, time=made.time)
    assert buckled.converged.mean() < 0.5  # none of the 20 rows stands under the weight

    result = fit(start, made, **options)
    loaded_start = errors(replay(start, made.commands, time=made.time), made)
    rmse = [e.rmse for e in result.load_rounds]  # mm: 3.14 (the start), 1.16, 0.93, 0.47, 0.34, 0.20
    assert rmse[0] == pytest.approx(loaded_start.rmse, rel=1e-9)
    assert len(rmse) >= 3 and all(b < a for a, b in zip(rmse, rmse[1:], strict=False))
    assert result.train_replay.converged.all() and result.train.rmse < 0.2 * loaded_start.rmse
    assert result.robot.design.E[0] == pytest.approx(15e9, rel=0.05)  # 15.2 GPa

def test_the_robot_schema_is_committed_and_the_example_follows_it():
    import jsonschema

    from tdcr.robot.real import robot_schema

    committed = json.loads((ROOT / "openapi" / "robot.schema.json").read_text())
    assert committed == json.loads(json.dumps(robot_schema())), "run: tdcr openapi"
    jsonschema.validate(json.loads(EXAMPLE.read_text()), committed)
    # the schema and the loader agree on a null column: no labels, but a recording always has its times
    unlabelled = json.loads(EXAMPLE.read_text()) | {"label_column": None}
    jsonschema.validate(unlabelled, committed)
    assert load_robot(unlabelled).label_column is None
    timeless = unlabelled | {"time_column": None}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(timeless, committed)
    with pytest.raises(RobotFileError, match="time_column: must be a column's name"):
        load_robot(timeless)
    robot = load_robot(EXAMPLE)
    assert load_robot(robot.to_json()).to_json() == robot.to_json()  # a saved robot file reads back the same


def test_a_robot_file_asked_of_the_solver_validates_its_design_once(monkeypatch):
    """``/exact`` and ``tdcr solve`` take a robot file through ``validate_json``: its design passes the
    one validation path once (with the caller's limits), the rest of the file the checks of
    ``load_robot`` (:func:`tdcr.robot.real.robot_from`), which give the same robot."""
    import tdcr.api.validation as validation
    from tdcr.robot.real import robot_from

    data = json.loads(FITTED.read_text())
    calls = []
    real = validation.validate_json

    def counted(body, **options):
        calls.append(body)
        return real(body, **options)

    monkeypatch.setattr(validation, "validate_json", counted)
    request = validation.validate_json(data, target="solver")
    assert len(calls) == 2 and calls[1] == {"designs": [data["design"]]}  # the file, then its design alone
    assert robot_from(data, request.groups[0]).to_json() == load_robot(data).to_json()


def test_fit_recovers_a_known_robot_from_its_own_replay():
    """A recording made by the solver from a known robot (with friction): the fit, started from
    perturbed values, finds E, the drive zeros and the base position again and replays it to ~0 error."""

    from tdcr.search.fit import fit

    truth = load_robot(EXAMPLE)
    truth = replace(truth, design=truth.design.replace(friction=np.full((1, 9), 0.1),
                                                       zero=KNOWN_ZEROS),
                    measurement=replace(truth.measurement, base_position=np.array([0.002, -0.001, -0.004]),
                                        time_constant=0.35))
    made, _ = _recorded_by(truth)
    start = replace(truth, design=truth.design.replace(E=np.array([40e9]), zero=np.zeros((1, 9))),
                    measurement=replace(truth.measurement, base_position=np.zeros(3), time_constant=0.0))
    result = fit(start, made, groups=("E", "zero", "base_position", "time_constant"), loss="linear", prior=None,
                 max_iterations=20, budget=120)
    assert result.initial.rmse > 2.0 and result.train.rmse < 0.05  # mm
    values = {p.name: p.value for p in result.parameters}
    assert values["E"] == pytest.approx(50e9, rel=2e-2)
    taut = replay(truth, made.commands).tension.max(axis=0) > 0.0  # a tendon slack throughout shows no zero
    assert taut.sum() >= 7
    np.testing.assert_allclose(np.array([values[f"zero[{i}]"] for i in range(9)])[taut],
                               truth.design.resolved("zero")[0, taut], atol=2e-5)
    np.testing.assert_allclose([values[f"base_position[{i}]"] for i in range(3)], [0.002, -0.001, -0.004], atol=2e-4)
    assert values["time_constant"] == pytest.approx(0.35, rel=2e-2)


def test_fit_finds_where_the_segments_end_and_keeps_the_tip_segment_at_the_tip():
    """The ``end`` group: a recording made by a known robot whose first two segments end 6 mm further
    and 7.5 mm nearer than its file says; the fit from the file's ends finds both again, and the
    tendons that end at the tip stay there.  A robot whose tendons all end at the tip has no end to
    fit, and says so."""
    from tdcr.search.fit import check_groups, fit

    start = load_robot(EXAMPLE)
    ends = start.design.ends.copy()  # (1, 9): 0.06, 0.1225 and L = 0.1865 m, three tendons each
    truth_ends = np.where(ends == 0.06, 0.066, np.where(ends == 0.1225, 0.115, ends))
    truth = replace(start, design=start.design.replace(end=truth_ends))
    made, _ = _recorded_by(truth)
    result = fit(start, made, groups=("end",), prior=None, max_iterations=20, budget=120)
    values = {p.name: p.value for p in result.parameters}
    assert list(values) == ["end[0]", "end[1]"] and all(p.unit == "m" for p in result.parameters)
    assert values["end[0]"] == pytest.approx(0.066, abs=2e-4) and values["end[1]"] == pytest.approx(0.115, abs=2e-4)
    np.testing.assert_allclose(result.robot.design.ends, truth_ends, rtol=0, atol=2e-4)
    assert result.initial.rmse > 1.0 and result.train.rmse < 0.05  # mm
    at_tip = replace(start, design=start.design.replace(end=np.full_like(ends, start.design.L[0])))
    assert "every tendon of this robot ends at the tip" in check_groups(("E", "end"), at_tip)
    assert check_groups(("E", "end"), start) is None


def test_the_lag_is_the_step_response_of_a_first_order_system():
    """eq. LAG against its closed form: after a step of the equilibrium from a to b at row 1, the
    measured point at row k >= 1 is b + (a - b) exp(-(t_k - t_0) / T) for uneven sample times; T = 0
    shows the equilibria as they are; a row that is not finite passes through and the next starts
    afresh; the robot's measured points with the rows' times are the lag of its static points."""

    from tdcr.robot.real import settle

    t = np.array([0.0, 0.4, 1.1, 1.5, 3.0, 3.2])
    a, b = np.array([1.0, -2.0, 0.5]), np.array([0.0, 1.0, 2.5])
    q = np.array([a] + [b] * 5)
    expected = b + (a - b) * np.exp(-(t - t[0]) / 0.7)[:, None]
    np.testing.assert_allclose(settle(q, t, 0.7), expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(settle(q, t, 0.0), q)
    q_nan = q.copy()
    q_nan[2] = np.nan
    lagged = settle(q_nan, t, 0.7)
    assert np.isnan(lagged[2]).all()
    np.testing.assert_array_equal(lagged[3], b)  # afresh from its own equilibrium
    np.testing.assert_allclose(lagged[4:], np.tile(b, (2, 1)), rtol=0, atol=1e-15)
    robot = load_robot(EXAMPLE)
    lagging = replace(robot.measurement, time_constant=0.3, marker=np.array([0.0, 0.003, 0.008]),
                      base_rotation=np.array([0.1, -0.2, 0.3]))
    rec = read_recording(SAMPLE, robot)
    answer = replay(robot, rec.commands)
    np.testing.assert_allclose(lagging.points(answer.tip_position, answer.tip_rotation, rec.time),
                               settle(lagging.points(answer.tip_position, answer.tip_rotation), rec.time, 0.3),
                               rtol=0, atol=1e-15)


def test_tdcr_solve_takes_a_robot_file():
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "solve", str(ROOT / "examples" / "ftdcr_v4_fitted.json")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (result,) = json.loads(run.stdout)["results"]
    assert result["status"] == "converged" and len(result["tension_profile"][0]) == 9


def test_register_finds_a_base_turned_by_half_a_turn_and_the_fit_starts_there():
    """The rigid registration (Kabsch) of a replay to points measured in a frame turned by about
    half a turn recovers that base pose exactly (same physics): least squares from the file's pose
    could not; the fit then starts from it and ends at ~0 error."""

    from tdcr.search.fit import fit, register

    robot = load_robot(EXAMPLE)
    turned = np.array([0.03, -0.02, 2.9])
    truth = replace(robot, measurement=replace(robot.measurement, base_position=np.array([0.01, -0.02, 0.005]),
                                               base_rotation=turned))
    rec = read_recording(SAMPLE, truth)
    answer = replay(robot, rec.commands)
    made = replace(rec, measured=truth.measurement.points(answer.tip_position, answer.tip_rotation))
    found = register(robot, answer, made).measurement
    np.testing.assert_allclose(found.base_rotation, turned, atol=1e-9)
    np.testing.assert_allclose(found.base_position, truth.measurement.base_position, atol=1e-9)
    result = fit(robot, made, groups=("base_position", "base_rotation"), max_iterations=3, budget=60)
    assert result.initial.rmse > 50.0 and result.train.rmse < 1e-3  # mm


def test_the_cli_checks_where_it_will_write_before_it_works(tmp_path):
    """An --out in no folder, or one that is a folder, exits 2 at once (a fit would lose its work at the end)."""
    for command, extra in [("replay", []), ("fit", ["--max-iterations", "1"])]:
        for out, words in [(tmp_path / "none" / "o.csv", "no folder"), (tmp_path, "is a directory")]:
            run = subprocess.run([sys.executable, "-m", "tdcr.cli", command, str(EXAMPLE), str(SAMPLE), *extra,
                                  "--out", str(out)], capture_output=True, text=True, timeout=60)
            assert run.returncode == 2 and "argument --out: " in run.stderr, run.stderr
            assert words in run.stderr and "Traceback" not in run.stderr


def test_a_fit_on_fewer_residuals_than_parameters_reports_no_standard_errors():
    """One measured row (3 coordinates) cannot fix a base rotation (the registration keeps the file's)
    nor a residual variance: the fit still runs and every standard error is unbounded (null)."""
    from tdcr.search.fit import fit, register

    robot = load_robot(EXAMPLE)
    rec = read_recording(SAMPLE, robot)
    one = rec.take(np.arange(len(rec.time)) == 3)
    answer = replay(robot, one.commands)
    assert register(robot, answer, one) is robot
    result = fit(robot, one, groups=("E", "marker", "base_position"), max_iterations=2, budget=60)
    assert len(result.parameters) == 7
    assert all(p.stderr == np.inf and p.stderr_independent == np.inf for p in result.parameters)
    assert all(p["stderr"] is None and p["stderr_independent"] is None for p in result.report()["parameters"])


def test_the_standard_errors_under_the_robust_loss_match_the_estimates_spread():
    """Huber's covariance scale (:func:`_covariance_scale`) against the spread it predicts: a location
    fitted with the soft-L1 loss (scipy's ``least_squares``, as the fit runs it) to 300 seeded samples
    of 200 points, 10 % of them 10x wider (gross errors).  The mean predicted standard error is the
    estimates' own standard deviation within 15 %; s^2 of plain least squares, taken at the same
    residuals, overstates it by more than 40 %.  For plain least squares the scale is s^2 exactly."""
    from scipy.optimize import least_squares

    from tdcr.search.fit import _covariance_scale

    rng = np.random.default_rng(7)
    n, f_scale = 200, 1.0
    estimates, predicted, plain = [], [], []
    for _ in range(300):
        y = rng.normal(0.0, 1.0, n) * np.where(rng.random(n) < 0.1, 10.0, 1.0)
        a = least_squares(lambda x, y=y: x[0] - y, [np.median(y)], loss="soft_l1", f_scale=f_scale).x[0]
        r = a - y
        estimates.append(a)
        predicted.append(np.sqrt(_covariance_scale(r, "soft_l1", f_scale, free=1) / n))  # (J^T J)^-1 = 1 / n
        plain.append(np.sqrt(float(r @ r) / (n - 1) / n))
    spread = np.std(estimates)
    assert abs(np.mean(predicted) / spread - 1.0) < 0.15
    assert np.mean(plain) / spread > 1.4
    r = rng.normal(size=50)
    assert _covariance_scale(r, "linear", f_scale, free=3) == pytest.approx(float(r @ r) / 47, rel=1e-14)


def test_the_clustered_standard_errors_match_the_spread_of_fits_whose_errors_last_a_sweep():
    """The cluster-robust sandwich (:func:`_covariance`) against the spread it predicts: a line
    y = a + b x fitted with the soft-L1 loss (as the fit runs it) to 300 seeded data sets of 40
    sweeps of 25 points, each sweep off by its own error (N(0, 1), as a model's error lasts a sweep)
    and at its own x, with N(0, 0.5) noise per point.  The mean predicted standard error of a and
    of b is the estimates' own standard deviation within 15 %; taken as independent (Huber's scale,
    ``groups=None``, 0 clusters), it is under 0.4 of it."""
    from scipy.optimize import least_squares

    from tdcr.search.fit import _covariance, _covariance_scale

    rng = np.random.default_rng(11)
    sweeps, points, f_scale = 40, 25, 1.0
    group = np.repeat(np.arange(sweeps), points)
    estimates, clustered, independent = [], [], []
    for _ in range(300):
        x = (rng.normal(size=sweeps)[group] + 0.1 * rng.normal(size=group.size))
        y = 1.0 + 2.0 * x + rng.normal(size=sweeps)[group] + rng.normal(0.0, 0.5, group.size)
        jac = np.stack([np.ones_like(x), x], axis=1)  # d r / d (a, b), r = a + b x - y
        fitted = least_squares(lambda v, x=x, y=y: v[0] + v[1] * x - y, [0.0, 0.0], loss="soft_l1",
                               f_scale=f_scale).x
        r = jac @ fitted - y
        estimates.append(fitted)
        cov, count = _covariance(jac, r, loss="soft_l1", f_scale=f_scale, groups=group)
        assert count == sweeps
        clustered.append(np.sqrt(np.diag(cov)))
        cov, count = _covariance(jac, r, loss="soft_l1", f_scale=f_scale, groups=None)
        assert count == 0
        np.testing.assert_allclose(cov, _covariance_scale(r, "soft_l1", f_scale, free=2)
                                   * np.linalg.inv(jac.T @ jac), rtol=1e-10)
        independent.append(np.sqrt(np.diag(cov)))
    spread = np.std(estimates, axis=0)
    assert np.all(np.abs(np.mean(clustered, axis=0) / spread - 1.0) < 0.15), np.mean(clustered, axis=0) / spread
    assert np.all(np.mean(independent, axis=0) / spread < 0.4), np.mean(independent, axis=0) / spread
    one = _covariance(jac, r, loss="soft_l1", f_scale=f_scale, groups=np.zeros_like(group))  # one sweep
    assert one[1] == 0 and np.allclose(one[0], cov, rtol=1e-14)


def test_the_fits_clusters_are_the_recordings_patterns_or_its_runs_between_pauses():
    """With labels each pattern is a cluster (a ``_hold`` row with its sweep), and the fit reports
    over how many its standard errors were taken; without labels the runs between pauses are."""
    from tdcr.robot.real import Recording
    from tdcr.search.fit import CORRELATION_SHOWN, PLOT_GAP, clusters, fit

    robot = load_robot(EXAMPLE)
    rec = read_recording(SAMPLE, robot)
    patterns = {str(label).removesuffix("_hold") for label in rec.labels}
    found = clusters(rec)
    assert len(np.unique(found)) == len(patterns) > 1
    for label in rec.labels:  # one cluster per pattern, its hold included
        same = np.array([str(other).removesuffix("_hold") == str(label).removesuffix("_hold") for other in rec.labels])
        assert len(np.unique(found[same])) == 1
    time = np.concatenate([np.arange(5.0), 5.0 + PLOT_GAP + np.arange(3.0)])
    bare = Recording(time=time, labels=np.full(8, ""), commands=np.zeros((8, robot.n_tendons)),
                     measured=np.zeros((8, 3)), rows=np.arange(1, 9), header=rec.header)
    assert clusters(bare).tolist() == [0] * 5 + [1] * 3
    made = replace(rec, measured=replay(robot, rec.commands).points + 1e-4 * np.sin(np.arange(len(rec.time)))[:, None])
    result = fit(robot, made, groups=("marker", "base_position"), max_iterations=2, budget=60)
    assert result.stderr_clusters == len(patterns) and result.report()["stderr_clusters"] == len(patterns)
    assert all(0 < p.stderr < np.inf and 0 < p.stderr_independent < np.inf for p in result.parameters)
    assert all(p["stderr_independent"] > 0 for p in result.report()["parameters"])
    # a marker offset and the base's position trade where the tip turns little: listed, each pair once
    pairs = result.report()["correlations"]
    assert pairs and all(abs(p["r"]) >= CORRELATION_SHOWN for p in pairs)
    assert all({p["a"][:6], p["b"][:6]} == {"marker", "base_p"} for p in pairs)
    assert [abs(p["r"]) for p in pairs] == sorted((abs(p["r"]) for p in pairs), reverse=True)


def test_the_reported_correlations_are_those_of_the_estimates():
    """:func:`_correlations` of a linear model's covariance against the correlation of its estimates
    over 300 seeded data sets: two near-collinear slopes are listed, within 0.02 of it; the third,
    independent slope is in no listed pair, and a parameter not identified is left out."""
    from tdcr.search.fit import CORRELATION_SHOWN, _correlations

    rng = np.random.default_rng(5)
    n = 200
    x1 = rng.normal(size=n)
    jac = np.stack([x1, x1 + 0.1 * rng.normal(size=n), rng.normal(size=n)], axis=1)
    estimates = [np.linalg.lstsq(jac, jac @ np.array([1.0, 2.0, 3.0]) + rng.normal(size=n), rcond=None)[0]
                 for _ in range(300)]
    names = ("b1", "b2", "b3")
    (shown,) = _correlations(np.linalg.inv(jac.T @ jac), names, np.ones(3, dtype=bool))
    assert shown[:2] == ("b1", "b2") and shown[2] <= -CORRELATION_SHOWN
    assert abs(shown[2] - np.corrcoef(np.array(estimates).T)[0, 1]) < 0.02
    assert _correlations(np.linalg.inv(jac.T @ jac), names, np.array([True, False, True])) == ()


def test_a_parameter_the_data_do_not_move_is_reported_as_not_identified():
    """A lag of 2 ms under samples 0.5-11 s apart moves no measured point (exp(-250) = 0): its
    standard error is unbounded (inf, null in the report), not the pseudo-inverse's 0, while the
    marker beside it is identified."""

    from tdcr.search.fit import fit

    robot = load_robot(EXAMPLE)
    robot = replace(robot, measurement=replace(robot.measurement, time_constant=0.002))
    rec = read_recording(SAMPLE, robot)
    made = replace(rec, measured=replay(robot, rec.commands).points + 1e-4 * np.sin(np.arange(len(rec.time)))[:, None])
    result = fit(robot, made, groups=("marker", "time_constant"), max_iterations=2, budget=60)
    found = {p.name: p for p in result.parameters}
    assert found["time_constant"].stderr == np.inf and np.isfinite(found["marker[0]"].stderr)
    assert found["time_constant"].stderr_independent == np.inf
    reported = {p["name"]: p for p in result.report()["parameters"]}
    assert reported["time_constant"]["stderr"] is None and reported["marker[0]"]["stderr"] > 0


def _sweeps(truth):
    """A recording of single-tendon sweeps made by the solver: each tendon pulled in by 1-4 mm in
    turn while the others are released to -5 mm, measured as ``truth`` replays it."""
    from tdcr.robot.real import Recording

    n = truth.n_tendons
    commands = np.full((4 * n, n), -0.005)  # m
    for k in range(n):
        commands[4 * k:4 * k + 4, k] = np.arange(1, 5) * 1e-3
    header = read_recording(SAMPLE, truth).header
    return Recording(time=0.5 * np.arange(4 * n), labels=np.repeat([f"tendon{k}_pull" for k in range(n)], 4),
                     commands=commands, measured=replay(truth, commands).points, rows=np.arange(1, 4 * n + 1),
                     header=header)


@pytest.mark.parametrize("group", ["tendon_offset", "tendon_angle"])
def test_fit_recovers_each_tendons_offset_and_angle(group):
    """Holes drilled off their nominal radius, or turned off their nominal angle: a recording made
    by the solver with every tendon's offset (4.1-4.9 mm) or angle (+-0.1 rad) its own, fitted from
    the robot file's values with ``tendon_offset`` or ``tendon_angle`` (without the default prior),
    gives each taut tendon's value again and replays it to ~0 error."""

    from tdcr.search.fit import fit

    start = load_robot(EXAMPLE)
    wave = np.sin(np.arange(9) * 2.0)
    field, values, atol = (("offset", 0.0045 + 0.0004 * wave, 2e-6) if group == "tendon_offset"
                           else ("angle", start.design.angles[0] + 0.1 * wave, 2e-4))  # m, rad
    truth = replace(start, design=start.design.replace(**{field: values[None]}))
    made = _sweeps(truth)
    result = fit(start, made, groups=(group,), max_iterations=10, budget=120, prior=None)  # identifiability alone
    assert result.initial.rmse > 0.5 and result.train.rmse < 0.01  # mm
    found = getattr(result.robot.design, "angles" if field == "angle" else field)[0]
    assert [p.name for p in result.parameters] == [f"{group}[{i}]" for i in range(9)]
    np.testing.assert_allclose(found, values, rtol=0, atol=atol)


def test_the_tendons_common_turn_is_the_bases_and_their_differences_are_identified():
    """A turn of every tendon together is, but for the marker, a turn of the base about its axis:
    fitted with ``base_rotation``, the reported tendon turns have zero mean, the base rotation holds
    the common part, and each turn's standard error is that of the differences (small), not of the
    ridge the pair would leave."""

    from tdcr.search.fit import fit

    start = load_robot(EXAMPLE)
    wave = 0.1 * np.sin(np.arange(9) * 2.0)
    wave -= wave.mean()  # rad
    truth = replace(start, design=start.design.replace(angle=(start.design.angles[0] + wave)[None]),
                    measurement=replace(start.measurement, base_rotation=np.array([0.0, 0.0, 0.05])))
    result = fit(start, _sweeps(truth), groups=("tendon_angle", "base_rotation"), max_iterations=10, budget=120,
                 prior=None)  # identifiability alone (the default prior holds the turns near the file's)
    assert result.train.rmse < 0.01  # mm
    turns = [p for p in result.parameters if p.name.startswith("tendon_angle")]
    assert abs(sum(p.value for p in turns)) < 1e-12
    np.testing.assert_allclose([p.value for p in turns], wave, rtol=0, atol=1e-3)
    np.testing.assert_allclose(result.robot.measurement.base_rotation, [0.0, 0.0, 0.05], rtol=0, atol=1e-3)
    assert all(0.0 < p.stderr < 1e-3 for p in turns)


def test_a_prior_on_one_group_holds_that_group_and_frees_the_others():
    """``fit``'s ``prior`` per group: a narrow prior on ``tendon_angle`` holds the turns at the
    file's angles though the recording was made with others, while ``marker``, without a prior,
    still moves to the true marker; a prior on no group, or a width <= 0, is refused."""

    from tdcr.search.fit import fit

    start = load_robot(EXAMPLE)
    wave = 0.1 * np.sin(np.arange(9) * 2.0)  # rad
    marker = start.measurement.marker + np.array([0.0, 0.0, 0.004])  # m
    truth = replace(start, design=start.design.replace(angle=(start.design.angles[0] + wave)[None]),
                    measurement=replace(start.measurement, marker=marker))
    made = _sweeps(truth)
    held = fit(start, made, groups=("tendon_angle", "marker"), prior={"tendon_angle": 1e-3}, max_iterations=6,
               budget=120)
    np.testing.assert_allclose(held.robot.design.angles[0], start.design.angles[0], rtol=0, atol=2e-3)
    assert held.robot.extra["fitted"]["prior"] == {"tendon_angle": 1e-3}  # the report says what held them
    assert abs(held.robot.measurement.marker[2] - start.measurement.marker[2]) > 1e-3  # moved toward 4 mm more
    for prior, words in (({"tendon_angel": 1.0}, "unknown tendon_angel"), ({"marker": 0.0}, "must be > 0")):
        with pytest.raises(ValueError, match=words):
            fit(start, made, groups=("marker",), prior=prior)
    for options, words in (({"loss": "cauchy"}, "loss: one of linear, soft_l1"),
                           ({"f_scale": 0.0}, "f_scale: must be a number of mm > 0")):
        with pytest.raises(ValueError, match=words):
            fit(start, made, groups=("marker",), **options)


def test_a_prior_is_read_as_it_is_written():
    """The CLI's ``--prior`` text: ``GROUP=WIDTH[,...]`` or ``none``, and the default written back."""
    from tdcr.search.fit import PRIOR, format_prior, parse_prior

    assert parse_prior(format_prior(PRIOR)) == dict(PRIOR)
    assert parse_prior(" tendon_angle = 0.2 , marker=1e-1") == {"tendon_angle": 0.2, "marker": 0.1}
    assert parse_prior("none") is None and format_prior(None) == "none"
    for text, words in (("tendon_angle", "expected GROUP=WIDTH"), ("tendon_angle=wide", "expected GROUP=WIDTH"),
                        ("turns=0.2", "unknown turns"), ("marker=-1", "must be > 0"), ("marker=nan", "must be > 0")):
        with pytest.raises(ValueError, match=words):
            parse_prior(text)


def test_a_recording_without_labels_has_no_patterns():
    """Without a label column every row's label is empty: the errors then list no pattern (not one
    named ""), and with labels each ``_hold`` row counts with its pattern."""
    from tdcr.search.fit import errors

    robot = load_robot(EXAMPLE)
    recording = read_recording(SAMPLE, robot)
    answer = replay(robot, recording.commands, time=recording.time)
    assert errors(answer, replace(recording, labels=np.full(len(recording.time), ""))).per_pattern == {}
    labelled = errors(answer, recording).per_pattern
    assert labelled and "" not in labelled and not any(k.endswith("_hold") for k in labelled)


def test_the_plots_lines_break_where_the_recording_pauses():
    """A row more than PLOT_GAP median intervals after the one before starts a new line."""
    from tdcr.search.fit import PLOT_GAP, pauses

    steady = np.arange(10) * 0.6
    paused = np.concatenate([steady, steady[-1] + 0.6 * PLOT_GAP + 0.1 + steady])
    assert pauses(steady).size == 0 and pauses(paused).tolist() == [10]
    assert pauses(np.append(steady, steady[-1] + 0.6 * PLOT_GAP)).size == 0  # at the bound: no pause
    assert pauses(np.array([3.0])).size == 0


def test_the_cli_fits_and_exits_2_on_groups_it_cannot_fit(tmp_path):
    from tdcr.search.fit import LOSS

    out, png = tmp_path / "fitted.json", tmp_path / "fit.png"
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "fit", str(EXAMPLE), str(SAMPLE), "--validate", str(SAMPLE),
                          "--fit", "marker,time_constant", "--max-iterations", "2", "--out", str(out), "--plot",
                          str(png), "--quiet", "--prior", "marker=0.5"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    fitted = load_robot(out)
    report = fitted.extra["fitted"]
    assert [p["name"] for p in report["parameters"]] == ["marker[0]", "marker[1]", "marker[2]", "time_constant"]
    assert [p["group"] for p in report["parameters"]] == ["marker"] * 3 + ["time_constant"]
    # the report says how it was searched: the groups, the loss and the prior given
    assert report["groups"] == ["marker", "time_constant"] and report["loss"] == LOSS
    assert report["prior"] == {"marker": 0.5}
    assert report["train"]["rmse_mm"] <= report["initial_train"]["rmse_mm"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for options, words in [(["--fit", "offset,tendon_offset"], "offset and tendon_offset set the same values"),
                            (["--fit", "angle,tendon_angle"], "angle and tendon_angle set the same values"),
                            (["--fit", "elasticity,stiffness"], "elasticity and stiffness set the same values"),
                            (["--fit", "E,bending"], "--fit: unknown bending"),
                            (["--fit", " , "], "--fit: name at least one group; they are E, zero"),
                            (["--prior", "tendon_angel=0.2"], "--prior: unknown tendon_angel; the groups are"),
                            (["--prior", "marker=0"], "--prior: a width must be > 0"),
                            (["--prior", "marker"], "expected GROUP=WIDTH"),
                            (["--f-scale", "0"], "--f-scale: must be a number of mm > 0"),
                            (["--loss", "cauchy"], "invalid choice: 'cauchy'"),
                            (["--max-iterations", "0"], "--max-iterations: must be at least 1, got 0"),
                            (["--budget", "nan"], "--budget: must be a finite number, got nan"),
                            (["--budget", "0"], "--budget: must be above 0 s"),
                            (["--workers", "-1"], "--workers: must be at least 0, got -1"),
                            (["--plot", str(tmp_path / "none" / "fit.png")], f"no folder {tmp_path / 'none'}"),
                            (["--validate", str(_write(tmp_path, HEADER, "header_only.csv"))], "no data rows")]:
        run = subprocess.run([sys.executable, "-m", "tdcr.cli", "fit", str(EXAMPLE), str(SAMPLE), *options,
                              "--out", str(tmp_path / "no.json")], capture_output=True, text=True, timeout=300)
        assert run.returncode == 2 and words in run.stderr and "Traceback" not in run.stderr, run.stderr
        assert not (tmp_path / "no.json").exists()


def test_a_robot_commanded_in_tensions_fits_without_the_groups_that_act_on_displacements(tmp_path):
    """Drives that command tensions: a drive's zero and the series compliance act on nothing, so the
    default groups leave them out (they would drift unidentified into the fitted file) and naming
    one is refused, by the API and by the CLI (exit 2).  The fit finds E, here the one parameter
    that moves the tips, from perturbed values."""
    from tdcr.robot.real import Recording
    from tdcr.search.fit import DISPLACEMENT_ONLY, default_groups, fit

    data = json.loads(EXAMPLE.read_text())
    data["actuation"] |= {"unit": "N", "kind": "tension", "deadband": 0.0}
    for tendon in data["design"]["tendons"]:
        tendon.pop("displacement", None)
        tendon["tension"] = 0.0
    truth = load_robot(data)
    assert set(default_groups(truth)).isdisjoint(DISPLACEMENT_ONLY)
    n = truth.n_tendons
    commands = np.zeros((3 * n, n))  # N: each tendon pulled with 0.5, 1 and 1.5 N in turn
    for k in range(n):
        commands[3 * k:3 * k + 3, k] = [0.5, 1.0, 1.5]
    made = Recording(time=0.5 * np.arange(3 * n), labels=np.repeat([f"t{k}" for k in range(n)], 3), commands=commands,
                     measured=replay(truth, commands).points, rows=np.arange(1, 3 * n + 1), header=())
    start = replace(truth, design=truth.design.replace(E=truth.design.E * 0.7))
    result = fit(start, made, groups=("E",), max_iterations=10, budget=120, prior=None)
    assert result.initial.rmse > 1.0 and result.train.rmse < 0.01  # mm
    assert result.parameters[0].value == pytest.approx(truth.design.E[0], rel=1e-4)
    for group in DISPLACEMENT_ONLY:
        with pytest.raises(ValueError, match=f"{group} acts only on displacement actuation"):
            fit(start, made, groups=("E", group))
    robot_file = tmp_path / "tension.json"
    robot_file.write_text(json.dumps(data))
    csv_file = tmp_path / "rec.csv"
    columns = [truth.time_column, *truth.actuation.columns, *truth.measurement.columns]
    rows = np.column_stack([made.time, commands, made.measured / truth.measurement.scale])
    csv_file.write_text(",".join(columns) + "\n" + "\n".join(",".join(f"{v:.9g}" for v in r) for r in rows) + "\n")
    run = subprocess.run([sys.executable, "-m", "tdcr.cli", "fit", str(robot_file), str(csv_file), "--fit", "E,zero",
                          "--out", str(tmp_path / "no.json")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and "--fit: zero acts only on displacement actuation" in run.stderr, run.stderr
    assert not (tmp_path / "no.json").exists()
