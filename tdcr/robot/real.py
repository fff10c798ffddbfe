"""A real robot: its design, how its drives are commanded and how its tip is measured (``ROBOT.json``),
and its recordings (CSV files of commands and motion-capture tips).

A robot file (JSON Schema: ``openapi/robot.schema.json``, :data:`ROBOT_SCHEMA`)::

    {"name": "ftdcr_v4",
     "design": {...a request design (``tdcr.api.schemas.Design``): E, r, L, poisson, and tendons with
                offset, angle, pitch, end, stiffness, friction, zero...; optionally gravity (m/s^2)
                with density (kg/m^3), tip_force and tip_moment, in the base frame, for every row},
     "actuation": {"columns": [one CSV column per tendon, in tendon order], "unit": "mm" | "m" | "N",
                   "kind": "displacement" | "tension", "deadband": the least command change that moves
                   a tendon (the actuation's unit; default 0): below it the tendon holds its motion,
                   "creep_rate": 1/s, how fast each tendon's series spring relaxes by creeping
                   (eq. CREEP; default 0: it does not)},
     "measurement": {"columns": ["tip_x", "tip_y", "tip_z"], "unit": "mm",
                     "marker": [x, y, z] m in the tip frame,
                     "base_position": [x, y, z] m and "base_rotation": [x, y, z] rad (a rotation
                     vector): where the robot's base frame sits in the measurement's frame,
                     "time_constant": s, with which the measured tip follows each row's
                     equilibrium (eq. LAG; default 0: at once)},
     "time_column": "timestamp", "label_column": "pattern_label" (optional),
     "fitted": {...what ``tdcr fit`` found, with standard errors (optional, informative)}}

A command row is a design: the robot's design with each tendon's displacement (or tension) from the
row, and its ``motion`` (pull or release, the sign of its friction, eq. CAP) from the command
history (:func:`motions`).  The measured point is base_position + Rot(base_rotation) (p(L) + R(L)
marker) (:meth:`Measurement.points`), seen through a first-order lag in time (:func:`settle`, eq. LAG)
when the robot has a ``time_constant``.  A robot whose tendons creep (``creep_rate``) replays its rows
as one chain in time: each pull-in falls short by what the tendon crept under its tension in the rows
before (eq. CREEP, :mod:`tdcr.physics.cosserat`; :meth:`Robot.creep`).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tdcr.robot.designs import DesignBatch, ExternalLoads
from tdcr.robot.fields import MOTIONS

if TYPE_CHECKING:
    from tdcr.api.validation import DesignGroup

#: Units of the actuation and measurement columns: name -> factor to SI (m or N).
UNITS: dict[str, float] = {"m": 1.0, "mm": 1e-3, "N": 1.0}
#: What a column of commands drives: the unit names each admits.
KINDS: dict[str, tuple[str, ...]] = {"displacement": ("m", "mm"), "tension": ("N",)}
#: The measurement's units (lengths).
LENGTH_UNITS = ("m", "mm")


class RobotFileError(ValueError):
    """A robot file or recording that cannot be used; the message names the key, column or row
    (the CLI exits with code 2)."""


def rotation_matrix(vector: np.ndarray) -> np.ndarray:
    """Rot(v) = exp(hat(v)) of rotation vectors ``(..., 3)`` rad (Rodrigues), ``(..., 3, 3)``."""
    v = np.asarray(vector, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(theta > 1e-8, np.sin(theta) / theta, 1.0 - theta**2 / 6.0)
        b = np.where(theta > 1e-8, (1.0 - np.cos(theta)) / theta**2, 0.5 - theta**2 / 24.0)
    return np.eye(3) + a * k + b * (k @ k)


@dataclass(frozen=True)
class Actuation:
    """How the drives are commanded: one CSV ``columns`` entry per tendon (tendon order), their
    ``unit`` (:data:`UNITS`), ``kind`` (:data:`KINDS`), ``deadband`` (SI, m or N): a command
    change below it keeps the tendon's motion, and ``creep_rate`` r (1/s): each displacement-driven
    tendon with a series stiffness k lengthens by r tau / k per second under its tension tau
    (eq. CREEP; 0: it does not creep)."""

    columns: tuple[str, ...]
    unit: str
    kind: str
    deadband: float = 0.0
    creep_rate: float = 0.0

    @property
    def scale(self) -> float:
        """Factor from the columns' unit to SI."""
        return UNITS[self.unit]


