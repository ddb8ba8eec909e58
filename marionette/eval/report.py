"""The evaluation report: run a protocol on a checkpoint and write a directory of the paper's tables and plots.

``evaluate`` takes a protocol (``config.EvalProtocol``: "paper" or "quick", fields overridable) and runs:

- on ``probe_windows`` held-out windows (``seed_frames`` + ``horizon``): the Free rollouts (rules "auto") and their
  state-layer metrics beside the recorded rows, and **Table 2**, the controllability probe (Free / Force-GT /
  Force-Shuf / run-level shuffle, GT < Shuf counts, per-class Shuf/GT ratios, compliance);
- on ``state_rollouts`` long held-out windows (``state_seconds``): the four driving states (``ablation_rollouts``)
  and **Table 3** at their final frame and the long-horizon curves (``video.long_horizon_curves``); on the first
  ``rollouts`` of them cut to ``rollout_seconds`` of video, with an observation model (and a pixel-AR baseline),
  **Table 1** and Table 3's FVD column (``video.video_tables``); a corpus with no segment long enough for
  ``state_seconds`` gets state rollouts as long as the painted ones (the table says so), one with none long enough
  for those gets the tables "not run" with the reason, the rest of the report still;
- then writes ``<out>/report.md`` (its first lines say which counts are smaller than the paper's), ``report.json``,
  the PNG plots and the contact sheet. The directory is built beside ``out`` and renamed into place, so a reader
  never sees half a report; an existing ``out`` is replaced only if it holds a previous report (or nothing).

Also here: ``rollout_clip`` (a rollout rendered through the bridge with a camera that starts at the recorded camera
of the clip's first frame — the first video frame at or after the last seed row — and then follows the generated
characters, beside the recorded RGB of the same frames, found in the segment's video chunks by their json "frames"
[a, b); ``WindowSkipped`` when they are not all there), and the earlier whole-clip proxy-FVD rows used by the
benchmark: ``observation_fvd`` (recorded pose-control chunks painted by the model) and ``rollout_fvd`` (Free
rollouts painted), each over whole clips and per model chunk with clip-level bootstrap intervals.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette.bridge.rules import RuleParams
from marionette.corpus import Corpus
from marionette.eval import fvd
from marionette.eval.config import EvalProtocol, parse_protocol
from marionette.eval.protocol import (
    Progress,
    Window,
    ablation_rollouts,
    controllability_probe,
    model_fps,
    model_scene,
    rule_ablation,
    run_windows,
    select_windows,
    state_layer,
)
from marionette.eval.video import long_horizon, long_horizon_curves, video_tables
from marionette.io import read_json, write_bytes, write_json

PLOTS = ("contact_sheet", "ablation", "class_ratios", "compliance", "drift", "fvd_per_chunk")


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


STATE_NAMES = {"free": "Free", "force_gt": "Force-GT", "force_shuf": "Force-Shuf", "force_shuf_runs": "run-level shuffle"}


def _fvd_cells(r: dict | None) -> list[str]:
    """value, bias-corrected interval, percentile interval of one Fréchet result (n/a cells when absent)."""
    if not r:
        return ["n/a"] * 3
    return [
        _num(r["value"], 3),
        f"[{_num(r['low'], 3)}, {_num(r['high'], 3)}]",
        f"[{_num(r['raw_low'], 3)}, {_num(r['raw_high'], 3)}]",
    ]


# (model key, baseline key, label, whether higher is better) of a dynamics training summary's held-out figures
_AGAINST = (
    ("action_accuracy", "copy_last_action_accuracy", "next-action accuracy against copy-last", True),
    ("action_accuracy", "most_frequent_action_accuracy", "next-action accuracy against the most frequent action", True),
    ("body_mse", "copy_last_body_mse", "body MSE against copy-last", False),
    ("root_mse", "constant_velocity_root_mse", "root MSE against constant velocity", False),
)


def training_against_baselines(dynamics_dir: Path | str) -> dict[str, Any] | None:
    """The dynamics training directory's held-out figures beside its trivial baselines (``summary.json``'s ``eval``
    and ``baselines``), one row per comparison with whether the model wins; None when the directory has none."""
    path = Path(dynamics_dir) / "summary.json"
    if not Path(dynamics_dir).is_dir() or not path.is_file():
        return None
    summary = read_json(path, max_bytes=1 << 20)
    ev, base = (summary.get(k) if isinstance(summary, dict) else None for k in ("eval", "baselines"))
    if not isinstance(ev, dict) or not isinstance(base, dict):
        return None
    rows = []
    for key, bkey, label, higher in _AGAINST:
        m, b = ev.get(key), base.get(bkey)
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (m, b)):
            raise ValueError(f"{path}: eval.{key} and baselines.{bkey} must be finite numbers, not {m!r} and {b!r}")
        rows.append({"what": label, "model": float(m), "baseline": float(b), "wins": m > b if higher else m < b})
    return {"steps": summary.get("steps"), "windows": ev.get("windows"), "rows": rows}


def _baseline_lines(report: dict) -> list[str]:
    """The report's first lines about the dynamics model against its trivial baselines (held-out, teacher-forced)."""
    tb = report.get("training")
    if not tb:
        return []
    lost = [r for r in tb["rows"] if not r["wins"]]
    head = (
        f"**The dynamics model does not beat every trivial baseline on held-out data** ({len(lost)} of {len(tb['rows'])} "
        "comparisons lost; its budget or its corpus is too small for the vocabulary):"
        if lost
        else "The dynamics model beats every trivial baseline on held-out data:"
    )
    rows = [[r["what"], _num(r["model"]), _num(r["baseline"]), "yes" if r["wins"] else "**no**"] for r in tb["rows"]]
    note = f"From the training run's summary: {tb['steps']} steps, {tb['windows']} held-out windows, one step ahead."
    return [head, "", _table(["comparison", "model", "baseline", "model wins"], rows), "", note, ""]


