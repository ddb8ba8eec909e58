"""Persistent entity references: a crop of each entity, kept and given to every chunk of a relay.

A relayed video is made chunk by chunk, each chunk starting from the last generated frame of the one before, so
what a body looks like is copied from a frame the model itself painted; errors in it compound over the relay
(appearance drift, a limitation the paper names). The remedy: each entity's look is taken from the first frame
that shows it (retaken only when a frame shows it at twice the size, "Which frame" below) and handed to every later
chunk beside its first frame.

- **Entities** are the render-id bands of the bridge's identity channel (``Rig.id_band``): the model's
  ``reference_bands``, the distinct bands of the corpus's layouts with overlapping ones merged (the monsters of
  a many-species corpus share one slot; two entities of one rig share a band and so a reference).
- **A reference** (4, r, r): the RGB (in [−1, 1]) of a square around the entity's pixels in the pose frame's id
  mask (its side 1.5 × the mask's larger extent plus two pixels, centred on the mask's box), bilinearly
  resampled to r × r, with the resampled mask as a fourth channel; where a sample touches the body (mask > 0) its
  colour is the body's pixels' alone (mask-weighted), so a body a few pixels across keeps its colour rather than a
  blend with the ground around it; all zeros where the entity has not been seen (mask 0 says "no reference").
- **Painted onto the bodies** (``paint``, a model's ``reference_paint``): besides being read as tokens, each
  entity's crop is laid over its pixels in every frame's pose frame — the crop's square fitted, as it was cut, to
  the box of the entity's mask in that frame, its body pixels where it has them and the crop's mean body colour
  elsewhere — so a token finds the look of the body it paints at its own pixels, with no search over slots.
- **Which frame**: the first frame in which the entity's mask has a pixel, then — an entity often comes into view a
  few pixels at a time, at the frame's edge or far off — retaken from the first later frame whose mask has at least
  ``RETAKE`` (2) × the pixels of the one it was last taken from, and so on: the best view so far, up a ladder of at
  most log₂ of the frame's pixels steps, never a look that changes frame to frame. In training, frames of the clip's
  own chunk up to the clip's start (never the frames the clip must paint); in a relay, the given first frame, then
  the generated frames as they are painted — an entity first seen in them, or seen larger than before, but never
  one whose crop is of the given frame: a painted view of a look the relay was given holds only that look and the
  model's errors (retaken from painted views, the error of the bodies the first frame showed grew by a third more;
  docs/tradeoffs.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from marionette.bridge.gbuffer import CODE_MAX

REF_PATCHES = 4  # a reference is 4 × 4 of the model's patches
MARGIN = 1.5  # the crop's side over the mask's larger extent
RETAKE = 2.0  # a reference is retaken from a view of its entity with this many times the pixels (docs/tradeoffs.md)


def merge_bands(bands: Iterable[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
    """Render-id bands [first, last], overlapping ones merged, in increasing order."""
    out: list[list[int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in bands):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return tuple((a, b) for a, b in out)


def layout_bands(layouts: Iterable) -> tuple[tuple[int, int], ...]:
    """The reference slots of a corpus: the id bands of every rendered entity of its layouts, merged."""
    return merge_bands(e.rig.id_band for layout in layouts for e in layout.entities if e.rig.id_band is not None)


def band_masks(pose: Tensor, bands: Sequence[tuple[int, int]]) -> Tensor:
    """Pose frames (…, 3, H, W) in [0, 1] → (…, E, H, W) bool: where each band's bones are drawn."""
    ids = torch.round(pose.narrow(-3, 1, 1) * CODE_MAX).long() * 255  # the 10-bit code of id / 255 → id (exact)
    ids = torch.div(ids + CODE_MAX // 2, CODE_MAX, rounding_mode="floor")
    return torch.cat([(ids >= a) & (ids <= b) for a, b in bands], dim=-3)


def crop(rgb: Tensor, mask: Tensor, size: int) -> Tensor:
    """RGB (3, H, W) and one entity's mask (H, W) with a pixel → its reference (4, size, size) (module doc)."""
    H, W = mask.shape
    ys, xs = torch.nonzero(mask, as_tuple=True)
    y0, y1, x0, x1 = float(ys.min()), float(ys.max()) + 1.0, float(xs.min()), float(xs.max()) + 1.0
    side = MARGIN * max(y1 - y0, x1 - x0) + 2.0
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    # grid_sample's normalised coordinates (align_corners=False): pixel edge 0 → −1, edge W → +1
    t = (torch.arange(size, dtype=torch.float32) + 0.5) / size - 0.5  # −½..½ across the crop
    gy = (cy + side * t) / H * 2 - 1
    gx = (cx + side * t) / W * 2 - 1
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], dim=-1)[None]  # (1, r, r, 2) as (x, y)
    m = mask[None].float()
    src = torch.cat([rgb.float(), rgb.float() * m, m], dim=0)[None]
    out = F.grid_sample(src, grid.to(src.device), mode="bilinear", padding_mode="zeros", align_corners=False)[0]
    # where a sample touches the body, the body's colour alone (its pixels' colours over their weights): a small
    # body's look is not washed out by what surrounds it; elsewhere the surroundings as they are
    body = out[6:7]
    return torch.cat([torch.where(body > 0, out[3:6] / body.clamp_min(1e-6), out[:3]), body], dim=0)