@dataclass(frozen=True)
class Measurement:
    """How the tip is measured: the CSV ``columns`` (x, y, z) in ``unit``, the ``marker`` (3,) m in
    the tip frame, the base frame's pose in the measurement frame: ``base_position`` (3,) m and
    ``base_rotation`` (3,) rad, a rotation vector; and the ``time_constant`` s with which the
    measured tip follows the equilibrium of each row (eq. LAG, :func:`settle`; 0: at once)."""

    columns: tuple[str, ...]
    unit: str
    marker: np.ndarray = field(default_factory=lambda: np.zeros(3))
    base_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    base_rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_constant: float = 0.0

    @property
    def scale(self) -> float:
        """Factor from the columns' unit to m."""
        return UNITS[self.unit]

    def points(self, tip_position: np.ndarray, tip_rotation: np.ndarray, time: np.ndarray | None = None) -> np.ndarray:
        """The measured points, m, measurement frame, ``(T, 3)``, of tips at ``tip_position`` ``(T, 3)``
        m with frames ``tip_rotation`` ``(T, 3, 3)`` (base frame): b + Rot(r) (p + R marker); with the
        rows' ``time`` ``(T,)`` s, seen through the lag of the ``time_constant`` (:func:`settle`)."""
        local = tip_position + np.einsum("tij,j->ti", tip_rotation, self.marker)
        static = self.base_position + local @ rotation_matrix(self.base_rotation).T
        return static if time is None else settle(static, time, self.time_constant)


def settle(points: np.ndarray, time: np.ndarray, time_constant: float) -> np.ndarray:
    """What a first-order lag with ``time_constant`` T (s) shows of ``points`` ``(T_rows, 3)``, each
    row's equilibrium, at the rows' ``time`` ``(T_rows,)`` s (eq. LAG): the measured point relaxes
    towards each new equilibrium q_t,

        y_0 = q_0,   y_t = q_t + (y_{t-1} - q_t) exp(-(t_t - t_{t-1}) / T),

    the step response of a first-order system between two samples (the robot still settling when the
    motion capture samples it).  T = 0 gives ``points``; a row that is not finite passes through, and
    the next starts afresh from its own equilibrium."""
    points = np.asarray(points, dtype=np.float64)
    if time_constant <= 0.0 or len(points) < 2:
        return points
    keep = np.exp(-np.diff(np.asarray(time, dtype=np.float64)) / time_constant)  # (T_rows - 1,)
    finite = np.isfinite(points).all(axis=1)
    out = points.copy()
    for t in range(1, len(points)):
        if finite[t - 1]:  # out[t - 1] is finite exactly where points[t - 1] is
            out[t] += keep[t - 1] * (out[t - 1] - points[t])
    return out