def _protocol_lines(report: dict) -> list[str]:
    """The report's first lines about its protocol: which counts and lengths are smaller than the paper's."""
    pr = report["protocol"]
    if pr["reduced"]:
        return [
            f"**Protocol `{pr['name']}` is smaller than the paper's**: " + "; ".join(pr["reduced"]) + ". "
            "Its numbers carry wider intervals than the paper's tables (docs/tradeoffs.md, evaluation protocol).",
            "",
        ]
    return [f"Protocol `{pr['name']}`: the paper's counts and lengths.", ""]


def _table1_lines(report: dict) -> list[str]:
    """Table 1: FVD16 and final-chunk FVD of the Marionette column beside the pixel-AR baseline."""
    v, p = report["video"], report["protocol"]
    out = ["## Table 1 — observation layer", ""]
    if not v.get("run"):
        return out + [f"Not run: {v['reason']}.", ""]
    t1 = v["table1"]
    metric = next((r["metric"] for r in t1.values() if r.get("run", True) and "metric" in r), fvd.PROXY_LABEL)
    rows = []
    for key, label in (
        ("marionette", "Marionette (dynamics → bridge → observation, collider on)"),
        ("baseline", "pixel-AR baseline"),
    ):
        r = t1[key]
        if "fvd16" not in r:
            rows.append([label, "n/a", "n/a", "n/a", "n/a", "n/a", "n/a", r.get("reason", "")])
            continue
        rows.append(
            [
                label,
                *_fvd_cells(r["fvd16"]),
                *_fvd_cells(r["final_chunk"]),
                f"{r['rollouts']} rollouts, {r['fvd16']['clips']} clips",
            ]
        )
    out += [
        f"{metric} over {len(v['windows'])} held-out rollouts of {p['rollout_seconds']:g} s ({v['frames']} video frames), "
        f"{p['clips_per_rollout']} clips of {p['clip_frames']} frames per rollout; final chunk = the last {p['final_frames']} "
        f"frames; {p['fvd_steps']} sampling steps; {p['resamples']} clip-bootstrap resamples (95 %).",
        "",
        _table(
            [
                "column",
                f"FVD{p['clip_frames']}",
                "bias-corrected",
                "percentile",
                "final chunk",
                "bias-corrected",
                "percentile",
                "over",
            ],
            rows,
        ),
        "",
    ]
    if metric == fvd.PROXY_LABEL:
        out += [
            "Proxy-FVD uses a fixed random feature extractor (not I3D): comparable only with itself; it is not FVD (--i3d gives FVD).",
            "",
        ]
    out += [f"- window {r['window']} ({r['segment']}, dynamics frame {r['start']}) skipped: {r['reason']}" for r in v["skipped"]]
    return out + [""]


