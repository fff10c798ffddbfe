"""Identify a real robot from motion-capture data (``tdcr fit``, :func:`fit`).

The model is the physics of :func:`tdcr.physics.replay.replay` (series-elastic tendons with drive
zeros, Capstan friction that follows each tendon's motion); the fit finds the parameters the data
can identify by nonlinear least squares on the measured points (``scipy.optimize.least_squares``,
trust-region reflective with bounds, forward-difference Jacobian, a soft-L1 loss by default: :data:`LOSS`):

* ``E``: Young's modulus of the backbone (one backbone: the bending stiffness of every segment);
* ``zero``: each tendon's drive zero, m (where it is just taut on the straight rod);
* ``elasticity``: each tendon's series compliance (eq. SE) as its drive's and its own length's,
  1 / k_i = c0 + end_i / EA: the drive compliance c0 (m/N) and the tendons' axial stiffness EA (N);
* ``stiffness``: instead, a series stiffness per segment's tendons, N/m;
* ``friction``: each segment's Capstan coefficient;
* ``creep``: the rate at which the tendons creep (``actuation.creep_rate``, 1/s, eq. CREEP).  The
  creep at the end of train is the state the fitted robot file starts from: its drive zeros are the
  fitted ones (reported as ``zero[i]``, the state at train's start) moved by it (:meth:`Robot.after`),
  so that a recording made after train (``--validate``, ``tdcr replay FITTED.json``) goes on from there;
* ``offset``: each segment's tendon offset, m; or ``tendon_offset``: each tendon's (holes drilled off
  their nominal radius);
* ``angle``: a rotation of each segment's tendon angles, rad (rough routing angles); or
  ``tendon_angle``: a turn of each tendon's angle, rad;
* ``end``: where each segment's tendons end, m, for the segments that end before the tip (not a
  default: on FTDCR v6 it fits train better, and both recordings validate worse, docs/real_robot.md);
* ``marker``, ``base_position``, ``base_rotation``: the measurement's registration, and
  ``time_constant``: the lag with which the measured tip follows the equilibria (eq. LAG, s); none
  needs a new solve.
  A robot file's rough registration (e.g. its tendon angles in another frame than the motion
  capture's) is first replaced by the rigid motion that best aligns the first replay's points with
  the measured ones (Kabsch, :func:`register`) when that lowers the error: least squares alone
  cannot turn the base by half a turn.

Under the robot file's loads (gravity, a tip wrench) a replay solves every row on the loaded solver,
60-90x slower than without, too slow for the least squares' hundreds of replays.  The fit then runs
in rounds (a defect correction, at most :data:`LOADED_ROUNDS`).  The first round is the fit without
the loads: a loaded replay at the file's values, far from the answer, is the costliest of all (but
if a row fails under the loads at its values, the start is replayed under them too, and the next
round starts there when that is better).  Each later round's least squares replays without the loads
and moves every row's tip pose by the loads' shift, the loaded replay's pose minus the unloaded
one's at the values the round starts from.  One loaded replay at each round's best values gives the
next shift and the loaded cost.  The rounds stop when one lowers that cost by less than
:data:`LOADED_RTOL` (a round that raises it is undone).  The reported errors are the loaded replay's
at the fitted values.  The search's Jacobian holds the shift fixed, so the steps and the standard
errors leave out how the loads' effect changes with the values: along a direction that only the
loads' effect tells apart the rounds move slowly.

A segment is the tendons that end together.  Every parameter is reported with its standard error
from the Jacobian at the optimum: the cluster-robust sandwich over train's patterns (:func:`clusters`,
:func:`_covariance`), since a model's error lasts a whole sweep and its rows are not independent; with
fewer than two such stretches, s^2 (J^T J)^-1, s^2 Huber's scale of the loss (:func:`_covariance_scale`,
SSR / (m - p) for plain least squares, reported beside it as ``stderr_independent``); none where
m <= p.  The report lists the pairs whose estimates correlate strongly (:data:`CORRELATION_SHOWN`,
from the latter's covariance).  Either is taken in
the span of the directions that move the robot: with ``base_rotation`` fitted, a common turn of every
tendon is the base's, so the turns are reported with zero mean.  Errors are the RMS of the
3-D point error over the rows with a measurement, mm: "plain", and "aligned" after removing the
mean error over the file (the metric of the public opencr-mujoco calibration).
"""

from __future__ import annotations

import itertools
import math
import os
import re
import threading
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np

from tdcr.physics.replay import REPLAY_OPTIONS, Replay, replay
from tdcr.robot.real import Measurement, Recording, Robot

#: The parameter groups :func:`fit` can identify, in order.
GROUPS = ("E", "zero", "elasticity", "stiffness", "friction", "creep", "offset", "tendon_offset", "angle",
          "tendon_angle", "end", "marker", "base_position", "base_rotation", "time_constant")
#: Those :func:`fit` identifies unless told otherwise (each tendon's angle turned from the robot file's: on
#: the shared recording's single-tendon sweeps the bend's direction was 1-8 degrees off, docs/real_robot.md).
DEFAULT_GROUPS = ("E", "zero", "elasticity", "friction", "creep", "offset", "tendon_angle", "marker",
                  "base_position", "base_rotation", "time_constant")
#: Groups that act only where the drives command displacements (a drive's zero and the tendons' series
#: compliance turn a pull-in into a tension, eq. SE); a robot commanded in tensions fits without them.
DISPLACEMENT_ONLY = ("zero", "elasticity", "stiffness", "creep")
#: Groups that set the same values: at most one of each.
EXCLUSIVE = (("elasticity", "stiffness"), ("offset", "tendon_offset"), ("angle", "tendon_angle"))
#: Those of the measurement (changing them needs no new solve).
REGISTRATION = ("marker", "base_position", "base_rotation", "time_constant")
#: Each group's unit of the search (one unit of the optimiser's variable).
_SCALE = {"E": 0.1, "zero": 1e-3, "elasticity": 0.1, "stiffness": 0.1, "friction": 0.1, "creep": 1.0, "offset": 0.05,
          "tendon_offset": 0.05, "angle": 0.1, "tendon_angle": 0.1, "end": 2e-3,
          "marker": 1e-3, "base_position": 1e-3, "base_rotation": 0.01, "time_constant": 0.1}
