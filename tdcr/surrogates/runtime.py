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
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tdcr.api.checks import (
    InvalidRequest,
    check_fractions,
    check_loads,
    check_model_loads,
    check_surrogate_features,
    check_tolerance,
    checkable_loads,
    loaded_rows,
    raise_problems,
)
from tdcr.physics.geometry import cubic_weights, orthonormalize, rigid_fit, tendon_offsets
from tdcr.robot.designs import N_LOAD_COLUMNS, DesignBatch, ExternalLoads
from tdcr.surrogates.bounds import (
    Calibration,
    CalibrationError,
    Guarded,
    calibration_grid,
    disagreement,
    guard,
)

#: Manifest (and manifest entry) format this runtime reads; training/operators/export.py writes it.
MANIFEST_FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
#: The shipped models, found from any working directory (a path relative to the package).
DEFAULT_MODELS_DIR = Path(__file__).resolve().parents[2] / "models"


def takes_loads(entry: dict) -> bool:
    """Whether a manifest entry's model takes the loads input ``(B, 10)`` (a loaded operator)."""
    return "loads" in entry.get("inputs", {})


def best_model(manifest: dict, *, loads: bool | None = False) -> str | None:
    """The default model, for the service and ``tdcr predict`` alike: of the manifest models that
    take no loads (``loads``: of those that do; None: of all, a loaded operator answering load-free
    designs with zero loads), the one with the lowest mean test relative l2 (the first by name if
    none has metrics); None if there is none."""
    models = {k: v for k, v in manifest.get("models", {}).items() if loads is None or takes_loads(v) == loads}

    def score(name):
        m = (models[name].get("metrics") or {}).get("test_relative_l2") or {}
        return m.get("mean", float("inf"))

    return min(sorted(models), key=score) if models else None


def as_load_matrix(loads: ExternalLoads | np.ndarray, n_designs: int) -> np.ndarray:
    """Loads as the ``(B, 10)`` float64 matrix of the graphs' input, absent values 0."""
    matrix = loads.matrix(n_designs) if isinstance(loads, ExternalLoads) else np.asarray(loads, dtype=np.float64)
    return np.nan_to_num(matrix.reshape(n_designs, N_LOAD_COLUMNS))


def _calibration(manifest: dict, entry: dict) -> Calibration | None:
    """An entry's calibration, checked (its sha256; its companion's sha256 against the manifest)."""
    record = entry.get("calibration")
    if record is None:
        return None
    try:
        calibration = Calibration.from_record(record, load_ranges=entry.get("load_ranges"))
    except CalibrationError as exc:
        raise ManifestError(f"{entry['name']}: {exc}") from None
    companion = calibration.companion
    if companion is not None and manifest["models"].get(companion, {}).get("sha256") != record["companion_sha256"]:
        raise ManifestError(f"{entry['name']}: its error bound was calibrated against another {companion!r}; "
                            "recalibrate (`tdcr calibrate`)")
    return calibration


def on_grid_tendons(out: dict[str, np.ndarray], fractions: np.ndarray) -> np.ndarray | None:
    """``out["tendons"]`` if ``fractions`` are the calibration grid, else None."""
    grid = calibration_grid()
    same = fractions.size == grid.size and np.allclose(fractions, grid, atol=1e-9)
    return out["tendons"] if same else None


def error_bound(calibration: Calibration | None, features: np.ndarray, loads: np.ndarray | None, *,
                tendons: np.ndarray | None, own, companion) -> np.ndarray:
    """The bound ``(B,)`` of an operator's answers (:meth:`Calibration.bound`; ``inf`` without a
    calibration): its score from
    ``tendons`` on the calibration grid (computed by ``own(features, grid, loads=, pose=False,
    check=False)`` when None) and the ``companion``'s (a predictor of the same signature).  The one
    computation of a bound, for :meth:`Surrogate.error_bound` and the engine alike."""
    if calibration is None:
        return np.full(len(features), np.inf)
    score = None
    if calibration.companion is not None:
        grid = calibration_grid()
        if tendons is None:
            tendons = own(features, grid, loads=loads, pose=False, check=False)["tendons"]
        theirs = companion.predict(features, grid, loads=loads if companion.takes_loads else None, pose=False,
                                   check=False)["tendons"]
        with np.errstate(all="ignore"):
            score = disagreement(tendons, theirs)
    return calibration.bound(features, score, loads)


def finite_rows(arrays, n_designs: int) -> np.ndarray:
    """Per design ``(B,)``: every value of its rows of ``arrays`` (each ``(B, ...)``) is finite, by
    the finiteness of the row sums (a NaN or an infinity makes its sum so; a sum that overflows from
    finite values beyond 1e38 counts as not finite too): one vectorised pass, 10x cheaper than
    testing every value of an answer."""
    finite = np.ones(n_designs, dtype=bool)
    for v in arrays:
        with np.errstate(all="ignore"):
            finite &= np.isfinite(v.reshape(n_designs, -1).sum(axis=1))
    return finite


