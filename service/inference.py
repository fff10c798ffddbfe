"""Torch-free inference with the exported ONNX operators (onnxruntime + numpy).

``Surrogate.predict`` turns raw SI designs ``(B, 15)`` and arclength fractions ``(n,)`` into
backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m:

* every graph gives all three: pose models tendons = p + R rho_i, tendon models the pose as the
  least-squares rigid fit (Kabsch) of the known offsets rho_i(s) onto the predicted tendons;
* FNO models answer on their 42-point grid; other s are produced by cubic interpolation along
  s of the grid outputs (rotations re-orthonormalised by SVD).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from training.designs import DesignBatch
from training.physics import tendon_routing


def tendon_offsets(features: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Body-frame tendon offsets rho_i(s), m, ``(B, n, N_t, 3)`` for features ``(B, 3 + 3 N_t)``."""
    return tendon_routing(DesignBatch.from_features(features), np.asarray(sigma, dtype=np.float64))[0]


def _cubic_weights(grid: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Matrix ``(n_out, n_grid)`` of natural-cubic-spline interpolation from ``grid`` to ``sigma``."""
    n = grid.size
    eye = np.eye(n)
    # natural cubic spline of each unit vector, evaluated at sigma (small dense solve, once per request)
    h = np.diff(grid)
    a = np.zeros((n, n))
    rhs = np.zeros((n, n))
    a[0, 0] = a[-1, -1] = 1.0
    for i in range(1, n - 1):
        a[i, i - 1], a[i, i], a[i, i + 1] = h[i - 1], 2 * (h[i - 1] + h[i]), h[i]
        rhs[i] = 6 * ((eye[i + 1] - eye[i]) / h[i] - (eye[i] - eye[i - 1]) / h[i - 1])
    m = np.linalg.solve(a, rhs)  # second derivatives per unit vector, (n, n)
    k = np.clip(np.searchsorted(grid, sigma, side="right") - 1, 0, n - 2)
    t0, t1 = grid[k], grid[k + 1]
    hk = t1 - t0
    A, B = (t1 - sigma) / hk, (sigma - t0) / hk
    w = A[:, None] * eye[k] + B[:, None] * eye[k + 1]
    w += ((A**3 - A)[:, None] * m[k] + (B**3 - B)[:, None] * m[k + 1]) * (hk**2 / 6)[:, None]
    return w


def _orthonormalize(rot: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rot)
    return u @ vt


@dataclass
class Surrogate:
    """One exported model: its manifest entry and an onnxruntime session."""

    name: str
    entry: dict
    session: object

    @classmethod
    def load(cls, models_dir: str | Path, name: str, *, threads: int = 0, verify: bool = True) -> Surrogate:
        import onnxruntime as ort

        models_dir = Path(models_dir)
        entry = json.loads((models_dir / "manifest.json").read_text())["models"][name]
        path = models_dir / entry["file"]
        if verify and hashlib.sha256(path.read_bytes()).hexdigest() != entry["sha256"]:
            raise ValueError(f"{path}: sha256 does not match the manifest")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        return cls(name=name, entry=entry, session=session)

    @property
    def grid(self) -> np.ndarray | None:
        g = self.entry.get("grid")
        return None if g is None else np.asarray(g)

    def run(self, features: np.ndarray, sigma: np.ndarray) -> dict[str, np.ndarray]:
        """Raw graph outputs at ``sigma`` (DeepONet) or on the grid (FNO), float32."""
        feed = {"design": np.ascontiguousarray(features, dtype=np.float32)}
        if self.grid is None:
            feed["s"] = np.ascontiguousarray(sigma, dtype=np.float32)
        names = [o.name for o in self.session.get_outputs()]
        return dict(zip(names, self.session.run(names, feed), strict=True))

    def predict(self, features: np.ndarray, sigma: np.ndarray, *, pose: bool = True) -> dict[str, np.ndarray]:
        """Backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m, float64.

        ``pose=False`` returns ``tendons`` only (saves the conversion and, off the FNO grid, the
        interpolation of the pose).
        """
        features = np.asarray(features, dtype=np.float64)
        sigma = np.asarray(sigma, dtype=np.float64)
        grid = self.grid
        out = {k: v.astype(np.float64) for k, v in self.run(features, sigma).items() if pose or k == "tendons"}
        if grid is not None and not (grid.size == sigma.size and np.allclose(grid, sigma, atol=1e-9)):
            w = _cubic_weights(grid, sigma)
            out = {k: np.einsum("mn,bn...->bm...", w, v) for k, v in out.items()}
            if "rotation" in out:
                out["rotation"] = _orthonormalize(out["rotation"])
        if pose and grid is not None and self.entry["kind"] == "pose":  # keep tendons = p + R rho after interpolation
            rho = tendon_offsets(features, sigma)
            out["tendons"] = out["backbone"][:, :, None, :] + np.einsum("bnij,bntj->bnti", out["rotation"], rho)
        return out
