"""Replay a real robot's commands through the physics (``tdcr replay``, :func:`replay`).

Each command row is a design (:meth:`tdcr.robot.real.Robot.designs`): the robot's design with each
tendon's displacement (or tension) from the row and its motion from the command history (pull or
release, the sign of its friction, eq. CAP; a hold keeps the last).  Given the motions the rows are
independent equilibria, so they are solved side by side on every core, each run of rows in order
with warm starts (``solve(..., sequence=True)``; under the robot file's loads, the loaded
displacement solve, its Jacobians shared along the sequence); the measured point of each tip follows from the
robot's marker and base pose, seen through its lag in time when the rows' times are given
(:meth:`tdcr.robot.real.Measurement.points`, eq. LAG).  With the rows' times, a robot whose tendons
creep (``actuation.creep_rate``) is one chain in time instead: each row's pull-ins fall short by what
its tendons crept in the rows before (eq. CREEP), so its rows are solved in order on one thread (under
loads, in sweeps of the whole chain, each on every core: :func:`tdcr.physics.cosserat.crept_by`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from tdcr.physics.cosserat import SolverOptions, solve
from tdcr.physics.status import STATUS
from tdcr.robot.real import Recording, Robot

#: The solver's settings for replays, far below motion capture's error: a base step of L / 20, the
#: step control at 1e-5 relative and the pull-ins met to 10 nm (defaults: L / 41, 3e-7 and 0.1 nm).
#: On the shared FTDCR v4 recording the tips move by at most 0.1 um against step_tol 1e-8 and 0.1 nm,
#: at 1.8x the speed (benchmarks/real_robot.py).
REPLAY_OPTIONS = SolverOptions(max_step=1.0 / 20.0, step_tol=1e-5, displacement_tol=1e-8)


@dataclass(frozen=True)
class Replay:
    """The answer of :func:`replay` for ``T`` command rows: ``points`` ``(T, 3)`` m, the predicted
    measured points (measurement frame); ``tip_position`` ``(T, 3)`` m and ``tip_rotation``
    ``(T, 3, 3)``, the tip poses in the base frame; ``tension`` ``(T, N_t)`` N at the drives;
    ``motion`` ``(T, N_t)`` (1 pull, -1 release); ``status`` ``(T,)`` (indices into
    :data:`tdcr.physics.STATUS`); ``crept`` ``(T, N_t)`` m, how far each tendon had crept by its
    row (eq. CREEP; zeros without creep)."""

    points: np.ndarray
    tip_position: np.ndarray
    tip_rotation: np.ndarray
    tension: np.ndarray
    motion: np.ndarray
    status: np.ndarray
    crept: np.ndarray

    @property
    def converged(self) -> np.ndarray:
        return self.status == 0

    def take(self, keep: np.ndarray) -> Replay:
        """The rows where ``keep`` ``(T,)`` (bool) is true, in their order (as ``Recording.take``)."""
        return Replay(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})


def replay(robot: Robot, commands: np.ndarray, *, time: np.ndarray | None = None, motion: np.ndarray | None = None,
           workers: int = 0, options: SolverOptions = REPLAY_OPTIONS, progress: bool = False) -> Replay:
    """The robot's tip for each command row.

    Args:
        robot: the robot (:func:`tdcr.robot.real.load_robot`).
        commands: ``(T, N_t)`` SI (m of displacement or N of tension, by ``robot.actuation.kind``),
            in the order they were sent.
        time: the rows' times ``(T,)`` s: the measured points follow the equilibria with the
            measurement's ``time_constant`` (eq. LAG), and the tendons creep at the actuation's
            ``creep_rate`` (eq. CREEP); ``None``: each row's equilibrium as it is (no clock: no lag,
            no creep).
        motion: each tendon's motion per row ``(T, N_t)`` (default: from the command history,
            :func:`tdcr.robot.real.motions`).
        workers: kernel threads (0: one per core).
        options: the solver's settings.
        progress: show a progress bar of the rows solved (tqdm, on stderr).  Under loads it moves
            :data:`tdcr.physics.cosserat.LOADED_CHUNK` rows at a time (the answers do not change), and
            a creeping chain's sweeps each go through the rows again; elsewhere (thousands of rows a
            second) it fills at the end.
    """
    commands = np.asarray(commands, dtype=np.float64)
    designs = robot.designs(commands, motion)  # checks the commands and motions
    if time is not None:
        time = np.asarray(time, dtype=np.float64)
        if time.shape != (len(commands),) or not np.isfinite(time).all() or (np.diff(time) <= 0).any():
            raise ValueError(f"time: must be ({len(commands)},) finite seconds that increase, one per command row")
    motion = designs.motion
    creep = robot.creep(time) if time is not None and robot.creeps else None
    from tqdm import tqdm  # here: 30 ms that ``import tdcr`` need not pay

    rows = len(commands)
    sweeps = creep is not None and robot.loads is not None
    with tqdm(total=rows, desc="replay, sweep 1" if sweeps else "replay", unit="row", disable=not progress,
              leave=False) as bar:
        def solved(n: int) -> None:
            if bar.n + n > bar.total:  # a creeping chain's next sweep under loads
                bar.total += rows
                bar.set_description(f"replay, sweep {bar.total // rows}")
            bar.update(n)

        sol = solve(designs, np.ones(1), loads=robot.row_loads(rows), options=options, workers=workers,
                    sequence=True, creep=creep, progress=solved if progress else None)
        bar.update(bar.total - bar.n)
    position, rotation = sol.backbone[:, -1], sol.rotation[:, -1]
    return Replay(points=robot.measurement.points(position, rotation, time), tip_position=position,
                  tip_rotation=rotation, tension=sol.tension, motion=motion, status=sol.status.astype(np.int32),
                  crept=np.zeros(commands.shape) if sol.crept is None else sol.crept)


def write_predictions(path: str | Path, robot: Robot, recording: Recording, answer: Replay) -> None:
    """The predicted points as a CSV in the measurement's own columns and unit, one row per command
    row: the time column, the label column (if the robot names one), the measurement's columns and
    the solver's ``status``."""
    scale = robot.measurement.scale
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        labels = [robot.label_column] if robot.label_column else []
        out.writerow([robot.time_column, *labels, *robot.measurement.columns, "status"])
        for t in range(len(recording.time)):
            label = [recording.labels[t]] if robot.label_column else []
            out.writerow([repr(float(recording.time[t])), *label,
                          *(f"{v / scale:.6f}" for v in answer.points[t]), STATUS[int(answer.status[t])]])