def _table2_lines(report: dict) -> list[str]:
    """Table 2: Free / Force-GT / Force-Shuf / run-level shuffle, the win counts and the per-class Shuf/GT ratios."""
    pr = report["probe"]
    e = pr["entity"]
    out = [f"## Table 2 — Controllability probe ({e})", ""]
    out += [
        _table(
            ["condition", f"{e} RA-MPJPE (m)", "windows"],
            [[STATE_NAMES[k], _pm(v), str(v["n"])] for k, v in pr["conditions"].items()],
        ),
        "",
        f"Force-GT < Force-Shuf on **{pr['force_gt_beats_shuf']} of {pr['compared']}** windows "
        f"(< run-level shuffle on {pr['force_gt_beats_shuf_runs']}). The run-level shuffle permutes whole action runs, "
        "so progress within a run is intact: its gap to Force-GT is the token's effect alone.",
        "",
        f"Per class of the recorded token at each frame: mean per-frame {e} RA-MPJPE (m) over those frames, all windows pooled.",
        "",
    ]
    rows = [
        [
            c,
            str(v["frames"]),
            _num(v["force_gt"]),
            _num(v["force_shuf"]),
            _num(v["force_shuf/force_gt"], 2),
            _num(v["force_shuf_runs/force_gt"], 2),
        ]
        for c, v in pr["class_ratios"].items()
    ]
    out += [_table(["class", "frames", "Force-GT", "Force-Shuf", "Shuf/GT", "run-shuffle/GT"], rows), ""]
    out += [
        "Compliance (secondary): share of the recorded action runs whose motion the corpus's own class rule puts in the forced class.",
        "",
        _table(
            ["class", "runs", "Free", "Force-GT", "recorded"],
            [
                [c, str(v["runs"]), _num(v["free"], 2), _num(v["force_gt"], 2), _num(v["recorded"], 2)]
                for c, v in pr["compliance"].items()
            ],
        ),
        "",
    ]
    return out


