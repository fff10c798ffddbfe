"""The paper's studies (Section IV), each reproducible with one command: ``tdcr study NAME``.

Studies (``STUDIES``), each run for both presets (``paper`` and ``tuned``):

* ``n-sweep``  held-out relative l2 against the number of training designs N, mean +- std over seeds;
* ``dropout``  the effect of dropout q at the largest N (paper Fig. L2vDrop);
* ``seeds``    the spread over 3 seeds at the largest N where every model gets 3 seeds;
* ``ood``      the paper's out-of-distribution bins (every parameter at high * (1 + p)) and the same
  bins on a Table I box widened in every direction (each parameter below its low or above its high
  bound by p of the range's width);
* ``timing``   training seconds per epoch against N, inference at 1, 1,000 and 80,000 designs
  (onnxruntime, shipped models), beside the paper's RTX 4090 tables;
* ``worst``    the 20 worst held-out designs of each model, what they share, and the error against
  the linearised bending angle theta = max_i tau_i |rho_i| L / (E I).

Compute is fixed by a :class:`Budget` in epochs, never in seconds, so that a study re-run with the
same seed reproduces its numbers (CPU, one thread per run, deterministic algorithms).  Every
training run is a :class:`RunSpec`; its directory under ``runs`` holds the resumable checkpoint and,
once evaluated, ``result.json``: studies share runs (the N = 80,000 seed-0 run is a point of the N
sweep, the dropout study's q = 0 and the OOD study's model).  Each study appends one JSON line per
finished record to ``docs/study/NAME.jsonl`` (budget, machine, seed in every line) and redraws
``docs/study/NAME.png`` from it; a re-run skips the records already there.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from tdcr import design_space
from tdcr.metrics import relative_l2
from tdcr.physics import solve
from tdcr.robot.designs import DesignBatch
from tdcr.surrogates.bounds import bending_angle

#: Format of the study records (every JSON line carries it).
RECORD_VERSION = 1
PRESET_NAMES = ("paper", "tuned")
MODEL_NAMES = ("deeponet", "deeponet_pose", "fno", "fno_pose")
#: In the order ``tdcr study all`` runs them (timing last: it wants a quiet machine).
STUDIES = ("n-sweep", "dropout", "seeds", "ood", "worst", "timing")

#: The paper's Table "trainingTimes" (RTX 4090, JAX): seconds of training at N = 1, 1,000, 80,000.
PAPER_TRAINING_SECONDS = {
    "deeponet": {1: 149.4, 1000: 150.6, 80_000: 108 * 60.0},
    "deeponet_pose": {1: 144.2, 1000: 148.3, 80_000: 106 * 60.0},
    "fno": {1: 13.66, 1000: 14.66, 80_000: 15.5 * 60.0},
    "fno_pose": {1: 14.56, 1000: 15.28, 80_000: 15.8 * 60.0},
}
#: The paper's Table "inferenceTimes" (RTX 4090, JAX): seconds for 1, 1,000 and 80,000 designs.
PAPER_INFERENCE_SECONDS = {
    "deeponet": {1: 0.0019, 1000: 0.0022, 80_000: 0.0878},
    "deeponet_pose": {1: 0.0017, 1000: 0.0021, 80_000: 0.0756},
    "fno": {1: 0.0015, 1000: 0.0015, 80_000: 0.1997},
    "fno_pose": {1: 0.0014, 1000: 0.0016, 80_000: 0.2009},
}
#: Epochs the paper's models took to converge (Section IV, training details).
PAPER_EPOCHS = {"deeponet": 20_000, "deeponet_pose": 20_000, "fno": 1500, "fno_pose": 1500}
PAPER_HARDWARE = "NVIDIA RTX 4090 (paper, JAX)"

#: Widened-box OOD bins: fractions of each Table I range's width outside the box.
WIDENED_BINS: tuple[tuple[float, float], ...] = ((0.0, 0.05), (0.05, 0.10), (0.10, 0.15), (0.15, 0.20))
#: Records of ``training.gpu_schedule`` beside the studies' (the timing study plots them too).
GPU_RECORDS = "gpu.jsonl"
#: How many of the worst held-out designs the ``worst`` study lists per model.
N_WORST = 20


def family(model: str) -> str:
    """``'fno'`` or ``'deeponet'``: the budget's unit of cost."""
    return "fno" if model.startswith("fno") else "deeponet"


