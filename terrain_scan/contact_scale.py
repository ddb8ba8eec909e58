"""The contact scale: one factor on every depth that puts the ground where the characters stood.

A body's thickness leaves the depth mapping's fit with a bias the joints alone cannot remove: a joint's offset and
the mapping's slope trade against each other over the narrow band of distances each species is seen at
(docs/tradeoffs.md). ``fit_contact_scale`` removes it with a reference that has no body in front of it: where a
character stood (the scan's contact rule), the depth must show ground at the height its feet had. Every depth point
of a recording that falls on one of that recording's contact cells gives one equation, and the scale s that
multiplies every depth (``DepthDecoder.scaled``, exact for every kind) is the least-absolute fit of them all: a
point at ``cam + s·(p − cam)`` should have the cell's contact height.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from marionette.recordings.wildworld import DEPTH_FILE, SampleRef, read_sample
from marionette.schema import Layout
from terrain_scan.accumulate import cell_keys, contact_positions, frame_points
from terrain_scan.depth import DepthDecoder
from terrain_scan.recording_video import depth_frames

CONTACT_CELL_M = 0.25  # contacts and depth points are compared on cells this small (slopes move a 1 m cell's points)
CONTACT_MIN_POINTS = 200  # fewer depth points on contact cells than this: no contact scale (noted)
CONTACT_ROUNDS = 3  # rounds of scaling, finding which cell each point falls in, and scaling again
CONTACT_SCALE_RANGE = (0.8, 1.25)  # a scale outside this is not applied: the contacts and the depth disagree


def _cell_key(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """One int64 per ``CONTACT_CELL_M`` cell of world x, z (``accumulate.cell_keys``)."""
    return cell_keys(x, z, CONTACT_CELL_M)


@dataclass
class ContactPoints:
    """Depth points on the small cells where a character stood, kept so that any depth scale can be tried without
    reading a video again: the camera (n, 3), the point's offset from it under the decoder it was read with
    (n, 3), its recording (n,), and per recording the sorted keys of its contact cells and their heights (median
    of the contacts in each)."""

    cam: np.ndarray
    off: np.ndarray
    rec: np.ndarray
    cells: list[tuple[np.ndarray, np.ndarray]]
    frames: int = 0

    def residuals(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every point that falls on a contact cell of its own recording once every depth is multiplied by
        ``s``: its height − the cell's contact height, the slope of that in s, and which cell (an index unique
        across recordings)."""
        p = self.cam + s * self.off
        key = _cell_key(p[:, 0], p[:, 2])
        r, slope, cell, base = [], [], [], 0
        for k, (keys, h) in enumerate(self.cells):
            m = self.rec == k
            if m.any() and len(keys):
                at = np.clip(np.searchsorted(keys, key[m]), 0, len(keys) - 1)
                hit = keys[at] == key[m]
                r.append(p[m][hit, 1] - h[at[hit]])
                slope.append(self.off[m][hit, 1])
                cell.append(base + at[hit])
            base += len(keys)
        cat = lambda x, dt=np.float64: np.concatenate(x).astype(dt) if x else np.zeros(0, dt)  # noqa: E731
        return cat(r), cat(slope), cat(cell, np.int64)


def contact_points(ref: SampleRef, layout: Layout, decoder: DepthDecoder, frame_stride: int, knobs: dict) -> ContactPoints:
    """One recording's ``ContactPoints``: its contacts (``contact_positions``) and every ``frame_stride``-th valid
    frame's ground points (``frame_points``, characters masked) read with ``decoder``; ``knobs`` are scan options
    (``ScanOptions.scan_kwargs()``; those the two steps read are used, the rest ignored)."""
    sample = read_sample(ref, layout)
    q = contact_positions(
        sample, layout, knobs.get("contact_speed", 0.2), knobs.get("contact_window", 2), knobs.get("contact_tol_m", 0.05)
    )
    keys, inv = np.unique(_cell_key(q[:, 0], q[:, 2]), return_inverse=True)
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(len(keys) + 1))
    heights = np.array([np.median(q[order[bounds[c] : bounds[c + 1]], 1]) for c in range(len(keys))])
    none = ContactPoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), [(keys, heights)])
    if not len(keys):
        return none
    # a point may move to a neighbouring cell under another scale: keep those on a contact cell or next to one
    near = np.unique(np.concatenate([keys + dx * 4_294_967_296 + dz for dx in (-1, 0, 1) for dz in (-1, 0, 1)]))
    point_knobs = (
        "max_depth_m",
        "smooth_radius",
        "smooth_tol",
        "edge_rel",
        "mask_radius_scale",
        "mask_margin_m",
        "image_normal_y",
    )
    kw = {k: knobs[k] for k in point_knobs if k in knobs}
    cams, offs, frames = [], [], 0
    for i, codes in enumerate(depth_frames(ref.path / DEPTH_FILE, keep=lambda i: i % frame_stride == 0)):
        if i >= sample.n_frames:
            break
        if i % frame_stride or sample.camera_valid is None or not sample.camera_valid[i]:
            continue
        frames += 1
        P, _ = frame_points(codes, sample, layout, i, decoder, subsample=knobs.get("depth_subsample", 1), **kw)
        on = np.isin(_cell_key(P[:, 0], P[:, 2]), near)
        cam = np.asarray(sample.camera_pos[i], np.float64)
        cams.append(np.broadcast_to(cam, (int(on.sum()), 3)))
        offs.append(P[on] - cam)
    if not cams:
        return replace(none, frames=frames)
    cam, off = np.concatenate(cams), np.concatenate(offs)
    return ContactPoints(cam, off, np.zeros(len(cam), np.int64), [(keys, heights)], frames)