@dataclass(frozen=True)
class Robot:
    """A real robot (a robot file): its ``design`` (one design, :class:`DesignBatch`), its
    :class:`Actuation` and :class:`Measurement`, the recording's ``time_column`` and optional
    ``label_column``, the file's ``extra`` keys (e.g. ``fitted``), kept as they are, and the
    design's ``loads`` (gravity and a tip wrench in the base frame, one row; None: none), which
    every command row carries."""

    name: str
    design: DesignBatch
    actuation: Actuation
    measurement: Measurement
    time_column: str = "timestamp"
    label_column: str | None = None
    extra: dict = field(default_factory=dict)
    loads: ExternalLoads | None = None

    def row_loads(self, n_rows: int) -> ExternalLoads | None:
        """The loads of ``n_rows`` command rows (each the robot's), or None without loads."""
        return None if self.loads is None else self.loads.take(np.zeros(n_rows, dtype=np.int64))

    @property
    def n_tendons(self) -> int:
        return self.design.n_tendons

    def to_json(self) -> dict:
        """The robot file's JSON (the design as a request gives it)."""
        a, m = self.actuation, self.measurement
        design = self.design.to_dicts()[0]
        if self.loads is not None:  # as a request gives them: the loads that act (a weight with its density)
            acting = {"gravity": self.loads.gravity, "density": self.loads.gravity,
                      "tip_force": self.loads.tip_force, "tip_moment": self.loads.tip_moment}
            design |= {name: np.asarray(getattr(self.loads, name))[0].tolist() for name, value in acting.items()
                       if value is not None and np.any(value)}
        out = {"name": self.name, "design": design,
               "actuation": {"columns": list(a.columns), "unit": a.unit, "kind": a.kind,
                             "deadband": a.deadband / a.scale, "creep_rate": a.creep_rate},
               "measurement": {"columns": list(m.columns), "unit": m.unit, "marker": m.marker.tolist(),
                               "base_position": m.base_position.tolist(),
                               "base_rotation": m.base_rotation.tolist(), "time_constant": m.time_constant},
               "time_column": self.time_column}
        if self.label_column is not None:
            out["label_column"] = self.label_column
        return out | self.extra

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @property
    def creeps(self) -> bool:
        """Whether a replay with the rows' times carries the tendons' creep (eq. CREEP)."""
        return self.actuation.kind == "displacement" and self.actuation.creep_rate > 0.0

    def creep(self, time: np.ndarray) -> np.ndarray:
        """How far each tendon lengthens per newton of its tension after each row at ``time`` ``(T,)``
        s, ``(T, N_t)`` m/N: r (t_{k+1} - t_k) / k_i (eq. CREEP; a rigid tendon does not creep, and the
        last row's creep comes after the recording)."""
        interval = np.append(np.diff(np.asarray(time, dtype=np.float64)), 0.0)  # (T,) s to the next row
        return self.actuation.creep_rate * interval[:, None] * self.design.compliance[0][None, :]

    def after(self, crept: np.ndarray) -> Robot:
        """The robot once its tendons crept by ``crept`` ``(N_t,)`` m: each drive's zero moved by it
        (a crept tendon needs that much more pull-in to be taut), the state a later recording starts
        from."""
        return replace(self, design=self.design.replace(zero=self.design.resolved("zero") + crept[None, :]))

    def designs(self, commands: np.ndarray, motion: np.ndarray | None = None) -> DesignBatch:
        """One design per command row: ``commands`` ``(T, N_t)`` SI (m of displacement or N of
        tension, by the actuation's kind) and each tendon's ``motion`` ``(T, N_t)`` (1 pull, -1
        release; default :func:`motions` of the commands).  Commands of another shape, or one that is
        not a finite number, raise ``ValueError`` naming it (NaN is not "no command")."""
        commands = np.asarray(commands, dtype=np.float64)
        if commands.ndim != 2 or commands.shape[1] != self.n_tendons or not len(commands):
            raise ValueError(f"commands: must be (T, N_t) = (T >= 1, {self.n_tendons}) for this robot's "
                             f"{self.n_tendons} tendons, got shape {commands.shape}")
        bad = np.argwhere(~np.isfinite(commands))
        if bad.size:
            raise ValueError(f"commands[{bad[0][0]}, {bad[0][1]}] (row, tendon): not a finite number, "
                             f"got {commands[tuple(bad[0])]}")
        if motion is not None and (np.shape(motion) != commands.shape
                                   or not np.isin(motion, list(MOTIONS.values())).all()):
            raise ValueError(f"motion: must be {commands.shape} of {MOTIONS} (pull, release)")
        rows = self.design.take(np.zeros(len(commands), dtype=np.int64))
        motion = motions(commands, self.actuation.deadband) if motion is None else motion
        if self.actuation.kind == "tension":
            return rows.replace(tension=commands, displacement=None, motion=motion)
        return rows.replace(tension=np.zeros_like(commands), displacement=commands, motion=motion)


def motions(commands: np.ndarray, deadband: float = 0.0) -> np.ndarray:
    """Each tendon's motion through its guides at each command row, ``(T, N_t)``: pull (1) where its
    command rose by more than ``deadband`` since the row before, release (-1) where it fell by more,
    else (holding) the motion it had; the first row pulls.  ``commands`` ``(T, N_t)``."""
    commands = np.asarray(commands, dtype=np.float64)
    out = np.empty(commands.shape)
    state = np.full(commands.shape[1], MOTIONS["pull"])
    last = commands[0].copy() if len(commands) else None
    for t in range(len(commands)):
        step = commands[t] - last
        moved = np.abs(step) > deadband
        state = np.where(moved, np.where(step > 0, MOTIONS["pull"], MOTIONS["release"]), state)
        last = np.where(moved, commands[t], last)  # a hold accumulates its small steps
        out[t] = state
    return out


