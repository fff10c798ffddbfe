"""Torch-free inference with the exported ONNX operators (onnxruntime + numpy).

``Surrogate.predict`` turns raw SI designs ``(B, 15)`` and arclength fractions ``(n,)`` into
backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m:

* a pose model's graph gives all three (tendons = p + R rho_i);
* a tendon model's graph gives tendons; the pose is the least-squares rigid fit (Kabsch) of the
  known body-frame offsets rho_i(s) onto the predicted tendon points, at each s (float64);
* FNO models answer on their 42-point grid; other s are produced by cubic interpolation along
  s of the grid outputs (rotations re-orthonormalised by SVD).
"""

from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from training.designs import DesignBatch
from training.physics import tendon_routing


def tendon_offsets(features: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Body-frame tendon offsets rho_i(s), m, ``(B, n, N_t, 3)`` for features ``(B, 3 + 3 N_t)``."""
    return tendon_routing(DesignBatch.from_features(features), np.asarray(sigma, dtype=np.float64),
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


def _session(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # parallelism comes from running chunks side by side (Surrogate.run)
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@dataclass
class Surrogate:
    """One exported model: its manifest entry and a single-threaded onnxruntime session.

    Batches up to ``chunk`` designs run in one call (no thread-pool hand-offs for a few designs).
    Larger batches run as chunks of ``chunk`` designs side by side on a thread pool: the graph is
    mostly elementwise work on small arrays, which onnxruntime parallelises poorly inside one call,
    and chunks stay in cache (docs/results.md, "Inference").
    """

    name: str
    entry: dict
    session: object
    chunk: int = 512
    _pool: ThreadPoolExecutor | None = field(default=None, repr=False)

    @classmethod
    def load(cls, models_dir: str | Path, name: str, *, threads: int = 0, verify: bool = True,
             chunk: int = 512) -> Surrogate:
        """``threads``: chunks run side by side for large batches (0: one per core)."""
        models_dir = Path(models_dir)
        entry = json.loads((models_dir / "manifest.json").read_text())["models"][name]
        path = models_dir / entry["file"]
        if verify and hashlib.sha256(path.read_bytes()).hexdigest() != entry["sha256"]:
            raise ValueError(f"{path}: sha256 does not match the manifest")
        workers = threads or os.cpu_count() or 1
        pool = ThreadPoolExecutor(workers, thread_name_prefix=f"onnx-{name}") if workers > 1 else None
        return cls(name=name, entry=entry, session=_session(path), chunk=chunk, _pool=pool)

    @property
    def grid(self) -> np.ndarray | None:
        g = self.entry.get("grid")
        return None if g is None else np.asarray(g)

    def _row_slices(self, n: int) -> list[slice]:
        """Rows of a batch of ``n`` designs in chunks of at most ``chunk``."""
        return [slice(i, i + self.chunk) for i in range(0, n, self.chunk)]

    def _side_by_side(self, fn, n: int) -> list:
        """``fn(rows)`` for every chunk of ``n`` rows, on the thread pool when there are several."""
        chunks = self._row_slices(n)
        if len(chunks) <= 1 or self._pool is None:
            return [fn(rows) for rows in chunks]
        return list(self._pool.map(fn, chunks))

    def run(self, features: np.ndarray, sigma: np.ndarray) -> dict[str, np.ndarray]:
        """Raw graph outputs at ``sigma`` (DeepONet) or on the grid (FNO), float32, batch first.

        onnxruntime writes every chunk straight into its rows of preallocated outputs (I/O
        binding): no per-chunk output allocation and no concatenation.
        """
        features = np.ascontiguousarray(features, dtype=np.float32)
        sigma32 = np.ascontiguousarray(sigma, dtype=np.float32)
        n_points = len(sigma32) if self.grid is None else self.grid.size
        outputs = {name: np.empty((len(features), n_points, *shape[2:]), dtype=np.float32)
                   for name, shape in self.entry["outputs"].items()}
        if len(features) == 0:
            return outputs

        def run_rows(rows: slice) -> None:
            binding = self.session.io_binding()
            binding.bind_cpu_input("design", features[rows])
            if self.grid is None:
                binding.bind_cpu_input("s", sigma32)
            for name, array in outputs.items():
                view = array[rows]  # contiguous: the batch axis is the leading one
                binding.bind_output(name, "cpu", 0, np.float32, list(view.shape), view.ctypes.data)
            self.session.run_with_iobinding(binding)

        self._side_by_side(run_rows, len(features))
        return outputs

    def predict(self, features: np.ndarray, sigma: np.ndarray, *, pose: bool = True) -> dict[str, np.ndarray]:
        """Backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m.

        Graph outputs stay float32 (the networks' precision); the pose fit of tendon models and
        the FNO interpolation compute in float64, in chunks side by side.

        ``pose=False`` returns ``tendons`` only (saves the conversion and, off the FNO grid, the
        interpolation of the pose).
        """
        features = np.asarray(features, dtype=np.float64)
        sigma = np.asarray(sigma, dtype=np.float64)
        raw = {k: v for k, v in self.run(features, sigma).items() if pose or k == "tendons"}
        grid = self.grid
        on_grid = grid is None or (grid.size == sigma.size and np.allclose(grid, sigma, atol=1e-9))
        if on_grid and (not pose or "rotation" in raw):
            return raw  # nothing to post-process
        weights = None if on_grid else _cubic_weights(grid, sigma)
        parts = self._side_by_side(
            lambda rows: self._post(features[rows], {k: v[rows] for k, v in raw.items()}, sigma, pose, weights),
            len(features))
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _post(self, features: np.ndarray, out: dict[str, np.ndarray], sigma: np.ndarray, pose: bool,
              weights: np.ndarray | None) -> dict[str, np.ndarray]:
        """For one chunk: cubic interpolation off the FNO grid (``weights`` ``(n, n_grid)``, None on
        the grid) and the pose fit of tendon models."""
        on_grid = weights is None
        if not on_grid:
            out = {k: np.einsum("mn,bn...->bm...", weights, v) for k, v in out.items()}
            if "rotation" in out:
                out["rotation"] = _orthonormalize(out["rotation"])
        if pose and "rotation" not in out:
            out["backbone"], out["rotation"] = rigid_fit(tendon_offsets(features, sigma), out["tendons"])
        elif pose and not on_grid:  # keep tendons = p + R rho consistent after interpolation
            rho = tendon_offsets(features, sigma)
            out["tendons"] = out["backbone"][:, :, None, :] + np.einsum("bnij,bntj->bnti", out["rotation"], rho)
        return out
