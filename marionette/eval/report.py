"""The evaluation report: run the protocol on a checkpoint and write a directory of tables and plots.

``evaluate`` runs, on the same held-out windows (``protocol.select_windows``), the state-layer metrics of
the Free rollouts (rules "auto") beside the recorded rows, the controllability probe, the rule ablation
and, with an observation model, proxy-FVD; then writes ``<out>/report.md``, ``report.json`` and PNG
plots. The directory is built beside ``out`` and renamed into place, so a reader never sees half a
report; an existing ``out`` is replaced only if it holds a previous report (or nothing).

Observation layer, two rows of proxy-FVD (``fvd.ProxyExtractor``, never called FVD), each over the whole
clips and per model chunk with clip-level bootstrap intervals:

- recorded pose (``observation_fvd``): the observation model paints each held-out video chunk of the
  windows' segments from its *recorded* pose-control video and first frame (relayed over the chunk) — the
  observation layer alone;
- rollouts (``rollout_fvd``): per window, the Free rollout is rendered through the bridge at the video's
  rate and the chunk's size, with a camera that starts at the recorded camera of the clip's first frame
  (the first video frame at or after the last seed row, whose state is recorded) and then follows the
  generated characters (``follow_cameras`` seeded at it); the model paints it from the recorded RGB of that
  frame and it is compared with the recorded RGB of the same frames, found in the segment's video chunks by
  their json "frames" [a, b) (consecutive chunks may share a clip). A window whose frames are not all in
  the chunks (or lack RGB or a recorded camera) is skipped and listed with its reason. Every window's clip
  has the same length: as many model chunks as every horizon holds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette.corpus import Corpus
from marionette.eval import fvd
from marionette.eval.protocol import (
    Progress,
    Window,
    controllability_probe,
    model_fps,
    rule_ablation,
    run_windows,
    select_windows,
    state_layer,
)
from marionette.io import write_bytes, write_json

PLOTS = ("ablation", "compliance", "drift", "fvd_per_chunk")


# -- the observation layer ------------------------------------------------------------------------------


def _chunk_frames(frames: int, extractor: Any, length: int) -> int:
    """Frames of the per-chunk pieces: the model's chunk, or for I3D (which needs 9) whole model chunks enough for it."""
    from marionette.eval.i3d import MIN_FRAMES

    if not extractor.is_fvd or frames >= MIN_FRAMES:
        return frames
    k = -(-(MIN_FRAMES - 1) // (frames - 1))  # model chunks spanning ≥ 9 frames
    return min(1 + k * (frames - 1), length)


def _paint_and_score(
    model: Any,
    clips: Sequence[tuple[torch.Tensor, torch.Tensor, int]],
    chunks: int,
    steps: int,
    seed: int,
    resamples: int,
    extractor: Any,
    progress: Progress | None = None,
    phase: str = "painting clips",
) -> dict[str, Any]:
    """Paint each (rgb, pose, seed) clip's first 1 + chunks·(frames − 1) frames from its first RGB frame and score them
    against the recorded RGB: the whole clips and per chunk, with bootstrap intervals (proxy extractor by default;
    ``progress`` told per clip painted)."""
    from marionette.observation.model import generate

    f = model.config.frames
    T = 1 + chunks * (f - 1)
    real, gen = [], []
    with torch.inference_mode():
        for rgb, pose, k in clips:
            real.append(rgb[:T])
            gen.append(generate(model, pose[:T], rgb[0], chunks=chunks, steps=steps, seed=k).clamp(-1, 1))
            if progress is not None:
                progress(phase, len(gen), len(clips))
    real_v, gen_v = torch.stack(real), torch.stack(gen)
    ex = extractor or fvd.ProxyExtractor()
    return {
        "frames": T,
        "whole": fvd.fvd_report(real_v, gen_v, ex, resamples=resamples, seed=seed),
        "per_chunk": fvd.fvd_per_chunk(real_v, gen_v, ex, frames=_chunk_frames(f, ex, T), resamples=resamples, seed=seed),
    }


def observation_fvd(
    model: Any,
    clips: Sequence[tuple[torch.Tensor, torch.Tensor]],
    steps: int = 20,
    seed: int = 0,
    resamples: int = 200,
    max_frames: int | None = None,
    extractor: Any = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """FVD (I3D ``extractor``) or proxy-FVD (default) of RGB the observation ``model`` paints from recorded pose clips against the recorded RGB.

    ``clips``: (rgb (T, 3, H, W) in [−1, 1], pose (T, 3, H, W) in [0, 1]) at the model's size, T ≥ the
    model's frames; each is relayed over as many model chunks as fit (1 + n·(frames − 1) frames, at most
    ``max_frames``). ``progress`` is told per clip painted."""
    if len(clips) < 2:
        raise ValueError(f"proxy-FVD needs at least 2 clips, got {len(clips)}")
    f = model.config.frames
    n = min((len(rgb) - 1) // (f - 1) for rgb, _ in clips)
    if max_frames is not None:
        n = min(n, (int(max_frames) - 1) // (f - 1))
    if n < 1:
        raise ValueError(f"clips of {min(len(r) for r, _ in clips)} frames are shorter than the model's {f}")
    scored = _paint_and_score(
        model,
        [(rgb, pose, seed + k) for k, (rgb, pose) in enumerate(clips)],
        n,
        steps,
        seed,
        resamples,
        extractor,
        progress,
        "proxy-FVD: painting recorded-pose chunks",
    )
    return {
        "run": True,
        "clips": len(clips),
        "steps": steps,
        **scored,
        "what": "observation model on recorded pose-control chunks vs recorded RGB",
    }


def _corpus_clips(c: Corpus, segments: set[str], frames: int, size: tuple[int, int], limit: int) -> tuple[list, dict]:
    """Up to ``limit`` whole video chunks (rgb, pose) of ``segments`` at the model's size, and why others were skipped."""
    from marionette.observation.data import ClipSource

    src = ClipSource(c, "test", frames, size)
    src.segments = set(segments)
    out = []
    for clip in src.chunks():
        out.append((clip.rgb, clip.pose))
        if len(out) >= limit:
            break
    return out, dict(src.skipped)


class WindowSkipped(ValueError):
    """A window whose rollout clip cannot be made (its reason is the message); the report lists it."""


@dataclass
class RolloutClip:
    """One window's rollout clip at the observation model's size: ``rgb`` (T, 3, h, w) the recorded frames in
    [−1, 1], ``pose`` (T, 3, h, w) the rollout's pose-control frames in [0, 1], ``cameras`` the bridge camera
    per frame (the chunk's size), ``start`` the recorded camera it starts from, the source frames [a, b) and
    the video chunks they came from."""

    rgb: torch.Tensor
    pose: torch.Tensor
    cameras: Any
    start: Any
    source_frames: tuple[int, int]
    chunks: list[str]


def segment_chunks(c: Corpus, segment: str) -> list[dict[str, Any]]:
    """The video chunks of a segment in frame order: each chunk json's record with "key" and "rgb" (the
    rgb.mp4 bytes, None if the shard lacks it)."""
    from marionette.corpus import video_shards

    vpath = c.video_path(c.segment_row(segment)["shard"])
    if not vpath.exists():
        return []
    chunks = video_shards.read_chunks(vpath, segment, kinds=("json", "rgb.mp4"))
    recs = {k: video_shards.chunk_record(m["json"], k, str(vpath)) for k, m in chunks.items() if "json" in m}
    return sorted(({**r, "key": k, "rgb": chunks[k].get("rgb.mp4")} for k, r in recs.items()), key=lambda r: r["frames"][0])


def _horizon_times(table: pa.Table, seed_frames: int, seg_t: np.ndarray) -> tuple[int, int]:
    """(first row, count) of the segment's source rows whose times lie in the rollout's predicted span, from
    the last seed row (recorded state) to the last predicted row."""
    t = table["t"].to_numpy()
    t0, t1 = float(t[seed_frames - 1]), float(t[-1])
    i0 = int(np.searchsorted(seg_t, t0 - 1e-6))
    return i0, int(np.searchsorted(seg_t, t1 + 1e-6)) - i0


def rollout_clip(
    c: Corpus,
    window: Window,
    table: pa.Table,
    frames: int,
    size: tuple[int, int],
    seg_rows: pa.Table,
    chunks: Sequence[dict],
    terrain: Any = None,
) -> RolloutClip:
    """The window's rollout rendered through the bridge and the recorded RGB of the same ``frames`` video frames.

    The clip starts at the first source video frame at or after the last seed row (whose state is the recorded
    one) and runs at the video's rate; the camera is the recorded camera of that frame (the chunk's
    intrinsics), then follows the generated characters (``follow_cameras`` seeded at it). Rendered at the
    chunk's size and reduced to ``size`` like the training clips (``reduce_codes``, area-averaged RGB). Raises
    ``WindowSkipped`` when the frames are not all in the segment's video chunks (or lack RGB, or a camera)."""
    from marionette.bridge.camera import recorded_cameras
    from marionette.corpus import fixed_rows
    from marionette.eval.protocol import rollout_pose_codes
    from marionette.ingest.video import decode_frames
    from marionette.observation.data import check_size, pose_frames, rgb_frames

    seg_t, seg_f = seg_rows["t"].to_numpy(), seg_rows["frame"].to_numpy()
    i0, avail = _horizon_times(table, window.seed_frames, seg_t)
    if avail < frames:
        raise WindowSkipped(f"the horizon holds {avail} video frames, fewer than the clip's {frames}")
    idx = np.arange(i0, i0 + frames)
    src = seg_f[idx]
    if not np.array_equal(src, np.arange(src[0], src[0] + frames)):
        raise WindowSkipped(f"source frames from {src[0]} are not consecutive rows of the segment")
    which = []
    for f in src:
        k = next((i for i, r in enumerate(chunks) if r["frames"][0] <= f < r["frames"][1]), None)
        if k is None:
            spans = [tuple(r["frames"]) for r in chunks]
            raise WindowSkipped(f"source frames [{src[0]}, {src[-1] + 1}) are not all in the segment's video chunks {spans}")
        if chunks[k]["rgb"] is None:
            raise WindowSkipped(f"video chunk {chunks[k]['key']} has no rgb.mp4")
        which.append(k)
    used = sorted(set(which))
    H, W = (int(v) for v in chunks[used[0]]["resize"])
    try:
        factor = check_size((H, W), size, chunks[used[0]]["key"])
    except ValueError as err:
        raise WindowSkipped(str(err)) from err
    rgb = np.empty((frames, H, W, 3), np.uint8)
    for k in used:
        a = chunks[k]["frames"][0]
        mine = [j for j, kk in enumerate(which) if kk == k]
        got = decode_frames(chunks[k]["rgb"], {int(src[j] - a) for j in mine})
        if len(got) != len(mine):
            raise WindowSkipped(f"video chunk {chunks[k]['key']} decodes to fewer frames than its json spans")
        for j in mine:
            rgb[j] = got[int(src[j] - a)]
    first = chunks[which[0]]
    K = np.asarray(first["K"], np.float64)[int(src[0] - first["frames"][0])][None]
    row = seg_rows.slice(int(idx[0]), 1)
    start = recorded_cameras(
        K, fixed_rows(row["camera.pos"], 3), fixed_rows(row["camera.rot"], 4), row["valid"].to_numpy(zero_copy_only=False), W, H
    )
    if not start.valid[0]:
        raise WindowSkipped(f"no valid recorded camera at source frame {src[0]}")
    codes, cams = rollout_pose_codes(c.layout, table, seg_t[idx], start, terrain)
    return RolloutClip(
        rgb_frames(rgb, factor),
        pose_frames(codes, factor),
        cams,
        start,
        (int(src[0]), int(src[-1]) + 1),
        [chunks[k]["key"] for k in used],
    )


def rollout_clips(
    c: Corpus,
    windows: Sequence[Window],
    tables: Sequence[pa.Table],
    model_frames: int,
    size: tuple[int, int],
    progress: Progress | None = None,
) -> tuple[list[tuple[int, RolloutClip]], list[dict[str, Any]], int]:
    """(window index, clip) of every window whose clip can be made, the skipped ones with their reasons, and
    the clip length T = 1 + n·(model_frames − 1) (the most model chunks every window's horizon holds; 0: none);
    ``progress`` told per window."""
    from marionette.eval.protocol import terrain_scene

    rows = {s: c.read_segment(s) for s in {w.segment for w in windows}}
    avail = [_horizon_times(t, w.seed_frames, rows[w.segment]["t"].to_numpy())[1] for w, t in zip(windows, tables)]
    n = (min(avail) - 1) // (model_frames - 1)
    if n < 1:
        return (
            [],
            [
                {
                    "window": k,
                    "segment": w.segment,
                    "start": w.start,
                    "reason": f"the horizon holds {min(avail)} video frames, fewer than one model chunk's {model_frames}",
                }
                for k, w in enumerate(windows)
            ],
            0,
        )
    T = 1 + n * (model_frames - 1)
    chunks = {s: segment_chunks(c, s) for s in rows}
    scenes: dict[str, Any] = {}
    out, skipped = [], []
    for k, (w, table) in enumerate(zip(windows, tables)):
        if w.stage not in scenes:
            scenes[w.stage] = terrain_scene(c, w.segment)
        try:
            out.append((k, rollout_clip(c, w, table, T, size, rows[w.segment], chunks[w.segment], scenes[w.stage])))
        except WindowSkipped as err:
            skipped.append({"window": k, "segment": w.segment, "start": w.start, "reason": str(err)})
        if progress is not None:
            progress("proxy-FVD: rendering rollout clips", k + 1, len(windows))
    return out, skipped, T


def rollout_fvd(
    model: Any,
    c: Corpus,
    windows: Sequence[Window],
    tables: Sequence[pa.Table],
    steps: int = 20,
    seed: int = 0,
    resamples: int = 200,
    max_frames: int | None = None,
    extractor: Any = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Proxy-FVD of the observation ``model`` painting each window's *rollout* (``rollout_clip``: bridge camera
    starting from the recorded view) from the recorded first frame, relayed over model chunks, against the
    recorded RGB of the same video frames: whole clips and per model chunk, with bootstrap intervals (the first
    ``max_frames`` frames of each clip, a whole number of model chunks, when given)."""
    f = model.config.frames
    clips, skipped, T = rollout_clips(c, windows, tables, f, model.config.size, progress)
    base = {
        "what": "observation model on the rollouts' pose-control video (bridge camera from the recorded view) vs recorded RGB",
        "skipped": skipped,
        "steps": steps,
    }
    if len(clips) < 2:
        return {"run": False, "reason": f"{len(clips)} windows with a rollout clip, 2 needed", **base}
    n = (T - 1) // (f - 1) if max_frames is None else min((T - 1) // (f - 1), (int(max_frames) - 1) // (f - 1))
    if n < 1:
        return {"run": False, "reason": f"max_frames {max_frames} is shorter than one model chunk ({f})", **base}
    painted = [(cl.rgb, cl.pose, seed + k) for k, cl in clips]
    scored = _paint_and_score(model, painted, n, steps, seed, resamples, extractor, progress, "proxy-FVD: painting rollouts")
    return {
        "run": True,
        **base,
        "clips": len(clips),
        **scored,
        "windows": [{"window": k, "source_frames": list(cl.source_frames), "chunks": cl.chunks} for k, cl in clips],
    }


# -- writing ---------------------------------------------------------------------------------------------------


def _plain(x: Any) -> Any:
    """JSON-ready: arrays to lists, NaN/inf to None, tuples to lists."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return _plain(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _num(x: float | None, digits: int = 4) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pm(s: dict) -> str:
    return "n/a" if s["mean"] is None or not math.isfinite(s["mean"]) else f"{s['mean']:.4f} ± {s['std']:.4f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def render_markdown(report: dict) -> str:
    """The report's markdown: the state-layer, probe, ablation and observation tables."""
    st, pr, ab, ob = report["state_layer"], report["probe"], report["ablation"], report["observation"]
    ws = report["windows"]
    out = [
        f"# Evaluation of `{report['dynamics']}`",
        "",
        f"Corpus `{report['corpus']}`; {len(ws)} windows of {report['seed_frames']} seed + {report['horizon']} predicted "
        f"frames at {report['fps']:g} fps (split {report['split']!r}, window seed {report['seed']}, temperature "
        f"{report['temperature']:g}).",
        "",
        "## State layer (Free rollouts, rules auto)",
        "",
    ]
    rows = [
        [k.split("/")[0], k.split("/")[1], _pm(v["generated"]), _pm(v["recorded"]), str(v["generated"]["n"])]
        for k, v in st["metrics"].items()
    ]
    out += [_table(["metric", "entity", "generated", "recorded", "windows"], rows), ""]
    out += [f"- {n}" for n in st["notes"]] + [
        "- RA-MPJPE and root drift compare with the recorded rows: 0 on the recorded side by definition.",
        "- body share: follow camera, pose-control frame rendered at "
        f"{report['render_size'][0]}×{report['render_size'][1]}, weapon counted for its owner.",
        "",
    ]
    out += [f"## Controllability probe ({pr['entity']})", ""]
    names = {"free": "Free", "force_gt": "Force-GT", "force_shuf": "Force-Shuf"}
    out += [
        _table(
            ["condition", f"{pr['entity']} RA-MPJPE (m)", "windows"],
            [[names[k], _pm(v), str(v["n"])] for k, v in pr["conditions"].items()],
        ),
        "",
    ]
    out += [
        f"Force-GT < Force-Shuf on {pr['force_gt_beats_shuf']} of {pr['compared']} windows.",
        "",
        "Per-class compliance: share of the recorded action runs (forced run by run in Force-GT) whose motion the "
        "corpus's own class rule puts in the forced class.",
        "",
    ]
    out += [
        _table(
            ["class", "runs", "Free", "Force-GT", "recorded"],
            [
                [c, str(v["runs"]), _num(v["free"], 2), _num(v["force_gt"], 2), _num(v["recorded"], 2)]
                for c, v in pr["compliance"].items()
            ],
        ),
        "",
    ]
    out += ["## Rule ablation", ""]
    out += [
        _table(
            ["condition", "CFR", "MMP (m)", "Skate (m/s)", "Sep (m)", "note"],
            [
                [r["condition"], _num(r["cfr"], 3), _num(r["mmp_m"]), _num(r["skate_mps"]), _num(r["sep_m"], 2), r["note"]]
                for r in ab["conditions"]
            ],
        ),
        "",
    ]
    out += [
        "CFR, MMP and skate are means over the articulated entities (per entity in report.json); Sep is the "
        "horizontal root separation.",
        "",
        "## Observation layer",
        "",
    ]
    if "rollouts" in ob:
        i3d = ob.get("whole", {}).get("metric") == fvd.FVD_LABEL
        note = (
            "FVD: features of the Inception-I3D weights given (--i3d)."
            if i3d
            else "Proxy-FVD uses a fixed random feature extractor (not I3D): comparable only with itself; it is not FVD."
        )
        out += [note, "", "### Recorded pose-control video (the observation model alone)", ""]
    out += _fvd_section(ob)
    if "rollouts" in ob:
        ro = ob["rollouts"]
        out += ["### Rollouts (dynamics → bridge → observation model)", ""]
        out += _fvd_section(ro)
        if ro.get("skipped"):
            out += ["Windows without a rollout clip:", ""]
            out += [f"- window {r['window']} ({r['segment']}, dynamics frame {r['start']}): {r['reason']}" for r in ro["skipped"]]
            out += [""]
    out += ["## Plots", ""] + [f"![{k}]({v})" for k, v in report["plots"].items()] + [""]
    return "\n".join(out)


def _fvd_section(ob: dict) -> list[str]:
    """The lines of one proxy-FVD result: what it measures, the whole-clip row and one row per chunk."""
    if not ob.get("run"):
        return [f"Not run: {ob['reason']}.", ""]
    w = ob["whole"]
    return [
        f"{ob['what']}: {ob['clips']} clips of {ob['frames']} frames, {ob['steps']} sampling steps.",
        "",
        _table(
            ["clips", "metric", "value", "95 % interval", "extractor"],
            [["whole", w["metric"], _num(w["value"], 3), f"[{_num(w['low'], 3)}, {_num(w['high'], 3)}]", w["extractor"]]]
            + [
                [
                    f"chunk {r['chunk']} (frames {r['start_frame']}–{r['end_frame']})",
                    r["metric"],
                    _num(r["value"], 3),
                    f"[{_num(r['low'], 3)}, {_num(r['high'], 3)}]",
                    r["extractor"],
                ]
                for r in ob["per_chunk"]
            ],
        ),
        "",
    ]


def _save(fig: Any, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    write_bytes(path, buf.getvalue())


def plot_all(report: dict, drift: dict[str, np.ndarray], out: Path) -> dict[str, str]:
    """The report's PNG plots in ``out`` (matplotlib's Agg canvas, no global backend): name → file name."""
    from matplotlib.figure import Figure

    files = {}
    ab = report["ablation"]["conditions"]
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
        ax.set_title(label)
    _save(fig, out / "ablation.png")
    files["ablation"] = "ablation.png"

    comp = report["probe"]["compliance"]
    fig = Figure(figsize=(6, 3.2))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(comp))
    for j, (src, label) in enumerate((("free", "Free"), ("force_gt", "Force-GT"), ("recorded", "recorded"))):
        ax.bar(x + (j - 1) * 0.27, [comp[c][src] for c in comp], width=0.27, label=label)
    ax.set_xticks(x, [f"{c} ({comp[c]['runs']})" for c in comp])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("compliant share of runs")
    ax.set_title(f"per-class compliance ({report['probe']['entity']})")
    ax.legend(fontsize=7)
    _save(fig, out / "compliance.png")
    files["compliance"] = "compliance.png"

    fig = Figure(figsize=(5 * len(drift), 3.2))
    for k, (name, d) in enumerate(drift.items()):
        ax = fig.add_subplot(1, len(drift), k + 1)
        t = (np.arange(d.shape[1]) + 1) / report["fps"]
        for row in d:
            ax.plot(t, row, color="tab:blue", alpha=0.25, lw=0.8)
        ax.plot(t, d.mean(axis=0), color="tab:blue", lw=2.5, label=f"mean of {len(d)}")
        ax.set_xlabel("horizon (s)")
        ax.set_ylabel("root drift (m)")
        ax.set_title(name)
        ax.legend(fontsize=7)
    _save(fig, out / "drift.png")
    files["drift"] = "drift.png"

    ob = report["observation"]
    series = [
        (label, r["per_chunk"])
        for label, r in (("recorded pose", ob), ("rollouts", ob.get("rollouts", {})))
        if r.get("run") and r["per_chunk"]
    ]
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
                label=f"{label} ({len(ch)} chunks)",
            )
        metric = series[0][1][0]["metric"]
        ax.set_xlabel("chunk (model clip) of the video")
        ax.set_ylabel(metric)
        ax.set_title("per-chunk " + metric + ", 95 % bootstrap intervals")
        ax.legend(fontsize=7)
        _save(fig, out / "fvd_per_chunk.png")
        files["fvd_per_chunk"] = "fvd_per_chunk.png"
    return files


def _check_replaceable(out: Path) -> None:
    """Fail unless ``out`` is absent, empty, or a previous report directory."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "report.json").exists())):
        raise FileExistsError(f"{out}: exists and is not a previous report; refusing to replace it")


def _swap_in(tmp: Path, out: Path) -> None:
    """Rename the finished report directory ``tmp`` to ``out``, replacing a previous report there."""
    _check_replaceable(out)
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old / out.name)
        os.replace(tmp, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)


def headline(report: dict) -> dict[str, float | int | None]:
    """The few numbers a dashboard shows: probe means, the Force-GT win count, ablation CFR/MMP, proxy-FVD."""
    pr = report["probe"]
    h: dict[str, Any] = {"windows": len(report["windows"])}
    for k, v in pr["conditions"].items():
        h[f"{pr['entity']}_ra_mpjpe_{k}_m"] = v["mean"]
    h["force_gt_beats_shuf"] = pr["force_gt_beats_shuf"]
    for k, v in report["state_layer"]["metrics"].items():
        if k.startswith("root_drift_final_m/"):
            h[f"{k.split('/')[1]}_root_drift_final_m"] = v["generated"]["mean"]
    for r in report["ablation"]["conditions"]:
        slug = r["condition"].replace("+ ", "").replace(" ", "_")
        h[f"cfr_{slug}"], h[f"mmp_{slug}_m"] = r["cfr"], r["mmp_m"]
    for part, suffix in ((report["observation"], ""), (report["observation"].get("rollouts", {}), "_rollouts")):
        if part.get("run"):  # "fvd" only from the I3D extractor, else "proxy_fvd"
            h[("fvd" if part["whole"]["metric"] == fvd.FVD_LABEL else "proxy_fvd") + suffix] = part["whole"]["value"]
    return _plain(h)


def evaluate(
    dynamics_dir: Path | str,
    corpus: Path | str,
    out_dir: Path | str,
    *,
    observation: Path | str | None = None,
    segments: int = 8,
    seed_frames: int = 64,
    horizon: int = 120,
    seed: int = 0,
    log: Callable[[str], Any] = print,
    temperature: float = 0.0,
    entity: str = "hunter",
    render_size: tuple[int, int] = (72, 128),
    fvd_steps: int = 20,
    fvd_frames: int | None = None,
    i3d: Path | str | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the protocol (module doc) and write the report directory ``out_dir``.

    Returns {"out_dir", "report_md", "report_json", "plots" (name → path), "headline" (name → number),
    "windows" (count)}. ``fvd_steps``: sampling steps of the observation model; ``fvd_frames``: at most this many
    video frames of each proxy-FVD clip (None: whole chunks and whole rollouts); ``i3d``: an Inception-I3D safetensors
    file, for FVD proper instead of the proxy; ``progress(phase, done, total)`` is told the progress of every long loop
    (rollouts, per-window metrics, painting)."""
    c = Corpus(Path(corpus))
    out = Path(out_dir)
    _check_replaceable(out)  # before any compute
    extractor = fvd.extractor_for(Path(i3d)) if i3d is not None else None  # a bad I3D file fails here too
    fps = model_fps(dynamics_dir)
    split = "test" if c.segment_ids("test") else "train"
    windows = select_windows(c, segments, seed_frames, horizon, seed, split=split, fps=fps)
    names = [e.name for e in c.layout.articulated]
    entity = entity if entity in names else names[-1]
    log(f"evaluate: {len(windows)} windows of {seed_frames} + {horizon} frames from split {split!r}")
    free, ran = run_windows(
        dynamics_dir, c, windows, rules="auto", temperature=temperature, seed=seed, progress=progress, phase="Free rollouts"
    )
    log(f"evaluate: Free rollouts done (rules per stage {ran}); state-layer metrics")
    state = state_layer(dynamics_dir, c, windows, free, render_size=render_size, progress=progress)
    log("evaluate: controllability probe")
    probe = controllability_probe(
        dynamics_dir, c, windows, entity=entity, temperature=temperature, seed=seed, free=free, progress=progress
    )
    log("evaluate: rule ablation")
    ablation = rule_ablation(dynamics_dir, c, windows, temperature=temperature, seed=seed, progress=progress)
    if observation is None:
        obs: dict[str, Any] = {"run": False, "reason": "no observation model given (--observation)"}
    else:
        from marionette.observation.train import load_model

        model = load_model(observation)
        clips, skipped = _corpus_clips(c, {w.segment for w in windows}, model.config.frames, model.config.size, max(segments, 2))
        if len(clips) < 2:
            obs = {
                "run": False,
                "reason": f"{len(clips)} usable video chunks in the windows' segments, 2 needed "
                f"(skipped: {dict(list(skipped.items())[:3])})",
            }
        else:
            log(f"evaluate: proxy-FVD over {len(clips)} video chunks")
            obs = observation_fvd(
                model, clips, steps=fvd_steps, seed=seed, max_frames=fvd_frames, extractor=extractor, progress=progress
            )
        log("evaluate: proxy-FVD of the Free rollouts through the bridge")
        obs["rollouts"] = rollout_fvd(
            model, c, windows, free, steps=fvd_steps, seed=seed, max_frames=fvd_frames, extractor=extractor, progress=progress
        )
        obs["observation"] = str(observation)
    report = {
        "dynamics": str(dynamics_dir),
        "corpus": str(c.path),
        "split": split,
        "fps": fps,
        "seed": seed,
        "seed_frames": seed_frames,
        "horizon": horizon,
        "temperature": temperature,
        "render_size": list(render_size),
        "windows": [asdict(w) for w in windows],
        "rules_free": ran,
        "state_layer": state,
        "probe": probe,
        "ablation": ablation,
        "observation": obs,
    }
    report = _plain(report)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes 0700; reports are read by other users and services
    try:
        report["plots"] = plot_all(report, state["drift"], tmp)
        report["headline"] = headline(report)
        write_json(tmp / "report.json", report)
        write_bytes(tmp / "report.md", render_markdown(report).encode())
        _swap_in(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log(f"evaluate: report in {out}")
    return {
        "out_dir": str(out),
        "report_md": str(out / "report.md"),
        "report_json": str(out / "report.json"),
        "plots": {k: str(out / v) for k, v in report["plots"].items()},
        "headline": report["headline"],
        "windows": len(windows),
    }


def load_report(out_dir: Path | str) -> dict[str, Any]:
    """A written report's report.json."""
    return json.loads((Path(out_dir) / "report.json").read_text())
