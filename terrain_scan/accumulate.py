"""Scanning one recording into per-cell terrain observations: depth back-projection plus ground contacts.

Two sources of evidence, both in world metres (Y up), binned into 1 m cells by floor(x), floor(z):

1. **Depth.** Every ``frame_stride``-th depth.mkv frame with a valid camera is read (``depth_frames``:
   the frames between are decoded only where a later frame is predicted from them), its codes
   de-quantised and decoded (``DepthDecoder``), and every valid pixel back-projected through the recorded pinhole camera. Pixel (row i, column j) has its
   centre at (u, v) = (j + ½, i + ½); in the OpenGL camera frame (x right, y up, looking down −Z)
   the point at z-depth z is ``p_cam = ((u − cx)/fx · z, −(v − cy)/fy · z, −z)`` and
   ``p_world = pos + R(rot) p_cam`` (``rot`` camera-to-world, xyzw). Points near a recorded
   skeleton (within the rig's capsule radius × ``mask_radius_scale`` + ``mask_margin_m`` of a bone,
   a bone being a kept joint and its rig parent) are characters, not ground, and are dropped; so are
   pixels whose normal in the frame's own pixel grid is steep (``frame_points``). The
   remaining points of a frame are reduced to their mean per ``voxel_m`` / 2 voxel, and those
   means of all frames to their mean per ``voxel_m`` voxel (``VoxelMeans``); outliers are removed
   (statistical, open3d), normals estimated over a radius of ``normal_radius_voxels`` voxels and oriented
   to +Y; points whose normal has ny ≥ ``min_normal_y`` (walkable, upward-facing) each give one
   observation of hit weight 1 at their own height, except those of a layer lying wholly within
   ``edge_m`` of a cell edge at the height of the cell across it: a neighbour's surface leaked a few
   centimetres over the edge (``edge_leaks``).
2. **Contacts.** A contact joint touching the ground marks the surface exactly: a leaf contact
   joint of an articulated rig (one with no kept child: the hunter's ``toe_tip_*``, the drake's
   ``claw_*``, ``jaw_tip``, ``tail10``) counts at a frame when it is at rest — speed below
   ``contact_speed`` m/s at every frame of a ±``contact_window`` frame window — and lies within
   ``contact_tol_m`` of the entity's lowest kept joint. It adds an observation of weight
   ``contact_hits`` at the joint's own (x, y, z), normal +Y. This assumes a planted contact joint
   lies on the surface (the synthetic game puts ``toe_tip_*`` and ``claw_*`` at 0 m while planted).

The observations are merged per cell with ``layers.merge``; their timestamp is the recording's
time (``recording_time``), never the wall clock.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from marionette.geometry import quat_to_matrix
from marionette.recordings.errors import SampleError
from marionette.recordings.wildworld import DEPTH_FILE, RGB_FILE, RecordedSample, SampleRef, read_sample
from marionette.schema import Layout

from ._points_kernel import character_hits, grid_points, voxel_add, voxel_table
from .depth import DepthDecoder, smooth_codes
from .image_points import subsampled
from .layers import AWAY, MERGE_M, Observations, aliases, layer_labels, merge
from .recording_video import depth_frames, recording_time

ALL_CODES = np.arange(256, dtype=np.uint8)
MIN_CONTACT_CELLS = 10  # a recording whose feet stood on this many cells, none of them seen as ground, has a wrong mapping


@dataclass
class ScanResult:
    """One recording's merged observations and what went into them."""

    observations: Observations
    recording_ts: int
    frames_total: int = 0  # depth frames read (after the stride)
    frames_used: int = 0
    frames_skipped_camera: int = 0  # frames whose recorded camera is invalid
    points_valid: int = 0  # back-projected pixels kept by the depth range, edge and steepness tests
    points_masked: int = 0  # of those, dropped as characters
    points_kept: int = 0  # after down-sampling, outlier removal, the normal test and the edge-leak test
    points_leaked: int = 0  # dropped as a neighbouring cell's surface leaked across a cell edge (``edge_leaks``)
    contacts_added: int = 0
    # how far the depth's ground stands above where the characters' feet stood (``contact_gap``), m; nan: no cell
    # held both. Metres off means the depth mapping is wrong for this recording (``marionette calibrate-depth``).
    contact_gap_m: float = float("nan")
    contact_gap_cells: int = 0  # cells where both the depth's ground and a contact were seen
    contact_cells: int = 0  # cells where a contact was seen

    def mapping_misfit(self, bound_m: float, min_contact_cells: int = MIN_CONTACT_CELLS) -> str | None:
        """Why the depth mapping does not fit this recording, or None: its ground stands further than ``bound_m``
        from the contacts, or no ground was seen on any of at least ``min_contact_cells`` contact cells."""
        gap = self.contact_gap_m
        if gap == gap and abs(gap) > bound_m:
            return (
                f"the scanned ground stands {gap:+.2f} m from where the characters' feet stood "
                f"({self.contact_gap_cells} cells; the bound is {bound_m:g} m)"
            )
        if gap != gap and self.contact_cells >= min_contact_cells:
            return f"the scan shows no ground on any of the {self.contact_cells} cells where the characters' feet stood"
        return None

    points: np.ndarray | None = field(default=None, repr=False)  # (P, 3) kept world points, if asked for

    def counters(self) -> dict[str, int]:
        keys = (
            "frames_total",
            "frames_used",
            "frames_skipped_camera",
            "points_valid",
            "points_masked",
            "points_kept",
            "points_leaked",
            "contacts_added",
        )
        return {k: getattr(self, k) for k in keys}