def _vector(value, where: str) -> np.ndarray:
    numbers = isinstance(value, list) and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
    v = np.asarray(value, dtype=np.float64) if numbers else None
    if v is None or v.shape != (3,) or not np.isfinite(v).all():
        raise RobotFileError(f"{where}: must be a list of 3 finite numbers, got {value!r}")
    return v


def _choice(section: dict, key: str, where: str, allowed, default=None):
    value = section.get(key, default)
    if not isinstance(value, str) or value not in allowed:
        raise RobotFileError(f"{where}.{key}: must be one of {list(allowed)}, got {value!r}")
    return value


def _nonnegative(section: dict, key: str, where: str) -> float:
    """``section[key]`` (default 0), a finite number >= 0."""
    value = section.get(key, 0.0)
    if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value) and value >= 0):
        raise RobotFileError(f"{where}.{key}: must be a number >= 0, got {value!r}")
    return float(value)


def _name(data: dict, key: str, default: str | None) -> str | None:
    """``data[key]``, a column's name: a non-empty string (``default`` when absent); a column whose
    default is None (optional: none) may also be null."""
    value = data.get(key, default)
    if not (isinstance(value, str) and value) and not (default is None and value is None):
        raise RobotFileError(f"{key}: must be a column's name (a non-empty string), got {value!r}")
    return value


def _columns(section: dict, where: str, count: int) -> tuple[str, ...]:
    cols = section.get("columns")
    if not isinstance(cols, list) or len(cols) != count or not all(isinstance(c, str) and c for c in cols):
        raise RobotFileError(f"{where}.columns: must be a list of {count} column names, got {cols!r}")
    return tuple(cols)


def load_robot(source: str | Path | dict) -> Robot:
    """A :class:`Robot` from a robot file (a path or its parsed JSON).  The design goes through the
    one validation path (:func:`tdcr.api.validation.validate_json`, the solver's checks), the rest
    through :func:`robot_from`; every problem raises :class:`RobotFileError` naming its key."""
    from tdcr.api.checks import InvalidRequest
    from tdcr.api.validation import validate_json

    if isinstance(source, dict):
        data = source
    else:
        try:
            data = json.loads(Path(source).read_text())
        except OSError as exc:
            raise RobotFileError(f"{source}: cannot read ({exc.strerror})") from None
        except json.JSONDecodeError as exc:
            raise RobotFileError(f"{source}: not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise RobotFileError("the robot file must be a JSON object")
    if not isinstance(data.get("design"), dict):
        raise RobotFileError("design: missing (an object)")
    try:
        request = validate_json({"designs": [data["design"]], "points": 2}, target="solver")
    except InvalidRequest as exc:
        raise RobotFileError("; ".join(f"design{_where(p.loc[2:])}: {p.msg}" for p in exc.problems)) from None
    return robot_from(data, request.groups[0])


def robot_from(data: dict, group: DesignGroup) -> Robot:
    """The :class:`Robot` of robot file ``data`` whose design has passed the one validation path as
    :class:`tdcr.api.validation.DesignGroup` ``group`` (one design; its loads, absent ones as zeros):
    the rest of the file checked here, each problem a :class:`RobotFileError` naming its key (the
    service's ``/exact`` takes a robot file through this too, without validating its design again)."""
    for key in ("actuation", "measurement"):
        if not isinstance(data.get(key), dict):
            raise RobotFileError(f"{key}: missing (an object)")
    design, loads = group.designs, group.loads
    loads = None if loads is None or loads.is_zero() else loads
    a, m = data["actuation"], data["measurement"]
    kind = _choice(a, "kind", "actuation", KINDS, "displacement")
    unit = _choice(a, "unit", "actuation", KINDS[kind])
    actuation = Actuation(columns=_columns(a, "actuation", design.n_tendons), unit=unit, kind=kind,
                          deadband=_nonnegative(a, "deadband", "actuation") * UNITS[unit],
                          creep_rate=_nonnegative(a, "creep_rate", "actuation"))
    if actuation.creep_rate > 0.0 and kind != "displacement":
        raise RobotFileError("actuation.creep_rate: creep moves a displacement-driven tendon's pull-in; this "
                             f"robot's drives command {kind}s (actuation.kind), which creep does not change")
    measurement = Measurement(columns=_columns(m, "measurement", 3), unit=_choice(m, "unit", "measurement",
                                                                                   LENGTH_UNITS),
                              time_constant=_nonnegative(m, "time_constant", "measurement"),
                              **{k: _vector(m.get(k, [0.0, 0.0, 0.0]), f"measurement.{k}")
                                 for k in ("marker", "base_position", "base_rotation")})
    known = {"name", "design", "actuation", "measurement", "time_column", "label_column"}
    return Robot(name=str(data.get("name", "robot")), design=design, actuation=actuation, measurement=measurement,
                 time_column=_name(data, "time_column", "timestamp"), label_column=_name(data, "label_column", None),
                 extra={k: v for k, v in data.items() if k not in known}, loads=loads)


def _where(loc: tuple) -> str:
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)