#: Searched as logarithms (positive, relative steps).
LOG_SEARCHED = ("E", "elasticity", "stiffness", "friction", "creep", "offset", "tendon_offset", "time_constant")
#: Where a log-searched value starts when the robot file's is 0 or infinite (friction, rigid tendons,
#: no lag: at 0 s the lag's gradient vanishes).
_LOG_START = {"friction": 0.05, "stiffness": 1e4, "E": 1e10, "time_constant": 0.2, "creep": 1e-3}
#: The search's bounds of each group's value (logs for :data:`LOG_SEARCHED`): physical ranges, and the
#: admissible ranges of the design fields.
_BOUNDS = {"E": (math.log(1e9), math.log(1e12)), "zero": (-0.02, 0.02), "stiffness": (math.log(50.0), math.log(1e7)),
           "drive_compliance": (math.log(1e-9), math.log(0.1)), "tendon_EA": (math.log(1.0), math.log(1e9)),
           "friction": (math.log(1e-3), math.log(1.0)), "creep": (math.log(1e-6), math.log(1.0)),
           "offset": (math.log(1e-4), math.log(0.1)),
           "tendon_offset": (math.log(1e-4), math.log(0.1)),
           "angle": (-0.5, 0.5), "tendon_angle": (-0.5, 0.5), "end": (1e-3, math.inf), "marker": (-0.05, 0.05),
           "base_position": (-0.25, 0.25), "base_rotation": (-4.0, 4.0),
           "time_constant": (math.log(1e-3), math.log(5.0))}
#: The least-squares iterations (each a Jacobian) and the search's budget, s: on the shared recording 15
#: iterations take 210 s on 2 cores; more fit train closer and validate worse.
MAX_ITERATIONS, BUDGET = 15, 270.0
#: Forward-difference step in the search's units (large against the solver's tolerances).
DIFF_STEP = 1e-2
#: The fit's loss on the point errors, its scale (mm) and the prior's widths (search units, :func:`fit`).
#: A soft-L1 loss at 5 mm by default (since 2026-12-07): with the creep among the groups it scored the
#: held-out folds of train better than plain least squares in all five of the shared recording's and
#: in sum on FTDCR v6's, and it even ends at a lower train RMSE on both recordings
#: (``benchmarks/real_robot_holdout.py --loss``, docs/real_robot.md "A robust loss").  Smaller scales
#: (down to 0.3 mm) scored those folds better still, and validated worse on both recordings: a
#: near-L1 fit gives up the single-tendon sweeps that pin each tendon (``--f-scale``, the same).  A prior
#: 0.2 units (0.02 rad) wide on the tendons' turns only: a turn the recording pins (a tendon's own
#: sweep) moves as freely as before, one it barely constrains stays near the file's angle
#: (held-out halves of train, ``benchmarks/real_robot_holdout.py --prior``).
LOSS, F_SCALE, PRIOR = "soft_l1", 5.0, MappingProxyType({"tendon_angle": 0.2})
#: The report lists the pairs of parameters whose estimates correlate at least this much, either sign:
#: values the recording hardly tells apart (lmfit's fit report lists its correlations so).
CORRELATION_SHOWN = 0.9
#: The losses :func:`fit` offers (``least_squares``'s names).
LOSSES = ("linear", "soft_l1")
#: Under loads: the most rounds of least squares with the loads' shift held; they stop once a round
#: lowers the loaded replay's cost by less than this fraction (and one that raises it is undone).
LOADED_ROUNDS, LOADED_RTOL = 6, 0.01
#: :func:`plot` draws no line across a pause of more than this many times the recording's median interval.
PLOT_GAP = 4.0
#: A row whose answer is not finite scores this error per coordinate, m.
FAILED_ERROR = 0.05


@dataclass(frozen=True)
class Parameter:
    """One identified value: ``name`` (e.g. ``zero[3]``), ``value`` and ``stderr`` in ``unit`` (SI;
    ``inf`` where the data do not move it: not identified, ``null`` in the report), and its ``group``;
    ``stderr_independent``: the standard error were train's residuals independent (the same as
    ``stderr`` with fewer than two :func:`clusters`; smaller when a model's error lasts a sweep)."""

    name: str
    value: float
    stderr: float
    unit: str
    group: str = ""
    stderr_independent: float = math.nan


@dataclass(frozen=True)
class Errors:
    """Point errors of a replay against a recording, mm: ``rmse`` (plain), ``aligned`` (after the mean
    error is removed), ``max``, ``rows`` scored, ``skipped`` rows (no measurement), ``failed`` rows
    (the solver did not converge), ``per_pattern`` label -> aligned-by-file RMSE (a ``_hold`` row
    counts with its pattern)."""

    rmse: float
    aligned: float
    max: float
    rows: int
    skipped: int
    failed: int
    per_pattern: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"rmse_mm": self.rmse, "aligned_rmse_mm": self.aligned, "max_mm": self.max, "rows": self.rows,
                "skipped": self.skipped, "failed": self.failed, "per_pattern_mm": self.per_pattern}


def errors(answer: Replay, recording: Recording) -> Errors:
    """:class:`Errors` of ``answer`` (:func:`tdcr.physics.replay.replay` of the recording's commands)."""
    scored = recording.has_measurement
    err = (answer.points - recording.measured)[scored] * 1e3
    aligned = err - err.mean(axis=0)
    dist, dist_aligned = np.linalg.norm(err, axis=1), np.linalg.norm(aligned, axis=1)
    patterns = _patterns(recording)[scored]
    per = {p: float(np.sqrt((dist_aligned[patterns == p] ** 2).mean())) for p in dict.fromkeys(patterns)
           if p}  # a row without a label (a recording with no label column) belongs to no pattern
    return Errors(rmse=float(np.sqrt((dist**2).mean())), aligned=float(np.sqrt((dist_aligned**2).mean())),
                  max=float(dist.max()), rows=int(scored.sum()), skipped=recording.skipped,
                  failed=int((~answer.converged[scored]).sum()), per_pattern=per)


def _patterns(recording: Recording) -> np.ndarray:
    """Each row's pattern ``(T,)``: its label less a ``_hold`` suffix (a hold belongs to the sweep it
    ends; "" where the recording has no label)."""
    return np.array([re.sub(r"_hold$", "", str(label)) for label in recording.labels])


def clusters(recording: Recording) -> np.ndarray:
    """The stretches of a recording whose errors the fit's standard errors take as correlated
    ``(T,)`` (int, one per stretch): its patterns (:func:`_patterns`) where it has labels, otherwise
    the runs between its :func:`pauses`.  A model's error lasts as long as the motion that causes it,
    so the rows of one sweep are not independent samples (the standard errors: :func:`_covariance`)."""
    patterns = _patterns(recording)
    if (patterns != "").any():
        return np.unique(patterns, return_inverse=True)[1]
    runs = np.zeros(len(recording.time), dtype=np.int64)
    runs[pauses(recording.time)] = 1
    return np.cumsum(runs)


def segments(robot: Robot) -> list[np.ndarray]:
    """The tendons of each segment (those that end together), base first: index arrays."""
    ends = robot.design.ends[0]
    return [np.nonzero(np.isclose(ends, e, rtol=0, atol=1e-9))[0] for e in np.unique(ends)]


def _inner_segments(robot: Robot) -> list[np.ndarray]:
    """The :func:`segments` whose tendons end before the tip (the ``end`` group moves those ends;
    tendons that end at the tip stay there)."""
    length = float(robot.design.L[0])
    return [seg for seg in segments(robot) if robot.design.ends[0, seg[0]] < length - 1e-9]