# ------------------------------------------------------------------------------------------------
# pure pieces


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (P, S) from points p (P, 3) to segments a→b (S, 3)."""
    ab = b - a  # (S, 3)
    ap = p[:, None, :] - a[None]  # (P, S, 3)
    t = np.clip(np.einsum("psk,sk->ps", ap, ab) / np.maximum(np.einsum("sk,sk->s", ab, ab), 1e-12)[None], 0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return np.sqrt(np.einsum("psk,psk->ps", d, d))


def character_mask(points: np.ndarray, bones: Iterable[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """(P,) bool: points within ``radius`` of a segment of some bone set [(a (S, 3), b (S, 3), radius)].

    A point is tested against a set only inside the set's bounding box (grown by the radius), and then only
    against the bones whose own grown box holds it (``_points_kernel.character_hits``), so a character filling
    the view costs about its points × the few bones near each, not × all of them."""
    sets = [(np.asarray(a, np.float64), np.asarray(b, np.float64), float(r)) for a, b, r in bones]
    if not sets or not len(points):
        return np.zeros(len(points), bool)
    a = np.concatenate([a for a, _, _ in sets])  # (S, 3) every set's bones, set after set
    b = np.concatenate([b for _, b, _ in sets])
    r = np.array([r for _, _, r in sets])
    lo = np.array([np.minimum(a.min(0), b.min(0)) - r for a, b, r in sets])  # (sets, 3) grown boxes
    hi = np.array([np.maximum(a.max(0), b.max(0)) + r for a, b, r in sets])
    first = np.cumsum([0] + [len(a) for a, _, _ in sets])
    return character_hits(np.ascontiguousarray(points, np.float64), a, b, r, lo, hi, first)


def entity_bones(sample: RecordedSample, layout: Layout, frame: int, radius_scale: float, margin_m: float):
    """Bones (segments kept joint → rig parent) of every entity valid at ``frame``, with mask radii."""
    out = []
    for e in layout.entities:
        t = sample.entities.get(e.name)
        if t is None or not t.valid[frame]:
            continue
        par = np.array(e.rig.parents)
        child = np.flatnonzero(par >= 0)
        J = t.joints_world[frame]
        if len(child):
            out.append((J[child], J[par[child]], e.rig.capsule_radius_m * radius_scale + margin_m))
        else:  # a single point
            out.append((J, J, e.rig.capsule_radius_m * radius_scale + margin_m))
    return out


def contact_positions(
    sample: RecordedSample, layout: Layout, speed: float = 0.2, window: int = 2, tol_m: float = 0.05
) -> np.ndarray:
    """(n, 3) world positions of every articulated entity's ground contacts (rule in the module docstring)."""
    parts = []
    dt_s = 1.0 / (sample.fps or 30.0)
    for e in layout.articulated:
        t = sample.entities.get(e.name)
        if t is None or not len(t.valid):
            continue
        par = set(e.rig.parents)
        leaves = [k for k in e.rig.contact_index if k not in par]
        if not leaves:
            continue
        J = t.joints_world  # (N, K, 3)
        P = J[:, leaves]  # (N, C, 3)
        v = np.full(P.shape[:2], np.inf)
        ok_pair = t.valid[1:] & t.valid[:-1]
        step = np.linalg.norm(P[1:] - P[:-1], axis=-1) / dt_s  # (N-1, C)
        # speed at frame i: the larger of the steps into and out of it (inf where a neighbour is invalid)
        sp = np.where(ok_pair[:, None], step, np.inf)
        v[1:] = sp
        v[:-1] = np.maximum(v[:-1], sp)
        if len(v) == 1:
            v[:] = np.inf
        slow = v < speed
        # at rest over the whole ±window
        rest = slow.copy()
        for d in range(1, window + 1):
            rest[d:] &= slow[:-d]
            rest[:-d] &= slow[d:]
            rest[:d] = False
            rest[len(rest) - d :] = False
        lowest = np.min(np.where(np.isfinite(J[..., 1]), J[..., 1], np.inf), axis=1)  # (N,), inf where absent
        low = (P[..., 1] - lowest[:, None]) <= tol_m
        ok = rest & low & t.valid[:, None] & np.isfinite(P).all(-1)
        fi, ci = np.nonzero(ok)
        parts.append(P[fi, ci])
    return np.concatenate(parts) if parts else np.zeros((0, 3))