def _table3_lines(report: dict) -> list[str]:
    """Table 3: the four driving states at the final frame, with the FVD of each painted by the same observation model."""
    ab, v = report["ablation"], report["video"]
    if not ab.get("run", True):
        return ["## Table 3 — driving states", "", f"Not run: {ab['reason']}.", ""]
    t3 = v.get("table3", {}) if v.get("run") else {}
    rows = []
    for r in ab["conditions"]:
        f = t3.get(r["condition"], {}).get("fvd16")
        rows.append(
            [
                r["condition"],
                _num(r["cfr"], 3),
                _num(r["mmp_m"]),
                _num(r["skate_mps"]),
                _num(r["sep_m"], 2),
                _num(r.get("beyond_cap", float("nan")), 2),
                "n/a" if not f else f"{_num(f['value'], 3)} [{_num(f['low'], 3)}, {_num(f['high'], 3)}]",
                _num(r["on_ground"], 3),
                r["note"],
            ]
        )
    p = report["protocol"]
    segments = len({w["segment"] for w in ab["windows"]})
    seconds = ab.get("seconds", p["rollout_seconds"])
    painted = ""
    if v.get("run") and (len(v["windows"]) < len(ab["windows"]) or seconds > p["rollout_seconds"]):
        painted = f"the first {len(v['windows'])} of them (Table 1's painted rollouts, {p['rollout_seconds']:g} s), "
    return [
        "## Table 3 — driving states",
        "",
        f"{len(ab['windows'])} long rollouts of {seconds:g} s from {segments} held-out segment{'s' * (segments > 1)}; "
        "CFR, MMP, skate and Sep at the **final frame** "
        "(CFR: share of rollouts with a key joint below H − 0.15 m there; means over the articulated entities, per entity in "
        "report.json; Sep horizontal; beyond cap: share of rollouts ending farther apart than max(6 m, their separation at the "
        "seed's last frame), the bound the cap holds; every rollout starts with the pair within 6 m where its segment "
        f"allows). FVD{p['clip_frames']}: {painted}each state painted by the same observation model "
        "(bias-corrected 95 % interval); root on ground: share of frames whose root stands over scanned ground.",
        "",
        *([f"Note: {ab['cut']}.", ""] if ab.get("cut") else []),
        _table(
            [
                "state",
                "CFR",
                "MMP (m)",
                "Skate (m/s)",
                "Sep (m)",
                "beyond cap",
                f"FVD{p['clip_frames']}",
                "root on ground",
                "note",
            ],
            rows,
        ),
        "",
    ]


def _long_lines(report: dict) -> list[str]:
    """The long-horizon figures as tables: root divergence at whole seconds, FVD per chunk index, body share first/last chunk."""
    lh = report["long_horizon"]
    out = ["## Long horizon", ""]
    if not lh.get("run", True):
        return out + [f"Not run: {lh['reason']}.", ""]
    fps = lh["fps"]
    for name, d in lh["drift_m"].items():
        at = [k for k in range(len(d)) if (k + 1) % int(round(fps)) == 0]
        out += [f"Root divergence of the {name} (m, Marionette state against the recorded rows, mean of the rollouts):", ""]
        out += [
            _table(["horizon (s)"] + [f"{(k + 1) / fps:g}" for k in at], [["divergence (m)"] + [_num(d[k], 3) for k in at]]),
            "",
        ]
    v = report["video"]
    if v.get("run"):
        series = [(k, r) for k, r in v["table1"].items() if "per_chunk" in r]
        if series:
            spans = series[0][1]["per_chunk"]
            out += [f"{series[0][1]['metric']} per chunk index ({report['protocol']['final_frames']} frames each):", ""]
            out += [
                _table(
                    ["column"] + [f"chunk {c['chunk']} ({c['frames'][0]}–{c['frames'][1]})" for c in spans],
                    [[k] + [_num(c["value"], 3) for c in r["per_chunk"]] for k, r in series],
                ),
                "",
            ]
    bs = lh["body_share"]
    rows = [[s, n, _num(x["first"], 4), _num(x["last"], 4)] for s, per in bs.items() for n, x in per.items()]
    out += ["Body share of the pose-control frame (follow camera) in the first and the last chunk:", ""]
    return out + [_table(["state", "entity", "first chunk", "last chunk"], rows), ""]