class EntityReferences:
    """The references of one video as it is read (training: a chunk; a relay: the frames it has so far): each band's
    crop from the first frame that shows it, retaken from a later frame that shows the entity with at least
    ``RETAKE`` × the pixels of the view it was last taken from (module doc, "Which frame")."""

    def __init__(self, bands: Sequence[tuple[int, int]], size: int) -> None:
        self.bands, self.size = tuple(bands), int(size)
        self.taken: list[list[tuple[int, Tensor]]] = [[] for _ in self.bands]  # every (frame, crop), in order
        self.pixels: list[int] = [0] * len(self.bands)  # the entity's mask pixels in the frame of its latest crop
        self.recorded: list[bool] = [False] * len(self.bands)  # whether its latest crop is of a recorded frame

    @property
    def crops(self) -> list[Tensor | None]:
        """Each entity's latest crop (None: not seen)."""
        return [t[-1][1] if t else None for t in self.taken]

    @property
    def frame(self) -> list[int | None]:
        """Where each entity's latest crop was taken (None: not seen)."""
        return [t[-1][0] if t else None for t in self.taken]

    def see(self, rgb: Tensor, pose: Tensor, offset: int = 0, painted: bool = False) -> None:
        """Read these frames (T, 3, H, W), the video's frames ``offset`` … ``offset`` + T − 1, in order: an entity not
        seen yet is taken from the first that shows it, one seen is retaken from the first that shows it with at
        least ``RETAKE`` × its pixels (and so on, up the ladder) — except from ``painted`` frames (a relay's own) one
        whose crop is of a recorded frame: a painted view of it, however large, is a copy of that look with the
        model's errors in it (module doc, "Which frame")."""
        if not len(rgb):
            return
        masks = band_masks(pose, self.bands)  # (T, E, H, W)
        area = masks.flatten(2).sum(-1)  # (T, E)
        for e in range(len(self.bands)):
            if painted and self.recorded[e]:
                continue
            t = 0
            while True:
                need = max(1, math.ceil(RETAKE * self.pixels[e]))  # 1 for an entity not seen yet
                hits = torch.nonzero(area[t:, e] >= need, as_tuple=True)[0]
                if not len(hits):
                    break
                t += int(hits[0])
                self.taken[e].append((offset + t, crop(rgb[t], masks[t, e], self.size)))
                self.pixels[e], self.recorded[e] = int(area[t, e]), not painted
                t += 1

    def tensor(self, upto: int | None = None) -> Tensor:
        """(E, 4, r, r): each entity's latest crop taken at a frame ≤ ``upto`` (the latest of all when None), zeros
        for an entity not seen by then."""
        out = torch.zeros(len(self.bands), 4, self.size, self.size)
        for e, taken in enumerate(self.taken):
            for frame, c in taken:
                if upto is not None and frame > upto:
                    break
                out[e] = c
        return out


def chunk_references(rgb: Tensor, pose: Tensor, bands: Sequence[tuple[int, int]], size: int) -> EntityReferences:
    """The references of a whole chunk (T, 3, H, W), every crop it takes kept; ``tensor(upto=start)`` gives a clip
    starting at ``start`` what a relay would have by then."""
    refs = EntityReferences(bands, size)
    refs.see(rgb, pose)
    return refs


