"""The observation layer over long rollouts: Table 1, Table 3's FVD column and the long-horizon curves.

Every long rollout is one held-out window of ``protocol.seed_frames`` seed rows and as many predicted rows as
``protocol.rollout_seconds`` of video need (plus the frames the relay's last chunk reaches past them). Its video
clip (``report.rollout_clip``) starts at the first video frame at or after the last seed row, seen through the
bridge's follow camera seeded with the recorded camera of that frame, and is painted from the recorded RGB of that
frame, relayed over the model's chunks; the first T = round(rollout_seconds · video fps) frames are scored against
the recorded RGB of the same frames:

- **FVD16** (``fvd16_clips``): ``clips_per_rollout`` clips of ``clip_frames`` frames per rollout, clip k starting
  at video frame k · (T // clips_per_rollout) — eight 16-frame clips per 16 s rollout at the paper's size; the
  Fréchet distance of all rollouts' clips, with clip-bootstrap intervals both bias-corrected and raw percentile
  (the paper's; ``fvd.fvd_with_interval``).
- **Final chunk**: the last ``final_frames`` frames [T − final_frames, T) of each rollout, one clip per rollout.
- **Per chunk index** (``chunks.relay_spans``): chunk k = frames [k·(F − 1), k·(F − 1) + F), F = final_frames, while it
  fits in T — the relay's chunks at the paper's 81 frames.

Table 1 sets the Marionette column (the "+ collider" driving state painted by the observation model) beside the
pixel-AR baseline (an observation model trained with control "actions", given the recorded action tokens of the
same video frames and the same first frame, relayed the same way). Table 3 paints each driving state (recorded,
no rule, + collider, + collider + cap) with the same observation model. Windows whose frames no video chunk
covers are skipped with the reason (``report.WindowSkipped``); a column with fewer than 2 rollouts left is not run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette.chunks import relay_frames, relay_spans, relay_step
from marionette.corpus import Corpus, world_of_rows
from marionette.corpus.vocab import ActionTokens
from marionette.eval import fvd
from marionette.eval import metrics as M
from marionette.eval.clips import WindowSkipped, rollout_clip, segment_chunks
from marionette.eval.config import EvalProtocol
from marionette.eval.protocol import Progress, Window, body_share_frames, predicted, terrain_scene

MARIONETTE_STATE = "+ collider"  # the driving state Table 1's Marionette column paints
SHEET_POINTS = 4  # time points of the contact sheet


def paint_frames(T: int, model_frames: int) -> int:
    """Video frames the relay paints to cover T: 1 + n·(model_frames − 1), the fewest n with that ≥ T."""
    return relay_frames(max(1, math.ceil((T - 1) / relay_step(model_frames))), model_frames)


def long_horizon(protocol: EvalProtocol, video_fps: float, model_fps: float, model_frames: Sequence[int] = ()) -> int:
    """Predicted dynamics frames of a long rollout: enough for the video frames every model's relay paints (and one more row)."""
    T = protocol.video_frames(video_fps)
    painted = max([T] + [paint_frames(T, f) for f in model_frames])
    return math.ceil(painted / video_fps * model_fps) + 2


def fvd16_clips(videos: torch.Tensor, starts: Sequence[int], frames: int) -> torch.Tensor:
    """The FVD clips (N · len(starts), frames, 3, H, W) of videos (N, T, 3, H, W): per video, frames [s, s + frames) per start."""
    if videos.ndim != 5:
        raise ValueError(f"videos: shape {tuple(videos.shape)}, expected (N, T, 3, H, W)")
    T = videos.shape[1]
    if any(s < 0 or s + frames > T for s in starts):
        raise ValueError(f"clips of {frames} frames at {list(starts)} do not fit videos of {T} frames")
    return torch.stack([videos[:, s : s + frames] for s in starts], dim=1).flatten(0, 1)


def final_chunk(videos: torch.Tensor, T: int, frames: int) -> torch.Tensor:
    """The final chunk (N, frames, 3, H, W): video frames [T − frames, T) of videos (N, ≥ T, 3, H, W)."""
    if videos.shape[1] < T or frames > T:
        raise ValueError(f"a final chunk of {frames} frames ending at frame {T} does not fit videos of {videos.shape[1]} frames")
    return videos[:, T - frames : T]


def _interval(a: np.ndarray, b: np.ndarray, resamples: int, seed: int) -> dict[str, Any]:
    """Fréchet distance of features a, b with the bias-corrected interval and, beside it, the raw percentile one."""
    r = fvd.fvd_with_interval(a, b, resamples=resamples, seed=seed)
    raw = fvd.fvd_with_interval(a, b, resamples=resamples, seed=seed, bias_correct=False)
    return {**r, "raw_low": raw["low"], "raw_high": raw["high"]}


