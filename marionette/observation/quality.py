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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from marionette.bridge.gbuffer import CODE_MAX
from marionette.observation.data import Clip
from marionette.observation.model import VideoDiT, generate, sample_chunk
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


def copy_error(chunks: list[Clip], frames: int) -> float:
    """``relay_error`` of repeating the first frame (over the same frames)."""
    errs = []
    for ch in chunks:
        n = 1 + (len(ch.rgb) - 1) // (frames - 1) * (frames - 1)
        errs.append(float((ch.rgb[1:n] - ch.rgb[0]).abs().mean()))
    return float(np.mean(errs))


class Segmenter:
    """RGB frames (N, 3, H, W) in [−1, 1] → silhouettes (N, 1, H, W) in {0, 1} (module doc)."""

    def __init__(self, chunks: list[Clip], steps: int = 1500, batch: int = 64, seed: int = 0) -> None:
        rgb = torch.cat([c.rgb for c in chunks])
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
            )
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
            return (self.net(rgb) > 0).float()

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