@dataclass(frozen=True)
class _Layout:
    """Where each parameter sits in the search vector: ``names`` (p,), ``groups`` (p,), ``index`` (p,)
    (the tendon, segment or coordinate within its group)."""

    names: tuple[str, ...]
    groups: tuple[str, ...]
    index: tuple[int, ...]

    @property
    def physics(self) -> np.ndarray:
        return np.array([g not in REGISTRATION for g in self.groups], dtype=bool)


def _layout(robot: Robot, groups: Sequence[str]) -> _Layout:
    n_seg = len(segments(robot))
    n_t = robot.n_tendons
    counts = {"E": 1, "zero": n_t, "elasticity": 2, "stiffness": n_seg, "friction": n_seg, "creep": 1, "offset": n_seg,
              "tendon_offset": n_t, "angle": n_seg, "tendon_angle": n_t, "end": len(_inner_segments(robot)),
              "marker": 3, "base_position": 3,
              "base_rotation": 3, "time_constant": 1}
    names, gs, index = [], [], []
    for g in GROUPS:
        if g in groups:
            for i in range(counts[g]):
                names.append(_NAMES[g][i] if g in _NAMES else g if counts[g] == 1 else f"{g}[{i}]")
                gs.append(g)
                index.append(i)
    return _Layout(tuple(names), tuple(gs), tuple(index))


def _values(robot: Robot, layout: _Layout) -> np.ndarray:
    """The robot's current values of the layout's parameters (search space: logs for :data:`LOG_SEARCHED`)."""
    d, m, segs = robot.design, robot.measurement, segments(robot)
    out = []
    for g, i in zip(layout.groups, layout.index, strict=True):
        if g == "E":
            out.append(math.log(d.E[0]))
        elif g == "zero":
            out.append(d.resolved("zero")[0, i])
        elif g == "elasticity":  # half the mean compliance in the drive, half in the tendons' lengths
            half = 0.5 * float(np.mean(d.compliance[0])) or 1e-4
            out.append(math.log(half if i == 0 else float(np.mean(d.ends[0])) / half))
        elif g == "tendon_offset":
            out.append(math.log(d.offset[0, i]))
        elif g in ("stiffness", "friction", "offset"):
            v = d.resolved(g)[0, segs[i]].mean()
            out.append(math.log(v if np.isfinite(v) and v > 0 else _LOG_START[g]))
        elif g in ("angle", "tendon_angle"):
            out.append(0.0)
        elif g == "end":
            out.append(float(d.ends[0, _inner_segments(robot)[i][0]]))
        elif g == "time_constant":
            out.append(math.log(m.time_constant if m.time_constant > 0 else _LOG_START[g]))
        elif g == "creep":
            rate = robot.actuation.creep_rate
            out.append(math.log(rate if rate > 0 else _LOG_START[g]))
        else:
            out.append(getattr(m, g)[i])
    return np.array(out)


def _without_common_turn(layout: _Layout, values: np.ndarray) -> np.ndarray:
    """``values`` (search space) with the mean of the ``angle`` or ``tendon_angle`` turns removed
    when ``base_rotation`` is fitted too: a common turn of every tendon is (but for the marker's few
    mm) a turn of the base about its axis, so the pair would leave a ridge and the turns' standard
    errors would hold it; the base rotation carries the common part."""
    if "base_rotation" not in layout.groups:
        return values
    out = values.copy()
    for g in ("angle", "tendon_angle"):
        turns = np.array([k == g for k in layout.groups])
        if turns.any():
            out[turns] -= out[turns].mean()
    return out


def _free_directions(layout: _Layout) -> np.ndarray:
    """An orthonormal basis ``(p, q)`` of the search directions that move the robot: all of them, less
    the common turn that :func:`_without_common_turn` removes (the covariance lives in their span)."""
    basis = np.eye(len(layout.groups))
    if "base_rotation" not in layout.groups:
        return basis
    keep = np.ones(len(layout.groups), dtype=bool)
    for g in ("angle", "tendon_angle"):
        turns = np.nonzero([k == g for k in layout.groups])[0]
        if len(turns) > 1:
            centred = np.eye(len(turns)) - 1.0 / len(turns)  # its range: the turns with zero mean
            basis[np.ix_(turns, turns)] = np.linalg.svd(centred)[0]
            keep[turns[-1]] = False  # the column along the common turn (singular value 0, last)
        elif len(turns) == 1:
            keep[turns] = False
    return basis[:, keep]


def _apply(robot: Robot, layout: _Layout, values: np.ndarray, base_angles: np.ndarray) -> Robot:
    """The robot with the layout's parameters at ``values`` (search space)."""
    d, segs = robot.design, segments(robot)
    values = _without_common_turn(layout, values)
    fields = {"zero": d.resolved("zero").copy(), "stiffness": d.resolved("stiffness").copy(),
              "friction": d.resolved("friction").copy(), "offset": d.offset.copy(), "angle": base_angles.copy(),
              "end": d.ends.copy()}
    inner = _inner_segments(robot)
    E = d.E.copy()
    actuation = robot.actuation
    elastic = [np.nan, np.nan]  # the drive's compliance c0 (m/N) and the tendons' axial stiffness EA (N)
    m = robot.measurement
    reg = {"marker": m.marker.copy(), "base_position": m.base_position.copy(),
           "base_rotation": m.base_rotation.copy(), "time_constant": m.time_constant}
    for g, i, v in zip(layout.groups, layout.index, values, strict=True):
        if g == "E":
            E[0] = math.exp(v)
        elif g == "zero":
            fields["zero"][0, i] = v
        elif g == "elasticity":
            elastic[i] = math.exp(v)
        elif g in ("stiffness", "friction", "offset"):
            fields[g][0, segs[i]] = math.exp(v)
        elif g == "tendon_offset":
            fields["offset"][0, i] = math.exp(v)
        elif g == "angle":
            fields["angle"][0, segs[i]] = base_angles[0, segs[i]] + v
        elif g == "tendon_angle":
            fields["angle"][0, i] = base_angles[0, i] + v
        elif g == "end":
            fields["end"][0, inner[i]] = min(v, float(d.L[0]))
        elif g == "time_constant":
            reg[g] = math.exp(v)
        elif g == "creep":
            actuation = replace(actuation, creep_rate=math.exp(v))
        else:
            reg[g][i] = v
    if not np.isnan(elastic).any():  # eq. SE's k of a tendon of length end: 1 / k = c0 + end / EA
        fields["stiffness"] = 1.0 / (elastic[0] + fields["end"] / elastic[1])
    measurement = replace(m, **reg)
    return replace(robot, design=d.replace(E=E, **fields), actuation=actuation, measurement=measurement)