def render_markdown(report: dict) -> str:
    """The report's markdown: the protocol, Tables 1–3, the long-horizon figures, the state layer, the contact sheet."""
    st = report["state_layer"]
    ws = report["windows"]
    out = [f"# Evaluation of `{report['dynamics']}`", ""] + _protocol_lines(report) + _baseline_lines(report)
    out += [
        f"Corpus `{report['corpus']}`; probe windows: {len(ws)} of {report['seed_frames']} seed + {report['horizon']} "
        f"predicted frames at {report['fps']:g} fps (split {report['split']!r}, window seed {report['seed']}, temperature "
        f"{report['temperature']:g}).",
        "",
    ]
    out += _table1_lines(report) + _table2_lines(report) + _table3_lines(report) + _long_lines(report)
    out += ["## State layer (Free rollouts of the probe windows, rules auto)", ""]
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
    if "contact_sheet" in report["plots"]:
        sheet = report["video"]["sheet"]
        out += [
            "## Contact sheet",
            "",
            f"The first long rollout at video frames {sheet['frames']} (source frames from {sheet['source_frames'][0]}): "
            "pose-control frames, painted frames and the recorded RGB, top to bottom.",
            "",
            f"![contact sheet]({report['plots']['contact_sheet']})",
            "",
        ]
    out += ["## Plots", ""] + [f"![{k}]({v})" for k, v in report["plots"].items() if k != "contact_sheet"] + [""]
    return "\n".join(out)


def _save(fig: Any, path: Path) -> None:
    import io

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
    """The few numbers a dashboard shows: probe means, the GT < Shuf counts, per-class Shuf/GT, Table 1 and Table 3."""
    pr = report["probe"]
    h: dict[str, Any] = {"windows": len(report["windows"]), "protocol": report["protocol"]["name"]}
    for k, v in pr["conditions"].items():
        h[f"{pr['entity']}_ra_mpjpe_{k}_m"] = v["mean"]
    h["force_gt_beats_shuf"] = pr["force_gt_beats_shuf"]
    h["force_gt_beats_shuf_runs"] = pr["force_gt_beats_shuf_runs"]
    for c, v in pr["class_ratios"].items():
        h[f"shuf_over_gt_{c}"] = v["force_shuf/force_gt"]
    for r in report["ablation"]["conditions"]:
        slug = r["condition"].replace("+ ", "").replace(" ", "_")
        h[f"cfr_{slug}"], h[f"mmp_{slug}_m"], h[f"sep_{slug}_m"] = r["cfr"], r["mmp_m"], r["sep_m"]
    v = report["video"]
    if v.get("run"):
        for col, r in v["table1"].items():
            if "fvd16" in r:  # "fvd" only from the I3D extractor, else "proxy_fvd"
                name = "fvd" if r["metric"] == fvd.FVD_LABEL else "proxy_fvd"
                h[f"{name}16_{col}"], h[f"{name}_final_{col}"] = r["fvd16"]["value"], r["final_chunk"]["value"]
    return _plain(h)


