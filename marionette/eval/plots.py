"""The report's plots (PNG, matplotlib): the ablation, the per-class ratios, compliance, drift, per-chunk FVD."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from marionette.io import write_bytes


def _save(fig: Any, path: Path) -> None:

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    write_bytes(path, buf.getvalue())


def plot_all(report: dict, sheet: dict | None, out: Path) -> dict[str, str]:
    """The report's PNG plots in ``out`` (matplotlib's Agg canvas, no global backend): name → file name."""
    from matplotlib.figure import Figure

    files = {}
    if sheet is not None:
        rows = sheet["rows"]
        fig = Figure(figsize=(2.4 * len(sheet["frames"]), 1.6 * len(rows)))
        for i, (label, frames) in enumerate(rows.items()):
            for j, t in enumerate(sheet["frames"]):
                ax = fig.add_subplot(len(rows), len(sheet["frames"]), i * len(sheet["frames"]) + j + 1)
                ax.imshow(frames[j], interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if j == 0:
                    ax.set_ylabel(label, fontsize=7)
                if i == 0:
                    ax.set_title(f"frame {t}", fontsize=7)
        _save(fig, out / "contact_sheet.png")
        files["contact_sheet"] = "contact_sheet.png"

    ab = report["ablation"]["conditions"]
    if ab:
        files["ablation"] = _plot_ablation(ab, out)
    files["class_ratios"] = _plot_ratios(report["probe"], out)
    files["compliance"] = _plot_compliance(report["probe"], out)
    lh = report["long_horizon"]
    if lh["drift_m"]:
        files["drift"] = _plot_drift(lh["drift_m"], lh["fps"], f"mean of {len(report['ablation']['windows'])} long rollouts", out)
    else:  # no long rollouts: the probe windows' Free rollouts
        free = {k: np.mean(np.asarray(v, np.float64), axis=0) for k, v in report["state_layer"]["drift"].items()}
        files["drift"] = _plot_drift(free, report["fps"], f"Free, mean of {len(report['windows'])} probe windows", out)
    v = report["video"]
    series = [(k, r["per_chunk"]) for k, r in v.get("table1", {}).items() if r.get("per_chunk")] if v.get("run") else []
    if series:
        files["fvd_per_chunk"] = _plot_per_chunk(series, v["table1"][series[0][0]]["metric"], out)
    return files


def _plot_ablation(ab: list[dict], out: Path) -> str:
    """Table 3's state columns as bars, the recorded state as a dashed line."""
    from matplotlib.figure import Figure

    rec, conds = ab[0], ab[1:]
    fig = Figure(figsize=(12, 3.2))
    for k, (key, label) in enumerate((("cfr", "CFR"), ("mmp_m", "MMP (m)"), ("skate_mps", "Skate (m/s)"), ("sep_m", "Sep (m)"))):
        ax = fig.add_subplot(1, 4, k + 1)
        vals = [np.nan if c[key] is None else c[key] for c in conds]
        ax.bar(range(len(conds)), np.nan_to_num(vals), color="tab:blue")
        for i, v in enumerate(vals):
            if not np.isfinite(v):
                ax.text(i, 0, "n/a", ha="center", va="bottom")
        if rec[key] is not None and np.isfinite(rec[key]):
            ax.axhline(rec[key], color="k", ls="--", label="recorded")
            ax.legend(fontsize=7)
        ax.set_xticks(range(len(conds)), [c["condition"] for c in conds], rotation=20, fontsize=7)
        ax.set_title(label + " at the final frame")
    _save(fig, out / "ablation.png")
    return "ablation.png"


def _plot_ratios(probe: dict, out: Path) -> str:
    """Per-class Shuf/GT and run-shuffle/GT ratios of per-frame RA-MPJPE."""
    from matplotlib.figure import Figure

    ratios = probe["class_ratios"]
    fig = Figure(figsize=(6, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(ratios))
    for j, (key, label) in enumerate((("force_shuf/force_gt", "Shuf/GT"), ("force_shuf_runs/force_gt", "run-shuffle/GT"))):
        ax.bar(x + (j - 0.5) * 0.35, [np.nan_to_num(ratios[c][key] or 0.0) for c in ratios], width=0.35, label=label)
    ax.axhline(1.0, color="k", ls="--", lw=0.8)
    ax.set_xticks(x, [f"{c} ({ratios[c]['frames']})" for c in ratios])
    ax.set_ylabel("RA-MPJPE ratio")
    ax.set_title(f"per-class Shuf/GT ({probe['entity']})")
    ax.legend(fontsize=7)
    _save(fig, out / "class_ratios.png")
    return "class_ratios.png"


def _plot_compliance(probe: dict, out: Path) -> str:
    """Per-class compliance of Free, Force-GT and the recorded motion."""
    from matplotlib.figure import Figure

    comp = probe["compliance"]
    fig = Figure(figsize=(6, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(comp))
    for j, (src, label) in enumerate((("free", "Free"), ("force_gt", "Force-GT"), ("recorded", "recorded"))):
        ax.bar(x + (j - 1) * 0.27, [comp[c][src] for c in comp], width=0.27, label=label)
    ax.set_xticks(x, [f"{c} ({comp[c]['runs']})" for c in comp])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("compliant share of runs")
    ax.set_title(f"per-class compliance ({probe['entity']})")
    ax.legend(fontsize=7)
    _save(fig, out / "compliance.png")
    return "compliance.png"


def _plot_drift(drift: dict, fps: float, what: str, out: Path) -> str:
    """Root divergence against horizon, per entity."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    for name, d in drift.items():
        ax.plot((np.arange(len(d)) + 1) / fps, d, lw=2, label=name)
    ax.set_xlabel("horizon (s)")
    ax.set_ylabel("root divergence (m)")
    ax.set_title(f"root divergence, {what}")
    ax.legend(fontsize=7)
    _save(fig, out / "drift.png")
    return "drift.png"


def _plot_per_chunk(series: list, metric: str, out: Path) -> str:
    """FVD per chunk index of Table 1's columns, with their intervals."""
    from matplotlib.figure import Figure

    if series:
        fig = Figure(figsize=(6, 3.2))
        ax = fig.add_subplot(1, 1, 1)
        for j, (label, ch) in enumerate(series):
            x = np.array([r["chunk"] for r in ch]) + 0.08 * (j - (len(series) - 1) / 2)  # side by side, not on top
            ax.errorbar(
                x,
                [r["value"] for r in ch],
                yerr=[[r["value"] - r["low"] for r in ch], [r["high"] - r["value"] for r in ch]],
                marker="o",
                capsize=3,
                label=label,
            )
        ax.set_xlabel("chunk index of the rollout")
        ax.set_ylabel(metric)
        ax.set_title("per-chunk " + metric + ", 95 % bootstrap intervals")
        ax.legend(fontsize=7)
        _save(fig, out / "fvd_per_chunk.png")
    return "fvd_per_chunk.png"