@dataclass(frozen=True)
class FitResult:
    """The answer of :func:`fit`: the fitted ``robot``, its ``parameters`` with standard errors, the
    ``train`` and (if given) ``validate`` :class:`Errors`, the replays ``train_replay`` and
    ``validate_replay``, the ``initial`` train errors, ``seconds``, ``solves`` (replays run) and
    ``prior``, the prior's width of each fitted group that had one (search units: the standard
    errors of those groups carry it), the search's ``groups``, ``loss`` and ``f_scale`` (mm), and
    under loads ``load_rounds``: the loaded replay's train errors after each round kept (the first
    round fits without the loads, so ``initial`` is the start's replay without them); ``train_end``:
    the time of train's last row (s, the recording's clock), where the written file's creep stands;
    ``stderr_clusters``: over how many of train's :func:`clusters` the standard errors were estimated (0:
    its residuals taken as independent, with fewer than two); ``correlations``: the pairs of
    parameters (a, b, r) whose estimates correlate by at least :data:`CORRELATION_SHOWN` under the
    covariance of the loss's curvature (``stderr_independent``'s), strongest first (for a logarithm's
    group, its logarithm's)."""

    robot: Robot
    parameters: list[Parameter]
    train: Errors
    validate: Errors | None
    train_replay: Replay
    validate_replay: Replay | None
    initial: Errors
    seconds: float
    solves: int
    prior: dict[str, float] = field(default_factory=dict)
    groups: tuple[str, ...] = ()
    loss: str = LOSS
    f_scale: float = F_SCALE
    load_rounds: tuple[Errors, ...] = ()
    train_end: float | None = None
    stderr_clusters: int = 0
    correlations: tuple[tuple[str, str, float], ...] = ()

    def report(self) -> dict:
        """The fit as JSON (the robot file's ``fitted``).  ``crept_m``: how far each tendon had crept
        by train's last row (m, tendon order; ``crept_at_s``: that row's time, s), by which the
        written file's drive zeros are moved (as train left them, for a recording made after it); so
        the file's own replay of train starts crept (:func:`starts_crept` says so), and
        :func:`at_start` gives the robot as train found it."""
        rounds = {"load_rounds": [e.as_dict() for e in self.load_rounds]} if self.load_rounds else {}
        crept = {"crept_m": [float(c) for c in self.train_replay.crept[-1]], "crept_at_s": self.train_end}
        return rounds | crept | {"parameters": [{"name": p.name, "value": p.value, "stderr": _finite(p.stderr),
                                                 "stderr_independent": _finite(p.stderr_independent),
                                                 "unit": p.unit, "group": p.group}
                                                for p in self.parameters],
                "train": self.train.as_dict(), "validate": None if self.validate is None else self.validate.as_dict(),
                "initial_train": self.initial.as_dict(), "seconds": self.seconds, "solves": self.solves,
                "prior": self.prior, "groups": list(self.groups), "loss": self.loss, "f_scale_mm": self.f_scale,
                "stderr_clusters": self.stderr_clusters,
                "correlations": [{"a": a, "b": b, "r": r} for a, b, r in self.correlations]}


def _finite(value: float) -> float | None:
    """``value``, or None (JSON's null) where it is not finite."""
    return value if math.isfinite(value) else None


#: The parameters of a group that are not alike: their own names (and units).
_NAMES = {"elasticity": ("drive_compliance", "tendon_EA")}
_NAME_UNITS = {"drive_compliance": "m/N", "tendon_EA": "N"}
_UNITS = {"E": "Pa", "zero": "m", "end": "m", "stiffness": "N/m", "friction": "", "creep": "1/s", "offset": "m",
          "tendon_offset": "m", "angle": "rad", "tendon_angle": "rad", "marker": "m", "base_position": "m",
          "base_rotation": "rad", "time_constant": "s"}


def default_groups(robot: Robot) -> tuple[str, ...]:
    """The groups :func:`fit` identifies unless told otherwise: :data:`DEFAULT_GROUPS`, less
    :data:`DISPLACEMENT_ONLY` for a robot commanded in tensions, and less ``creep`` under loads (named,
    it is fitted there too; by default it is not: on the shared FTDCR v4 recording in gravity the
    rounds kept only the first, val 8.66 / 9.23 mm against 6.29 / 6.55 without it, docs/real_robot.md)."""
    left_out = (DISPLACEMENT_ONLY if robot.actuation.kind != "displacement" else ()) + (
        ("creep",) if robot.loads is not None else ())
    return tuple(g for g in DEFAULT_GROUPS if g not in left_out)


def check_groups(groups: Sequence[str], robot: Robot | None = None) -> str | None:
    """Why :func:`fit` cannot identify ``groups`` (none, an unknown one, two of :data:`EXCLUSIVE`, for
    a ``robot`` commanded in tensions one of :data:`DISPLACEMENT_ONLY`, or ``end`` for a robot whose
    tendons all end at the tip), or None."""
    if not groups:
        return f"name at least one group; they are {', '.join(GROUPS)}"
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        return f"unknown {', '.join(unknown)}; they are {', '.join(GROUPS)}"
    for pair in EXCLUSIVE:
        if set(pair) <= set(groups):
            return f"{pair[0]} and {pair[1]} set the same values: give one of them"
    inert = [g for g in groups if g in DISPLACEMENT_ONLY]
    if robot is not None and robot.actuation.kind != "displacement" and inert:
        verb = "acts" if len(inert) == 1 else "act"
        return (f"{', '.join(inert)} {verb} only on displacement actuation; this robot's drives command "
                f"{robot.actuation.kind}s (actuation.kind)")
    if robot is not None and "end" in groups and not _inner_segments(robot):
        return "end moves the ends of segments that end before the tip; every tendon of this robot ends at the tip"
    return None


def check_prior(prior: float | Mapping[str, float] | None) -> str | None:
    """Why :func:`fit` cannot take ``prior`` (a name that is no group, a width that is not > 0), or None."""
    if prior is None:
        return None
    named = prior if isinstance(prior, Mapping) else {"every group": prior}
    unknown = sorted(set(named) - set(GROUPS)) if isinstance(prior, Mapping) else []
    if unknown:
        return f"unknown {', '.join(unknown)}; the groups are {', '.join(GROUPS)}"
    bad = {g: w for g, w in named.items() if not float(w) > 0.0}
    return f"a width must be > 0, got {bad}" if bad else None


def check_f_scale(f_scale: float) -> str | None:
    """Why :func:`fit` cannot take the loss's scale ``f_scale`` (mm), or None."""
    return None if math.isfinite(f_scale) and f_scale > 0 else f"must be a number of mm > 0, got {f_scale!r}"