def score_videos(
    real: torch.Tensor, generated: torch.Tensor, protocol: EvalProtocol, video_fps: float, extractor: Any, seed: int = 0
) -> dict[str, Any]:
    """FVD16, final-chunk FVD and per-chunk-index FVD of generated videos (N, ≥ T, 3, H, W) against the real ones."""
    T = protocol.video_frames(video_fps)
    if real.shape != generated.shape:
        raise ValueError(f"real videos {tuple(real.shape)} and generated {tuple(generated.shape)} differ")
    metric = fvd.FVD_LABEL if extractor.is_fvd else fvd.PROXY_LABEL
    ex = extractor.extract
    starts = protocol.clip_starts(video_fps)
    r16, g16 = fvd16_clips(real, starts, protocol.clip_frames), fvd16_clips(generated, starts, protocol.clip_frames)
    out: dict[str, Any] = {"metric": metric, "extractor": extractor.name, "rollouts": int(len(real)), "frames": T}
    out["fvd16"] = {
        "clips": int(len(r16)),
        "clip_frames": protocol.clip_frames,
        "starts": starts,
        **_interval(ex(r16), ex(g16), protocol.resamples, seed),
    }
    fr, fg = final_chunk(real, T, protocol.final_frames), final_chunk(generated, T, protocol.final_frames)
    out["final_chunk"] = {"frames": [T - protocol.final_frames, T], **_interval(ex(fr), ex(fg), protocol.resamples, seed)}
    out["per_chunk"] = [
        {"chunk": k, "frames": [a, b], **_interval(ex(real[:, a:b]), ex(generated[:, a:b]), protocol.resamples, seed)}
        for k, (a, b) in enumerate(relay_spans(T, protocol.final_frames))
    ]
    return out


def _paint(model: Any, control: torch.Tensor, first: torch.Tensor, frames: int, steps: int, seed: int) -> torch.Tensor:
    """``frames`` painted RGB frames (frames, 3, H, W) in [−1, 1]: the relay over as many model chunks as they take."""
    from marionette.observation.relay import generate

    chunks = (frames - 1) // (model.config.frames - 1)
    with torch.inference_mode():
        return generate(model, control[:frames], first, chunks=chunks, steps=steps, seed=seed).clamp(-1, 1)


def recorded_actions(c: Corpus, rows: pa.Table, source_frames: tuple[int, int]) -> torch.Tensor:
    """The recorded action tokens (T, N) int64 of the segment's source frames [a, b) (``rows``: its source rows): the baseline's control."""

    tokens, _ = ActionTokens.from_corpus(c).encode(c.layout, rows, where=str(c.path))
    f = rows["frame"].to_numpy()
    want = np.arange(*source_frames)
    idx = np.searchsorted(f, want)
    if idx.max() >= len(f) or not np.array_equal(f[idx], want):
        raise ValueError(f"{c.path}: source frames {source_frames} are not all rows of segment {rows['segment'][0]}")
    return torch.from_numpy(tokens[idx])


