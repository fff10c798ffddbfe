"""PNG figures of the studies (matplotlib, Agg), drawn from their JSON-lines records only.

One function per study, registered in ``PLOTS``; each takes the records of ``docs/study/NAME.jsonl``
and returns a figure with one panel per preset where the study has presets.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

MODEL_ORDER = ("deeponet", "deeponet_pose", "fno", "fno_pose")
PRESET_ORDER = ("paper", "tuned")
_MARKERS = {"deeponet": "o", "deeponet_pose": "s", "fno": "^", "fno_pose": "D"}


def _figure(ncols: int, width: float = 5.0):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(width * ncols, 4.0), squeeze=False, constrained_layout=True)
    return fig, list(axes[0])


def _by_preset(records: list[dict]) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        groups[r["preset"]].append(r)
    return {p: groups[p] for p in PRESET_ORDER if p in groups}


def _mean_std_lines(ax, records: list[dict], x_key: str) -> None:
    """Mean +- std over seeds of the held-out mean relative l2, one line per model."""
    for model in MODEL_ORDER:
        points: dict[float, list[float]] = defaultdict(list)
        for r in records:
            if r["model"] == model:
                points[r[x_key]].append(r["test"]["mean"])
        if not points:
            continue
        xs = sorted(points)
        mean = np.array([np.mean(points[x]) for x in xs])
        std = np.array([np.std(points[x]) for x in xs])
        seeds = [len(points[x]) for x in xs]
        ax.errorbar(xs, mean, yerr=std, marker=_MARKERS[model], capsize=3,
                    label=f"{model} (seeds: {min(seeds)}-{max(seeds)})")


def _per_preset_lines(records: list[dict], x_key: str, *, xscale: str, xlabel: str, title: str):
    """One panel per preset: mean +- std over seeds of the held-out error against ``x_key``."""
    groups = _by_preset(records)
    fig, axes = _figure(len(groups))
    for ax, (preset, recs) in zip(axes, groups.items(), strict=True):
        _mean_std_lines(ax, recs, x_key)
        n = max(r["n_train"] for r in recs)
        ax.set(xscale=xscale, yscale="log", xlabel=xlabel, ylabel="held-out mean relative l2 (mean +- std, seeds)",
               title=title.format(preset=preset, n=n))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    return fig


def plot_n_sweep(records: list[dict]):
    return _per_preset_lines(records, "n_train", xscale="log", xlabel="training designs N",
                             title="preset {preset}: error against N")


def plot_dropout(records: list[dict]):
    return _per_preset_lines(records, "dropout", xscale="linear", xlabel="dropout probability q",
                             title="preset {preset}: dropout at N = {n:,}")


def plot_seeds(records: list[dict]):
    groups = _by_preset(records)
    fig, axes = _figure(len(groups))
    for ax, (preset, recs) in zip(axes, groups.items(), strict=True):
        for k, model in enumerate(MODEL_ORDER):
            errs = [r["test"]["mean"] for r in recs if r["model"] == model]
            if errs:
                ax.scatter([k] * len(errs), errs, marker=_MARKERS[model], label=model)
                ax.hlines(np.mean(errs), k - 0.25, k + 0.25, color="k")
        n = max(r["n_train"] for r in recs)
        ax.set(yscale="log", xticks=range(len(MODEL_ORDER)), xticklabels=MODEL_ORDER,
               ylabel="held-out mean relative l2", title=f"preset {preset}: seeds at N = {n:,} (bar: mean)")
        ax.grid(True, which="both", alpha=0.3)
    return fig


def plot_ood(records: list[dict]):
    protocols = [p for p in ("paper", "widened") if any(r["protocol"] == p for r in records)]
    fig, axes = _figure(len(protocols), width=6.0)
    for ax, protocol in zip(axes, protocols, strict=True):
        recs = [r for r in records if r["protocol"] == protocol]
        bins = list(dict.fromkeys(r["bin"] for r in recs))
        series: dict[str, dict[str, float]] = defaultdict(dict)
        for r in recs:
            label = r["model"] if r["preset"] == "-" else f"{r['model']} ({r['preset']})"
            series[label][r["bin"]] = r["error"]["mean"]
        for label, row in series.items():
            style = "--" if "(" not in label else ("-" if "tuned" in label else ":")
            ax.plot(range(len(bins)), [row.get(b, np.nan) for b in bins], style, marker="o", label=label)
        ax.set(yscale="log", xticks=range(len(bins)), xticklabels=bins, ylabel="mean relative l2",
               xlabel="p" + (" of the upper bound" if protocol == "paper" else " of the range width, both sides"),
               title=f"OOD, {protocol} protocol")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    return fig


def _hardware(record: dict) -> str:
    """Where a timing record was measured: the GPU (``training.gpu_schedule``) or this CPU."""
    return record["machine"].get("gpu") or "CPU"


def plot_timing(records: list[dict]):
    """Training seconds per epoch, one panel per hardware (CPU: one thread; GPU records come from
    ``gpu.jsonl``), and inference against the batch size beside the paper's RTX 4090 figures."""
    train = [r for r in records if r["kind"] == "training"]
    hardware = list(dict.fromkeys(_hardware(r) for r in train))
    fig, axes = _figure(len(hardware) + 1, width=5.5)
    for ax, hw in zip(axes, hardware, strict=False):
        for preset in PRESET_ORDER:
            for model in MODEL_ORDER:
                rs = sorted((r for r in train if (r["preset"], r["model"], _hardware(r)) == (preset, model, hw)),
                            key=lambda r: r["n"])
                if rs:
                    ax.plot([r["n"] for r in rs], [r["seconds_per_epoch"] for r in rs],
                            "-" if preset == "tuned" else ":", marker=_MARKERS[model], label=f"{model} ({preset})")
        ax.set(xscale="log", yscale="log", xlabel="training designs N", ylabel="seconds per epoch",
               title=f"training on {hw}" + (" (1 thread)" if hw == "CPU" else ""))
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    ax = axes[-1]
    infer = [r for r in records if r["kind"] == "inference"]
    for model in MODEL_ORDER:
        color = None
        for hw in dict.fromkeys(_hardware(r) for r in infer):
            rs = sorted((r for r in infer if r["model"] == model and _hardware(r) == hw), key=lambda r: r["n"])
            if rs:
                line = ax.plot([r["n"] for r in rs], [r["seconds"] for r in rs], "-" if hw == "CPU" else "-.",
                               marker=_MARKERS[model], color=color, label=f"{model} ({rs[0]['preset']}, {hw})")
                color = line[0].get_color()
        paper = sorted({(r["n"], r["paper_seconds"]) for r in infer
                        if r["model"] == model and r["paper_seconds"] is not None})
        if paper:
            ax.plot(*zip(*paper, strict=True), "--", marker=_MARKERS[model], color=color, alpha=0.5,
                    label=f"{model} (paper, RTX 4090)")
    ax.set(xscale="log", yscale="log", xlabel="designs per call", ylabel="seconds", title="inference (42 points)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=5, ncol=2)
    return fig


def plot_worst(records: list[dict]):
    """Error against the bending angle: one row per preset (shipped, paper, tuned), one column per model."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    rows = [p for p in ("shipped", *PRESET_ORDER) if any(r["preset"] == p for r in records)]
    fig, axes = plt.subplots(len(rows), len(MODEL_ORDER), figsize=(3.4 * len(MODEL_ORDER), 3.0 * len(rows)),
                             squeeze=False, constrained_layout=True, sharex=True)
    for r in records:
        ax = axes[rows.index(r["preset"])][MODEL_ORDER.index(r["model"])]
        curve = [b for b in r["error_vs_bending_angle"] if b["median_error"] is not None]
        ax.plot([np.sqrt(b["theta_low"] * b["theta_high"]) for b in curve], [b["median_error"] for b in curve],
                "-o", ms=3, label="median per bin")
        ax.scatter([w["bending_angle"] for w in r["worst"]], [w["error"] for w in r["worst"]], color="C3",
                   marker="x", label=f"{len(r['worst'])} worst")
        ax.set(xscale="log", yscale="log", title=f"{r['model']} ({r['preset']})")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("bending angle tau rho L / (E I), rad")
    for row in axes:
        row[0].set_ylabel("relative l2")
    axes[0][0].legend(fontsize=7)
    return fig


PLOTS: dict[str, Callable[[list[dict]], object]] = {
    "n-sweep": plot_n_sweep, "dropout": plot_dropout, "seeds": plot_seeds,
    "ood": plot_ood, "timing": plot_timing, "worst": plot_worst,
}


def plot(name: str, records: list[dict], path: Path) -> Path | None:
    """Draw study ``name`` from its records into ``path`` (PNG); ``None`` when there is nothing yet."""
    if not records:
        return None
    from matplotlib import pyplot as plt

    fig = PLOTS[name](records)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, metadata={"Software": None})  # no version string: re-runs give the same file
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------
# Markdown tables of the same records (docs/report.md quotes them)


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3g}"


def _mean_std_table(records: list[dict], x_key: str, x_label: str) -> str:
    """One row per preset and model, one column per ``x_key`` value: the held-out mean relative l2
    as mean +- std over seeds (number of seeds), and the 99th percentile at the largest x."""
    xs = sorted({r[x_key] for r in records})
    groups: dict[tuple, dict] = defaultdict(lambda: defaultdict(list))
    for r in records:
        groups[(r["preset"], r["model"])][r[x_key]].append(r)
    label = (lambda x: f"{x:,}") if all(isinstance(x, int) for x in xs) else (lambda x: f"{x:g}")
    rows = ["| preset | model | " + " | ".join(f"{x_label} = {label(x)}" for x in xs) + f" | p99 at {label(xs[-1])} |",
            "|---|---|" + "---|" * (len(xs) + 1)]
    for (preset, model), by_x in sorted(groups.items(), key=lambda kv: (PRESET_ORDER.index(kv[0][0]),
                                                                        MODEL_ORDER.index(kv[0][1]))):
        cells = []
        for x in xs:
            rs = by_x.get(x, [])
            means = np.array([r["test"]["mean"] for r in rs])
            spread = f" +- {means.std():.2g}" if len(rs) > 1 else ""
            cells.append(f"{means.mean():.3g}{spread} ({len(rs)})" if rs else "-")
        last = by_x.get(xs[-1], [])
        p99 = f"{np.mean([r['test']['p99'] for r in last]):.3g}" if last else "-"
        rows.append(f"| {preset} | {model} | " + " | ".join(cells) + f" | {p99} |")
    return "\n".join(rows)


def table(name: str, records: list[dict]) -> str:
    """A Markdown summary of study ``name``'s records."""
    if not records:
        return "(no records yet)"
    if name == "n-sweep":
        return _mean_std_table(records, "n_train", "N")
    if name == "dropout":
        return _mean_std_table(records, "dropout", "q")
    if name == "seeds":
        return _mean_std_table(records, "n_train", "N")
    if name == "ood":
        lines = []
        for protocol in ("paper", "widened"):
            recs = [r for r in records if r["protocol"] == protocol]
            if not recs:
                continue
            bins = list(dict.fromkeys(r["bin"] for r in recs))
            labels = list(dict.fromkeys(r["model"] if r["preset"] == "-" else f"{r['model']} ({r['preset']})"
                                        for r in recs))
            cell = {(r["model"] if r["preset"] == "-" else f"{r['model']} ({r['preset']})", r["bin"]): r
                    for r in recs}
            lines += [f"{protocol} protocol, mean relative l2 (designs solved per bin: "
                      f"{', '.join(str(cell[(labels[0], b)]['designs']) for b in bins)}):", "",
                      "| model | " + " | ".join(bins) + " |", "|---|" + "---:|" * len(bins)]
            lines += [f"| {label} | " + " | ".join(_fmt(cell[(label, b)]["error"]["mean"]) if (label, b) in cell
                                                   else "-" for b in bins) + " |" for label in labels]
            lines.append("")
        return "\n".join(lines)
    if name == "worst":
        lines = ["| preset | model | mean | max | 20 worst: median bending angle (all) | mean abs pitch "
                 "(all) rad/m | slenderness L/r (all) |", "|---|---|---:|---:|---|---|---|"]
        for r in records:
            c = r["common"]
            lines.append(f"| {r['preset']} | {r['model']} | {r['error']['mean']:.3g} | {r['error']['max']:.3g} "
                         f"| {c['bending_angle']['worst_median']:.3g} ({c['bending_angle']['all_median']:.3g}) "
                         f"| {c['mean_abs_pitch']['worst_median']:.3g} ({c['mean_abs_pitch']['all_median']:.3g}) "
                         f"| {c['slenderness']['worst_median']:.3g} ({c['slenderness']['all_median']:.3g}) |")
        return "\n".join(lines)
    if name == "timing":
        lines = ["Training: seconds per epoch (CPU: one thread), that times the paper's epoch count (20,000 "
                 "DeepONet, 1,500 FNO), and the paper's total training time (RTX 4090).", "",
                 "| hardware | preset | model | N | s / epoch | x paper's epochs (s) | paper total (s) |",
                 "|---|---|---|---:|---:|---:|---:|"]
        lines += [f"| {_hardware(r)} | {r['preset']} | {r['model']} | {r['n']:,} | {r['seconds_per_epoch']:.3g} "
                  f"| {r['paper_schedule_seconds']:.3g} | {_fmt(r.get('paper_seconds'))} |"
                  for r in records if r["kind"] == "training"]
        lines += ["", "Inference (CPU: the shipped models in onnxruntime, 2 threads; GPU: torch, the paper preset "
                  "trained there; best of the repeats) beside the paper's:", "",
                  "| hardware | model | designs | ours (s) | paper (s, RTX 4090) |", "|---|---|---:|---:|---:|"]
        lines += [f"| {_hardware(r)} | {r['model']} | {r['n']:,} | {r['seconds']:.3g} "
                  f"| {_fmt(r.get('paper_seconds'))} |" for r in records if r["kind"] == "inference"]
        return "\n".join(lines)
    raise ValueError(f"unknown study {name!r}")
