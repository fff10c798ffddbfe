"""The real-robot commands on robots of other shapes: made-up robots whose recordings the solver makes.

    python benchmarks/synthetic_robots.py [--rows 400] [--noise-mm 0.3] [--keep DIR]

For each robot below a robot file (the truth) is written, its recordings are made by
``tdcr.replay`` of random bends and returns (train: ``--rows`` rows with three rows of motion capture
missing; val: 160 rows of other bends, recorded later), with Gaussian noise of ``--noise-mm`` per
coordinate, and a start file is written with rough values (E 0.6x, every tendon turned by 0.05 rad,
series stiffness 3,000 N/m where the truth has 2,000, the base pose unknown: 10 mm off and turned by
0.7 rad about z).  Then ``benchmarks/real_robot.py`` runs unchanged on the three files, as on the
shared recording.  The fit should end at the noise: sqrt(3) x ``--noise-mm`` RMSE.

* two segments of four tendons driven in tension (N);
* one segment of three tendons driven in displacement, columns in m;
* two segments of three helical tendons (3 rad/m), displacement in mm.

Figures depend on the machine: it is printed (by real_robot.py, per robot).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tdcr.physics.replay import replay  # noqa: E402
from tdcr.robot.real import load_robot  # noqa: E402

#: (name, segments, tendons per segment, L m, actuation kind, unit, pitch rad/m)
ROBOTS = (("two segments in tension", 2, 4, 0.2, "tension", "N", 0.0),
          ("one segment in m", 1, 3, 0.15, "displacement", "m", 0.0),
          ("helical, two segments in mm", 2, 3, 0.2, "displacement", "mm", 3.0))
#: Each drive's largest command: m of displacement, N of tension.
AMPLITUDE = {"displacement": 0.004, "tension": 2.0}
SAMPLING = 0.5  # s between rows


def robot_file(segments: int, per_segment: int, length: float, kind: str, unit: str, pitch: float) -> dict:
    """The truth: a robot file with Capstan friction 0.05 and, driven in displacement, series
    stiffness 2,000 N/m; its base 10 mm off and turned by 0.7 rad about z in the capture's frame."""
    tendons = []
    for k in range(segments):
        for i in range(per_segment):
            tendon = {"offset": 0.005, "pitch": pitch, "friction": 0.05, "end": length * (k + 1) / segments,
                      "angle": 2.0 * np.pi * i / per_segment + k * np.pi / (per_segment * segments)}
            tendon |= {"displacement": 0.0, "stiffness": 2000.0, "zero": 0.0} if kind == "displacement" else {
                "tension": 0.0}
            tendons.append(tendon)
    return {"design": {"E": 40e9, "r": 0.0006, "L": length, "tendons": tendons},
            "actuation": {"columns": [f"drive{j}_{unit}" for j in range(len(tendons))], "unit": unit, "kind": kind,
                          "deadband": 0.0},
            "measurement": {"columns": ["X", "Y", "Z"], "unit": "mm", "marker": [0.0, 0.0, 0.005],
                            "base_position": [0.003, -0.002, 0.01], "base_rotation": [0.0, 0.0, 0.7]},
            "time_column": "time", "label_column": "label"}


def rough(truth: dict) -> dict:
    """The start: what a builder knows before the fit."""
    start = json.loads(json.dumps(truth))
    start["design"]["E"] *= 0.6
    start["measurement"] |= {"base_position": [0.0, 0.0, 0.0], "base_rotation": [0.0, 0.0, 0.0]}
    for tendon in start["design"]["tendons"]:
        tendon["angle"] += 0.05
        if "stiffness" in tendon:
            tendon["stiffness"] = 3000.0
    return start


def bends(n_tendons: int, rows: int, kind: str, rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """``rows`` command rows ``(T, N_t)`` SI: random bends, each out in 10 rows and back in 10 (half
    the drives let out, or at 0 N), and their labels."""
    out, labels = [], []
    for pattern in range(rows // 20):
        target = rng.uniform(-0.3, 1.0, n_tendons) * AMPLITUDE[kind]
        target[rng.random(n_tendons) < 0.5] = -0.3 * AMPLITUDE[kind]
        for s in (*np.linspace(0.0, 1.0, 10), *np.linspace(1.0, 0.0, 10)):
            out.append(s * target)
            labels.append(f"bend{pattern}")
    commands = np.array(out)
    return (np.maximum(commands, 0.0) if kind == "tension" else commands), labels


def write_recording(path: Path, data: dict, commands: np.ndarray, labels: list[str], time: np.ndarray,
                    tips_m: np.ndarray) -> None:
    """A CSV in the robot file's columns and units (an empty cell where the capture has no tip)."""
    scale = 1e3 if data["actuation"]["unit"] == "mm" else 1.0
    lines = [",".join(["time", "label", *data["actuation"]["columns"], "X", "Y", "Z"])]
    for t, label, row, tip in zip(time, labels, commands, tips_m * 1e3, strict=True):
        cells = ["" if not np.isfinite(v) else f"{v:.4f}" for v in tip]
        lines.append(",".join([f"{t:.3f}", label, *(f"{v * scale:.6g}" for v in row), *cells]))
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=400, help="train rows per robot (val: 160)")
    parser.add_argument("--noise-mm", type=float, default=0.3, help="motion-capture noise per coordinate, mm")
    parser.add_argument("--keep", default=None, help="write the files here (default: a temporary folder)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(args.keep or scratch)
        folder.mkdir(parents=True, exist_ok=True)
        for name, segments, per_segment, length, kind, unit, pitch in ROBOTS:
            truth = robot_file(segments, per_segment, length, kind, unit, pitch)
            robot = load_robot(truth)
            stem = name.replace(" ", "_").replace(",", "")
            paths = {}
            for split, rows, t0 in (("train", args.rows, 0.0), ("val", 160, 10.0 * args.rows)):
                commands, labels = bends(robot.n_tendons, rows, kind, rng)
                time = t0 + SAMPLING * np.arange(len(commands))
                answer = replay(robot, commands, time=time)
                tips = answer.points + rng.normal(0.0, args.noise_mm * 1e-3, answer.points.shape)
                if split == "train":
                    tips[5:8] = np.nan  # motion capture lost the marker
                paths[split] = folder / f"{stem}_{split}.csv"
                write_recording(paths[split], truth, commands, labels, time, tips)
            paths["robot"] = folder / f"{stem}.json"
            paths["robot"].write_text(json.dumps(rough(truth), indent=1) + "\n")
            print(f"\n## {name}: {robot.n_tendons} tendons, noise {args.noise_mm} mm per coordinate "
                  f"(the fit's floor: {np.sqrt(3.0) * args.noise_mm:.2f} mm RMSE)\n", flush=True)
            subprocess.run([sys.executable, str(ROOT / "benchmarks" / "real_robot.py"), "--robot", str(paths["robot"]),
                            "--train", str(paths["train"]), "--validate", str(paths["val"]), "--repeats", "1"],
                           check=True)


if __name__ == "__main__":
    main()