def video_tables(
    c: Corpus,
    windows: Sequence[Window],
    states: dict[str, list[pa.Table]],
    protocol: EvalProtocol,
    observation: Any = None,
    baseline: Any = None,
    *,
    extractor: Any = None,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Table 1 and Table 3's FVD column (module doc) over long-rollout ``windows``; ``states``: driving state → rollout
    tables per window (``ablation.ablation_rollouts``). Returns {"table1": {"marionette", "baseline"}, "table3": {state:
    scores}, "skipped": [...], "sheet": the contact sheet's frames}; a model not given is "not run" with the reason."""

    video_fps = float(c.fps)
    T = protocol.video_frames(video_fps)
    ex = extractor or fvd.ProxyExtractor()
    models = {k: m for k, m in (("observation", observation), ("baseline", baseline)) if m is not None}
    if not models:
        return {"run": False, "reason": "no observation model given (--observation)"}
    sizes = {m.config.size for m in models.values()}
    if len(sizes) > 1:
        raise ValueError(
            f"the observation model and the baseline paint at different sizes {sorted(sizes)}; Table 1 compares like with like"
        )
    size = sizes.pop()
    frames = max(paint_frames(T, m.config.frames) for m in models.values())
    rows = {s: c.read_segment(s) for s in {w.segment for w in windows}}
    chunks = {s: segment_chunks(c, s) for s in rows}
    scenes: dict[str, Any] = {}
    clips: dict[str, list[Any]] = {s: [] for s in states}
    skipped, kept = [], []
    for k, w in enumerate(windows):
        if w.stage not in scenes:
            scenes[w.stage] = terrain_scene(c, w.segment)
        try:
            got = {
                s: rollout_clip(c, w, t[k], frames, size, rows[w.segment], chunks[w.segment], scenes[w.stage])
                for s, t in states.items()
            }
        except WindowSkipped as err:
            skipped.append({"window": k, "segment": w.segment, "start": w.start, "reason": str(err)})
        else:
            kept.append(k)
            for s, clip in got.items():
                clips[s].append(clip)
        if progress is not None:
            progress("video: rendering long rollouts", k + 1, len(windows))
    out: dict[str, Any] = {"run": True, "frames": T, "painted_frames": frames, "skipped": skipped, "windows": kept}
    if len(kept) < 2:
        return {**out, "run": False, "reason": f"{len(kept)} long rollouts with a video clip, 2 needed"}
    real = torch.stack([cl.rgb[:frames] for cl in clips["recorded"]])
    painted: dict[str, torch.Tensor] = {}
    todo = [(s, "observation") for s in states if "observation" in models] + (
        [("baseline", "baseline")] if "baseline" in models else []
    )
    done = 0
    for name, which in todo:
        model, vids = models[which], []
        for j, k in enumerate(kept):
            ref = clips[MARIONETTE_STATE if name == "baseline" else name][j]
            control = recorded_actions(c, rows[windows[k].segment], ref.source_frames) if name == "baseline" else ref.pose
            vids.append(_paint(model, control, ref.rgb[0], frames, protocol.fvd_steps, seed + k))
            done += 1
            if progress is not None:
                progress("video: painting long rollouts", done, len(todo) * len(kept))
        painted[name] = torch.stack(vids)
    scores = {name: score_videos(real, v, protocol, video_fps, ex, seed) for name, v in painted.items()}
    table3 = {s: scores[s] for s in states if s in scores}
    no_obs = {"run": False, "reason": "no observation model given (--observation)"}
    no_base = {"run": False, "reason": "no baseline given (--baseline)"}
    out["table1"] = {"marionette": table3.get(MARIONETTE_STATE, no_obs), "baseline": scores.get("baseline", no_base)}
    out["table3"] = table3 or {s: no_obs for s in states}
    out["sheet"] = contact_sheet(
        clips[MARIONETTE_STATE][0], real[0], {k: v[0] for k, v in painted.items() if k in (MARIONETTE_STATE, "baseline")}, T
    )
    return out


def contact_sheet(clip: Any, real: torch.Tensor, painted: dict[str, torch.Tensor], T: int) -> dict[str, Any]:
    """The contact sheet's rows at ``SHEET_POINTS`` time points of the first long rollout: the pose-control frames, each
    painted video and the recorded RGB, as uint8 (points, H, W, 3)."""
    t = np.linspace(0, T - 1, SHEET_POINTS).round().astype(int)
    rgb = lambda v: ((v[t].permute(0, 2, 3, 1).numpy() + 1) * 127.5).clip(0, 255).astype(np.uint8)  # noqa: E731
    rows = {"pose control": (clip.pose[t].permute(0, 2, 3, 1).numpy() * 255).clip(0, 255).astype(np.uint8)}
    rows.update({("Marionette" if k == MARIONETTE_STATE else "pixel-AR baseline"): rgb(v) for k, v in painted.items()})
    rows["recorded RGB"] = rgb(real)
    return {"frames": t.tolist(), "rows": rows, "source_frames": list(clip.source_frames)}


def long_horizon_curves(
    c: Corpus, windows: Sequence[Window], states: dict[str, list[pa.Table]], protocol: EvalProtocol, fps: float
) -> dict[str, Any]:
    """Root divergence (m) against horizon per entity (mean over windows, of the Marionette state against the recorded
    rows) and the body share of the pose frame in the first and last chunk (``final_frames`` of video) per state."""
    L = c.layout
    gen = [world_of_rows(L, predicted(t, w)) for t, w in zip(states[MARIONETTE_STATE], windows)]
    rec = [world_of_rows(L, predicted(t, w)) for t, w in zip(states["recorded"], windows)]
    drift = {
        e.name: np.stack([M.root_drift(g[e.name][:, 0], r[e.name][:, 0]) for g, r in zip(gen, rec)]).mean(axis=0)
        for e in L.articulated
    }
    n = max(2, int(round(protocol.final_frames / c.fps * fps)))  # dynamics rows of one chunk
    shares: dict[str, dict[str, dict[str, float]]] = {}
    for s in ("recorded", MARIONETTE_STATE):
        first, last = [], []
        for t, w in zip(states[s], windows):
            h = predicted(t, w)
            terrain = terrain_scene(c, w.segment)
            first.append(body_share_frames(L, h.slice(0, n), terrain))
            last.append(body_share_frames(L, h.slice(h.num_rows - n, n), terrain))
        shares[s] = {
            name: {
                "first": float(np.mean([f[name].mean() for f in first])),
                "last": float(np.mean([f[name].mean() for f in last])),
            }
            for name in first[0]
        }
    return {"fps": fps, "drift_m": drift, "body_share": shares, "chunk_rows": n}
