"""Tendon geometry and pose fitting in numpy (float64): body-frame offsets, the rigid (Kabsch)
fit of a pose to tendon points, natural-cubic-spline weights along s, re-orthonormalisation."""

from __future__ import annotations

import numpy as np

from tdcr.physics.cosserat import tendon_routing
from tdcr.robot.designs import DesignBatch


def tendon_offsets(features: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Body-frame tendon offsets rho_i(s), m, ``(B, n, N_t, 3)`` for features ``(B, 3 + 3 N_t)``."""
    return tendon_routing(DesignBatch.from_features(features), np.asarray(fractions, dtype=np.float64),
                          derivative=False)[0]


def rigid_fit(body: np.ndarray, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transform world ~ p + R body (Kabsch) for body points in the plane z = 0.

    The first two columns of R are the polar factor A (A^T A)^(-1/2) of the 3 x 2 cross-covariance
    A = sum_i (w_i - w_bar)(b_i - b_bar)_{xy}^T, in closed form for the 2 x 2 matrix
    (sqrt(S) = (S + sqrt(det S) I) / sqrt(tr S + 2 sqrt(det S))); the third column is their cross
    product, so det R = +1.  Computed on contiguous per-component arrays.

    Args:
        body: body-frame points with z = 0, ``(..., N_t, 3)``; world: measured points ``(..., N_t, 3)``.

    Returns:
        ``(p (..., 3), R (..., 3, 3))``.
    """
    mean = np.full(body.shape[-2], 1.0 / body.shape[-2])  # sums over the short tendon axis as BLAS products
    bx, by = (np.ascontiguousarray(body[..., k], dtype=np.float64) for k in (0, 1))
    bx_c, by_c = bx - (bx @ mean)[..., None], by - (by @ mean)[..., None]
    a0, a1, centre = [], [], []
    for k in range(3):
        w = np.ascontiguousarray(world[..., k], dtype=np.float64)
        wm = w @ mean
        w_c = w - wm[..., None]
        a0.append((w_c * bx_c) @ mean)  # 1 / N_t times the sums: the scale cancels in the polar factor
        a1.append((w_c * by_c) @ mean)
        centre.append(wm)
    s00 = a0[0] ** 2 + a0[1] ** 2 + a0[2] ** 2
    s11 = a1[0] ** 2 + a1[1] ** 2 + a1[2] ** 2
    s01 = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2]
    root_det = np.sqrt(np.maximum(s00 * s11 - s01 * s01, 0.0))
    t = np.sqrt(s00 + s11 + 2.0 * root_det)
    r00, r11, r01 = (s00 + root_det) / t, (s11 + root_det) / t, s01 / t
    det = r00 * r11 - r01 * r01
    i00, i11, i01 = r11 / det, r00 / det, -r01 / det
    c1 = np.stack([a0[k] * i00 + a1[k] * i01 for k in range(3)], axis=-1)
    c2 = np.stack([a0[k] * i01 + a1[k] * i11 for k in range(3)], axis=-1)
    rot = np.stack([c1, c2, np.cross(c1, c2)], axis=-1)
    cb = np.stack([bx @ mean, by @ mean, np.zeros_like(bx[..., 0])], axis=-1)
    p = np.stack(centre, axis=-1) - np.einsum("...ij,...j->...i", rot, cb)
    return p, rot


def cubic_weights(grid: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Matrix ``(n_out, n_grid)`` of natural-cubic-spline interpolation from ``grid`` to ``fractions``."""
    n = grid.size
    eye = np.eye(n)
    # natural cubic spline of each unit vector, evaluated at fractions (small dense solve, once per request)
    h = np.diff(grid)
    a = np.zeros((n, n))
    rhs = np.zeros((n, n))
    a[0, 0] = a[-1, -1] = 1.0
    for i in range(1, n - 1):
        a[i, i - 1], a[i, i], a[i, i + 1] = h[i - 1], 2 * (h[i - 1] + h[i]), h[i]
        rhs[i] = 6 * ((eye[i + 1] - eye[i]) / h[i] - (eye[i] - eye[i - 1]) / h[i - 1])
    m = np.linalg.solve(a, rhs)  # second derivatives per unit vector, (n, n)
    k = np.clip(np.searchsorted(grid, fractions, side="right") - 1, 0, n - 2)
    t0, t1 = grid[k], grid[k + 1]
    hk = t1 - t0
    A, B = (t1 - fractions) / hk, (fractions - t0) / hk
    w = A[:, None] * eye[k] + B[:, None] * eye[k + 1]
    w += ((A**3 - A)[:, None] * m[k] + (B**3 - B)[:, None] * m[k + 1]) * (hk**2 / 6)[:, None]
    return w


def orthonormalize(rot: np.ndarray) -> np.ndarray:
    """The nearest rotation (polar factor by SVD) of each ``(..., 3, 3)`` matrix; NaN where a
    matrix is not finite (SVD would fail on it)."""
    finite = np.isfinite(rot).all(axis=(-2, -1))
    u, _, vt = np.linalg.svd(np.where(finite[..., None, None], rot, np.eye(3)))
    out = u @ vt
    out[~finite] = np.nan
    return out
