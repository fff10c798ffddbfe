"""SO(3) / SE(3) helpers used by the rod integrators (private).

All functions are vectorised over leading batch axes and run in float64.
"""

from __future__ import annotations

import numpy as np

_SMALL_ANGLE = 1e-2  # below this |w| (rad) the Taylor series of the coefficients are used


def hat(w: np.ndarray) -> np.ndarray:
    """Skew matrix of ``w``: ``hat(w) @ x == cross(w, x)``.  ``(..., 3) -> (..., 3, 3)``."""
    out = np.zeros(w.shape + (3,), dtype=w.dtype)
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def _exp_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, stable near t = 0."""
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, np.sin(t) / t)
    b = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return a, b, c


def se3_exp(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exponential of the twist ``(v, w)`` on SE(3).

    Rodrigues' formula R = I + A W + B W^2 and p = (I + B W + C W^2) v with W = hat(w).

    Args:
        v: linear part, ``(..., 3)``.
        w: angular part, ``(..., 3)``.

    Returns:
        ``(R, p)`` with shapes ``(..., 3, 3)`` and ``(..., 3)``.
    """
    theta = np.linalg.norm(w, axis=-1)
    a, b, c = _exp_coefficients(theta)
    W = hat(w)
    W2 = W @ W
    eye = np.eye(3)
    R = eye + a[..., None, None] * W + b[..., None, None] * W2
    V = eye + b[..., None, None] * W + c[..., None, None] * W2
    p = np.einsum("...ij,...j->...i", V, v)
    return R, p


def se3_bracket(v1, w1, v2, w2) -> tuple[np.ndarray, np.ndarray]:
    """Lie bracket [xi1, xi2] of twists xi = (v, w) in se(3): (w1 x v2 - w2 x v1, w1 x w2)."""
    return np.cross(w1, v2) - np.cross(w2, v1), np.cross(w1, w2)
