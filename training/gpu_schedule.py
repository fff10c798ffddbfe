"""The paper's training schedule on a GPU, in the device time a session is lent (issue #15).

``python -m training.gpu_schedule --data DIR --out FILE --train-minutes M --deadline-minutes D``

Three phases, each appending JSON lines (``study: "gpu"``, the machine and GPU in every line) to
``--out`` as soon as it has them, so that a run cut off at its deadline keeps what it measured:

1. ``training``: seconds per epoch of every preset and model at N = 1, 1,000 and 80,000 (one run
   at a time, the GPU to itself; the first epoch is a warm-up), and what the paper's schedule
   (20,000 DeepONet / 1,500 FNO epochs) would take at that rate;
2. ``schedule``: the four models of the paper preset trained side by side at N = 80,000 with the
   paper's cyclic schedule compressed into ``--train-minutes`` of wall-clock time
   (``TrainConfig.time_budget_min``), then scored on the held-out designs (relative l2);
3. ``inference``: those trained models on the GPU (torch, float32) at 1, 1,000 and 80,000 designs,
   the reference robot included, beside the paper's RTX 4090 table;
4. ``--full MODEL ...``: those models trained alone, in turn, with the paper's whole schedule
   (20,000 / 1,500 epochs), however long it takes, and scored.

Phases past ``--deadline-minutes`` (from the start) are skipped.  The numbers depend on wall-clock
time (phase 2), so unlike ``tdcr study`` they are measurements, not reproducible to the bit.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from training import studies

#: Designs each timing point trains on, and inference batch sizes (the paper's tables).
TIMING_N = (1, 1000, 80_000)
INFERENCE_SIZES = (1, 1000, 80_000)
TIMING_EPOCHS = 3  #: per timing point; the first is a warm-up
INFERENCE_REPEATS = 5
N_SCHEDULE = 80_000


def _append(path: Path, record: dict) -> None:
    import torch

    machine = {**studies.machine(), "threads_per_run": torch.get_num_threads()}  # torch's default here
    studies._append(path, {"version": studies.RECORD_VERSION, "study": "gpu", "machine": machine, **record})


def _epoch_seconds(preset: str, model: str, n: int, data: Path, runs: Path) -> dict:
    """Seconds per epoch after a warm-up epoch, from the run's metrics.jsonl."""
    import shutil

    from training.operators.train import make_config, train

    out = runs / "timing" / preset / model / f"n{n}"
    shutil.rmtree(out, ignore_errors=True)
    cfg = make_config(model, preset, epochs=TIMING_EPOCHS, n_train=n, seed=0, patience=10**9)
    train(cfg, data, out, progress=False, monitor_designs=1)
    seconds = [json.loads(line)["seconds"] for line in (out / "metrics.jsonl").read_text().splitlines()]
    return {"seconds_per_epoch": (seconds[-1] - seconds[0]) / (len(seconds) - 1), "first_epoch_seconds": seconds[0]}


def _train_paper_schedule(model: str, data: str, runs: str, minutes: float) -> dict:
    """One model of the paper preset, N = 80,000, its paper epochs compressed into ``minutes``
    (``None``: the whole schedule); returns the training summary and the held-out error."""
    from training.operators.train import load_trained, make_config, train

    out = Path(runs) / "schedule" / model
    cfg = make_config(model, "paper", epochs=studies.PAPER_EPOCHS[model], n_train=N_SCHEDULE, seed=0,
                      patience=10**9, time_budget_min=minutes)
    summary = train(cfg, data, out, progress=False, monitor_designs=500)
    trained, _ = load_trained(out / "model.pt")
    features, truth = studies._test_split(Path(data), studies.BUDGETS["full"].eval_designs)
    errors = studies.relative_l2(studies.predict_tendons(trained, features), truth)
    return {"summary": summary, "test": studies._summary(errors), "model_path": str(out / "model.pt")}


