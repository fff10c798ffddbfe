"""Build and run ContinuumRobotExamples' tendon-robot statics (J. Till, public C++ examples) and store
their answers as the reference of ``tests/peers/test_peers.py``.

The two examples of issue #27: ``01_Statics/05_Tendon_Robot`` (straight routing) and the helical
variant ``01_Statics/06_Tendon_Robot_Variants/Cpp_2``: E = 200 GPa, G = 80 GPa (nu = 0.25),
r = 1 mm, L = 0.5 m, 4 tendons at 15.06 mm, tau = (15, 0, 0, 0) N, gravity 9.81 m/s^2 along +x,
density 8000 kg/m^3; shooting on n(0), m(0) with Levenberg-Marquardt and RK4.  Each source is
compiled unchanged except for 2001 RK4 points instead of 100 (so that its own step error is far
below the comparison's 1e-6), full precision in its output files, and a print of its shooting
residual (checked before the answer is trusted).

Usage: ``python benchmarks/peers/continuum_robot_examples.py REPO_DIR [--out tests/data/continuum_robot_examples.json]``
with REPO_DIR a checkout of https://github.com/JohnDTill/ContinuumRobotExamples (needs g++).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import tempfile

import numpy as np

EXAMPLES = {"straight": "01_Statics/05_Tendon_Robot/Cpp/main.cpp",
            "helical": "01_Statics/06_Tendon_Robot_Variants/Cpp_2/main.cpp"}
POINTS = 2001


def patched(source: str) -> str:
    """The example with more RK4 points, full-precision output and its residual printed."""
    source = source.replace("ode4<cosseratTendonRobotOde>(y0, L)", f"ode4<cosseratTendonRobotOde, {POINTS}>(y0, L)")
    source = source.replace("ode4<cosseratTendonRobotOde>(y0, 0, L)",
                            f"ode4<cosseratTendonRobotOde, {POINTS}>(y0, 0, L)")
    source = source.replace('std::fstream file("centerline.dat", std::fstream::out);',
                            'std::fstream file("centerline.dat", std::fstream::out); file.precision(17);')
    source = source.replace('file = std::fstream("tendonlines.dat", std::fstream::out);',
                            'file = std::fstream("tendonlines.dat", std::fstream::out); file.precision(17);')
    marker = "    //Save results for Blender visualization"
    report = ('    std::printf("residual %.17g\\n", shootingFunction(wrench_soln).norm());\n'
              '    std::printf("guess");\n    for(int i = 0; i < 6; i++) std::printf(" %.17g", wrench_soln(i));\n'
              '    std::printf("\\n");\n')
    assert marker in source and str(POINTS) in source, "the example's source changed"
    return source.replace(marker, report + marker)


def run(repo: pathlib.Path, name: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        (work / "main.cpp").write_text(patched((repo / EXAMPLES[name]).read_text()))
        library = repo / "Library"
        subprocess.run(["g++", "-O2", "-std=c++14", f"-I{library}", f"-I{library / 'eigen'}", "main.cpp", "-o", "peer"],
                       cwd=work, check=True)
        out = subprocess.run(["./peer"], cwd=work, check=True, capture_output=True, text=True).stdout
        lines = dict(line.split(" ", 1) for line in out.strip().splitlines())
        tendon_lines = np.loadtxt(work / "tendonlines.dat")  # (3 N_t, POINTS)
        backbone = np.loadtxt(work / "centerline.dat")  # (3, POINTS)
    every = (POINTS - 1) // 20  # 21 equispaced arclengths
    tendons = tendon_lines.reshape(4, 3, POINTS).transpose(2, 0, 1)[::every]  # (21, 4, 3)
    return {"source": EXAMPLES[name], "rk4_points": POINTS, "shooting_residual": float(lines["residual"]),
            "base_wrench_guess": [float(v) for v in lines["guess"].split()],
            "s": np.linspace(0.0, 1.0, 21).tolist(), "backbone": backbone.T[::every].tolist(),
            "tendons": tendons.tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("repo", type=pathlib.Path, help="a checkout of JohnDTill/ContinuumRobotExamples")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("tests/data/continuum_robot_examples.json"))
    args = parser.parse_args()
    cases = {name: run(args.repo, name) for name in EXAMPLES}
    design = {"E": 200e9, "poisson": 0.25, "r": 0.001, "L": 0.5, "density": 8000.0, "gravity": [9.81, 0.0, 0.0],
              "offset": 0.01506, "tension": [15.0, 0.0, 0.0, 0.0],
              "pitch": {"straight": 0.0, "helical": 2 * np.pi / 0.5}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"peer": "https://github.com/JohnDTill/ContinuumRobotExamples", "design": design,
                                    "cases": cases}, indent=1))
    for name, case in cases.items():
        print(f"{name}: shooting residual {case['shooting_residual']:.3g}, tip {case['backbone'][-1]}")


if __name__ == "__main__":
    main()
