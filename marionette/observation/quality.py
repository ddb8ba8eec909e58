"""How well an observation model paints held-out video and follows its pose: the measures its tests and
benchmarks share.

- ``relay_error``: mean |generated − recorded| (RGB in [−1, 1]) over whole held-out chunks, each relayed
  from its recorded first frame under its own control (pose video, or the baseline's action schedule);
  ``copy_error`` is the same for repeating the first frame.
- ``Segmenter``: the instrument that reads bodies off RGB frames — a small dilated convolutional net
  fitted to recorded frames against the bridge's id mask (``bodies``: pixels whose identity code is a
  bone). Its IoU on recorded held-out frames (``iou_on``) is the ceiling of any score read through it.
- ``swap_pairs`` and ``follow_scores``: the pose-following test. Chunk A's first frame and chunk B's pose
  frames make one chunk; the silhouettes of its generated frames are scored (IoU) against B's id masks
  (the pose it was given) and against A's (the bodies of the first frame, where a model that copies its
  first frame leaves them). Pairs are chosen whose masks overlap little, so that the two are told apart.
- ``entity_drift``: appearance drift over a relay. Per relay chunk, the per-entity appearance error: for each
  entity (render-id band) and frame in which the recorded pose shows it, the mean |generated − recorded| over its
  mask's pixels; its growth from the first chunks to the last is what persistent references are for. With
  ``forced`` every chunk starts from the recorded frame instead of the last painted one (and a model with references
  takes them from the recorded frames): the same error without the relay, so that what the relay adds (relayed −
  forced) is told from what the video's later frames ask anyway (bodies turned away from their first look, bodies
  come back into view).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette.bridge.gbuffer import CODE_MAX
from marionette.chunks import relay_chunks, relay_frames, relay_step
from marionette.corpus.paths import parse_chunk_key
from marionette.observation.data import Clip
from marionette.observation.model import VideoDiT, sample_chunk
from marionette.observation.references import EntityReferences, band_masks
from marionette.observation.relay import generate
from marionette.observation.train import control_of


def bodies(pose: Tensor) -> Tensor:
    """(…, 3, H, W) pose frames → (…, 1, H, W) float mask, 1 where a bone is drawn (identity code > 0)."""
    return (pose.narrow(-3, 1, 1) > 0.5 / CODE_MAX).float()


def iou(a: Tensor, b: Tensor) -> float:
    """Intersection over union of two binary masks (1 when both are empty)."""
    union = float(((a + b) > 0).sum())
    return float((a * b).sum()) / union if union else 1.0


def relay_error(model: VideoDiT, chunks: list[Clip], steps: int = 16, seed: int = 0) -> float:
    """Mean |generated − recorded| over every chunk's frames after the first, relayed from its first frame."""
    errs = []
    for ch in chunks:
        video = generate(model, control_of(ch, model.config.control), ch.rgb[0], steps=steps, seed=seed)
        errs.append(float((video[1:] - ch.rgb[1 : len(video)]).abs().mean()))
    return float(np.mean(errs))


def entity_drift(
    model: VideoDiT,
    videos: list[Clip],
    bands: tuple[tuple[int, int], ...],
    steps: int = 16,
    seed: int = 0,
    references: bool = True,
    forced: bool = False,
    handoff: float | None = None,
) -> dict[str, np.ndarray | float]:
    """``appearance_drift`` of the model's relays (``references``: whether a model with reference slots is given
    them; ``forced``: each chunk from its recorded first frame, ``forced_chunks``; ``handoff``: the relay's hand-off
    noise, default the model's)."""

    def paint(pose: Tensor, recorded: Tensor, chunks: int) -> Tensor:
        if forced:
            return forced_chunks(model, pose, recorded, chunks, steps=steps, seed=seed, references=references)
        return generate(model, pose, recorded[0], chunks=chunks, steps=steps, seed=seed, references=references, handoff=handoff)

    return appearance_drift(videos, bands, model.config.frames - 1, paint)


def forced_chunks(
    model: VideoDiT, pose: Tensor, recorded: Tensor, chunks: int, steps: int = 16, seed: int = 0, references: bool = True
) -> Tensor:
    """A video made as a relay's (1 + N·(T − 1) frames, noise from one generator seeded by ``seed``) but with every chunk
    started from the recorded frame at its start, and a model with reference slots given each entity's crop from the
    recorded frames up to that start (as a relay takes it): the relay's error without its hand-offs."""
    c = model.config
    step = relay_step(c.frames)
    g = torch.Generator().manual_seed(int(seed))
    seen = EntityReferences(c.reference_bands, c.reference_size) if c.references and references else None
    out, upto = [recorded[:1]], 0
    for k in range(chunks):
        a = k * step
        refs = None
        if seen is not None:
            seen.see(recorded[upto : a + 1], pose[upto : a + 1], offset=upto)
            upto, refs = a + 1, seen.tensor()[None]
        with torch.no_grad():
            out.append(sample_chunk(model.eval(), pose[None, a : a + c.frames], recorded[None, a], steps, g, refs)[0, 1:])
    return torch.cat(out)