@dataclass(frozen=True)
class Recording:
    """A recording's rows that the robot can replay: ``time`` ``(T,)`` s, ``labels`` ``(T,)`` (the
    label column, or ""), ``commands`` ``(T, N_t)`` SI, ``measured`` ``(T, 3)`` m (NaN where the row
    has no motion-capture value), the CSV's data-row numbers ``rows`` ``(T,)`` (1: the first data
    row), and ``header`` (the CSV's columns)."""

    time: np.ndarray
    labels: np.ndarray
    commands: np.ndarray
    measured: np.ndarray
    rows: np.ndarray
    header: tuple[str, ...]

    @property
    def has_measurement(self) -> np.ndarray:
        """Per row ``(T,)``: the row has a motion-capture value."""
        return np.isfinite(self.measured).all(axis=1)

    @property
    def skipped(self) -> int:
        """Rows without a motion-capture value (replayed, not scored)."""
        return int((~self.has_measurement).sum())

    def take(self, keep: np.ndarray) -> Recording:
        """The rows where ``keep`` ``(T,)`` (bool) is true, in their order (a fold of a recording)."""
        keep = np.asarray(keep, dtype=bool)
        return Recording(time=self.time[keep], labels=self.labels[keep], commands=self.commands[keep],
                         measured=self.measured[keep], rows=self.rows[keep], header=self.header)


def _number(text: str) -> float:
    try:
        return float(text) if text.strip() else math.nan
    except ValueError:
        return math.nan