@dataclass
class ContactScale:
    """What ``contact_scale`` found: the scale (1.0 where it was not applied, and why), the points and recordings
    it came from, and the median height of the depth above the contacts before and after (m)."""

    scale: float
    points: int
    recordings: int
    frames: int
    before_m: float
    after_m: float
    note: str = ""

    @property
    def applied(self) -> bool:
        return not self.note

    def summary(self) -> dict:
        return {k: getattr(self, k) for k in ("scale", "points", "recordings", "frames", "before_m", "after_m", "note")}

    def line(self) -> str:
        if not self.applied:
            return f"contact scale: not applied ({self.note})"
        return (
            f"contact scale: every depth × {self.scale:.5f}, from {self.points:,} depth points on contact cells of "
            f"{self.recordings} recording(s): the ground stands {100 * self.before_m:+.1f} cm from where the feet "
            f"stood before, {100 * self.after_m:+.1f} cm after"
        )


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The value where the weights ``w`` (≥ 0) on either side balance."""
    order = np.argsort(x, kind="stable")
    c = np.cumsum(w[order])
    return float(x[order][min(int(np.searchsorted(c, 0.5 * c[-1])), len(x) - 1)])


def fit_contact_scale(points: list[ContactPoints]) -> ContactScale:
    """The depth scale s that puts the recordings' ground where their characters stood: s minimises
    Σ |height(s) − contact height| over every point on a contact cell, each cell weighing as much as any other
    however many points it holds (a weighted median), the cells each point falls in found again under each
    round's scale (``CONTACT_ROUNDS``)."""
    parts = [p for p in points if len(p.cam)]
    frames = sum(p.frames for p in points)
    merged = ContactPoints(
        np.concatenate([p.cam for p in parts]) if parts else np.zeros((0, 3)),
        np.concatenate([p.off for p in parts]) if parts else np.zeros((0, 3)),
        np.concatenate([np.full(len(p.cam), k, np.int64) for k, p in enumerate(parts)]) if parts else np.zeros(0, np.int64),
        [p.cells[0] for p in parts],
        frames,
    )

    def cell_median(r: np.ndarray, cell: np.ndarray) -> float:
        w = 1.0 / np.bincount(cell)[cell]
        return weighted_median(r, w) if len(r) else float("nan")

    r0, _, c0 = merged.residuals(1.0)
    before = cell_median(r0, c0)
    s = 1.0
    for _ in range(CONTACT_ROUNDS):
        r, slope, cell = merged.residuals(s)
        ok = np.abs(slope) > 1e-6
        r, slope, cell = r[ok], slope[ok], cell[ok]
        if len(r) < CONTACT_MIN_POINTS:
            why = f"{len(r)} depth points on contact cells, fewer than {CONTACT_MIN_POINTS}"
            return ContactScale(1.0, len(r), len(parts), frames, before, before, why)
        # r = cam_y + s·off_y − h: each point asks for s − r / off_y, weighted by |off_y| (L1 through the origin)
        s = weighted_median(s - r / slope, np.abs(slope) / np.bincount(cell)[cell])
    lo, hi = CONTACT_SCALE_RANGE
    if not lo <= s <= hi:
        why = f"the contacts ask for × {s:.3f}, outside {lo}–{hi}: check the rigs' contact joints"
        return ContactScale(1.0, len(r0), len(parts), frames, before, before, why)
    r, _, cell = merged.residuals(s)
    return ContactScale(s, len(r), len(parts), frames, before, cell_median(r, cell))