GAP_CELL_M = 0.5  # the depth's ground and the contacts are compared on cells this small


def cell_keys(x: np.ndarray, z: np.ndarray, cell_m: float) -> np.ndarray:
    """One int64 per ``cell_m`` cell of world x, z (any within ±2·10⁹ cells of the origin)."""
    gx, gz = (np.floor(np.asarray(v) / cell_m).astype(np.int64) for v in (x, z))
    return gx * 4_294_967_296 + (gz + 2_147_483_648)


def contact_gap(ground: np.ndarray, contacts: np.ndarray, cell_m: float = GAP_CELL_M) -> tuple[float, int, int]:
    """How far the depth's ground points (P, 3) stand above the contacts (C, 3): over the ``cell_m`` cells holding
    both, the median of (the ground points' median height − the contacts' median height); how many cells held both;
    and how many held a contact (nan, 0, n when none held both). A right depth mapping puts the gap within
    centimetres, with ground seen on many contact cells; a wrong one, metres, or no ground where the feet stood."""
    if not len(contacts):
        return float("nan"), 0, 0
    kc, kg = cell_keys(contacts[:, 0], contacts[:, 2], cell_m), cell_keys(ground[:, 0], ground[:, 2], cell_m)
    common = np.intersect1d(kc, kg)
    if not len(common):
        return float("nan"), 0, len(np.unique(kc))

    def medians(keys: np.ndarray, y: np.ndarray) -> np.ndarray:
        m = np.isin(keys, common)
        order = np.lexsort((y[m], keys[m]))
        k, v = keys[m][order], y[m][order]
        starts = np.searchsorted(k, common)
        ends = np.searchsorted(k, common, side="right")
        return np.array([np.median(v[a:b]) for a, b in zip(starts, ends)])

    gaps = medians(kg, ground[:, 1]) - medians(kc, contacts[:, 1])
    return float(np.median(gaps)), len(common), len(np.unique(kc))


def contact_observations(q: np.ndarray, ts: int, hits: int = 1) -> Observations:
    """Ground contacts (``contact_positions``, (n, 3)) as observations of their cells: height exact, normal +Y,
    weight ``hits``."""
    if not len(q):
        return Observations.empty()
    return Observations(
        np.floor(q[:, 0]).astype(np.int64),
        np.floor(q[:, 2]).astype(np.int64),
        q[:, 1].copy(),
        np.tile([0.0, 1.0, 0.0], (len(q), 1)),
        np.full(len(q), hits, np.int64),
        np.full(len(q), ts, np.int64),
    )


def ground_cloud(
    means: np.ndarray,
    voxel_m: float,
    min_normal_y: float,
    normal_radius_voxels: float = 4.0,
    outlier_neighbors: int = 16,
    outlier_std: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """From a recording's voxel means (``VoxelMeans`` at ``voxel_m``, (V, 3)): drop outliers, estimate upward normals,
    keep walkable points: (P, 3) points, (P, 3) normals. open3d's steps give the same result on any number of
    threads."""
    if len(means) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3))
    # work relative to a local origin: world coordinates near x = −950 lose precision in float32
    origin = np.floor(means.min(0))
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor((means - origin).astype(np.float32)))
    kept = np.arange(len(means))
    if len(means) > outlier_neighbors:
        pc, inlier = pc.remove_statistical_outliers(nb_neighbors=outlier_neighbors, std_ratio=outlier_std)
        kept = np.flatnonzero(inlier.numpy())
    if len(kept) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pc.estimate_normals(max_nn=64, radius=normal_radius_voxels * voxel_m)
    pc.orient_normals_to_align_with_direction(o3d.core.Tensor(np.array([0.0, 1.0, 0.0], np.float32)))
    p = means[kept]
    n = pc.point.normals.numpy().astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    keep = (n[:, 1] >= min_normal_y) & np.isfinite(p).all(1) & np.isfinite(n).all(1)
    return p[keep], n[keep]