@dataclass(frozen=True)
class Budget:
    """The compute of every study, in epochs and designs (never in seconds).

    A run at N training designs trains ``epochs_at_max[family] * sqrt(max(n_values) / N)`` epochs:
    the designs seen grow as sqrt(N), so small N gets more passes and the sweep's cost stays
    bounded.  ``seeds[family]`` seeds at N <= ``all_seeds_up_to``, one seed above.
    """

    name: str
    n_total: int  #: designs of the dataset (80 % train, 20 % test)
    n_values: tuple[int, ...]
    epochs_at_max: dict = field(default_factory=dict)
    seeds: int = 3
    all_seeds_up_to: dict = field(default_factory=dict)  #: family -> largest N with every seed
    dropouts: tuple[float, ...] = (0.0, 0.05, 0.1, 0.2)
    eval_designs: int = 20_000  #: held-out designs each run is scored on
    monitor_designs: int = 500
    ood_designs: int = 1000  #: per bin
    timing_n: tuple[int, ...] = (1, 1000, 80_000)
    timing_epochs: int = 2  #: the first is a warm-up
    inference_sizes: tuple[int, ...] = (1, 1000, 80_000)
    inference_repeats: int = 3

    def epochs(self, model: str, n_train: int) -> int:
        return max(1, round(self.epochs_at_max[family(model)] * math.sqrt(max(self.n_values) / n_train)))

    def seeds_at(self, model: str, n_train: int) -> tuple[int, ...]:
        return tuple(range(self.seeds if n_train <= self.all_seeds_up_to[family(model)] else 1))


BUDGETS = {
    # 9.0 CPU-hours measured on the 2-core development VM (docs/report.md lists the seeds of every point)
    "full": Budget("full", 100_000, (1000, 5000, 10_000, 20_000, 40_000, 80_000),
                   epochs_at_max={"deeponet": 60, "fno": 6},
                   all_seeds_up_to={"deeponet": 80_000, "fno": 10_000}),
    # the tests' version: seconds
    "tiny": Budget("tiny", 400, (80, 160), epochs_at_max={"deeponet": 2, "fno": 1}, seeds=2,
                   all_seeds_up_to={"deeponet": 160, "fno": 80}, dropouts=(0.0, 0.1), eval_designs=40,
                   monitor_designs=10, ood_designs=8, timing_n=(1, 80), timing_epochs=2,
                   inference_sizes=(1, 50), inference_repeats=2),
}


@dataclass(frozen=True)
class RunSpec:
    """One training run of a study: everything its result depends on."""

    preset: str
    model: str
    n_train: int
    seed: int
    epochs: int
    dropout: float = 0.0

    @property
    def key(self) -> str:
        return f"{self.preset}/{self.model}/n{self.n_train}-s{self.seed}-q{self.dropout:g}-e{self.epochs}"


@dataclass(frozen=True)
class Context:
    """Where a study reads and writes, and what it may spend."""

    data: Path
    runs: Path
    out: Path
    budget: Budget
    presets: tuple[str, ...] = PRESET_NAMES
    models: tuple[str, ...] = MODEL_NAMES
    workers: int = 1
    stop_at: float | None = None  #: ``time.time()`` after which no new work starts
    models_dir: Path = Path("models")
    progress: Callable[[str], None] = print


def machine() -> dict:
    """The hardware and software a record was measured with."""
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cores": os.cpu_count(), "threads_per_run": 1, "gpu": gpu,
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__}


# ---------------------------------------------------------------------------------------------
# records: one JSON line each, appended atomically enough (one write + fsync per line)