def reference_sheet(refs: Tensor, height: int, width: int) -> Tensor:
    """Entity references (E, 4, r, r) as one image (3, H, W) in [−1, 1], for a backbone that takes a reference image
    (Wan-Fun's ``ref_conv``): each seen entity's crop, grey (0) outside its mask, resized to a square tile of side
    min(H, W // E) and laid left to right from the top-left corner of a grey canvas; an unseen entity's tile stays
    grey."""
    E = len(refs)
    side = min(int(height), int(width) // max(E, 1))
    if side < 1:
        raise ValueError(f"a {height}×{width} reference sheet has no room for {E} entities")
    sheet = torch.zeros(3, int(height), int(width))
    for e in range(E):
        rgb, mask = refs[e, :3], refs[e, 3:4]
        if not bool((mask > 0).any()):
            continue
        tile = F.interpolate((rgb * mask)[None], size=(side, side), mode="bilinear", align_corners=False)[0]
        sheet[:, :side, e * side : (e + 1) * side] = tile.clamp(-1.0, 1.0)
    return sheet


def boxes(masks: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Masks (…, H, W) bool → each mask's box as (y0, y1, x0, x1) in pixel edges (floats); an empty mask's is
    (0, H, 0, W)."""
    H, W = masks.shape[-2:]
    rows, cols = masks.any(-1), masks.any(-2)
    y0 = rows.float().argmax(-1).float()  # the first row with a pixel
    y1 = H - rows.flip(-1).float().argmax(-1).float()
    x0 = cols.float().argmax(-1).float()
    x1 = W - cols.flip(-1).float().argmax(-1).float()
    return y0, y1, x0, x1


def paint(refs: Tensor, pose: Tensor, bands: Sequence[tuple[int, int]]) -> Tensor:
    """Entity references (B, E, 4, r, r) and pose frames (B, T, 3, H, W) → (B, T, 4, H, W): each seen entity's crop
    laid over its mask in every frame (module doc; RGB, then 1 where a reference was laid), zeros elsewhere.

    The crop was cut as a square of side ``MARGIN`` × the mask's larger extent (+ 2 px) centred on its box; a frame's
    pixel (y, x) reads the crop where it would lie had the crop been cut from that frame: at ((y + ½ − cy) / side,
    (x + ½ − cx) / side) of the crop's extent, (cy, cx) and side from that frame's mask."""
    B, E = refs.shape[:2]
    T, H, W = pose.shape[1], pose.shape[-2], pose.shape[-1]
    masks = band_masks(pose.float(), bands)  # (B, T, E, H, W)
    y0, y1, x0, x1 = boxes(masks)
    side = MARGIN * torch.maximum(y1 - y0, x1 - x0) + 2.0  # (B, T, E)
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    ys = torch.arange(H, dtype=torch.float32, device=pose.device) + 0.5
    xs = torch.arange(W, dtype=torch.float32, device=pose.device) + 0.5
    # grid_sample's coordinates (align_corners=False): the crop's extent is −1..1, so twice the fraction of a side
    gy = 2 * (ys - cy[..., None]) / side[..., None]  # (B, T, E, H)
    gx = 2 * (xs - cx[..., None]) / side[..., None]  # (B, T, E, W)
    grid = torch.stack(torch.broadcast_tensors(gx[..., None, :], gy[..., :, None]), dim=-1)  # (B, T, E, H, W, 2)
    rgb, body = refs[:, :, :3].float(), refs[:, :, 3:].float()  # (B, E, ·, r, r)
    src = torch.cat([rgb * body, body], dim=2)  # the body's colour only (premultiplied by its mask)
    src = src[:, None].expand(B, T, *src.shape[1:]).reshape(B * T * E, *src.shape[2:])
    laid = F.grid_sample(src, grid.reshape(B * T * E, H, W, 2), mode="bilinear", padding_mode="zeros", align_corners=False)
    laid = laid.view(B, T, E, 4, H, W)
    weight = body.sum((-1, -2))  # (B, E, 1)
    mean = (rgb * body).sum((-1, -2)) / weight.clamp_min(1e-6)  # (B, E, 3): the crop's mean body colour
    seen = (weight[..., 0] > 0).float()[:, None, :, None, None, None]  # (B, 1, E, 1, 1, 1)
    on = masks[:, :, :, None].float() * seen  # (B, T, E, 1, H, W): this entity's pixels, where it has a reference
    colour = laid[:, :, :, :3] + mean[:, None, :, :, None, None] * (1 - laid[:, :, :, 3:])
    out = torch.cat([colour * on, on], dim=3).sum(2)  # bands are disjoint: at most one entity a pixel
    return out.to(refs.dtype)
