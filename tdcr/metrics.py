"""The error measure of the whole project: relative l2 per design (paper eq. l2Error)."""

from __future__ import annotations

import numpy as np


def relative_l2(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-design relative l2 error ``||pred - truth|| / ||truth||`` over all axes after the first.

    Args:
        pred, truth: batches ``(B, ...)``, e.g. tendon positions ``(B, n, N_t, 3)`` m.

    Returns:
        ``(B,)`` errors (dimensionless).  For one design, pass ``x[None]``.
    """
    pred, truth = np.asarray(pred, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    axes = tuple(range(1, truth.ndim))
    return np.sqrt(((pred - truth) ** 2).sum(axis=axes) / (truth**2).sum(axis=axes))