def records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _append(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _summary(errors: np.ndarray) -> dict:
    return {"mean": float(errors.mean()), "median": float(np.median(errors)),
            "p95": float(np.percentile(errors, 95)), "p99": float(np.percentile(errors, 99)),
            "max": float(errors.max()), "n": int(errors.size)}


# ---------------------------------------------------------------------------------------------
# training runs (in worker processes: one torch thread each)


def _test_split(data: Path, n: int | None) -> tuple[np.ndarray, np.ndarray]:
    from training import dataset

    test = dataset.load(data, "test")
    return test["features"][:n], test["tendons"][:n]


def predict_tendons(model, features: np.ndarray, *, chunk: int = 2048) -> np.ndarray:
    """A trained torch operator's tendon positions on the 42-point grid, m, ``(B, n, N_t, 3)``."""
    import torch

    fractions = torch.linspace(0.0, 1.0, design_space.DEFAULT_POINTS, dtype=torch.float32)
    parts = []
    with torch.no_grad():
        for i in range(0, len(features), chunk):
            x = torch.as_tensor(features[i:i + chunk], dtype=torch.float32)
            grid = getattr(model, "grid", fractions)
            ref = None if model.config.reference == "undeformed" else model.reference(x, grid)
            parts.append(model.tendons(x, fractions, ref).double().numpy())
    return np.concatenate(parts)


def run_training(spec: RunSpec, data: Path, runs: Path, budget: Budget, stop_at: float | None) -> dict | None:
    """Train (or resume) and score one run; ``None`` if ``stop_at`` interrupted it (resumable)."""
    import torch

    from training.operators.train import load_trained, make_config, train

    torch.set_num_threads(1)
    out = runs / spec.key
    result_path = out / "result.json"
    if result_path.exists():
        return json.loads(result_path.read_text())
    if stop_at is not None and time.time() >= stop_at:  # past the chunk's end: do not even start
        return None
    cfg = make_config(spec.model, spec.preset, epochs=spec.epochs, n_train=spec.n_train, seed=spec.seed,
                      dropout=spec.dropout, patience=spec.epochs + 1)
    summary = train(cfg, data, out, progress=False, monitor_designs=budget.monitor_designs, stop_at=stop_at)
    if summary["stop"] == "interrupted":
        return None
    model, _ = load_trained(out / "model.pt")
    features, truth = _test_split(data, budget.eval_designs)
    errors = relative_l2(predict_tendons(model, features), truth)
    result = {**asdict(spec), "key": spec.key, "test": _summary(errors), "train_seconds": summary["train_seconds"],
              "seconds_per_epoch": summary["train_seconds"] / max(spec.epochs, 1),
              "designs_seen": spec.epochs * summary["n_train"], "final_train_loss": summary["final_train_loss"]}
    tmp = result_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result))
    os.replace(tmp, result_path)
    return result


def _run_all(ctx: Context, specs: Iterable[RunSpec], on_result: Callable[[RunSpec, dict], None]) -> int:
    """Run the specs (``ctx.workers`` processes), calling ``on_result`` in this process as each
    finishes; returns how many are still unfinished (interrupted by ``ctx.stop_at``)."""
    specs = list(dict.fromkeys(specs))
    done_now = [s for s in specs if (ctx.runs / s.key / "result.json").exists()]
    for spec in done_now:
        on_result(spec, json.loads((ctx.runs / spec.key / "result.json").read_text()))
    todo = [s for s in specs if s not in done_now]
    unfinished = 0
    if not todo:
        return 0
    ctx.progress(f"{len(todo)} training runs to do ({ctx.workers} worker(s))")
    with ProcessPoolExecutor(max_workers=ctx.workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_training, s, ctx.data, ctx.runs, ctx.budget, ctx.stop_at): s for s in todo}
        for fut in as_completed(futures):
            spec, result = futures[fut], fut.result()
            if result is None:
                unfinished += 1
                ctx.progress(f"  interrupted (resumable): {spec.key}")
                continue
            ctx.progress(f"  {spec.key}: mean rel. l2 {result['test']['mean']:.4g} ({result['train_seconds']:.0f} s)")
            on_result(spec, result)
    return unfinished


# ---------------------------------------------------------------------------------------------
# the studies


def _record_base(ctx: Context, study: str) -> dict:
    return {"version": RECORD_VERSION, "study": study, "budget": asdict(ctx.budget), "machine": machine()}


def _training_study(ctx: Context, study: str, specs: list[RunSpec]) -> int:
    path = ctx.out / f"{study}.jsonl"
    have = {r["key"] for r in records(path)}

    def keep(spec: RunSpec, result: dict) -> None:
        if spec.key not in have:
            _append(path, {**_record_base(ctx, study), **result})
            have.add(spec.key)

    return _run_all(ctx, [s for s in specs if s.key not in have], keep)


def sweep_specs(ctx: Context) -> list[RunSpec]:
    """The N sweep, seed 0 of everything first (so an interrupted sweep has whole curves)."""
    b = ctx.budget
    specs = [RunSpec(p, m, n, seed, b.epochs(m, n)) for p in ctx.presets for m in ctx.models
             for n in b.n_values for seed in b.seeds_at(m, n)]
    return sorted(specs, key=lambda s: (s.seed, -s.epochs * s.n_train))


