"""The solver's per-design outcome: one enum, used by the compiled kernels (as its integer codes)
and by every caller (``RodSolution.status`` holds the codes; :data:`STATUS` their names)."""

from __future__ import annotations

import enum


class Status(enum.IntEnum):
    """``RodSolution.status``: 0 converged, else why not (the first that applies)."""

    CONVERGED = 0
    NEWTON_FAILED = 1  # the local equation (W1, W2) was not solved at some node
    NOT_FINITE = 2  # the shape or residual is not finite
    STEP_TOL_NOT_MET = 3  # the step error estimate stayed above step_tol after max_level halvings
    RESIDUAL_TOO_LARGE = 4  # the wrench residual exceeds residual_tol times the load scale
    SHOOTING_FAILED = 5  # loads: the tip condition M(L) = M_tip was not met
    MULTIPLE_EQUILIBRIA = 6  # loads: the shooting Jacobian has a real eigenvalue <= 0 (a fold or bifurcation)
    TENDON_COLLAPSED = 7  # a tendon's path would shrink to zero length: bent past its centre of curvature
    DISPLACEMENT_NOT_MET = 8  # displacement actuation: no tensions >= 0 pull in the displacements asked for


#: The status names, indexed by code (the OIP ``status`` output and /exact's ``status``).
STATUS: tuple[str, ...] = tuple(s.name.lower() for s in Status)
