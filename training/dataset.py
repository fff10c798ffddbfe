"""Solver datasets: generation in atomic, resumable shards, and loading.

Layout of a dataset directory::

    metadata.json          format version, seed, ranges, solver settings, counts (written last)
    split.npz              train / test design indices (80 / 20, seeded)
    shards/shard-00000.npz one file per ``shard_size`` designs, written atomically

Each shard holds, for its ``b`` designs (float64, SI units):

    index      (b,)             global design indices
    features   (b, 3 + 3 N_t)   [E, r, L, offsets, pitches, tensions]
    s          (b, n)           arclengths, m
    tendons    (b, n, N_t, 3)   tendon positions, m
    backbone   (b, n, 3)        backbone positions, m
    rotation   (b, n, 3, 3)     frames, body axes as columns
    converged  (b,)             solver flag
    status     (b,)             solver status code (``tdcr.physics.STATUS``)
    residual   (b,)             wrench residual, N
    error_estimate (b,)         estimated relative l2 error of the tendon positions (step control)

Datasets made with loads (``GenerateConfig.loads``) also hold, per design:

    gravity    (b, 3)           m/s^2, base frame (zeros without gravity)
    density    (b,)             kg/m^3 (zeros without gravity)
    tip_force  (b, 3)           N, base frame
    tip_moment (b, 3)           N m, base frame
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.physics import STATUS, SolverOptions, solve
from tdcr.robot.designs import LOAD_COLUMNS, N_LOAD_COLUMNS, DesignBatch, ExternalLoads
from tdcr.robot.fields import OPTIONAL

FORMAT_VERSION = 1
_ARRAYS = ("index", "features", "s", "tendons", "backbone", "rotation", "converged", "residual")
#: arrays of newer or loaded datasets, read where a shard has them
_OPTIONAL = ("status", "error_estimate", *LOAD_COLUMNS, *(f.name for f in OPTIONAL), "tension")


@dataclass(frozen=True)
class GenerateConfig:
    """What to generate: ``n`` Table I designs from ``seed``, at ``points`` equispaced arclengths;
    robots of ``segments`` segments with ``tendons_per_segment`` tendons each
    (:func:`tdcr.robot.design_space.sample_segmented_designs`; the default, one segment of 4 tendons, is
    the surrogates' design space)."""

    n: int
    seed: int = 0
    points: int = design_space.DEFAULT_POINTS
    shard_size: int = 1000
    test_fraction: float = 0.2
    loads: design_space.LoadSpace = design_space.LoadSpace()
    segments: int = 1
    tendons_per_segment: int = design_space.N_TENDONS

    @property
    def n_shards(self) -> int:
        return -(-self.n // self.shard_size)

    @property
    def n_tendons(self) -> int:
        return self.segments * self.tendons_per_segment

    def designs(self) -> DesignBatch:
        """The dataset's designs (seeded)."""
        if (self.segments, self.tendons_per_segment) == (1, design_space.N_TENDONS):
            return design_space.sample_designs(self.n, seed=self.seed)
        return design_space.sample_segmented_designs(self.n, seed=self.seed, segments=self.segments,
                                                     tendons_per_segment=self.tendons_per_segment)


#: Plan keys added after datasets were first made, with the value an older plan means.
_PLAN_DEFAULTS = {"segments": 1, "tendons_per_segment": design_space.N_TENDONS}


class DatasetMismatch(ValueError):
    """An existing output directory was made with other settings."""


def solve_shard(features: np.ndarray, index: np.ndarray, points: int,
                loads: dict[str, np.ndarray] | None = None,
                layout: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Solve one shard of designs ``(b, 3 + 3 N_t)`` (and their ``loads``, arrays as in the module
    doc; ``layout``: the general design's fields given, e.g. the tendons' ``angle`` and ``end``
    ``(b, N_t)`` of robots with segments);
    returns the shard's arrays."""
    designs = DesignBatch.from_features(features)
    if layout:
        designs = designs.replace(**layout)
    external = None if loads is None else ExternalLoads(**{k: v for k, v in loads.items() if v is not None})
    sol = solve(designs, np.linspace(0.0, 1.0, points), loads=external)
    arrays = {
        "index": index, "features": features, "s": sol.s, "tendons": sol.tendons,
        "backbone": sol.backbone, "rotation": sol.rotation, "converged": sol.converged,
        "status": sol.status, "residual": sol.residual, "error_estimate": sol.error_estimate,
        "displacement": sol.displacement,
    }
    if layout:
        arrays.update(layout)
    if loads is not None:
        b = features.shape[0]
        arrays.update(gravity=np.zeros((b, 3)) if loads["gravity"] is None else loads["gravity"],
                      density=np.zeros(b) if loads["density"] is None else loads["density"],
                      tip_force=loads["tip_force"], tip_moment=loads["tip_moment"])
    return arrays


def _load_rows(loads: ExternalLoads | None, rows: slice) -> dict[str, np.ndarray] | None:
    if loads is None:
        return None
    return {k: None if getattr(loads, k) is None else np.asarray(getattr(loads, k))[rows]
            for k in ("gravity", "density", "tip_force", "tip_moment")}


def shard_path(out: Path, k: int) -> Path:
    return out / "shards" / f"shard-{k:05d}.npz"


def _write_atomic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _write_json_atomic(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)


def _plan(out: Path, cfg: GenerateConfig) -> None:
    """Create the directory and its plan file, or check that an existing one matches ``cfg``."""
    (out / "shards").mkdir(parents=True, exist_ok=True)
    plan_file = out / "plan.json"
    plan = json.loads(json.dumps({"format_version": FORMAT_VERSION, **asdict(cfg)}))  # tuples as JSON lists
    if plan_file.exists():
        old = _PLAN_DEFAULTS | json.loads(plan_file.read_text())
        if old != plan:
            raise DatasetMismatch(f"{out} holds a dataset made with other settings: {old}")
    else:
        _write_json_atomic(plan_file, plan)


def generate(
    out: str | Path,
    cfg: GenerateConfig,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> dict:
    """Generate (or resume) a dataset in ``out``; returns its metadata.

    Shards already on disk are kept; the others are solved on ``workers`` local processes
    (default: all cores) or, with ``scheduler``, on a Dask distributed cluster at that address.
    Temporary files a killed run left behind are removed.
    """
    out = Path(out)
    _plan(out, cfg)
    for stale in (out / "shards").glob("*.tmp-*"):  # half-written by a killed run (one writer per dataset)
        stale.unlink()
    designs = cfg.designs()
    features = designs.features()
    layout = {f.name: designs.resolved(f.name) for f in OPTIONAL if getattr(designs, f.name) is not None} or None
    todo = [k for k in range(cfg.n_shards) if not shard_path(out, k).exists()]
    done_designs = cfg.n - sum(len(range(cfg.n)[_shard_range(cfg, k)]) for k in todo)
    bar = _progress_bar(cfg.n, done_designs, progress)
    started = time.perf_counter()
    loads = cfg.loads.sample(cfg.n, seed=cfg.seed)
    jobs = [(k, features[_shard_range(cfg, k)], np.arange(cfg.n)[_shard_range(cfg, k)],
             _load_rows(loads, _shard_range(cfg, k)),
             None if layout is None else {name: v[_shard_range(cfg, k)] for name, v in layout.items()})
            for k in todo]
    for k, arrays in _run_jobs(jobs, cfg.points, workers=workers, scheduler=scheduler):
        _write_atomic(shard_path(out, k), arrays)
        if bar is not None:
            bar.update(len(arrays["index"]))
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - started
    return _finish(out, cfg, solved=cfg.n - done_designs, elapsed=elapsed)


def _shard_range(cfg: GenerateConfig, k: int) -> slice:
    return slice(k * cfg.shard_size, min(cfg.n, (k + 1) * cfg.shard_size))


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="design", desc="solving", smoothing=0.1)


def _run_jobs(jobs, points: int, *, workers: int | None, scheduler: str | None):
    """Yield ``(shard index, arrays)`` as shards finish, in any order."""
    if not jobs:
        return
    if scheduler is not None:
        from distributed import Client
        from distributed import as_completed as dask_completed

        with Client(scheduler) as client:
            futures = {client.submit(solve_shard, f, i, points, ld, lay, pure=False): k for k, f, i, ld, lay in jobs}
            for fut in dask_completed(futures):
                yield futures[fut], fut.result()
        return
    workers = workers or os.cpu_count() or 1
    if workers == 1:
        for k, f, i, ld, lay in jobs:
            yield k, solve_shard(f, i, points, ld, lay)
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(solve_shard, f, i, points, ld, lay): k for k, f, i, ld, lay in jobs}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def split_indices(n: int, seed: int, n_test: int) -> tuple[np.ndarray, np.ndarray]:
    """The train / test split of a dataset of ``n`` designs from ``seed``: a permutation from
    ``seed + 1`` (the manifest's ``split_seed``), its first ``n_test`` the test set; sorted
    indices ``(train, test)``."""
    perm = np.random.default_rng(seed + 1).permutation(n)
    return np.sort(perm[n_test:]), np.sort(perm[:n_test])


def training_features(record: dict) -> np.ndarray:
    """The training designs ``(n_train, 15)`` of a dataset recorded as ``{"n", "seed", "n_test"}``
    (``tdcr export --data`` writes it into each manifest entry): regenerated, not read."""
    train, _ = split_indices(record["n"], record["seed"], record["n_test"])
    return design_space.sample_designs(record["n"], seed=record["seed"]).features()[train]


def _finish(out: Path, cfg: GenerateConfig, *, solved: int, elapsed: float) -> dict:
    converged = 0
    status = np.zeros(len(STATUS), dtype=np.int64)
    for k in range(cfg.n_shards):
        with np.load(shard_path(out, k)) as z:
            converged += int(z["converged"].sum())
            if "status" in z:
                status += np.bincount(z["status"].astype(np.int64), minlength=len(STATUS))
    n_test = int(round(cfg.test_fraction * cfg.n))
    train, test = split_indices(cfg.n, cfg.seed, n_test)
    np.savez(out / "split.npz", train=train, test=test)
    meta = {
        "format_version": FORMAT_VERSION,
        "generator": "tdcr generate",
        **asdict(cfg),
        "n_tendons": cfg.n_tendons,
        "feature_names": design_space.feature_names(cfg.n_tendons),
        "ranges": {k: {"name": v.name, "unit": v.unit, "low": v.low, "high": v.high, "admissible": v.admissible,
                       "exclusive_min": v.exclusive_min} for k, v in design_space.TABLE_I.items()},
        "fractions": np.linspace(0.0, 1.0, cfg.points).tolist(),  # the arclengths, fractions of L
        "solver": asdict(SolverOptions()),
        "converged": converged,
        "not_converged": cfg.n - converged,
        "convergence_rate": converged / cfg.n,
        "status_counts": {name: int(c) for name, c in zip(STATUS, status, strict=True) if c},
        "n_train": cfg.n - n_test,
        "n_test": n_test,
        "last_run": {"designs_solved": solved, "seconds": round(elapsed, 3)},
    }
    _write_json_atomic(out / "metadata.json", meta)
    return meta


def load_matrix(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """The loads of loaded dataset arrays as the loaded operators take them, ``(B, 10)``
    (:data:`tdcr.robot.designs.LOAD_COLUMNS`); zeros for a dataset made without loads."""
    n = len(arrays["features"])
    if "tip_force" not in arrays:
        return np.zeros((n, N_LOAD_COLUMNS))
    return ExternalLoads(**{k: arrays[k] for k in LOAD_COLUMNS}).matrix(n)


def load(path: str | Path, split: str = "all", *, converged_only: bool = True) -> dict[str, np.ndarray]:
    """Load a dataset (``split`` = 'train', 'test' or 'all'); arrays as in the module docstring."""
    path = Path(path)
    meta = json.loads((path / "metadata.json").read_text())
    parts = []
    for k in range(-(-meta["n"] // meta["shard_size"])):
        with np.load(shard_path(path, k)) as z:
            parts.append({name: z[name] for name in (*_ARRAYS, *_OPTIONAL) if name in z})
    names = [name for name in (*_ARRAYS, *_OPTIONAL) if all(name in p for p in parts)]
    data = {name: np.concatenate([p[name] for p in parts]) for name in names}
    if split != "all":
        with np.load(path / "split.npz") as z:
            keep = np.isin(data["index"], z[split])
        data = {k: v[keep] for k, v in data.items()}
    if converged_only:
        ok = data["converged"]
        data = {k: v[ok] for k, v in data.items()}
    return data