def appearance_drift(videos: list[Clip], bands: tuple[tuple[int, int], ...], step: int, paint) -> dict[str, np.ndarray | float]:
    """Appearance drift over relays: each video relayed by ``paint(pose, recorded video, chunks)`` from its recorded
    first frame (a relay reads only that frame of the recording) over as many chunks K of ``step`` new frames as the
    shortest holds. Per (entity, frame) where the recorded pose shows the entity, its colour error |mean generated RGB − mean recorded RGB| over the entity's mask
    (its look, whatever the shape) and its pixel error (mean |generated − recorded| over the mask: look and shape).
    Returns

    - ``colour``, ``pixel``: (K,) their means over relay chunk k's pairs (nan where none shows an entity);
    - ``known``, ``unknown``: (K,) the colour error's mean over the pairs of the entities the first frame shows (whose
      look the relay was given: its drift) and over the others' (a look the relay never saw, invented or taken from
      a frame it painted);
    - ``in_view``, ``after_gap``: the mean colour error where the entity has stayed in view since it was first
      shown, and where it left the view and came back (what a relay without references must paint from nothing);
      ``pairs``: how many of each."""

    K = min((len(v.rgb) - 1) // step for v in videos)
    n = 1 + K * step
    sums = {"colour": np.zeros(K), "pixel": np.zeros(K), "known": np.zeros(K), "unknown": np.zeros(K)}
    count = {name: np.zeros(K) for name in sums}
    history = {"in_view": [], "after_gap": []}
    for v in videos:
        pose, rgb = v.pose[:n], v.rgb[:n]
        video = paint(pose, rgb, K)[1:]
        masks = band_masks(pose, bands).float()[:, :, None]  # (n, E, 1, H, W)
        shown_at = masks.flatten(2).sum(-1) > 0  # (n, E)
        masks, shown = masks[1:], shown_at[1:].float()
        pixels = masks.sum((-2, -1)).clamp(min=1)  # (n − 1, E, 1)
        mean_gen, mean_rec = (masks * video[:, None]).sum((-2, -1)) / pixels, (masks * rgb[1:, None]).sum((-2, -1)) / pixels
        colour = (mean_gen - mean_rec).abs().mean(-1)  # (n − 1, E)
        pixel = (masks * (video - rgb[1:]).abs()[:, None]).sum((-2, -1)).mean(-1) / pixels[..., 0]
        known = shown_at[0].float()  # (E,): the entities whose look the relay was given in its first frame
        per = {
            "colour": (colour, shown),
            "pixel": (pixel, shown),
            "known": (colour, shown * known),
            "unknown": (colour, shown * (1 - known)),
        }
        for k in range(K):
            at = slice(k * step, (k + 1) * step)
            for name, (e, w) in per.items():
                sums[name][k] += float((e[at] * w[at]).sum())
                count[name][k] += float(w[at].sum())
        seen = shown_at.numpy()
        for e in range(seen.shape[1]):
            was_seen, gone = bool(seen[0, e]), False  # shown before this frame; out of view since then
            for t in range(1, n):
                if seen[t, e]:
                    history["after_gap" if gone else "in_view"].append(float(colour[t - 1, e]))
                    was_seen = True
                else:
                    gone = gone or was_seen
    out: dict[str, np.ndarray | float] = {
        name: np.where(count[name] > 0, t / np.maximum(count[name], 1), np.nan) for name, t in sums.items()
    }
    for name, errs in history.items():
        out[name] = float(np.mean(errs)) if errs else float("nan")
    out["pairs"] = {name: len(errs) for name, errs in history.items()}
    return out


def relay_videos(source, frames: int, every: int | None = None) -> list[Clip]:
    """Videos of ``frames`` frames for long relays: the runs of consecutive chunks of each segment of a
    ``ClipSource`` (chunks whose source frames follow on) joined, cut from their starts every ``every`` frames
    (default ``frames``), in the index's order."""

    runs: dict[str, list[list]] = {}
    for ref in source.index():
        seg = runs.setdefault(parse_chunk_key(ref.key)[0], [])
        if seg and seg[-1][-1].first_frame + seg[-1][-1].frames == ref.first_frame:
            seg[-1].append(ref)
        else:
            seg.append([ref])
    out = []
    for seg, chains in runs.items():
        for chain in chains:
            if sum(r.frames for r in chain) < frames:
                continue
            parts = [source.chunk(r) for r in chain]
            rgb, pose = torch.cat([p.rgb for p in parts]), torch.cat([p.pose for p in parts])
            for a in range(0, len(rgb) - frames + 1, every or frames):
                out.append(
                    Clip(rgb=rgb[a : a + frames], pose=pose[a : a + frames], key=f"{seg}@{chain[0].first_frame + a}", start=0)
                )
    return out


def quarters(errors: np.ndarray) -> tuple[float, float]:
    """A per-chunk error's mean over the first quarter of a relay's chunks and over the last (at least a chunk each)."""
    q = max(1, len(errors) // 4)
    return float(np.nanmean(errors[:q])), float(np.nanmean(errors[-q:]))


def drift_growth(errors: np.ndarray) -> float:
    """How much a per-chunk error grows over a relay: the mean of its last quarter of chunks less its first's."""
    first, last = quarters(errors)
    return last - first


def copy_error(chunks: list[Clip], frames: int) -> float:
    """``relay_error`` of repeating the first frame (over the same frames)."""
    errs = []
    for ch in chunks:
        n = relay_frames(relay_chunks(len(ch.rgb), frames), frames)
        errs.append(float((ch.rgb[1:n] - ch.rgb[0]).abs().mean()))
    return float(np.mean(errs))


class Segmenter:
    """RGB frames (N, 3, H, W) in [−1, 1] → silhouettes (N, 1, H, W) in {0, 1} (module doc)."""

    def __init__(self, chunks: list[Clip], steps: int = 1500, batch: int = 64, seed: int = 0) -> None:
        rgb = torch.cat([c.rgb for c in chunks]).contiguous(memory_format=torch.channels_last)
        mask = torch.cat([bodies(c.pose) for c in chunks])
        if not mask.any():
            raise ValueError("segmenter: no bone pixel in the frames it would learn from (pose targets without bodies?)")
        with torch.random.fork_rng():
            torch.manual_seed(int(seed))
            self.net = nn.Sequential(
                nn.Conv2d(3, 32, 3, padding=1),
                nn.GELU(),
                nn.Conv2d(32, 32, 3, padding=2, dilation=2),
                nn.GELU(),
                nn.Conv2d(32, 32, 3, padding=4, dilation=4),
                nn.GELU(),
                nn.Conv2d(32, 32, 3, padding=1),
                nn.GELU(),
                nn.Conv2d(32, 1, 1),
            ).to(memory_format=torch.channels_last)  # oneDNN convolves channels-last frames faster on a CPU
        opt = torch.optim.Adam(self.net.parameters(), 3e-3)
        share = float(mask.mean())
        weight = torch.tensor(((1 - share) / share) ** 0.5)  # bones are a few % of pixels: weigh them up, not all the way
        g = torch.Generator().manual_seed(int(seed))
        for _ in range(steps):
            idx = torch.randint(0, len(rgb), (batch,), generator=g)
            loss = F.binary_cross_entropy_with_logits(self.net(rgb[idx]), mask[idx], pos_weight=weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        self.net.eval().requires_grad_(False)

    def __call__(self, rgb: Tensor) -> Tensor:
        with torch.no_grad():
            return (self.net(rgb.contiguous(memory_format=torch.channels_last)) > 0).float().contiguous()

    def iou_on(self, chunks: list[Clip]) -> float:
        """IoU of the silhouettes read off the chunks' recorded frames against their id masks."""
        return iou(torch.cat([self(c.rgb) for c in chunks]), torch.cat([bodies(c.pose) for c in chunks]))


@dataclass(frozen=True)
class SwapPair:
    a: int  # the chunk that gives the first frame
    b: int  # the chunk that gives the pose frames
    start: int
    frames: int  # the clip: frames start … start + frames − 1, the first given
    overlap: float  # IoU of A's and B's id masks over the generated frames


def swap_pairs(chunks: list[Clip], frames: int, count: int, start: int = 0) -> list[SwapPair]:
    """The ``count`` ordered pairs of distinct chunks whose id masks over frames start+1 … start+frames−1
    overlap least (ties in index order); a chunk with no bone in those frames is in no pair."""
    masks = [bodies(c.pose[start + 1 : start + frames]) for c in chunks]
    seen = [k for k, m in enumerate(masks) if m.any()]
    pairs = [SwapPair(a, b, start, frames, iou(masks[a], masks[b])) for a in seen for b in seen if a != b]
    return sorted(pairs, key=lambda p: (p.overlap, p.a, p.b))[:count]


def follow_scores(
    model: VideoDiT, chunks: list[Clip], pairs: list[SwapPair], segmenter: Segmenter, steps: int = 16, seed: int = 0
) -> dict[str, float]:
    """Mean silhouette IoU of the generated frames against B's id masks (followed) and A's (first frame's)."""
    if model.config.control != "pose":
        raise ValueError("follow_scores: the model takes no pose video")
    T = model.config.frames
    if not pairs or any(p.frames != T for p in pairs):
        raise ValueError(f"follow_scores: needs pairs chosen for the model's {T}-frame clips")
    g = torch.Generator().manual_seed(int(seed))
    to_b, to_a = [], []
    for p in pairs:
        a, b, j = chunks[p.a], chunks[p.b], p.start
        clip = sample_chunk(model, b.pose[None, j : j + T], a.rgb[j][None], steps, g)[0, 1:]
        sil = segmenter(clip)
        to_b.append(iou(sil, bodies(b.pose[j + 1 : j + T])))
        to_a.append(iou(sil, bodies(a.pose[j + 1 : j + T])))
    return {"iou_pose": float(np.mean(to_b)), "iou_first_frame": float(np.mean(to_a)), "pairs": len(pairs)}