def _inference_seconds(model_path: str, sizes: tuple[int, ...]) -> dict[int, float]:
    """Best of ``INFERENCE_REPEATS`` GPU forward passes (tendon positions, reference robot
    included) at each batch size, s."""
    import torch

    from tdcr import design_space
    from training.operators.train import load_trained

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    model, _ = load_trained(model_path)
    model.to(device)
    low, high = design_space.feature_bounds()
    rng = np.random.default_rng(0)
    fractions = torch.linspace(0.0, 1.0, design_space.DEFAULT_POINTS, device=device)
    best = {}
    with torch.no_grad():
        for n in sizes:
            x = torch.as_tensor(rng.uniform(low, high, size=(n, low.size)), dtype=torch.float32, device=device)
            times = []
            for _ in range(INFERENCE_REPEATS + 1):  # the first is a warm-up
                if device.type == "cuda":
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                ref = (None if model.config.reference == "undeformed"
                       else model.reference(x, getattr(model, "grid", fractions)))
                model.tendons(x, fractions, ref)
                if device.type == "cuda":
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - t0)
            best[n] = min(times[1:])
    return best


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.gpu_schedule", description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="dataset with >= 80,000 training designs (generated if missing)")
    p.add_argument("--runs", default="runs/gpu")
    p.add_argument("--out", default=f"docs/study/{studies.GPU_RECORDS}")
    p.add_argument("--train-minutes", type=float, default=4.0)
    p.add_argument("--deadline-minutes", type=float, default=7.0)
    p.add_argument("--timing-n", type=int, nargs="*", default=list(TIMING_N))
    p.add_argument("--inference-sizes", type=int, nargs="*", default=list(INFERENCE_SIZES))
    p.add_argument("--full", nargs="*", default=[], choices=studies.MODEL_NAMES,
                   help="then train these models alone, in turn, with the paper's whole schedule")
    p.add_argument("--workers", type=int, default=None, help="processes generating the dataset")
    args = p.parse_args(argv)
    start = time.time()
    deadline = start + 60.0 * args.deadline_minutes
    data, runs, out = Path(args.data), Path(args.runs), Path(args.out)

    from training import dataset

    if not (data / "metadata.json").exists():
        t0 = time.perf_counter()
        dataset.generate(data, dataset.GenerateConfig(n=studies.BUDGETS["full"].n_total, seed=0), workers=args.workers,
                         progress=False)
        print(f"dataset: {time.perf_counter() - t0:.1f} s", flush=True)
    # every timing run below reloads the split; load it once in this process
    dataset.load = functools.lru_cache(maxsize=2)(dataset.load)

    for n in args.timing_n:  # every model at the smallest N first: a quick check that each runs here
        for preset in studies.PRESET_NAMES:
            for model in studies.MODEL_NAMES:
                if time.time() > deadline - 60.0 * args.train_minutes - 60:
                    break
                t = _epoch_seconds(preset, model, n, data, runs)
                _append(out, {"kind": "training", "preset": preset, "model": model, "n": n, **t,
                              "paper_epochs": studies.PAPER_EPOCHS[model],
                              "paper_schedule_seconds": t["seconds_per_epoch"] * studies.PAPER_EPOCHS[model],
                              "paper_seconds": studies.PAPER_TRAINING_SECONDS[model].get(n),
                              "paper_hardware": studies.PAPER_HARDWARE})
                print(f"timing {preset}/{model} N={n}: {t['seconds_per_epoch']:.4g} s/epoch", flush=True)

    def keep(model: str, r: dict, minutes: float | None, side_by_side: int) -> None:
        s = r["summary"]
        _append(out, {"kind": "schedule", "preset": "paper", "model": model, "n": N_SCHEDULE,
                      "train_minutes": minutes, "epochs": s["epochs"], "paper_epochs": studies.PAPER_EPOCHS[model],
                      "train_seconds": s["train_seconds"], "stop": s["stop"], "side_by_side": side_by_side,
                      "test": r["test"]})
        print(f"schedule {model}: {s['epochs']} of {studies.PAPER_EPOCHS[model]} epochs, "
              f"held-out mean {r['test']['mean']:.4g}", flush=True)

    trained = {}
    if args.train_minutes > 0 and time.time() < deadline - 60.0 * args.train_minutes:
        with ProcessPoolExecutor(len(studies.MODEL_NAMES), mp_context=get_context("spawn")) as pool:
            futures = {m: pool.submit(_train_paper_schedule, m, str(data), str(runs), args.train_minutes)
                       for m in studies.MODEL_NAMES}
            for model, future in futures.items():
                r = future.result()
                trained[model] = r["model_path"]
                keep(model, r, args.train_minutes, len(studies.MODEL_NAMES))

    for model, path in trained.items():
        if time.time() > deadline:
            break
        for n, seconds in _inference_seconds(path, tuple(args.inference_sizes)).items():
            _append(out, {"kind": "inference", "preset": "paper", "model": model, "n": n, "seconds": seconds,
                          "repeats": INFERENCE_REPEATS, "runtime": "torch float32, reference robot included",
                          "paper_seconds": studies.PAPER_INFERENCE_SECONDS[model].get(n),
                          "paper_hardware": studies.PAPER_HARDWARE})
            print(f"inference {model} {n}: {seconds * 1e3:.3g} ms", flush=True)
    for model in args.full:  # no deadline: the whole schedule, however long it takes
        keep(model, _train_paper_schedule(model, str(data), str(runs / "full"), None), None, 1)
    print(f"total {time.time() - start:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