def keep_tolerance(arrays: dict[str, np.ndarray], features: np.ndarray, fractions: np.ndarray,
                   loads: np.ndarray | None, *, tendons: np.ndarray | None, own, calibration: Calibration | None,
                   companion, tolerance: float | None,
                   exact: Callable[[np.ndarray], dict[str, np.ndarray]],
                   finite: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], Guarded]:
    """The one tolerance path of an operator's answer, for :meth:`Surrogate.predict` and the engine
    alike: each design's bound (:func:`error_bound`; ``inf`` where the answer is not ``finite``
    ``(B,)``: None, :func:`finite_rows` of its tendons, or of every array without them: the other
    outputs and the tendons derive from each other, tendons = p + R rho), then
    :func:`tdcr.surrogates.bounds.guard`: with ``tolerance``, the designs whose bound exceeds it
    answered by ``exact(rows)``.  ``tendons``: the answer on the calibration grid
    (:func:`on_grid_tendons`; None: ``own`` computes it)."""
    if finite is None:
        checked = [arrays["tendons"]] if "tendons" in arrays else arrays.values()
        finite = finite_rows(checked, len(features))
    with np.errstate(all="ignore"):
        bounds = error_bound(calibration, features, loads, tendons=tendons, own=own, companion=companion)
    return guard(arrays, np.where(finite, bounds, np.inf), tolerance=tolerance, exact=exact)


def solve_rows(features: np.ndarray, fractions: np.ndarray, loads: np.ndarray | None, *,
               pose: bool = True, workers: int = 0) -> dict[str, np.ndarray]:
    """The exact solver's tendons ``(m, n, 4, 3)`` (with ``pose``: backbone and rotation too) of
    ``features`` ``(m, 15)`` under ``loads`` ``(m, 10)`` (None: none), and ``converged`` ``(m,)``;
    on ``workers`` threads (0: every core; a few designs run on the calling thread)."""
    from tdcr.physics import solve

    external = None if loads is None or not loaded_rows(loads).any() else ExternalLoads.from_matrix(loads)
    sol = solve(DesignBatch.from_features(features), fractions, loads=external, workers=workers)
    out = {"tendons": sol.tendons} | ({"backbone": sol.backbone, "rotation": sol.rotation} if pose else {})
    return out | {"converged": sol.converged}