def evaluate(
    dynamics_dir: Path | str,
    corpus: Path | str,
    out_dir: Path | str,
    *,
    protocol: EvalProtocol | str = "paper",
    observation: Path | str | None = None,
    baseline: Path | str | None = None,
    seed: int = 0,
    log: Callable[[str], Any] = print,
    entity: str = "hunter",
    render_size: tuple[int, int] = (72, 128),
    i3d: Path | str | None = None,
    progress: Progress | None = None,
    **overrides: Any,
) -> dict[str, Any]:
    """Run the protocol (``config.PROTOCOLS`` name or an ``EvalProtocol``; ``overrides`` change its fields) and write the
    report directory ``out_dir`` (module doc).

    Returns {"out_dir", "report_md", "report_json", "plots" (name → path), "headline" (name → number), "windows"
    (probe windows)}. ``observation``: the observation model (Tables 1 and 3's FVD); ``baseline``: a pixel-AR baseline
    checkpoint (control "actions") for Table 1's second column; ``i3d``: an Inception-I3D safetensors file, for FVD
    proper instead of the proxy; ``progress(phase, done, total)`` is told the progress of every long loop."""
    proto = parse_protocol(protocol, **overrides)
    c = Corpus(Path(corpus), scene=model_scene(dynamics_dir))  # the scene the model was trained on
    out = Path(out_dir)
    _check_replaceable(out)  # before any compute
    extractor = fvd.extractor_for(Path(i3d)) if i3d is not None else None  # a bad I3D file fails here too
    models = _load_models(observation, baseline)
    fps = model_fps(dynamics_dir)
    proto.video_frames(float(c.fps))  # a protocol whose rollouts cannot hold its clips fails before any compute
    split = "test" if c.segment_ids("test") else "train"
    temp = proto.temperature
    windows = select_windows(c, proto.probe_windows, proto.seed_frames, proto.horizon, seed, split=split, fps=fps)
    horizon_long = long_horizon(proto, float(c.fps), fps, [m.config.frames for m in models.values()])
    long, why_not = long_windows(c, proto, horizon_long, seed + 1, split, fps)
    names = [e.name for e in c.layout.articulated]
    entity = entity if entity in names else names[-1]
    log(
        f"evaluate: protocol {proto.name!r}; {len(windows)} probe windows of {proto.seed_frames} + {proto.horizon} frames, "
        f"{len(long)} long rollouts of {long[0].horizon if long else 0} frames (the first {min(len(long), proto.rollouts)} "
        f"painted over {horizon_long}), split {split!r}"
    )
    free, ran = run_windows(
        dynamics_dir, c, windows, rules="auto", temperature=temp, seed=seed, progress=progress, phase="Free rollouts"
    )
    log(f"evaluate: Free rollouts done (rules per stage {ran}); state-layer metrics")
    state = state_layer(dynamics_dir, c, windows, free, render_size=render_size, progress=progress)
    log("evaluate: controllability probe (Table 2)")
    probe = controllability_probe(
        dynamics_dir, c, windows, entity=entity, temperature=temp, seed=seed, free=free, progress=progress
    )
    painted = (horizon_long, models, extractor)
    ablation, curves, video = _long_tables(dynamics_dir, c, long, why_not, proto, painted, seed, log, progress)
    sheet = video.pop("sheet", None)
    video.update({k: str(v) for k, v in (("observation", observation), ("baseline", baseline)) if v is not None})
    report = {
        "dynamics": str(dynamics_dir),
        "corpus": str(c.path),
        "protocol": {**proto.to_json(), "reduced": proto.reduced()},
        "split": split,
        "fps": fps,
        "seed": seed,
        "seed_frames": proto.seed_frames,
        "horizon": proto.horizon,
        "temperature": temp,
        "render_size": list(render_size),
        "windows": [asdict(w) for w in windows],
        "rules_free": ran,
        "state_layer": state,
        "probe": probe,
        "ablation": ablation,
        "long_horizon": curves,
        "video": video,
        "training": training_against_baselines(dynamics_dir),
    }
    report = _write_report(_plain(report), sheet, out)
    log(f"evaluate: report in {out}")
    return {
        "out_dir": str(out),
        "report_md": str(out / "report.md"),
        "report_json": str(out / "report.json"),
        "plots": {k: str(out / v) for k, v in report["plots"].items()},
        "headline": report["headline"],
        "windows": len(windows),
    }


def long_windows(c: Corpus, proto: EvalProtocol, painted: int, seed: int, split: str, fps: float) -> tuple[list[Window], str]:
    """The long rollouts' windows: ``proto.state_count`` of ``proto.state_length_s`` (at least ``painted`` predicted
    frames), started in the fight the cap is for; when no held-out segment holds that length, of ``painted`` frames
    instead. Returns (windows, why): no windows and the reason when not even ``painted`` fits, else why they were cut."""
    engaged = RuleParams().max_separation_m
    want = max(painted, math.ceil(proto.state_length_s * fps))
    why = ""
    for horizon in dict.fromkeys((want, painted)):
        try:
            got = select_windows(c, proto.state_count, proto.seed_frames, horizon, seed, split=split, fps=fps, engaged=engaged)
        except ValueError as err:  # a corpus of short segments: Table 3's rollouts are cut, or Tables 1 and 3 not run
            why = why or str(err)
            continue
        cut = f"state rollouts cut to the painted {painted / fps:g} s: {why}" if why else ""
        return got, cut
    return [], why


