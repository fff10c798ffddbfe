"""Resolved-rate control of a TDCR tip along a straight line, with the solver's exact tip Jacobian.

    python examples/resolved_rate.py

At each step the tension rate solves J_p dtau = v dt in the least-squares sense (damped, within
0 <= tau <= tau_max), the tip moves, and the tracking error is printed: a planner's inner loop.
"""

from __future__ import annotations

import numpy as np

from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch

TIP = np.array([1.0])
TENSION_MAX = 5.0  # N
DAMPING = 1e-6  # (m/N)^2, keeps the step finite near singular configurations


def tip_and_jacobian(design: DesignBatch, tension: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = DesignBatch(E=design.E, r=design.r, L=design.L, offset=design.offset, pitch=design.pitch,
                    tension=tension[None])
    sol = solve(d, TIP, jacobian=True)
    return sol.backbone[0, -1], sol.jacobian[0, -1, :3]  # (3,) m, (3, N_t) m/N


def main() -> None:
    design = DesignBatch(E=[3e10], r=[8e-4], L=[0.25], offset=[[0.008] * 4], pitch=[[2.0, 0.0, -2.0, 0.0]],
                         tension=[[1.0, 0.0, 0.0, 0.5]])
    tension = design.tension[0].copy()
    start, _ = tip_and_jacobian(design, tension)
    goal, _ = tip_and_jacobian(design, np.array([2.0, 0.8, 0.0, 0.5]))  # a reachable tip, 13 mm away
    steps = 30
    for k in range(1, steps + 1):
        tip, jacobian = tip_and_jacobian(design, tension)
        wanted = start + (goal - start) * k / steps  # the next point of the line
        error = wanted - tip
        # damped least squares: dtau = J^T (J J^T + lambda I)^-1 error, then the bounds
        dtau = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + DAMPING * np.eye(3), error)
        tension = np.clip(tension + dtau, 0.0, TENSION_MAX)
        if k % 5 == 0:
            reached, _ = tip_and_jacobian(design, tension)
            print(f"step {k:2d}/{steps}: tensions {np.round(tension, 3)} N, tracking error "
                  f"{np.linalg.norm(reached - wanted) * 1e3:.4f} mm")


if __name__ == "__main__":
    main()
