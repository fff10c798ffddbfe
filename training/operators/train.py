"""Training of the registered operators on a solver dataset (Adam, cyclic cosine schedule).

Losses (paper Section III-D): both compare tendon positions, averaged over designs and points:
pose models through p + R rho_i(s) (eq. loss1), tendon models directly (eq. loss2).
``loss='mse'`` is the paper's squared error in m^2; ``loss='relative'`` divides each design's
squared error by ||y||^2, which is the square of the reported metric (paper eq. l2Error);
``loss='relative_l2'`` (the tuned preset) is the reported metric itself, the mean over designs of
||y_hat - y|| / ||y||.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from training import dataset
from training.operators.models import build_model, count_parameters

#: Format of ``model.pt``, recorded in it; ``load_trained`` refuses others.
CHECKPOINT_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Schedule:
    """Cyclic cosine annealing with warm-up (SGDR-like), as a function of training progress in [0, 1].

    Each of ``cycles`` equal cycles warms up linearly from ``initial`` to ``peak * gamma^c`` over
    ``warmup`` of the cycle, then decays along a cosine to ``end``.
    """

    initial: float = 1e-4
    peak: float = 3e-3
    end: float = 5e-6
    warmup: float = 0.3
    cycles: int = 4
    gamma: float = 0.7

    def __call__(self, progress: float) -> float:
        progress = min(max(progress, 0.0), 1.0 - 1e-12)
        c = int(progress * self.cycles)
        t = progress * self.cycles - c
        peak = self.peak * self.gamma**c
        if t < self.warmup:
            return self.initial + (peak - self.initial) * t / self.warmup
        u = (t - self.warmup) / (1.0 - self.warmup)
        return self.end + 0.5 * (peak - self.end) * (1.0 + math.cos(math.pi * u))


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on (recorded in checkpoints and the manifest)."""

    model: str
    epochs: int = 2000
    batch_size: int = 5000
    loss: str = "mse"
    seed: int = 0
    dropout: float = 0.0
    n_train: int | None = None
    time_budget_min: float | None = None
    patience: int = 200
    clip_grad_norm: float | None = None
    schedule: Schedule = field(default_factory=Schedule)
    hyperparameters: dict = field(default_factory=dict)
    preset: str = "paper"


PRESETS: dict[str, dict] = {
    # the paper's settings: batch 5000, squared-error loss, cyclic schedule
    "paper": {"batch_size": 5000, "loss": "mse", "schedule": Schedule()},
    # ours: smaller batches, the reported metric as the loss, one long cosine cycle
    "tuned": {"batch_size": 500, "loss": "relative_l2", "clip_grad_norm": 1.0,
              "schedule": Schedule(initial=1e-4, peak=2e-3, end=1e-6, warmup=0.05, cycles=1, gamma=1.0)},
}


def make_config(model: str, preset: str = "tuned", **overrides) -> TrainConfig:
    base = dict(PRESETS[preset])
    base.update({k: v for k, v in overrides.items() if v is not None})
    if preset == "tuned":  # physics-informed inputs and the linearised reference robot unless overridden
        base["hyperparameters"] = {"inputs": "physics", "reference": "linearized", **base.get("hyperparameters", {})}
    return TrainConfig(model=model, preset=preset, **base)


