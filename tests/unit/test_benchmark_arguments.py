"""The real-robot benchmark scripts refuse bad arguments and unreadable files with exit code 2 and the
reason, before any fit (each run here is a real process)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("script", "arguments", "reason"), [
    ("real_robot_holdout.py", ["--f-scale", "0"], "--f-scale: must be a number of mm > 0, got 0.0"),
    ("real_robot_holdout.py", ["--f-scale", "2.5,x"], "--f-scale: numbers of mm separated by commas, got '2.5,x'"),
    ("real_robot_holdout.py", ["--f-scale", "2.5", "--prior", "E=3"], "judge one at a time"),
    ("real_robot_holdout.py", ["--loss", "linear", "--prior", "E=3"], "judge one at a time"),
    ("real_robot_holdout.py", ["--loss", "cauchy"], "--loss: invalid choice: 'cauchy'"),
    ("real_robot_holdout.py", ["--f-scale", "2.5", "--loss", "linear"], "plain least squares has no scale"),
    ("real_robot.py", ["--train", "no_such_recording.csv"], "no_such_recording.csv: cannot read"),
    ("real_robot_stderr.py", ["--train", "no_such_recording.csv"], "no_such_recording.csv: cannot read"),
])
def test_a_bad_argument_exits_2_naming_it(tmp_path, script, arguments, reason):
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *arguments], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert reason in done.stderr and "Traceback" not in done.stderr
    assert "|" not in done.stdout  # no table: nothing was fitted