def parse_prior(text: str) -> dict[str, float] | None:
    """A prior as the CLI gives it: ``GROUP=WIDTH[,GROUP=WIDTH...]`` (widths in search units, as
    :func:`fit` takes them), or ``none``.  ``ValueError`` saying why for anything else: a malformed
    item, an unknown group or a width that is not > 0."""
    if text.strip().lower() == "none":
        return None
    prior = {}
    for item in text.split(","):
        group, sep, width = item.partition("=")
        try:
            prior[group.strip()] = float(width)
        except ValueError:
            sep = ""
        if not sep:
            raise ValueError(f"expected GROUP=WIDTH[,GROUP=WIDTH...] or none, got {item.strip()!r}")
    problem = check_prior(prior)
    if problem:
        raise ValueError(problem)
    return prior


def format_prior(prior: Mapping[str, float] | None) -> str:
    """``prior`` as :func:`parse_prior` reads it."""
    return "none" if prior is None else ",".join(f"{g}={w:g}" for g, w in prior.items())


def fit(robot: Robot, train: Recording, *, validate: Recording | None = None, groups: Sequence[str] | None = None,
        max_iterations: int = MAX_ITERATIONS, budget: float = BUDGET, progress: bool = False, workers: int = 0,
        loss: str = LOSS, f_scale: float = F_SCALE, prior: float | Mapping[str, float] | None = PRIOR) -> FitResult:
    """Identify ``groups`` (:data:`GROUPS`) of the robot from the recording ``train``.

    Args:
        robot: the robot file's robot: the start of every parameter.
        train: the recording fitted (its rows without a measurement are skipped).
        validate: a recording only scored (the fitted robot replays it).
        groups: the parameter groups to identify (None: :func:`default_groups` of the robot).
        max_iterations: the most least-squares iterations (each a Jacobian: one replay per
            physics parameter).
        budget: seconds after which the search stops at the best point it has (the standard
            errors and the reports follow, about one more Jacobian).  Under loads the loaded
            replays (one after each round, and validate's) come on top of it.
        progress: show a progress bar of the replays (tqdm, on stderr).
        workers: kernel threads (0: one per core).
        loss, f_scale: ``least_squares``'s loss on each coordinate's error and its scale, mm
            (``"linear"``: plain least squares; ``"soft_l1"``, the default: an error beyond f_scale
            counts about linearly, so a few rows far off do not steer the search).
        prior: the width of a Gaussian prior around the robot file's values, in the search's units
            (:data:`_SCALE`: 1 mm of a zero, 10 % of E or of a stiffness, ...), against point errors
            of ``f_scale`` mm; ``None``: none; a mapping: a width per group (default
            :data:`PRIOR`), none on the groups it does not name.  It holds what the recording cannot tell
            apart (E against the tendons' stiffness, a tendon's angle without its own sweep) at the
            file's values.
    """
    from scipy.optimize import least_squares
    from tqdm import tqdm

    groups = default_groups(robot) if groups is None else groups
    problem = check_groups(groups, robot)
    if problem:
        raise ValueError(f"groups: {problem}")
    if loss not in LOSSES:
        raise ValueError(f"loss: one of {', '.join(LOSSES)}, got {loss!r}")
    for name, problem in (("prior", check_prior(prior)), ("f_scale", check_f_scale(f_scale))):
        if problem:
            raise ValueError(f"{name}: {problem}")
    start = time.perf_counter()
    layout = _layout(robot, groups)
    scale = np.array([_SCALE[g] for g in layout.groups])
    width = _prior_widths(prior, layout.groups)  # (p,) search units; inf: no prior
    held = np.isfinite(width)
    lower = np.array([_BOUNDS.get(n, _BOUNDS.get(g))[0] for n, g in zip(layout.names, layout.groups, strict=True)])
    upper = np.array([_BOUNDS.get(n, _BOUNDS.get(g))[1] for n, g in zip(layout.names, layout.groups, strict=True)])
    upper[np.array([g == "end" for g in layout.groups], dtype=bool)] = float(robot.design.L[0])  # on the rod
    x0 = np.clip(_values(robot, layout), lower + 1e-6 * (upper - lower), upper - 1e-6 * (upper - lower))
    base_angles = robot.design.angles.copy()
    scored = train.has_measurement
    physics = layout.physics
    threads = workers or os.cpu_count() or 1
    # a creeping robot's replay is one chain on one thread: the Jacobian's columns then run side by side
    creeping = robot.creeps or "creep" in groups
    columns_apart = creeping and threads > 1
    cache: dict[bytes, Replay] = {}
    lock = threading.Lock()  # the cache and counters, with the Jacobian's columns on threads
    bar = tqdm(desc="fit: replays", unit="replay", disable=not progress, leave=False)
    solves = [0]
    best = {"cost": np.inf, "z": np.zeros(len(x0)), "text": ""}  # text: the bar's postfix, the best point's RMSE
    unloaded = replace(robot, loads=None)
    shift: list[_LoadShift | None] = [None]  # the loads' shift of the rows' tip poses (None: no loads)
    loaded_replay: list[Replay | None] = [None]  # the last loaded replay, at the shift's values
    loaded_seconds = [0.0]  # spent in loaded replays: not the search's, so not its budget's

    def unloaded_replay(x: np.ndarray) -> Replay:
        """The replay at ``x`` without loads (cached)."""
        key = np.round(x[physics], 14).tobytes()
        with lock:
            if key in cache:
                return cache[key]
        # the rows' times where the robot creeps (its replay carries the creep; the caller applies the lag)
        answer = replay(_apply(unloaded, layout, x, base_angles), train.commands,
                        time=train.time if creeping else None, workers=1 if columns_apart else workers,
                        options=REPLAY_OPTIONS)
        with lock:
            if len(cache) > 64:
                cache.clear()
            cache[key] = answer
            solves[0] += 1
            bar.update(1)
        return answer

    def solved(x: np.ndarray) -> Replay:
        """The replay at ``x``: without loads, moved by the loads' ``shift`` (if any)."""
        return unloaded_replay(x) if shift[0] is None else shift[0].moved(unloaded_replay(x))

    def shift_at(x: np.ndarray) -> _LoadShift:
        """The loads' shift at ``x``: one loaded replay against the unloaded one."""
        begin = time.perf_counter()
        bar.set_postfix_str("a replay under the loads", refresh=True)  # one tick, 60-90x a plain replay's time
        loaded_replay[0] = replay(_apply(robot, layout, x, base_angles), train.commands,
                                  time=train.time if creeping else None, workers=workers, options=REPLAY_OPTIONS)
        solves[0] += 1
        bar.set_postfix_str(best["text"], refresh=False)
        bar.update(1)
        loaded_seconds[0] += time.perf_counter() - begin
        return _LoadShift.between(loaded_replay[0], unloaded_replay(x))

    def residual(z: np.ndarray, *, track: bool = True) -> np.ndarray:
        if track and time.perf_counter() - start - loaded_seconds[0] > budget:
            raise _OutOfTime
        x = x0 + z * scale
        fitted = _apply(robot, layout, x, base_angles)
        answer = solved(x)
        points = fitted.measurement.points(answer.tip_position, answer.tip_rotation, train.time)
        # a row whose pull-ins were missed still has an equilibrium (at the tensions found): scored as it is
        err = np.where(np.isfinite(points), points - train.measured, FAILED_ERROR)
        r = (err[scored] * 1e3).ravel()  # mm
        if held.any():
            r = np.concatenate([r, z[held] * (f_scale / width[held])])
        cost = _robust_cost(r, loss, f_scale)
        with lock:  # the Jacobian's columns may run on threads
            if track and cost < best["cost"]:
                best["cost"], best["z"] = cost, z.copy()
                best["text"] = f"train RMSE {math.sqrt(np.mean(np.sum(err[scored] ** 2, axis=1))) * 1e3:.2f} mm"
                bar.set_postfix_str(best["text"], refresh=False)
        return r

    def jacobian_apart(z: np.ndarray) -> np.ndarray:
        """``least_squares``' forward-difference Jacobian (its steps: DIFF_STEP max(1, |z|), away from
        a bound it would cross) with the columns' replays side by side, one thread each."""
        h = DIFF_STEP * np.maximum(1.0, np.abs(z)) * np.where(z >= 0.0, 1.0, -1.0)
        return _jacobian(residual, z, np.where((z + h > upper_z) | (z + h < lower_z), -h, h), threads=threads)

    initial_robot = _apply(robot, layout, x0, base_angles)
    initial = errors(_replay_points(initial_robot, solved(x0), train.time), train)
    if {"base_position", "base_rotation"} <= set(groups):
        registered = register(initial_robot, solved(x0), train)
        better = errors(_replay_points(registered, solved(x0), train.time), train)
        if better.rmse < initial.rmse:
            moved = _values(registered, layout)
            for k, g in enumerate(layout.groups):
                if g in ("base_position", "base_rotation"):
                    x0[k] = np.clip(moved[k], lower[k], upper[k])
    rounds = []  # under loads: the loaded replay's train errors after each round kept

    def loaded_errors(z: np.ndarray) -> Errors:
        return errors(_replay_points(_apply(robot, layout, x0 + z * scale, base_angles), loaded_replay[0],
                                     train.time), train)

    def loaded_cost(z: np.ndarray) -> float:
        """The loaded cost at ``z``: one loaded replay there, which becomes the shift."""
        shift[0] = shift_at(x0 + z * scale)
        return _robust_cost(residual(z, track=False), loss, f_scale)

    lower_z, upper_z = (lower - x0) / scale, (upper - x0) / scale  # the search's bounds, from the start
    cost = np.inf  # under loads: the loaded cost after the last round kept (none before the first)
    for _ in range(LOADED_ROUNDS if robot.loads is not None else 1):
        z_start, best["cost"] = best["z"].copy(), np.inf
        try:
            least_squares(residual, z_start, jac=jacobian_apart if columns_apart else "2-point",
                          bounds=(lower_z, upper_z), diff_step=DIFF_STEP, max_nfev=max_iterations, method="trf",
                          x_scale=1.0, loss=loss, f_scale=f_scale)
            spent = False
        except _OutOfTime:
            spent = True
        if robot.loads is None:
            break
        if not np.isfinite(best["cost"]):  # the budget was spent before this round searched: keep the last
            best["z"] = z_start
            if shift[0] is None:  # the first round: its start, replayed under the loads
                loaded_cost(z_start)
                rounds.append(loaded_errors(z_start))
            break
        last = (z_start, shift[0], loaded_replay[0])
        first = shift[0] is None
        z_new = best["z"]
        new_cost = loaded_cost(z_new)  # the loaded replay at the round's best
        if first and not loaded_replay[0].converged[scored].all():
            # values fitted without the loads may not stand under them (a soft column buckles under
            # its weight): the start replayed under the loads, and the next round from there if it is better
            found = shift[0], loaded_replay[0]
            start_cost = loaded_cost(z_start)
            if start_cost < new_cost:
                best["z"], cost = z_start, start_cost
                rounds.append(loaded_errors(z_start))
                continue
            shift[0], loaded_replay[0] = found
        if not new_cost < cost:  # the loaded fit got no better: keep the last round's
            best["z"], shift[0], loaded_replay[0] = last
            break
        best["z"] = z_new
        rounds.append(loaded_errors(z_new))
        if spent or new_cost > (1.0 - LOADED_RTOL) * cost:
            break
        cost = new_cost
    z = best["z"]
    jac = _jacobian(lambda v: residual(v, track=False), z, np.full(len(z), DIFF_STEP),
                    threads=threads if columns_apart else 1)
    bar.close()
    x = _without_common_turn(layout, x0 + z * scale)  # the values applied, as reported
    fitted = _apply(robot, layout, x, base_angles)
    free = _free_directions(layout)
    m, q = jac.shape[0], free.shape[1]
    r_best = residual(z, track=False)
    column = np.linalg.norm(jac, axis=0)

    def standard_errors(cov: np.ndarray) -> np.ndarray:
        """The standard errors ``(p,)`` (search units) of the covariance ``(q, q)`` along ``free``."""
        stderr = np.sqrt(np.clip(np.diag(free @ cov @ free.T), 0.0, None)) * scale
        # a parameter the residuals do not move (e.g. a lag far below the sampling interval) is not
        # identified: its variance is unbounded, not the 0 the pseudo-inverse gives its null direction
        stderr[column <= 1e-9 * max(float(column.max()), 1e-300)] = np.inf
        if m <= q:  # no more residuals than free directions: no residual variance to scale them by
            stderr[:] = np.inf
        return stderr

    clustered, count = _covariance(jac @ free, r_best, loss=loss, f_scale=f_scale,
                                   groups=np.repeat(clusters(train)[scored], 3))  # each residual's cluster
    apart, _ = _covariance(jac @ free, r_best, loss=loss, f_scale=f_scale, groups=None)
    stderrs = standard_errors(clustered), standard_errors(apart)
    # from the loss's curvature: the sandwich has rank at most the number of patterns, and fewer
    # patterns than parameters would make every pair of it correlate fully
    correlated = _correlations(free @ apart @ free.T, layout.names, np.isfinite(stderrs[1]))
    params = []
    for name, g, v, se, se_apart in zip(layout.names, layout.groups, x, *stderrs, strict=True):
        value = math.exp(v) if g in LOG_SEARCHED else v
        params.append(Parameter(name=name, value=float(value), stderr=float(value * se if g in LOG_SEARCHED else se),
                                unit=_NAME_UNITS.get(name) or _UNITS[g], group=g,
                                stderr_independent=float(value * se_apart if g in LOG_SEARCHED else se_apart)))
    # under loads the last loaded replay, at these values (the shift's): its own tensions and statuses
    train_replay = _replay_points(fitted, solved(x) if loaded_replay[0] is None else loaded_replay[0], train.time)
    fitted = fitted.after(train_replay.crept[-1])  # as train left it: what a later recording starts from
    val_replay = None if validate is None else replay(fitted, validate.commands, time=validate.time,
                                                      workers=workers, options=REPLAY_OPTIONS)
    seconds = time.perf_counter() - start
    out = FitResult(robot=fitted, parameters=params, train=errors(train_replay, train),
                    validate=None if validate is None else errors(val_replay, validate), train_replay=train_replay,
                    validate_replay=val_replay, initial=initial, seconds=seconds, solves=solves[0],
                    prior={g: float(w) for g, w in zip(layout.groups, width, strict=True) if np.isfinite(w)},
                    groups=tuple(dict.fromkeys(layout.groups)), loss=loss, f_scale=f_scale,
                    load_rounds=tuple(rounds), train_end=float(train.time[-1]), stderr_clusters=count,
                    correlations=correlated)
    return replace(out, robot=replace(fitted, extra=fitted.extra | {"fitted": out.report()}))