def relative_l2(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-design relative l2 error over all points and tendons (paper eq. l2Error), ``(B,)``."""
    dims = tuple(range(1, truth.ndim))
    return torch.linalg.vector_norm(pred - truth, dim=dims) / torch.linalg.vector_norm(truth, dim=dims)


def loss_fn(pred: torch.Tensor, truth: torch.Tensor, kind: str) -> torch.Tensor:
    """Training loss on tendon positions ``(B, n, N_t, 3)``."""
    sq = (pred - truth).square().sum(dim=(2, 3))  # (B, n): sum over tendons and coordinates
    if kind == "mse":
        return sq.mean()
    if kind == "relative":
        return (sq.sum(1) / truth.square().sum(dim=(1, 2, 3))).mean()
    if kind == "relative_l2":  # the reported metric itself: mean per-design relative l2
        return (sq.sum(1) / truth.square().sum(dim=(1, 2, 3))).sqrt().mean()
    raise ValueError(f"unknown loss {kind!r}")


def _load_split(data: str | Path, split: str, n: int | None, device
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(features (B, 15), tendons (B, n, 4, 3), loads (B, 10))`` of a split; loads are zeros for a
    dataset made without loads."""
    arrays = dataset.load(data, split)
    feats, tendons, loads = arrays["features"], arrays["tendons"], dataset.load_matrix(arrays)
    if n is not None:
        feats, tendons, loads = feats[:n], tendons[:n], loads[:n]
    return tuple(torch.as_tensor(x, dtype=torch.float32, device=device) for x in (feats, tendons, loads))


def _reference(model, features: torch.Tensor, fractions: torch.Tensor, loads: torch.Tensor, chunk: int = 4096):
    """The model's reference robot for every design (a fixed function of the design and its loads:
    computed once), batch last (:class:`~training.operators.kinematics.ReferenceRobot`), or ``None``
    for the undeformed robot."""
    if model.config.reference == "undeformed":
        return None
    points = getattr(model, "grid", fractions)  # FNOs answer on their own grid
    with torch.no_grad():
        parts = [model.reference(features[i:i + chunk], points, loads[i:i + chunk])
                 for i in range(0, features.shape[0], chunk)]
    return type(parts[0])(*(torch.cat(field, dim=-1) for field in zip(*parts, strict=True)))


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _config_dict(cfg: TrainConfig) -> dict:
    d = asdict(cfg)
    d.pop("time_budget_min")  # a budget may change between resumed runs
    return d


def train(cfg: TrainConfig, data: str | Path, out: str | Path, *, progress: bool = True,
          monitor_designs: int = 2000, stop_at: float | None = None) -> dict:
    """Train (or resume) one model; writes ``out``/checkpoint.pt, model.pt and metrics.jsonl.

    ``stop_at`` (a ``time.time()`` instant) interrupts a run between epochs: the checkpoint is saved,
    no model.pt is written, and the summary's ``stop`` is ``'interrupted'``; calling ``train`` again
    resumes it.  Each epoch reseeds torch's generator from ``(seed, epoch)``, so shuffling and dropout
    masks, and hence the weights, do not depend on where a run was interrupted.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(cfg.seed)
    if device.type == "cpu":
        torch.use_deterministic_algorithms(True)
    hyper = dict(cfg.hyperparameters)
    if cfg.dropout:
        hyper["dropout"] = cfg.dropout
    model = build_model(cfg.model, hyper).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.schedule.initial)
    x_train, y_train, l_train = _load_split(data, "train", cfg.n_train, device)
    x_mon, y_mon, l_mon = _load_split(data, "test", monitor_designs, device)
    fractions = torch.linspace(0.0, 1.0, y_train.shape[1], device=device)
    ref_train, ref_mon = _reference(model, x_train, fractions, l_train), _reference(model, x_mon, fractions, l_mon)

    ckpt_path = out / "checkpoint.pt"
    start_epoch, elapsed, best, stale = 0, 0.0, float("inf"), 0
    if ckpt_path.exists():
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
        if ckpt["config"] != _config_dict(cfg):
            raise ValueError(f"{ckpt_path} was written with another configuration; use another --out")
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        start_epoch, elapsed, best, stale = ckpt["epoch"], ckpt["elapsed"], ckpt["best"], ckpt["stale"]

    n = x_train.shape[0]
    budget = None if cfg.time_budget_min is None else 60.0 * cfg.time_budget_min
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.epochs, initial=start_epoch, unit="epoch", desc=cfg.model)
    log = open(out / "metrics.jsonl", "a")
    last_save = time.perf_counter()
    epoch = start_epoch
    stop_reason = "epochs"
    while epoch < cfg.epochs:
        t0 = time.perf_counter()
        progress_frac = epoch / cfg.epochs if budget is None else max(epoch / cfg.epochs, elapsed / budget)
        lr = cfg.schedule(progress_frac)
        for group in opt.param_groups:
            group["lr"] = lr
        model.train()
        torch.manual_seed(cfg.seed * 1_000_003 + epoch)  # dropout masks: reproducible across resumes
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
        perm = torch.randperm(n, generator=gen).to(device)
        total, count = 0.0, 0
        for i in range(0, n, cfg.batch_size):
            idx = perm[i:i + cfg.batch_size]
            ref = None if ref_train is None else type(ref_train)(*(x[..., idx] for x in ref_train))
            loss = loss_fn(model.tendons(x_train[idx], fractions, ref, l_train[idx]), y_train[idx], cfg.loss)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.clip_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip_grad_norm)
            opt.step()
            total += loss.item() * idx.numel()
            count += idx.numel()
        epoch += 1
        elapsed += time.perf_counter() - t0
        train_loss = total / count
        record = {"epoch": epoch, "lr": lr, "train_loss": train_loss, "seconds": round(elapsed, 4)}
        if epoch % 10 == 0 or epoch == cfg.epochs:
            model.eval()
            with torch.no_grad():
                record["monitor_rel_l2"] = float(relative_l2(model.tendons(x_mon, fractions, ref_mon, l_mon),
                                                             y_mon).mean())
        log.write(json.dumps(record) + "\n")
        log.flush()
        if bar is not None:
            bar.set_postfix(loss=f"{train_loss:.3e}", lr=f"{lr:.1e}", rel_l2=record.get("monitor_rel_l2", ""))
            bar.update(1)
        if train_loss < best * (1 - 1e-3):
            best, stale = train_loss, 0
        else:
            stale += 1
        interrupted = stop_at is not None and time.time() >= stop_at and epoch < cfg.epochs
        done = (stale >= cfg.patience or (budget is not None and elapsed >= budget) or epoch >= cfg.epochs
                or interrupted)
        if done or time.perf_counter() - last_save > 60:
            _save_atomic({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                          "elapsed": elapsed, "best": best, "stale": stale, "config": _config_dict(cfg)}, ckpt_path)
            last_save = time.perf_counter()
        if interrupted and stale < cfg.patience:
            stop_reason = "interrupted"
            break
        if stale >= cfg.patience:
            stop_reason = "converged"
            break
        if budget is not None and elapsed >= budget:
            stop_reason = "time budget"
            break
    log.close()
    if bar is not None:
        bar.close()
    summary = {"model": cfg.model, "epochs": epoch, "train_seconds": round(elapsed, 1), "stop": stop_reason,
               "parameters": count_parameters(model), "n_train": n, "device": device.type,
               "final_train_loss": train_loss if epoch > start_epoch else None}
    if stop_reason == "interrupted":
        return summary
    torch.save({"format_version": CHECKPOINT_FORMAT_VERSION, "name": cfg.model,
                "hyperparameters": asdict(model.config), "config": _config_dict(cfg),
                "state_dict": {k: v.cpu() for k, v in model.state_dict().items()}, "summary": summary},
               out / "model.pt")
    return summary


def load_trained(path: str | Path):
    """Rebuild a trained model from ``model.pt``; returns ``(model, record)``."""
    record = torch.load(Path(path), map_location="cpu", weights_only=False)
    if record.get("format_version", CHECKPOINT_FORMAT_VERSION) != CHECKPOINT_FORMAT_VERSION:
        raise ValueError(f"{path}: checkpoint format {record['format_version']} is not the supported "
                         f"{CHECKPOINT_FORMAT_VERSION}")
    model = build_model(record["name"], record["hyperparameters"])
    model.load_state_dict(record["state_dict"])
    model.eval()
    return model, record


__all__ = ["PRESETS", "Schedule", "TrainConfig", "load_trained", "make_config", "train"]
