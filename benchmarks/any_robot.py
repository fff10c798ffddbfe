"""Any robot (issue #27): the solver's speed on segments and displacement actuation, high tensions,
the two termination rules, and the public examples -- measured in one run on one machine.

    python benchmarks/any_robot.py [--designs 2000] [--plot docs/termination.png]

* Throughput, designs/s on every core (``solve(..., workers=0)``, 42 points, best of 3 after a
  warm-up): Table I designs with 4 tendons; two segments of 3 tendons (ends L/2 and L); the same
  under ``termination="rucker_webster"`` (it shoots); displacement actuation (the tensions found
  for displacements, then solved).
* Displacement actuation in gravity and under a tip force (``--loaded`` designs, random loads of
  the operators' training ranges): the displacements of a loaded tension solve given back, the
  tensions recovered (max error), the displacements met, and designs/s; and ``tdcr.replay`` of the
  shared FTDCR v4 robot (friction 0, and fitted with friction) in gravity, rows/s.
* tau = 20 N on one tendon of Table I designs: how many converge, and how many are flagged.
* The step control's own estimate on two-segment helical designs.
* The termination rules against each other: relative l2 of the tendon positions between
  ``exact`` and ``rucker_webster`` against the helical pitch, tdcr-modeling's default robot
  (two segments of 0.1 m), unloaded and with a 0.05 N tip force (``--plot``: the figure).
* The public examples (stored answers of their own code, ``benchmarks/peers/*.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import STATUS, SolverOptions, solve
from tdcr.robot.designs import DesignBatch, ExternalLoads

S42 = np.linspace(0.0, 1.0, 42)
DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "data")


def rate(designs: DesignBatch, repeats: int = 3, **kwargs) -> float:
    solve(designs.take(slice(0, 8)), S42, workers=0, **kwargs)  # compile / warm up
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        solve(designs, S42, workers=0, **kwargs)
        best = min(best, time.perf_counter() - start)
    return len(designs) / best


def throughput(n: int) -> None:
    plain = design_space.sample_designs(n, seed=2701)
    two = design_space.sample_segmented_designs(n, seed=2702, segments=2, tendons_per_segment=3)
    forward = solve(plain, S42, workers=0)
    driven = plain.replace(displacement=forward.displacement, tension=np.zeros_like(plain.tension))
    forward_two = solve(two, S42, workers=0)
    driven_two = two.replace(displacement=forward_two.displacement, tension=np.zeros_like(two.tension))
    rows = [("one segment, 4 tendons (Table I)", rate(plain), "-"),
            ("two segments, 3 + 3 tendons", rate(two), ">= 20,000"),
            ("two segments, termination rucker_webster", rate(two, repeats=1, termination="rucker_webster"), "-"),
            ("displacement actuation, 4 tendons", rate(driven), ">= 2,000"),
            ("displacement actuation, two segments", rate(driven_two), "-")]
    print(f"\n### Throughput ({n} designs, 42 points, {os.cpu_count()} cores)\n")
    print("| designs | designs/s | target |\n|---|---:|---|")
    for name, value, target in rows:
        print(f"| {name} | {value:,.0f} | {target} |")


def loaded_displacement(n: int) -> None:
    """Displacement actuation in gravity and under a tip force (the loaded displacement solve): the
    displacements of a loaded tension solve given back, its tensions recovered, and the rate."""
    rng = np.random.default_rng(2706)
    print(f"\n### Displacement actuation in gravity and under a tip force ({n} designs, 42 points, "
          f"{os.cpu_count()} cores)\n")
    print("| designs | loaded solves converged | displacements given back: converged | max tension error, N "
          "| max displacement miss, m | designs/s |\n|---|---:|---:|---:|---:|---:|")
    for name, designs in (("one segment, 4 tendons (Table I)", design_space.sample_designs(n, seed=2707)),
                          ("two segments, 3 + 3 tendons",
                           design_space.sample_segmented_designs(n, seed=2708, segments=2, tendons_per_segment=3))):
        loads = ExternalLoads(gravity=rng.normal(0.0, 1.0, (n, 3)) * 9.81 / np.sqrt(3.0),
                              density=rng.uniform(6450.0, 8000.0, n),
                              tip_force=rng.uniform(-0.02, 0.02, (n, 3)))
        forward = solve(designs, S42, loads=loads, workers=0)
        ok = forward.converged
        driven = designs.take(ok).replace(displacement=forward.displacement[ok],
                                          tension=np.zeros_like(designs.tension[ok]))
        best, back = np.inf, None
        for _ in range(2):
            start = time.perf_counter()
            back = solve(driven, S42, loads=loads.take(ok), workers=0)
            best = min(best, time.perf_counter() - start)
        good = back.converged
        print(f"| {name} | {int(ok.sum())} | {int(good.sum())} | "
              f"{np.abs(back.tension[good] - designs.tension[ok][good]).max():.1e} | "
              f"{np.abs(back.displacement[good] - forward.displacement[ok][good]).max():.1e} | "
              f"{ok.sum() / best:,.0f} |")


def replay_in_gravity(n: int) -> None:
    """The shared FTDCR v4 robot file (9 tendons) without friction, and the fitted one
    (``examples/ftdcr_v4_fitted.json``, with friction; without and with its creep), each without loads
    and in gravity: ``n`` rows of its val.csv replayed in order with their times (``tdcr.replay``: the
    loaded displacement solve, Jacobians shared along the sequence; a creeping robot's chain in gravity
    in sweeps, eq. CREEP), rows/s of the best of 2, and how far gravity moved the tips."""
    from pathlib import Path

    from tdcr.physics.replay import replay
    from tdcr.robot.real import load_robot, read_recording

    root = Path(__file__).resolve().parents[1]
    data = json.loads((root / "examples" / "ftdcr_v4.json").read_text())
    for tendon in data["design"]["tendons"]:
        tendon["friction"] = 0.0
    creeping = json.loads((root / "examples" / "ftdcr_v4_fitted.json").read_text())
    fitted = creeping | {"actuation": creeping["actuation"] | {"creep_rate": 0.0}}
    weight = {"gravity": [0.0, 3.0, -9.81], "density": 7800.0}
    robots = {"the robot file, friction 0": data, "the fitted robot, with friction": fitted,
              "the fitted robot, with friction and its creep": creeping}
    val = root.parent / "shared" / "real_robot" / "ftdcr_v4" / "val.csv"
    print(f"\n### Replay in gravity: the FTDCR v4 robot files, {n} val rows, g = (0, 3, -9.81) m/s^2, 7,800 kg/m^3\n")
    print("| robot | loads | rows converged | rows/s | tip moved by gravity, max mm |\n|---|---|---:|---:|---:|")
    for name, robot_data in robots.items():
        tips = None
        for loads, robot in (("none", load_robot(robot_data)),
                             ("gravity", load_robot(robot_data | {"design": robot_data["design"] | weight}))):
            recording = read_recording(val, robot)
            commands, times = recording.commands[:n], recording.time[:n]
            replay(robot, commands[:8])  # compiled
            best = np.inf
            for _ in range(2):
                start = time.perf_counter()
                answer = replay(robot, commands, time=times)
                best = min(best, time.perf_counter() - start)
            tips = answer.tip_position if tips is None else tips
            moved = 1e3 * np.linalg.norm(answer.tip_position - tips, axis=1).max()
            print(f"| {name} | {loads} | {int(answer.converged.sum())} / {len(commands)} | "
                  f"{len(commands) / best:,.0f} | {moved:.2f} |")


def high_tension(n: int) -> None:
    designs = design_space.sample_designs(n, seed=2703)
    print("\n### tau = 20 N on tendon 0 (Table I designs)\n")
    print("| tension | designs | " + " | ".join(STATUS) + " | seconds |\n|---|---:|" + "---:|" * (len(STATUS) + 1))
    for tau in (5.0, 20.0, 50.0):
        d = designs.replace(tension=np.tile([tau, 0.0, 0.0, 0.0], (n, 1)))
        start = time.perf_counter()
        sol = solve(d, S42, workers=0)
        seconds = time.perf_counter() - start
        counts = np.bincount(sol.status, minlength=len(STATUS))
        print(f"| {tau:g} N | {n} | " + " | ".join(str(c) for c in counts) + f" | {seconds:.2f} |")


def step_control(n: int) -> None:
    designs = design_space.sample_segmented_designs(n, seed=2704, segments=3, tendons_per_segment=2)
    sol = solve(designs, S42, workers=0)
    ok = sol.converged
    print(f"\n### Step control, three segments of 2 tendons ({n} Table I designs)\n")
    print(f"converged {ok.sum()} / {n}; estimate of the tendon positions' relative l2: median "
          f"{np.median(sol.error_estimate[ok]):.2g}, max {sol.error_estimate[ok].max():.2g} (step_tol "
          f"{SolverOptions().step_tol:g}); statuses "
          f"{dict(zip(STATUS, np.bincount(sol.status, minlength=len(STATUS)).tolist(), strict=True))}")


def tm_robot(pitch: float, tensions: np.ndarray) -> DesignBatch:
    """tdcr-modeling's default robot (two segments of 0.1 m, E 60 GPa, r 0.5 mm, 8 and 6 mm) with
    helical routing of ``pitch`` rad/m, for each row of ``tensions`` ``(B, 6)``."""
    b = len(tensions)
    angles = np.tile(np.deg2rad([90.0, -30.0, 210.0] * 2), (b, 1))
    return DesignBatch(E=np.full(b, 60e9), r=np.full(b, 5e-4), L=np.full(b, 0.2),
                       offset=np.tile([0.008] * 3 + [0.006] * 3, (b, 1)), pitch=np.full((b, 6), pitch),
                       tension=tensions, angle=angles, end=np.tile([0.1] * 3 + [0.2] * 3, (b, 1)))


def termination(plot: str | None) -> None:
    rng = np.random.default_rng(2705)
    tensions = rng.uniform(0.0, 2.0, (50, 6))
    pitches = np.array([0.0, 2.5, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0])
    force = ExternalLoads(tip_force=np.tile([0.05, 0.0, 0.0], (len(tensions), 1)))
    rows = []
    for pitch in pitches:
        d = tm_robot(pitch, tensions)
        out = []
        for loads in (None, force):
            a = solve(d, S42, loads=loads, workers=0)
            b = solve(d, S42, loads=loads, workers=0, termination="rucker_webster")
            ok = a.converged & b.converged
            gap = relative_l2(b.tendons[ok], a.tendons[ok])
            out.append((np.median(gap), gap.max(), int(ok.sum())))
        rows.append((pitch, out))
    print("\n### Termination rules: relative l2 of the tendon positions, exact vs rucker_webster\n")
    print("tdcr-modeling's default robot with helical routing, 50 tension sets in [0, 2] N\n")
    print("| pitch rad/m | unloaded: median | max | tip force 0.05 N: median | max | converged |")
    print("|---:|---:|---:|---:|---:|---:|")
    for pitch, ((m0, x0, n0), (m1, x1, n1)) in rows:
        print(f"| {pitch:g} | {m0:.2g} | {x0:.2g} | {m1:.2g} | {x1:.2g} | {min(n0, n1)} |")
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=120)
        for k, label in ((0, "tendon loads only"), (1, "with a 0.05 N tip force")):
            ax.semilogy(pitches, [max(r[1][k][1], 1e-16) for r in rows], "o-", label=f"max, {label}")
            ax.semilogy(pitches, [max(r[1][k][0], 1e-16) for r in rows], "s--", label=f"median, {label}")
        ax.set_xlabel("helical pitch of every tendon, rad/m")
        ax.set_ylabel("relative l2, tendon positions")
        ax.set_title("Dropped kink forces: rucker_webster vs exact\n(two segments of 0.1 m, tdcr-modeling's robot)",
                     fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(plot)
        print(f"\nwrote {plot}")


def peers() -> None:
    cre = json.load(open(os.path.join(DATA, "continuum_robot_examples.json")))
    design = cre["design"]
    print("\n### Public examples (their own code's answers; tests/peers/test_peers.py)\n")
    print("| example | peer residual | ours: relative l2, tendon positions | tip mm |\n|---|---:|---:|---:|")
    for name, case in cre["cases"].items():
        for nu in (design["poisson"], 0.3):
            d = DesignBatch(E=[design["E"]], r=[design["r"]], L=[design["L"]], offset=[[design["offset"]] * 4],
                            pitch=[[design["pitch"][name]] * 4], tension=[design["tension"]], poisson=[nu])
            loads = ExternalLoads(gravity=np.array([design["gravity"]]), density=np.array([design["density"]]))
            sol = solve(d, np.array(case["s"]), loads=loads)
            err = float(relative_l2(sol.tendons, np.array(case["tendons"])[None])[0])
            tip = 1e3 * np.linalg.norm(sol.backbone[0, -1] - np.array(case["backbone"][-1]))
            print(f"| ContinuumRobotExamples {name}, nu = {nu:g} | {case['shooting_residual']:.2g} | {err:.2g} "
                  f"| {tip:.2g} |")
    tm = json.load(open(os.path.join(DATA, "tdcr_modeling.json")))
    robot = tm["robot"]
    for case in tm["cases"]:
        disks = np.array(case["disk_positions"])[None]
        d = tm_robot(0.0, np.array([case["tension"]]))
        loads = ExternalLoads(tip_force=np.array([case["tip_force"]]))
        fr = np.linspace(0.0, 1.0, disks.shape[1])
        errs = [float(relative_l2(solve(d, fr, loads=loads, termination=t).backbone, disks)[0])
                for t in ("rucker_webster", "exact")]
        print(f"| tdcr-modeling, tau {case['tension']}, F {case['tip_force']} | chi2 {case['chi2']:.2g} | "
              f"rucker_webster {errs[0]:.2g}, exact {errs[1]:.2g} (backbone) | |")
    assert robot["E"] == 60e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--designs", type=int, default=2000)
    parser.add_argument("--plot", default=None, help="write the termination figure here (PNG)")
    parser.add_argument("--loaded", type=int, default=200, help="designs of the loaded displacement rows")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or platform.platform()}")
    throughput(args.designs)
    loaded_displacement(args.loaded)
    replay_in_gravity(args.loaded)
    high_tension(args.designs)
    step_control(500)
    termination(args.plot)
    peers()


if __name__ == "__main__":
    main()