def at_start(robot: Robot, result: FitResult, parameters: Sequence[Parameter] | None = None) -> Robot:
    """The robot file's ``robot`` (the fit's start) with ``result``'s parameters applied, or with
    ``parameters`` (the same names in the same order, e.g. another fit's values for some groups): the
    fitted robot as the fitted recording found it (``result.robot`` is as the recording left it, its
    drive zeros moved by what the tendons crept, :meth:`Robot.after`)."""
    layout = _layout(robot, result.groups)
    parameters = result.parameters if parameters is None else parameters
    if tuple(p.name for p in parameters) != layout.names:
        raise ValueError(f"parameters: must be {list(layout.names)} in this order (the fit's groups)")
    x = np.array([math.log(p.value) if g in LOG_SEARCHED else p.value
                  for p, g in zip(parameters, layout.groups, strict=True)])
    return _apply(robot, layout, x, robot.design.angles.copy())


def starts_crept(robot: Robot, time: np.ndarray | None) -> str | None:
    """Why a fitted file's replay of a recording that starts at or before its fit's train ended
    (``time`` ``(T,)`` s, the recording's clock) is not the fit's: the file's drive zeros are as train
    left them (its report's ``crept_m`` and ``crept_at_s``), so such a replay starts crept.  None for
    a later recording, a file without a fit's report, a fit whose tendons did not creep, or no clock."""
    report = robot.extra.get("fitted")
    if not isinstance(report, dict) or time is None or not len(time):
        return None
    crept, until = report.get("crept_m"), report.get("crept_at_s")
    if not crept or until is None or max(crept) <= 0.0 or time[0] > until:
        return None
    return (f"this recording starts at or before the last row of the fit's train (t = {until:.3f} s), but the "
            f"file's drive zeros are as train left them, crept by up to {max(crept) * 1e3:.3f} mm (its fitted "
            "crept_m): this replay starts crept, so it is not the fit's (tdcr.search.fit.at_start gives the robot "
            "as train found it)")