def painted_rollouts(
    long: Sequence[Window], tables: dict[str, list[pa.Table]], rollouts: int, horizon: int
) -> tuple[list[Window], dict[str, list[pa.Table]]]:
    """The painted rollouts of the state rollouts: the first ``rollouts`` windows cut to ``horizon`` predicted frames,
    and each driving state's tables cut to match."""
    windows = [replace(w, horizon=horizon) for w in long[:rollouts]]
    return windows, {k: [t.slice(0, w.length) for t, w in zip(v, windows)] for k, v in tables.items()}


def _long_tables(
    dynamics_dir: Path | str,
    c: Corpus,
    long: Sequence[Window],
    why_not: str,
    proto: EvalProtocol,
    painted: tuple[int, dict[str, Any], Any],
    seed: int,
    log: Callable[[str], Any],
    progress: Progress | None,
) -> tuple[dict, dict, dict]:
    """Table 3's state columns and the long-horizon curves over the long rollouts, the video tables over the first
    ``proto.rollouts`` of them cut to the ``painted`` = (predicted frames, models, extractor) the observation layer
    paints; with no long rollouts each is marked not run with ``why_not``, with some it says why they were cut."""
    fps = model_fps(dynamics_dir)
    horizon, models, extractor = painted
    if not long:
        log(f"evaluate: Tables 1 and 3 not run: {why_not}")
        return (
            {"run": False, "reason": why_not, "conditions": [], "windows": []},
            {"run": False, "reason": why_not, "fps": fps, "drift_m": {}, "body_share": {}},
            {"run": False, "reason": why_not},
        )
    log("evaluate: the driving states on the long rollouts (Table 3)")
    states = ablation_rollouts(dynamics_dir, c, long, temperature=proto.temperature, seed=seed, progress=progress)
    ablation = rule_ablation(dynamics_dir, c, long, rollouts=states) | {"seconds": long[0].horizon / fps, "cut": why_not}
    tables = {k: v["tables"] for k, v in states.items()}
    curves = long_horizon_curves(c, long, tables, proto, fps)
    log("evaluate: the observation layer (Tables 1 and 3)" if models else "evaluate: no observation model: no FVD")
    obs, base = models.get("observation"), models.get("baseline")
    windows, cut = painted_rollouts(long, tables, proto.rollouts, horizon)
    video = video_tables(c, windows, cut, proto, obs, base, extractor=extractor, seed=seed, progress=progress)
    return ablation, curves, video


def _write_report(report: dict, sheet: dict | None, out: Path) -> dict:
    """Write the plots, report.json and report.md to a temp directory beside ``out`` and rename it into place;
    returns the report with its "plots" and "headline"."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    os.chmod(tmp, 0o755)  # mkdtemp makes 0700; reports are read by other users and services
    try:
        report["plots"] = plot_all(report, sheet, tmp)
        if sheet is not None:
            report["video"]["sheet"] = {k: v for k, v in sheet.items() if k != "rows"} | {"rows": list(sheet["rows"])}
        report["headline"] = headline(report)
        write_json(tmp / "report.json", report)
        write_bytes(tmp / "report.md", render_markdown(report).encode())
        _swap_in(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return report


def _load_models(observation: Path | str | None, baseline: Path | str | None) -> dict[str, Any]:
    """The observation model (control "pose") and the baseline (control "actions") given, each checked for its control."""
    from marionette.observation.train import load_model

    out = {}
    for key, path, want in (("observation", observation, "pose"), ("baseline", baseline, "actions")):
        if path is not None:
            m = load_model(path)
            if m.config.control != want:
                raise ValueError(f"{path}: a {key} model is trained with control {want!r}, this one with {m.config.control!r}")
            out[key] = m
    return out


def load_report(out_dir: Path | str) -> dict[str, Any]:
    """A written report's report.json."""
    return json.loads((Path(out_dir) / "report.json").read_text())