def check_inputs(features: np.ndarray, fractions: np.ndarray, *, loads=None, tolerance: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """The one validation path's checks of an operator's inputs (:mod:`tdcr.api.checks`): designs
    ``(B, 15)`` inside their admissible bounds, loads inside theirs, fractions in [0, 1], the
    tolerance; a ``ValueError`` with the service's words else.  Returns the fractions (clamped
    within rounding) and the loads as their ``(B, 10)`` matrix (None: none)."""
    problems = check_surrogate_features(features)
    fractions, more = check_fractions(fractions, name="fractions")
    if loads is not None and not problems:
        n = len(features)
        loads = as_load_matrix(loads, n)
        more += check_loads(checkable_loads(ExternalLoads.from_matrix(loads), n), np.arange(n))
    more += check_tolerance(tolerance)
    raise_problems(problems + more)
    return fractions, loads


class ManifestError(ValueError):
    """A models directory whose manifest is missing, unreadable, of another format, or lacks a model."""


def load_manifest(models_dir: str | Path) -> dict:
    """``models_dir/manifest.json``, checked for its format version (top level and every entry)."""
    path = Path(models_dir) / MANIFEST_NAME
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ManifestError(f"cannot read the manifest {MANIFEST_NAME}: {exc.__class__.__name__}") from None
    versions = {manifest.get("format_version")} | {
        e.get("format_version") for e in manifest.get("models", {}).values()}
    if versions != {MANIFEST_FORMAT_VERSION}:
        raise ManifestError(f"manifest format {sorted(map(str, versions))} is not the supported "
                            f"{MANIFEST_FORMAT_VERSION}; re-export the models")
    return manifest


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
    #: where it was loaded from (its companion, the score of its error bound, is loaded from there)
    models_dir: Path | None = None
    #: its calibrated error bound (None: not calibrated)
    calibration: Calibration | None = None
    _pool: ThreadPoolExecutor | None = field(default=None, repr=False)
    _companion: Surrogate | None = field(default=None, repr=False)

    @classmethod
    def load(cls, models_dir: str | Path, name: str, *, threads: int = 0, verify: bool = True,
             chunk: int = 512, manifest: dict | None = None) -> Surrogate:
        """Load model ``name`` of ``models_dir`` (its manifest, or ``manifest`` if already read).

        ``threads``: chunks run side by side for large batches (0: one per core).  ``verify``:
        check the file's sha256 against the manifest (``ManifestError`` if it differs).
        """
        models_dir = Path(models_dir)
        manifest = load_manifest(models_dir) if manifest is None else manifest
        if name not in manifest.get("models", {}):
            raise ManifestError(f"model {name!r} is not in the manifest; available: {sorted(manifest['models'])}")
        entry = manifest["models"][name]
        path = models_dir / entry["file"]
        if verify and hashlib.sha256(path.read_bytes()).hexdigest() != entry["sha256"]:
            raise ManifestError(f"{entry['file']}: sha256 does not match the manifest")
        calibration = _calibration(manifest, entry)
        workers = threads or os.cpu_count() or 1
        pool = ThreadPoolExecutor(workers, thread_name_prefix=f"onnx-{name}") if workers > 1 else None
        return cls(name=name, entry=entry, session=_session(path), chunk=chunk, models_dir=models_dir,
                   calibration=calibration, _pool=pool)

    @classmethod
    def shipped(cls, name: str, **options) -> Surrogate:
        """The shipped operator ``name`` (``models/`` of this package, :data:`DEFAULT_MODELS_DIR`),
        e.g. ``Surrogate.shipped("fno_pose")``; ``options`` as :meth:`load`."""
        return cls.load(DEFAULT_MODELS_DIR, name, **options)

    @property
    def takes_loads(self) -> bool:
        """A loaded operator: its graph takes gravity, density and the tip wrench (``loads``)."""
        return takes_loads(self.entry)

    @property
    def load_ranges(self) -> dict[str, list[float]] | None:
        """The loads of its training data (:meth:`tdcr.robot.design_space.LoadSpace.ranges`), or None."""
        return self.entry.get("load_ranges")

    def load_matrix(self, loads, n_designs: int) -> np.ndarray | None:
        """``loads`` (:class:`ExternalLoads`, a ``(B, 10)`` matrix or None) as this graph's input:
        the matrix for a loaded operator (zeros without loads), None for another; a ``ValueError``
        when an operator that takes no loads is given some."""
        matrix = None if loads is None else as_load_matrix(loads, n_designs)
        if not self.takes_loads:
            if matrix is not None and loaded_rows(matrix).any():
                raise InvalidRequest(check_model_loads(ExternalLoads.from_matrix(matrix), np.arange(n_designs),
                                                       model=self.name))
            return None
        return np.zeros((n_designs, N_LOAD_COLUMNS)) if matrix is None else matrix

    def companion(self) -> Surrogate | None:
        """The operator whose disagreement scores this one's error (loaded once, from
        :attr:`models_dir`, sharing nothing); None when the bound needs none."""
        name = None if self.calibration is None else self.calibration.companion
        if name is None:
            return None
        if self._companion is None:
            self._companion = Surrogate.load(self.models_dir, name, chunk=self.chunk)
        return self._companion

    def error_bound(self, features: np.ndarray, *, loads: ExternalLoads | np.ndarray | None = None,
                    tendons: np.ndarray | None = None) -> np.ndarray:
        """The calibrated 99 % bound ``(B,)`` of the relative l2 error of each design's tendon
        positions (:mod:`tdcr.surrogates.bounds`; ``inf`` outside the calibrated region, and everywhere for a
        model without a calibration); ``tendons``: this operator's answer ``(B, 42, 4, 3)`` on the
        calibration grid if already computed.  Designs are not checked here."""
        if self.calibration is None:
            return np.full(len(features), np.inf)
        matrix = self.load_matrix(loads, len(features))
        return error_bound(self.calibration, np.asarray(features, dtype=np.float64), matrix, tendons=tendons,
                           own=self.predict, companion=self.companion())

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

    def run(self, features: np.ndarray, fractions: np.ndarray, loads: np.ndarray | None = None
            ) -> dict[str, np.ndarray]:
        """Raw graph outputs at ``fractions`` (DeepONet) or on the grid (FNO), float32, batch first;
        ``loads`` ``(B, 10)``: the loads input of a loaded operator (:meth:`load_matrix`).

        onnxruntime writes every chunk straight into its rows of preallocated outputs (I/O
        binding): no per-chunk output allocation and no concatenation.
        """
        features = np.ascontiguousarray(features, dtype=np.float32)
        fractions32 = np.ascontiguousarray(fractions, dtype=np.float32)
        loads32 = None if not self.takes_loads else np.ascontiguousarray(
            np.zeros((len(features), N_LOAD_COLUMNS)) if loads is None else loads, dtype=np.float32)
        n_points = len(fractions32) if self.grid is None else self.grid.size
        outputs = {name: np.empty((len(features), n_points, *shape[2:]), dtype=np.float32)
                   for name, shape in self.entry["outputs"].items()}
        if len(features) == 0:
            return outputs

        def run_rows(rows: slice) -> None:
            binding = self.session.io_binding()
            binding.bind_cpu_input("design", features[rows])
            if loads32 is not None:
                binding.bind_cpu_input("loads", loads32[rows])
            if self.grid is None:
                binding.bind_cpu_input("s", fractions32)
            for name, array in outputs.items():
                view = array[rows]  # contiguous: the batch axis is the leading one
                binding.bind_output(name, "cpu", 0, np.float32, list(view.shape), view.ctypes.data)
            self.session.run_with_iobinding(binding)

        self._side_by_side(run_rows, len(features))
        return outputs

    def predict(self, features: np.ndarray, fractions: np.ndarray, *, loads: ExternalLoads | np.ndarray | None = None,
                pose: bool = True, check: bool = True, bound: bool = False,
                tolerance: float | None = None) -> dict[str, np.ndarray]:
        """Backbone ``(B, n, 3)`` m, rotation ``(B, n, 3, 3)`` and tendons ``(B, n, 4, 3)`` m.

        ``bound``: add ``error_bound`` ``(B,)`` (:meth:`error_bound`).  ``tolerance`` (relative l2,
        at least :data:`tdcr.surrogates.bounds.EXACT_TOLERANCE`): designs whose bound exceeds it, or is not
        finite, are answered by the exact solver (:func:`tdcr.physics.solve`, float64), in order;
        adds ``error_bound`` and ``source`` ``(B,)`` (0: surrogate, 1: exact).

        ``loads``: gravity and a tip wrench per design (:class:`tdcr.ExternalLoads`, base frame, SI;
        or its ``(B, 10)`` matrix), for a loaded operator (:attr:`takes_loads`); another operator
        refuses non-zero loads (``ValueError`` naming the field).

        Graph outputs stay float32 (the networks' precision); the pose fit of tendon models and
        the FNO interpolation compute in float64, in chunks side by side.

        ``pose=False`` returns ``tendons`` only (saves the conversion and, off the FNO grid, the
        interpolation of the pose).

        ``check``: the one validation path's checks first (:mod:`tdcr.api.checks`): ``(B, 15)`` designs
        inside their admissible bounds, loads inside theirs, fractions in [0, 1]; a ``ValueError``
        with the service's words else.  The service's batcher, whose requests are validated
        already, skips them.
        """
        if check:
            fractions, loads = check_inputs(features, fractions, loads=loads, tolerance=tolerance)
        features = np.asarray(features, dtype=np.float64)
        fractions = np.asarray(fractions, dtype=np.float64)
        matrix = self.load_matrix(loads, len(features))
        if bound or tolerance is not None:
            out = self.predict(features, fractions, loads=matrix, pose=pose, check=False)

            def exact(rows: np.ndarray) -> dict[str, np.ndarray]:
                return solve_rows(features[rows], fractions, None if matrix is None else matrix[rows], pose=pose)

            out, guarded = keep_tolerance(out, features, fractions, matrix, tendons=on_grid_tendons(out, fractions),
                                          own=self.predict, calibration=self.calibration,
                                          companion=self.companion(), tolerance=tolerance, exact=exact)
            return out | {"error_bound": guarded.error_bound} | (
                {"source": guarded.source} if tolerance is not None else {})
        raw = {k: v for k, v in self.run(features, fractions, matrix).items() if pose or k == "tendons"}
        grid = self.grid
        on_grid = grid is None or (grid.size == fractions.size and np.allclose(grid, fractions, atol=1e-9))
        if on_grid and (not pose or "rotation" in raw):
            return raw  # nothing to post-process
        weights = None if on_grid else cubic_weights(grid, fractions)
        parts = self._side_by_side(
            lambda rows: self._post(features[rows], {k: v[rows] for k, v in raw.items()}, fractions, pose, weights),
            len(features))
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _post(self, features: np.ndarray, out: dict[str, np.ndarray], fractions: np.ndarray, pose: bool,
              weights: np.ndarray | None) -> dict[str, np.ndarray]:
        """For one chunk: cubic interpolation off the FNO grid (``weights`` ``(n, n_grid)``, None on
        the grid) and the pose fit of tendon models."""
        on_grid = weights is None
        if not on_grid:
            out = {k: np.einsum("mn,bn...->bm...", weights, v) for k, v in out.items()}
            if "rotation" in out:
                out["rotation"] = orthonormalize(out["rotation"])
        if pose and "rotation" not in out:
            out["backbone"], out["rotation"] = rigid_fit(tendon_offsets(features, fractions), out["tendons"])
        elif pose and not on_grid:  # keep tendons = p + R rho consistent after interpolation
            rho = tendon_offsets(features, fractions)
            out["tendons"] = out["backbone"][:, :, None, :] + np.einsum("bnij,bntj->bnti", out["rotation"], rho)
        return out