def study_n_sweep(ctx: Context) -> int:
    return _training_study(ctx, "n-sweep", sweep_specs(ctx))


def study_dropout(ctx: Context) -> int:
    """Dropout q at the largest N, seed 0; the cheap DeepONet runs first (a chunk that stops keeps
    whole curves)."""
    b, n = ctx.budget, max(ctx.budget.n_values)
    specs = [RunSpec(p, m, n, 0, b.epochs(m, n), q) for p in ctx.presets for m in ctx.models for q in b.dropouts]
    return _training_study(ctx, "dropout", sorted(specs, key=lambda s: (family(s.model) == "fno", s.preset == "paper")))


def study_seeds(ctx: Context) -> int:
    b = ctx.budget
    n = min(b.all_seeds_up_to.values())
    return _training_study(ctx, "seeds", [RunSpec(p, m, n, seed, b.epochs(m, n)) for p in ctx.presets
                                          for m in ctx.models for seed in range(b.seeds)])


def _largest_runs(ctx: Context) -> dict[tuple[str, str], RunSpec]:
    b, n = ctx.budget, max(ctx.budget.n_values)
    return {(p, m): RunSpec(p, m, n, 0, b.epochs(m, n)) for p in ctx.presets for m in ctx.models}


def widened_ood_designs(n: int, bin_range: tuple[float, float], *, seed: int) -> DesignBatch:
    """Every parameter outside Table I in a random direction: below ``low`` or above ``high`` by
    p of the range's width, p uniform in ``bin_range``; clipped to the admissible bounds (tensions
    cannot go below 0 N, so they always go above)."""
    rng = np.random.default_rng(seed)
    low, high = design_space.feature_bounds()
    a_low, a_high, _ = design_space.admissible_bounds()
    width = high - low
    p = rng.uniform(bin_range[0], bin_range[1], size=(n, low.size))
    below = rng.random((n, low.size)) < 0.5
    below &= (low - width * bin_range[1]) >= a_low  # only where going below stays admissible
    x = np.where(below, low - p * width, high + p * width)
    return DesignBatch.from_features(np.clip(x, a_low, a_high))


def study_ood(ctx: Context) -> int:
    from training.operators.evaluate import BASELINES
    from training.operators.train import load_trained

    path = ctx.out / "ood.jsonl"
    have = {(r["protocol"], r["bin"], r["preset"], r["model"]) for r in records(path)}
    runs = _largest_runs(ctx)
    models: dict[tuple[str, str], object] = {}
    unfinished = _run_all(ctx, runs.values(), lambda spec, _r: models.__setitem__(
        (spec.preset, spec.model), load_trained(ctx.runs / spec.key / "model.pt")[0]))
    fractions = np.linspace(0.0, 1.0, design_space.DEFAULT_POINTS)
    protocols = {"paper": (design_space.OOD_BINS, design_space.sample_ood_designs),
                 "widened": (WIDENED_BINS, widened_ood_designs)}
    for protocol, (bins, sampler) in protocols.items():
        for k, bin_range in enumerate(bins):
            label = f"{100 * bin_range[0]:+.0f}..{100 * bin_range[1]:+.0f} %"
            designs = sampler(ctx.budget.ood_designs, bin_range, seed=1000 * (protocol == "widened") + k)
            sol = solve(designs, fractions)
            features, truth = designs.features()[sol.converged], sol.tendons[sol.converged]
            base = {**_record_base(ctx, "ood"), "protocol": protocol, "bin": label, "bin_range": list(bin_range),
                    "designs": int(sol.converged.sum()), "not_converged": int((~sol.converged).sum())}
            rows = [("-", name, fn(features, fractions)) for name, fn in BASELINES.items()]
            rows += [(p, m, predict_tendons(model, features)) for (p, m), model in models.items()]
            for preset, name, pred in rows:
                if (protocol, label, preset, name) in have:
                    continue
                spec = runs.get((preset, name))
                extra = {} if spec is None else {"run": spec.key, "seed": spec.seed, "n_train": spec.n_train}
                _append(path, {**base, "preset": preset, "model": name, **extra,
                               "error": _summary(relative_l2(pred, truth))})
    return unfinished