@dataclass(frozen=True)
class _LoadShift:
    """What the robot file's loads do to each row's tip pose at some values: ``values`` ``(T, 12)``,
    the loaded pose (p_l, R_l) against the unloaded one (p_u, R_u) as p_l - p_u (m) and R_l R_u^T
    (row-major), so p_l = p_u + shift, R_l = shift R_u (base frame)."""

    values: np.ndarray

    @classmethod
    def between(cls, loaded: Replay, unloaded: Replay) -> _LoadShift:
        rotation = loaded.tip_rotation @ np.swapaxes(unloaded.tip_rotation, 1, 2)
        position = loaded.tip_position - unloaded.tip_position
        return cls(values=np.concatenate([position, rotation.reshape(-1, 9)], axis=1))

    def moved(self, answer: Replay) -> Replay:
        """The unloaded ``answer`` with its tip poses moved by the shift (NaN where a solve failed)."""
        return replace(answer, tip_position=answer.tip_position + self.values[:, :3],
                       tip_rotation=self.values[:, 3:].reshape(-1, 3, 3) @ answer.tip_rotation)


def _prior_widths(prior: float | Mapping[str, float] | None, groups: Sequence[str]) -> np.ndarray:
    """Each parameter's prior width ``(p,)`` in search units (inf: none) of :func:`fit`'s ``prior``
    (checked, :func:`check_prior`) for the parameters' ``groups`` (a group of the mapping that is
    not fitted has no parameter)."""
    if prior is None:
        return np.full(len(groups), np.inf)
    named = prior if isinstance(prior, Mapping) else dict.fromkeys(groups, prior)
    return np.array([float(named.get(g, np.inf)) for g in groups])


def register(robot: Robot, answer: Replay, recording: Recording) -> Robot:
    """The robot with the base pose (``base_position``, ``base_rotation``) that best aligns the
    replay's points with the recording's measured ones: the rigid motion of least squares between
    the two point sets (Kabsch's, by ``scipy.spatial.transform.Rotation.align_vectors``).  Points on one
    line (e.g. fewer than three rows) do not fix a rotation: then the robot is returned as it is."""
    from scipy.spatial.transform import Rotation

    m = robot.measurement
    local = answer.tip_position + np.einsum("tij,j->ti", answer.tip_rotation, m.marker)  # (T, 3) base frame
    keep = recording.has_measurement & np.all(np.isfinite(local), axis=1)
    measured, predicted = recording.measured[keep], local[keep]
    if min(_spread_rank(measured), _spread_rank(predicted)) < 2:
        return robot
    rotation, _ = Rotation.align_vectors(measured - measured.mean(axis=0), predicted - predicted.mean(axis=0))
    position = measured.mean(axis=0) - rotation.apply(predicted.mean(axis=0))
    return replace(robot, measurement=replace(m, base_position=position, base_rotation=rotation.as_rotvec()))


def _spread_rank(points: np.ndarray) -> int:
    """How many directions the points ``(T, 3)`` m span about their mean (0 to 3; a direction whose
    spread is below 1e-9 of the largest does not count)."""
    return int(np.linalg.matrix_rank(points - points.mean(axis=0), rtol=1e-9)) if len(points) > 1 else 0


def _robust_cost(r: np.ndarray, loss: str, f_scale: float) -> float:
    """The cost ``least_squares`` minimises (times 2): sum rho(r^2) of the residuals ``r``."""
    if loss == "linear":
        return float(r @ r)
    return float((2.0 * f_scale**2 * (np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0)).sum())  # soft_l1 (LOSSES)


