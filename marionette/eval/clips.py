"""Rollouts and recorded chunks as video clips, and the proxy-FVD rows of whole clips.

``rollout_clip``: a rollout rendered through the bridge with a camera that starts at the recorded camera of the
clip's first frame (the first video frame at or after the last seed row) and then follows the generated characters,
beside the recorded RGB of the same frames, found in the segment's video chunks by their json "frames" [a, b)
(``WindowSkipped`` when they are not all there). ``observation_fvd`` (recorded pose-control chunks painted by the
model) and ``rollout_fvd`` (Free rollouts painted): proxy-FVD over whole clips and per model chunk, with clip-level
bootstrap intervals (the benchmark's rows)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette.bridge.camera import recorded_cameras
from marionette.corpus import Corpus, fixed_rows, video_shards
from marionette.eval import fvd
from marionette.eval.i3d import MIN_FRAMES
from marionette.eval.protocol import (
    Progress,
    Window,
    rollout_pose_codes,
    terrain_scene,
)


def _chunk_frames(frames: int, extractor: Any, length: int) -> int:
    """Frames of the per-chunk pieces: the model's chunk, or for I3D (which needs 9) whole model chunks enough for it."""

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
    from marionette.observation.relay import generate

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

    vpath = c.video_path(c.segment_row(segment)["shard"])
    if not vpath.exists():
        return []
    chunks = video_shards.read_chunks(vpath, segment, kinds=(video_shards.CHUNK_KIND, video_shards.RGB_KIND))
    recs = {k: video_shards.chunk_record(m["json"], k, str(vpath)) for k, m in chunks.items() if "json" in m}
    return sorted(
        ({**r, "key": k, "rgb": chunks[k].get(video_shards.RGB_KIND)} for k, r in recs.items()), key=lambda r: r["frames"][0]
    )


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
    from marionette.observation.data import check_size, pose_frames, rgb_frames
    from marionette.video import decode_frames

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