def design_traits(features: np.ndarray) -> dict[str, np.ndarray]:
    """What the ``worst`` study compares: bending angle (rad), mean |pitch| (rad/m), slenderness L / r,
    total tension (N), the pitch-times-length twist (rad), each ``(B,)``."""
    lay = design_space.LAYOUT
    pitch = np.abs(features[:, lay.group("pitch")]).mean(axis=1)
    return {"bending_angle": bending_angle(features), "mean_abs_pitch": pitch,
            "slenderness": features[:, 2] / features[:, 1],
            "total_tension": features[:, lay.group("tension")].sum(axis=1),
            "twist": pitch * features[:, 2]}


def study_worst(ctx: Context) -> int:
    from tdcr.surrogates.runtime import Surrogate
    from training.operators.train import load_trained

    path = ctx.out / "worst.jsonl"
    have = {(r["preset"], r["model"]) for r in records(path)}
    features, truth = _test_split(ctx.data, ctx.budget.eval_designs)
    traits = design_traits(features)
    fractions = np.linspace(0.0, 1.0, truth.shape[1])
    predictions: dict[tuple[str, str], tuple[np.ndarray, dict]] = {}
    # the shipped models (tuned preset, onnxruntime) ...
    for name in ctx.models:
        if (ctx.models_dir / "manifest.json").exists():
            pred = Surrogate.load(ctx.models_dir, name).predict(features, fractions)["tendons"]
            predictions[("shipped", name)] = (pred, {"models_dir": str(ctx.models_dir)})
    # ... and the studies' largest runs of each preset
    runs = _largest_runs(ctx)
    unfinished = _run_all(ctx, runs.values(), lambda spec, _r: predictions.__setitem__(
        (spec.preset, spec.model), (predict_tendons(load_trained(ctx.runs / spec.key / "model.pt")[0], features),
                                    {"run": spec.key, "seed": spec.seed, "n_train": spec.n_train})))
    for (preset, name), (pred, extra) in predictions.items():
        if (preset, name) in have:
            continue
        errors = relative_l2(pred, truth)
        worst = np.argsort(errors)[::-1][:N_WORST]
        common = {k: {"worst_median": float(np.median(v[worst])), "all_median": float(np.median(v)),
                      "worst_percentile_of_median": float((v < np.median(v[worst])).mean() * 100)}
                  for k, v in traits.items()}
        # error against the bending angle: medians in 12 log-spaced bins (the PNG's line)
        theta = traits["bending_angle"]
        edges = np.geomspace(max(theta[theta > 0].min(), 1e-6), theta.max() * (1 + 1e-9), 13)
        idx = np.digitize(theta, edges) - 1
        binned = [{"theta_low": float(edges[i]), "theta_high": float(edges[i + 1]), "n": int((idx == i).sum()),
                   "median_error": float(np.median(errors[idx == i])) if (idx == i).any() else None}
                  for i in range(len(edges) - 1)]
        _append(path, {**_record_base(ctx, "worst"), "preset": preset, "model": name, **extra,
                       "error": _summary(errors), "common": common, "error_vs_bending_angle": binned,
                       "worst": [{"test_index": int(i), "error": float(errors[i]),
                                  "features": features[i].tolist(),
                                  **{k: float(v[i]) for k, v in traits.items()}} for i in worst]})
    return unfinished


def _epoch_seconds(spec: RunSpec, data: Path, runs: Path) -> dict:
    """Seconds per epoch of a short run of ``spec.epochs`` epochs (the first is a warm-up and not
    counted), from the run's own metrics.jsonl."""
    import shutil

    import torch

    from training.operators.train import make_config, train

    torch.set_num_threads(1)
    out = runs / "timing" / spec.key
    shutil.rmtree(out, ignore_errors=True)  # always a fresh run: this measures, it does not resume
    cfg = make_config(spec.model, spec.preset, epochs=spec.epochs, n_train=spec.n_train, seed=spec.seed,
                      patience=10**9)
    train(cfg, data, out, progress=False, monitor_designs=1)
    seconds = [json.loads(line)["seconds"] for line in (out / "metrics.jsonl").read_text().splitlines()]
    return {"seconds_per_epoch": (seconds[-1] - seconds[0]) / max(len(seconds) - 1, 1),
            "first_epoch_seconds": seconds[0], "epochs_timed": max(len(seconds) - 1, 1)}