def _influence(r: np.ndarray, loss: str, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The loss's influence function psi(r) = d(cost / 2) / dr of :func:`_robust_cost` and its
    derivative psi'(r), each ``(m,)`` for the residuals ``r`` ``(m,)``: r and 1 for plain least
    squares; r / sqrt(1 + z) and (1 + z)^-3/2, z = (r / f_scale)^2, for soft_l1."""
    if loss == "linear":
        return r, np.ones_like(r)
    z = (r / f_scale) ** 2
    return r / np.sqrt(1.0 + z), (1.0 + z) ** -1.5


def _covariance(jac: np.ndarray, r: np.ndarray, *, loss: str, f_scale: float,
                groups: np.ndarray | None) -> tuple[np.ndarray, int]:
    """The covariance ``(q, q)`` of the parameters along the Jacobian's ``jac`` ``(m, q)`` columns at an
    optimum with residuals ``r`` ``(m,)``, and the number of clusters it was estimated over.

    With ``groups`` ``(n,)`` (int: the cluster of each of the first n residuals, the data's; the rest,
    e.g. a prior's, are not sampled) of at least two clusters: the cluster-robust sandwich of an
    M-estimator (Cameron & Miller 2015, "A practitioner's guide to cluster-robust inference",
    J. Human Resources 50(2); statsmodels' ``cov_type="cluster"``), A^-1 B A^-1 with
    A = J^T diag(psi') J and B the sum over the G clusters g of s_g s_g^T, s_g = J_g^T psi_g, times
    G / (G - 1) (n - 1) / (n - q).  Otherwise (or with ``groups=None``) the residuals are taken as
    independent: :func:`_covariance_scale` (J^T J)^-1, and 0 clusters."""
    q = jac.shape[1]
    count = 0 if groups is None or len(groups) == 0 else int(np.unique(groups).size)
    if count < 2:
        return _covariance_scale(r, loss, f_scale, free=q) * np.linalg.pinv(jac.T @ jac), 0
    psi, slope = _influence(r, loss, f_scale)
    bread = np.linalg.pinv(jac.T @ (slope[:, None] * jac))
    n = len(groups)
    sums = np.zeros((int(groups.max()) + 1, q))
    np.add.at(sums, groups, jac[:n] * psi[:n, None])  # each cluster's score s_g
    meat = sums.T @ sums * count / (count - 1) * (n - 1) / max(n - q, 1)
    return bread @ meat @ bread, count


def _correlations(cov: np.ndarray, names: Sequence[str], identified: np.ndarray) -> tuple[tuple[str, str, float], ...]:
    """The pairs of ``names`` (a, b, r) whose estimates correlate by at least :data:`CORRELATION_SHOWN`
    (either sign) under the covariance ``cov`` ``(p, p)``, among the ``identified`` ``(p,)`` (bool)
    ones, strongest first."""
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    shown = []
    for i, j in itertools.combinations(np.nonzero(identified & (sd > 0))[0], 2):
        r = float(cov[i, j] / (sd[i] * sd[j]))
        if abs(r) >= CORRELATION_SHOWN:
            shown.append((names[i], names[j], r))
    return tuple(sorted(shown, key=lambda pair: -abs(pair[2])))


def _covariance_scale(r: np.ndarray, loss: str, f_scale: float, *, free: int) -> float:
    """The factor of (J^T J)^-1 in the parameters' covariance, in the residuals' units squared, for
    the residuals ``r`` ``(m,)`` at an optimum with ``p = free`` free directions: Huber's estimate for
    an M-estimator (Huber 1981, Robust Statistics, sec. 7.6; statsmodels' RLM ``cov="H1"``),
    K^2 [sum psi^2 / (m - p)] / [mean psi']^2, K = 1 + (p / m) var(psi') / mean(psi')^2.  For plain
    least squares (psi = r, psi' = 1) it is s^2 = SSR / (m - p)."""
    m = len(r)
    psi, slope = _influence(r, loss, f_scale)
    mean = float(slope.mean())
    k = 1.0 + free / m * float(slope.var()) / mean**2
    return k**2 * float(psi @ psi) / max(m - free, 1) / mean**2


class _OutOfTime(Exception):
    """The fit's time budget is spent."""


def _jacobian(residual, z: np.ndarray, steps: np.ndarray, *, threads: int = 1) -> np.ndarray:
    """Forward differences ``(m, p)`` of ``residual`` at ``z`` ``(p,)`` with ``steps`` ``(p,)`` (search
    units), the columns' evaluations on ``threads`` threads."""
    r0 = residual(z)
    moved = list(z + np.diag(steps))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            shifted = list(pool.map(residual, moved))
    else:
        shifted = [residual(v) for v in moved]
    return np.stack([(r - r0) / h for r, h in zip(shifted, steps, strict=True)], axis=1)


def _replay_points(robot: Robot, answer: Replay, time: np.ndarray) -> Replay:
    """``answer`` with its measured points under ``robot``'s measurement (rows at ``time`` ``(T,)`` s)."""
    return replace(answer, points=robot.measurement.points(answer.tip_position, answer.tip_rotation, time))


def pauses(time: np.ndarray) -> np.ndarray:
    """Where a recording pauses (e.g. between patterns): the indices of the rows that come more than
    :data:`PLOT_GAP` times the median interval after the row before, from the rows' ``time`` ``(T,)`` s."""
    intervals = np.diff(np.asarray(time, dtype=np.float64))
    if not intervals.size:
        return np.zeros(0, dtype=np.int64)
    return np.nonzero(intervals > PLOT_GAP * np.median(intervals))[0] + 1


def plot(result: FitResult, train: Recording, validate: Recording | None, path: str) -> None:
    """Measured against predicted tips (x, y, z over the rows) and the error over time, for the
    train and validation recordings, into ``path`` (PNG); the lines break at the recordings'
    :func:`pauses`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = [("train", train, result.train_replay, result.train)]
    if validate is not None:
        sets.append(("validate", validate, result.validate_replay, result.validate))
    fig, axes = plt.subplots(2, len(sets), figsize=(7 * len(sets), 7), squeeze=False)
    for col, (name, rec, answer, err) in enumerate(sets):
        t = rec.time - rec.time[0]
        gaps = pauses(t)  # the lines break there instead of bridging rows the recording lacks
        t_lines = np.insert(t, gaps, np.nan)
        ax = axes[0, col]
        for a, axis in enumerate("xyz"):  # one colour per coordinate: measured dots, the predicted line
            ax.plot(t, rec.measured[:, a] * 1e3, ".", ms=2, color=f"C{a}", label=f"measured {axis}")
            ax.plot(t_lines, np.insert(answer.points[:, a], gaps, np.nan) * 1e3, "-", lw=0.8, color=f"C{a}",
                    label=f"predicted {axis}")
        ax.set(title=f"{name}: tip, mm (RMSE {err.rmse:.2f}, aligned {err.aligned:.2f})", xlabel="time, s")
        ax.legend(fontsize=6, ncol=3)
        ax = axes[1, col]
        error = np.linalg.norm(answer.points - rec.measured, axis=1) * 1e3
        ax.plot(t_lines, np.insert(error, gaps, np.nan), lw=0.8)
        ax.set(title=f"{name}: |error|, mm (max {err.max:.2f})", xlabel="time, s", ylabel="mm")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["GROUPS", "Errors", "FitResult", "Measurement", "Parameter", "at_start", "clusters", "errors", "fit",
           "pauses", "plot", "segments", "starts_crept"]