def edge_leaks(points: np.ndarray, edge_m: float = 0.1, merge_m: float = MERGE_M) -> np.ndarray:
    """(P,) bool: the points of layers that are a neighbouring cell's surface leaked across a cell edge.

    A surface that ends on a cell edge (a ledge's side, a wall's foot, a deck's rim) puts points a
    few centimetres into the next cell (depth error along the ray; measured up to 6 cm on the
    synthetic terraces), where they would make a layer metres from that cell's own surface. Points
    are grouped into per-cell layers by the merge rule (``layers.layer_labels``, each point one hit);
    a layer is a leak when all its points lie within ``edge_m`` of its cell's edges and the cell across
    one of those edges holds a layer within ``merge_m`` of its height with points away from every edge
    (``layers.aliases`` by position, as the stage applies it to the merged layers). Only the layer's
    position tells it apart: its hits can match the cell's own surface where that is seen sparsely.
    """
    if not len(points):
        return np.zeros(0, bool)
    gx, gz = np.floor(points[:, 0]).astype(np.int64), np.floor(points[:, 2]).astype(np.int64)
    bits = edge_bits(points, edge_m)
    order = np.lexsort((points[:, 1], gz, gx))
    label = np.empty(len(points), np.int64)
    label[order] = layer_labels(gx[order], gz[order], points[:, 1][order], np.ones(len(points)), merge_m)
    n = int(label.max()) + 1
    hits = np.bincount(label, minlength=n)
    h = np.bincount(label, weights=points[:, 1], minlength=n) / hits
    _, first = np.unique(label, return_index=True)  # a point of each layer, for its cell
    hugs = np.zeros(n, np.uint8)
    np.bitwise_or.at(hugs, label, bits)
    layers = Observations(gx[first], gz[first], h, np.tile([0.0, 1.0, 0.0], (n, 1)), hits, np.zeros(n, np.int64), hugs)
    return aliases(layers, merge_m, fraction=0.0)[label]  # by position only: the stage's rule on this recording's layers


def edge_bits(points: np.ndarray, edge_m: float) -> np.ndarray:
    """(P,) uint8 ``Observations.hugs`` of each point (x, y, z): the edges of its cell (floor(x), floor(z)) it lies
    within ``edge_m`` of, as ``layers.EDGES`` bits (west x, east x + 1, south z, north z + 1), or ``AWAY``."""
    fx, fz = points[:, 0] - np.floor(points[:, 0]), points[:, 2] - np.floor(points[:, 2])
    near = (fx < edge_m, fx >= 1 - edge_m, fz < edge_m, fz >= 1 - edge_m)
    out = np.zeros(len(points), np.uint8)
    for e, m in enumerate(near):
        out |= m.astype(np.uint8) << e
    out[out == 0] = AWAY
    return out


class VoxelMeans:
    """Running mean point of each occupied ``voxel_m`` voxel (indices floor(p / ``voxel_m``), world coordinates) of the
    points added so far; one pass over each batch (``_points_kernel.voxel_add``), memory in the voxels held."""

    def __init__(self, voxel_m: float, capacity: int = 1024):
        self.voxel_m = float(voxel_m)
        self.count = 0  # voxels held
        capacity = 1 << max(int(capacity) - 1, 1).bit_length()  # a power of 2, as the table's size must be
        self.index = np.empty((capacity, 3), np.int64)
        self.sums = np.zeros((capacity, 3))
        self.counts = np.zeros(capacity, np.int64)
        self.table = np.full(2 * capacity, -1, np.int64)

    def add(self, points: np.ndarray) -> None:
        """Add points (P, 3) (finite, float64) to their voxels' sums, in order."""
        points = np.ascontiguousarray(points, np.float64)
        done = 0
        while True:
            self.count, done = voxel_add(self.table, self.index, self.sums, self.counts, self.count, points, done, self.voxel_m)
            if done == len(points):
                return
            self._grow()

    def _grow(self) -> None:
        cap = 2 * len(self.counts)
        self.index = np.resize(self.index, (cap, 3))
        self.sums = np.concatenate([self.sums, np.zeros_like(self.sums)])
        self.counts = np.concatenate([self.counts, np.zeros_like(self.counts)])
        self.table = voxel_table(self.index, self.count, 2 * cap)

    def means(self, ordered: bool = True) -> np.ndarray:
        """(V, 3) the voxels' mean points: in (x, y, z) index order, or (``ordered`` False) in order of first appearance."""
        m = self.count
        mean = self.sums[:m] / self.counts[:m, None]
        if not ordered:
            return mean
        i = self.index[:m]
        return mean[np.lexsort((i[:, 2], i[:, 1], i[:, 0]))]