def study_timing(ctx: Context) -> int:
    from tdcr.surrogates.runtime import Surrogate

    path = ctx.out / "timing.jsonl"
    have = {(r["kind"], r["preset"], r["model"], r["n"]) for r in records(path)}
    b = ctx.budget
    todo = [RunSpec(preset, name, n, 0, b.timing_epochs) for preset in ctx.presets for name in ctx.models
            for n in b.timing_n if ("training", preset, name, n) not in have]
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:  # one clean 1-thread process, runs in turn
        for spec in todo:
            if ctx.stop_at and time.time() > ctx.stop_at:
                break
            preset, name, n = spec.preset, spec.model, spec.n_train
            t = pool.submit(_epoch_seconds, spec, ctx.data, ctx.runs).result()
            paper_s = PAPER_TRAINING_SECONDS[name].get(n)
            _append(path, {**_record_base(ctx, "timing"), "kind": "training", "preset": preset, "model": name,
                           "n": n, **t, "paper_epochs": PAPER_EPOCHS[name],
                           "paper_schedule_seconds": t["seconds_per_epoch"] * PAPER_EPOCHS[name],
                           "paper_seconds": paper_s, "paper_hardware": PAPER_HARDWARE})
            ctx.progress(f"  training {preset}/{name} N={n}: {t['seconds_per_epoch']:.3g} s/epoch")
    if (ctx.models_dir / "manifest.json").exists():
        rng = np.random.default_rng(0)
        low, high = design_space.feature_bounds()
        fractions = np.linspace(0.0, 1.0, design_space.DEFAULT_POINTS)
        for name in ctx.models:
            model = Surrogate.load(ctx.models_dir, name)
            for n in b.inference_sizes:
                if ("inference", "shipped", name, n) in have:
                    continue
                x = rng.uniform(low, high, size=(n, low.size))
                model.predict(x, fractions)  # warm-up
                times = []
                for _ in range(b.inference_repeats):
                    t0 = time.perf_counter()
                    model.predict(x, fractions)
                    times.append(time.perf_counter() - t0)
                _append(path, {**_record_base(ctx, "timing"), "kind": "inference", "preset": "shipped",
                               "model": name, "n": n, "seconds": min(times), "repeats": b.inference_repeats,
                               "runtime": "onnxruntime (tdcr.surrogates.runtime.Surrogate.predict, 2 threads)",
                               "paper_seconds": PAPER_INFERENCE_SECONDS[name].get(n),
                               "paper_hardware": PAPER_HARDWARE})
    return 0


RUNNERS: dict[str, Callable[[Context], int]] = {
    "n-sweep": study_n_sweep, "dropout": study_dropout, "seeds": study_seeds,
    "ood": study_ood, "timing": study_timing, "worst": study_worst,
}


def ensure_dataset(ctx: Context) -> None:
    """Generate the study's dataset (seed 0) if it is not there; resumes a partial one."""
    from training import dataset

    if not (ctx.data / "metadata.json").exists():
        ctx.progress(f"generating {ctx.budget.n_total} designs into {ctx.data}")
        dataset.generate(ctx.data, dataset.GenerateConfig(n=ctx.budget.n_total, seed=0,
                                                          shard_size=min(1000, ctx.budget.n_total)),
                         workers=ctx.workers, progress=False)


def run_study(name: str, ctx: Context, *, plot_only: bool = False) -> dict:
    """Run (or resume) one study and redraw its plot; returns ``{"unfinished": runs, "png": path,
    "table": Markdown summary}``."""
    from training import study_plots

    if name not in RUNNERS:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(STUDIES)}")
    unfinished = 0
    if not plot_only:
        ensure_dataset(ctx)
        unfinished = RUNNERS[name](ctx)
    recs = records(ctx.out / f"{name}.jsonl")
    if name == "timing":  # and the GPU's, where one was lent (python -m training.gpu_schedule)
        recs += [r for r in records(ctx.out / GPU_RECORDS) if r["kind"] in ("training", "inference")]
    png = study_plots.plot(name, recs, ctx.out / f"{name}.png")
    return {"unfinished": unfinished, "png": None if png is None else str(png), "table": study_plots.table(name, recs)}


__all__ = ["BUDGETS", "Budget", "Context", "RunSpec", "STUDIES", "bending_angle", "records", "run_study",
           "widened_ood_designs"]