def read_recording(path: str | Path, robot: Robot, *, measured: bool | None = True) -> Recording:
    """A recording of ``robot`` (CSV with a header, UTF-8 with or without a byte-order mark; blank lines
    are ignored): its time, command and (with ``measured``; None: where the file has them) measurement
    columns.  A file without data rows, a missing column, a command that is not a finite number, or a
    time that is not finite or not increasing raises :class:`RobotFileError` naming the column and row
    (the CSV's data-row number); a row without a motion-capture value is kept with NaN
    (:attr:`Recording.skipped`)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # -sig: a spreadsheet's byte-order mark
            reader = csv.reader(f)
            header = tuple(next(reader, ()))
            numbered = [(row, line) for row, line in enumerate(reader, start=1) if any(c.strip() for c in line)]
    except OSError as exc:
        raise RobotFileError(f"{path}: cannot read ({exc.strerror})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise RobotFileError(f"{path}: not a UTF-8 CSV file ({exc})") from None
    if not any(c.strip() for c in header):
        raise RobotFileError(f"{path}: empty (a CSV file with a header row of column names is expected)")
    if measured is None:
        measured = all(c in header for c in robot.measurement.columns)
    wanted = [robot.time_column, *robot.actuation.columns] + (list(robot.measurement.columns) if measured else [])
    missing = [c for c in wanted if c not in header]
    if missing:
        raise RobotFileError(f"{path}: missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                             f"(the file has {', '.join(header)})")
    if not numbered:
        raise RobotFileError(f"{path}: no data rows below the header")
    rows = np.array([row for row, _ in numbered])
    lines = [line for _, line in numbered]
    index = {c: header.index(c) for c in header}

    def cell(line: list[str], name: str) -> str:
        return line[index[name]] if index[name] < len(line) else ""

    def column(name: str) -> np.ndarray:
        return np.array([_number(cell(line, name)) for line in lines])

    time = column(robot.time_column)
    commands = np.stack([column(c) for c in robot.actuation.columns], axis=1)
    for name, values in [(robot.time_column, time)] + [(c, commands[:, i]) for i, c in
                                                       enumerate(robot.actuation.columns)]:
        bad = np.nonzero(~np.isfinite(values))[0]
        if bad.size:
            raise RobotFileError(f"{path}: column {name}, row {rows[bad[0]]}: not a finite number "
                                 f"({cell(lines[bad[0]], name)!r})")
    back = np.nonzero(np.diff(time) <= 0)[0]
    if back.size:
        raise RobotFileError(f"{path}: column {robot.time_column}, row {rows[back[0] + 1]}: timestamps must "
                             f"increase ({time[back[0] + 1]!r} after {time[back[0]]!r})")
    if measured:
        tips = np.stack([column(c) for c in robot.measurement.columns], axis=1) * robot.measurement.scale
    else:
        tips = np.full((len(lines), 3), np.nan)
    labels = np.array([cell(line, robot.label_column) if robot.label_column in index else "" for line in lines])
    return Recording(time=time, labels=labels, commands=commands * robot.actuation.scale, measured=tips,
                     rows=rows, header=header)


def robot_schema(*, ref_template: str = "#/$defs/{model}") -> dict:
    """The robot file's JSON Schema (``openapi/robot.schema.json``); its ``design`` is the solver's
    request design (``tdcr.api.schemas.Design``), its definitions under ``$defs`` referred to by
    ``ref_template`` (the OpenAPI document's components: ``#/components/schemas/{model}``)."""
    from tdcr.api.schemas import Design

    design = Design.model_json_schema(ref_template=ref_template)
    defs = design.pop("$defs", {})
    vector = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
    columns = {"type": "array", "items": {"type": "string", "minLength": 1}}
    # each kind its units (the default kind may be left out); creep moves displacement-driven tendons only
    by_kind = [{"properties": {"kind": {"const": "displacement"}, "unit": {"enum": list(KINDS["displacement"])}}},
               {"required": ["kind"], "properties": {"kind": {"const": "tension"},
                                                     "unit": {"enum": list(KINDS["tension"])},
                                                     "creep_rate": {"maximum": 0}}}]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema", "title": "tdcr robot file",
        "description": "A real robot for tdcr replay and tdcr fit (tdcr/robot/real.py): its design, how its drives are "
                       "commanded (one CSV column per tendon) and how its tip is measured. Other keys are kept.",
        "type": "object", "required": ["design", "actuation", "measurement"],
        "properties": {
            "name": {"type": "string"},
            "design": design,
            "actuation": {"type": "object", "required": ["columns", "unit"], "anyOf": by_kind, "properties": {
                "columns": columns | {"description": "one column per tendon, in tendon order"},
                "unit": {"enum": list(UNITS)}, "kind": {"enum": list(KINDS), "default": "displacement"},
                "deadband": {"type": "number", "minimum": 0, "default": 0,
                             "description": "the least command change (the actuation's unit) that moves a tendon; "
                                            "below it the tendon keeps its motion (pull or release)"},
                "creep_rate": {"type": "number", "minimum": 0, "default": 0,
                               "description": "1/s: each displacement-driven tendon of series stiffness k "
                                              "lengthens by creep_rate * tension / k per second and never "
                                              "recovers (a replay with times; 0: no creep)"}}},
            "measurement": {"type": "object", "required": ["columns", "unit"], "properties": {
                "columns": columns | {"minItems": 3, "maxItems": 3}, "unit": {"enum": list(LENGTH_UNITS)},
                "marker": vector | {"description": "the measured point in the tip frame, m"},
                "base_position": vector | {"description": "the base frame's origin in the measurement frame, m"},
                "base_rotation": vector | {"description": "the base frame's rotation in the measurement frame, a "
                                                          "rotation vector, rad"},
                "time_constant": {"type": "number", "minimum": 0, "default": 0,
                                  "description": "s: the measured tip follows each row's equilibrium with this "
                                                 "first-order lag (0: at once)"}}},
            "time_column": columns["items"] | {"default": "timestamp"},  # a column's name, as load_robot checks
            "label_column": {"anyOf": [columns["items"], {"type": "null"}], "description": "null: no labels"},
            "fitted": {"type": "object", "description": "what tdcr fit found: parameters with standard errors, "
                                                        "train and validation errors (informative)"}},
        "$defs": defs}