def voxel_reduce(points: np.ndarray, voxel_m: float, ordered: bool = True) -> np.ndarray:
    """Mean point of each occupied voxel, in (x, y, z) voxel order (or, ``ordered`` False, in order of first
    appearance): the per-frame reduction before the recording's voxel means (``VoxelMeans``)."""
    if not len(points):
        return np.zeros((0, 3))
    acc = VoxelMeans(voxel_m, capacity=max(1024, len(points) // 4))
    acc.add(points)
    return acc.means(ordered)


def frame_points(
    codes: np.ndarray,
    sample: RecordedSample,
    layout: Layout,
    i: int,
    decoder: DepthDecoder,
    max_depth_m: float = 20.0,
    smooth_radius: int = 3,
    smooth_tol: float = 1.0,
    edge_rel: float = 0.1,
    mask_radius_scale: float = 3.0,
    mask_margin_m: float = 0.3,
    image_normal_y: float = 0.8,
    subsample: int = 1,
) -> tuple[np.ndarray, int]:
    """One frame's non-character world points (P, 3) and how many valid points were masked as characters.

    ``subsample`` f > 1 keeps every f-th pixel of every f-th row (the one at offset f // 2 in each f × f
    block: codes are never interpolated, which would mix surfaces) with the intrinsics mapped to match
    (``subsampled``), so every later step costs about 1 / f² of the full frame's.

    The frame's camera must be valid. Codes are de-quantised (``smooth_codes``), pixels next to a
    depth edge dropped (their depth mixes two surfaces after smoothing), depths beyond ``max_depth_m``
    dropped (one code spans ~z²/511 m under the synthetic mapping: 0.8 m at 20 m). Pixels whose
    normal in the image (``image_normals`` of the back-projected grid, facing the camera) has
    ny < ``image_normal_y`` are dropped before any points are pooled: the rows of a distant vertical
    face, once pooled with other frames, look like horizontal strips to a neighbourhood normal, and
    the crease at a wall's foot or top mixes both surfaces; in the image they are still recognisably
    steep. The underside of a deck seen from below faces down and is dropped too. Everything after
    the de-quantising is one compiled pass over the pixels (``_points_kernel.grid_points``, whose
    numpy definition is ``grid_points_reference``).
    """
    codes, K = subsampled(codes, sample.camera_K[i], subsample)
    z_raw = decoder.decode(ALL_CODES)[codes]  # (H, W) float32: a code's depth, looked up
    z = decoder.decode(smooth_codes(codes, smooth_radius, smooth_tol)) if smooth_radius > 0 else z_raw
    R = quat_to_matrix(np.asarray(sample.camera_rot[i], dtype=np.float64))  # camera-to-world (3, 3)
    pos = np.asarray(sample.camera_pos[i], dtype=np.float64)
    P = grid_points(z, z_raw, np.asarray(K, np.float64), R, pos, max_depth_m, edge_rel, image_normal_y)
    m = character_mask(P, entity_bones(sample, layout, i, mask_radius_scale, mask_margin_m))
    return P[~m], int(m.sum())


# ------------------------------------------------------------------------------------------------
# the scan


def load_kernels() -> None:
    """Load the scan's compiled kernels (numba's cache) into this process, so that workers forked from it share
    them instead of each paying numba's start (about half a CPU-second a process)."""
    codes = np.full((3, 3), 100, np.uint8)
    K = np.array([1.0, 1.0, 1.5, 1.5])
    z = DepthDecoder().decode(smooth_codes(codes))
    P = grid_points(z, z, K, np.eye(3), np.zeros(3), 20.0, 0.1, 0.0)
    character_mask(P, [(P[:1], P[:1], 0.1)])
    voxel_reduce(P, 0.1, ordered=False)


def use_threads(n: int) -> None:
    """Let the scan's thread pools take at most ``n`` threads in this process: open3d's (its outlier and normal
    steps give the same result on any number). The numba kernels and numpy steps run on one thread, and
    BLAS sees only 3 × 3 products, which it never splits."""
    o3d.utility.set_max_threads(max(1, int(n)))


def scan_sample(
    sample: RecordedSample,
    layout: Layout,
    frames: Iterable[np.ndarray],
    decoder: DepthDecoder,
    recording_ts: int = 0,
    frame_stride: int = 1,
    voxel_m: float = 0.25,
    min_normal_y: float = 0.5,
    max_depth_m: float = 20.0,
    smooth_radius: int = 3,
    smooth_tol: float = 1.0,
    edge_rel: float = 0.1,
    normal_radius_voxels: float = 2.0,
    edge_m: float = 0.1,
    mask_radius_scale: float = 3.0,
    mask_margin_m: float = 0.3,
    image_normal_y: float = 0.8,
    contact_speed: float = 0.2,
    contact_window: int = 2,
    contact_tol_m: float = 0.05,
    contact_hits: int = 1,
    keep_points: bool = False,
    depth_subsample: int = 1,
) -> ScanResult:
    """Scan a read sample with its depth frames (codes, (H, W) uint8, one item per frame: those the stride leaves out
    may be None); see ``scan_recording``.
    ``depth_subsample``: ``frame_points``' ``subsample``."""
    res = ScanResult(Observations.empty(), int(recording_ts))
    stride = max(1, int(frame_stride))
    n = sample.n_frames
    voxels = VoxelMeans(voxel_m)  # the recording's voxels, the mean of each frame's half-size voxel means
    for i, codes in enumerate(frames):
        if i >= n:
            break
        if i % stride:
            continue
        res.frames_total += 1
        if sample.camera_valid is None or not sample.camera_valid[i]:
            res.frames_skipped_camera += 1
            continue
        P, masked = frame_points(
            codes,
            sample,
            layout,
            i,
            decoder,
            max_depth_m,
            smooth_radius,
            smooth_tol,
            edge_rel,
            mask_radius_scale,
            mask_margin_m,
            image_normal_y,
            depth_subsample,
        )
        res.frames_used += 1
        res.points_valid += len(P) + masked
        res.points_masked += masked
        voxels.add(voxel_reduce(P, voxel_m / 2, ordered=False))
    p, nrm = ground_cloud(voxels.means(), voxel_m, min_normal_y, normal_radius_voxels)
    leak = edge_leaks(p, edge_m)
    p, nrm = p[~leak], nrm[~leak]
    res.points_leaked = int(leak.sum())
    res.points_kept = len(p)
    if keep_points:
        res.points = p
    ts = res.recording_ts
    depth_obs = Observations(
        np.floor(p[:, 0]).astype(np.int64),
        np.floor(p[:, 2]).astype(np.int64),
        p[:, 1].copy(),
        nrm,
        np.ones(len(p), np.int64),
        np.full(len(p), ts, np.int64),
        edge_bits(p, edge_m),
    )
    contacts = Observations.empty()
    if n and sample.entities:
        q = contact_positions(sample, layout, contact_speed, contact_window, contact_tol_m)
        res.contact_gap_m, res.contact_gap_cells, res.contact_cells = contact_gap(p, q)
        contacts = contact_observations(q, ts, contact_hits)
    res.contacts_added = len(contacts)
    res.observations = merge(Observations.concat([depth_obs, contacts]))
    return res


def scan_recording(
    ref: SampleRef,
    layout: Layout,
    decoder: DepthDecoder,
    frame_stride: int = 1,
    voxel_m: float = 0.25,
    min_normal_y: float = 0.5,
    **options,
) -> ScanResult:
    """Scan one recording (``data_part<x>/<id>/``): its depth frames and contacts → merged observations.

    ``options`` are ``scan_sample``'s (depth range, character mask, contact rule, ``keep_points``).
    A missing depth.mkv raises SampleError; zero frames or only invalid cameras give empty depth
    observations without error.
    """
    sample = read_sample(ref, layout)
    depth = ref.path / DEPTH_FILE
    if not depth.exists():
        raise SampleError(f"{depth}: missing")
    ts = recording_time(ref.path / RGB_FILE)
    stride = max(1, int(frame_stride))
    frames = depth_frames(depth, keep=lambda i: i % stride == 0)
    return scan_sample(sample, layout, frames, decoder, ts, frame_stride, voxel_m, min_normal_y, **options)
