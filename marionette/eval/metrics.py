"""State-layer metrics (DESIGN "Evaluation definitions"): pure numpy over world skeletons, in metres.

Inputs are world skeletons as the rest of the project holds them (``corpus.world_of_rows``,
``geometry.state_to_world``, ``bridge.rules``): per entity an (N, K, 3) float array of world joints
(m, Y up), N frames, K the rig's kept joints, joint 0 the root of an articulated entity. An absent
entity holds NaN; a frame with a non-finite value is left out of a metric rather than counted (each
function says how). Everything is computed in float64 on differences, so a scene thousands of metres
from the origin, or at negative coordinates, gives the same numbers as one at the origin.

- ``ra_mpjpe``: root-aligned mean per-joint position error — world joints minus the world root,
  against the recorded ones, mean Euclidean distance (m) over frames and non-root joints.
- ``root_drift``: distance (m) between generated and recorded root at every frame of the horizon.
- ``bone_length_cv``: per bone, std / mean of its length over frames (population std), averaged over bones.
- ``foot_contacts`` / ``foot_skate``: local floor = rolling 1 s minimum of the foot height (centred:
  the frames within ±0.5 s); a frame is in contact when the foot is within 8 cm of that floor and its
  vertical speed is below 3 cm/frame; skate = mean horizontal foot speed (m/s) over contact frames.
  Speeds are backward differences (frame t − 1 → t), so frame 0 is never in contact.
- ``clearances`` / ``key_joint_clearances``: signed y_j − H (m), H the surface layer nearest the
  entity's root height (a joint under a bridge deck is measured against the layer the body stands on).
  Penetration = max(0, −clearance).
- ``contact_failure_rate`` (CFR): share of frames where any key joint lies below H − margin.
  ``mean_max_penetration`` (MMP): mean over frames of that frame's largest penetration.
- ``separation``: 3-D and horizontal (x, z) distance between two roots per frame.
- ``body_shares``: per entity, the pixels of its render ids over the frame's pixels (the G-buffer's id
  channel as ``bridge.gbuffer.decode_codes`` returns it: −1 background, 0 terrain, else a bone's id).

Validation: ``check_rollout_table`` (a rollout or state table against a layout), ``check_skeletons``
(world skeletons against a layout) and ``check_window`` (a window inside one segment's rows) raise a
ValueError naming the table or array and what is wrong.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from marionette.schema import Layout, Rig, check_layout, state_schema

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

CONTACT_HEIGHT_M = 0.08  # a foot within this of its local floor may be in contact (m)
CONTACT_VERTICAL_M_PER_FRAME = 0.03  # ... if its vertical speed is below this (m per frame of the sequence)
FLOOR_WINDOW_S = 1.0  # the local floor is the minimum foot height over this window, centred (s)
PENETRATION_MARGIN_M = 0.15  # CFR counts a key joint below H − this (m)
_MIN_BONE_M = 1e-9  # bones shorter than this on average have no defined CV and are left out (m)


class Surface(Protocol):
    """A layered surface: ``query(x, z, ref_y)`` → height (m) of the layer nearest ``ref_y``, NaN where
    unknown; inputs broadcast. ``terrain_scan.field.LayeredField`` is one."""

    def query(self, x: np.ndarray, z: np.ndarray, ref_y: np.ndarray) -> np.ndarray: ...


# -- array checks ----------------------------------------------------------------------------------------


def _points(name: str, a: ArrayLike, ndim: int) -> np.ndarray:
    """``a`` as float64 with ``ndim`` axes, the last of size 3, or a ValueError naming it."""
    x = np.asarray(a, np.float64)
    if x.ndim != ndim or x.shape[-1] != 3:
        want = {2: "(N, 3)", 3: "(N, K, 3)"}.get(ndim, f"{ndim} axes ending in 3")
        raise ValueError(f"{name}: shape {x.shape}, expected {want} world points (m)")
    return x


def _same_shape(names: tuple[str, str], a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{names[0]} has shape {a.shape} but {names[1]} has {b.shape}; they must match")


# -- pose and root -----------------------------------------------------------------------------------------


def ra_mpjpe_frames(
    joints_gen: ArrayLike, joints_rec: ArrayLike, roots_gen: ArrayLike | None = None, roots_rec: ArrayLike | None = None
) -> np.ndarray:
    """Per-frame root-aligned joint error (N,) (m): mean over joints of |(X − x) − (X_rec − x_rec)|.

    ``joints_*`` (N, K, 3) world joints. Without ``roots_*`` joint 0 is the root and is left out of the
    mean (its error is 0 by construction); with ``roots_*`` (N, 3) — e.g. an attachment's owner's root —
    every joint counts. NaN on frames where either side is not finite."""
    g, r = _points("joints_gen", joints_gen, 3), _points("joints_rec", joints_rec, 3)
    _same_shape(("joints_gen", "joints_rec"), g, r)
    if (roots_gen is None) != (roots_rec is None):
        raise ValueError("give both roots_gen and roots_rec, or neither (joint 0 is then the root)")
    if roots_gen is None:
        if g.shape[1] < 2:
            raise ValueError(f"joints_gen: shape {g.shape} holds only the root; no joint to compare")
        rel_g, rel_r = g[:, 1:] - g[:, :1], r[:, 1:] - r[:, :1]
    else:
        xg, xr = _points("roots_gen", roots_gen, 2), _points("roots_rec", roots_rec, 2)
        if xg.shape != (g.shape[0], 3) or xr.shape != (g.shape[0], 3):
            raise ValueError(f"roots_gen {xg.shape} and roots_rec {xr.shape} must be ({g.shape[0]}, 3), one root per frame")
        rel_g, rel_r = g - xg[:, None], r - xr[:, None]
    return np.linalg.norm(rel_g - rel_r, axis=-1).mean(axis=-1)  # (N,); NaN propagates per frame


def ra_mpjpe(
    joints_gen: ArrayLike, joints_rec: ArrayLike, roots_gen: ArrayLike | None = None, roots_rec: ArrayLike | None = None
) -> float:
    """RA-MPJPE (m): ``ra_mpjpe_frames`` averaged over the frames where both sides are finite; NaN if none."""
    per = ra_mpjpe_frames(joints_gen, joints_rec, roots_gen, roots_rec)
    ok = np.isfinite(per)
    return float(per[ok].mean()) if ok.any() else float("nan")


def root_drift(roots_gen: ArrayLike, roots_rec: ArrayLike) -> np.ndarray:
    """Distance (m) between generated and recorded root at each horizon frame: (..., H, 3) × 2 → (..., H)."""
    g, r = np.asarray(roots_gen, np.float64), np.asarray(roots_rec, np.float64)
    if g.ndim < 2 or g.shape[-1] != 3:
        raise ValueError(f"roots_gen: shape {g.shape}, expected (..., H, 3) world roots (m)")
    _same_shape(("roots_gen", "roots_rec"), g, r)
    return np.linalg.norm(g - r, axis=-1)


def bone_lengths(joints_world: ArrayLike, parents: tuple[int, ...] | list[int]) -> np.ndarray:
    """Length (m) of every bone (child, parent ≥ 0) per frame: (N, K, 3) → (N, B), bones in joint order."""
    j = _points("joints_world", joints_world, 3)
    par = np.asarray(parents, np.int64)
    if par.shape != (j.shape[1],):
        raise ValueError(f"parents: {par.shape[0] if par.ndim == 1 else par.shape} entries for {j.shape[1]} joints")
    if ((par < -1) | (par >= j.shape[1])).any():
        raise ValueError(f"parents: entries must lie in [-1, {j.shape[1] - 1}], got {par.tolist()}")
    child = np.flatnonzero(par >= 0)
    return np.linalg.norm(j[:, child] - j[:, par[child]], axis=-1)


def bone_length_cv(joints_world: ArrayLike, parents: tuple[int, ...] | list[int]) -> float:
    """Bone-length coefficient of variation: per bone std / mean of its length over the finite frames
    (population std), averaged over bones (dimensionless; 0 for a rigid skeleton). ``parents`` is the
    rig's parent table (``Rig.parents``, −1 at the top); bones of (near) zero mean length are left out.
    NaN if no bone qualifies."""
    lengths = bone_lengths(joints_world, parents)  # (N, B)
    lengths = lengths[np.isfinite(lengths).all(axis=1)]
    if not len(lengths):
        return float("nan")
    mean = lengths.mean(axis=0)
    keep = mean > _MIN_BONE_M
    if not keep.any():
        return float("nan")
    std = np.sqrt(((lengths[:, keep] - mean[keep]) ** 2).mean(axis=0))  # two-pass: no cancellation
    return float((std / mean[keep]).mean())


def separation(roots_a: ArrayLike, roots_b: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Distance between two entities' roots per frame: 3-D (m) and horizontal (x, z) (m); (..., 3) × 2 → (...) × 2."""
    a, b = np.asarray(roots_a, np.float64), np.asarray(roots_b, np.float64)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"roots_a: shape {a.shape}, expected (..., 3) world roots (m)")
    _same_shape(("roots_a", "roots_b"), a, b)
    d = b - a
    return np.linalg.norm(d, axis=-1), np.hypot(d[..., 0], d[..., 2])


# -- foot skate --------------------------------------------------------------------------------------------


def _feet(feet_world: ArrayLike) -> np.ndarray:
    f = np.asarray(feet_world, np.float64)
    if f.ndim == 2:
        f = f[:, None]
    return _points("feet_world", f, 3)  # (N, F, 3)


def local_floor(heights: ArrayLike, fps: float, window_s: float = FLOOR_WINDOW_S) -> np.ndarray:
    """Rolling minimum (m) of heights (N, ...) over the frames within ±window_s/2 of each frame
    (clipped at the ends; non-finite heights ignored; +inf where a window holds none)."""
    if fps <= 0 or window_s < 0:
        raise ValueError(f"fps must be > 0 and window_s ≥ 0, not fps={fps}, window_s={window_s}")
    y = np.asarray(heights, np.float64)
    half = int(np.floor(window_s * fps / 2 + 1e-9))  # frames on each side
    y = np.where(np.isfinite(y), y, np.inf)
    padded = np.pad(y, [(half, half)] + [(0, 0)] * (y.ndim - 1), constant_values=np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1, axis=0).min(axis=-1)


def foot_contacts(
    feet_world: ArrayLike,
    fps: float,
    contact_height_m: float = CONTACT_HEIGHT_M,
    max_vertical_m_per_frame: float = CONTACT_VERTICAL_M_PER_FRAME,
    window_s: float = FLOOR_WINDOW_S,
) -> np.ndarray:
    """Contact flags (N, F): the foot is within ``contact_height_m`` of its local floor (``local_floor``)
    and moved less than ``max_vertical_m_per_frame`` vertically since the previous frame. ``feet_world``
    (N, F, 3) or (N, 3) world foot joints (m) at ``fps``. Frame 0 (no previous frame) is never in contact."""
    f = _feet(feet_world)
    y = f[..., 1]
    floor = local_floor(y, fps, window_s)
    contact = np.zeros(y.shape, bool)
    vertical = np.abs(y[1:] - y[:-1])  # (N − 1, F) m/frame, frame t − 1 → t
    contact[1:] = (y[1:] - floor[1:] <= contact_height_m) & (vertical < max_vertical_m_per_frame)
    return contact


def foot_skate(
    feet_world: ArrayLike,
    fps: float,
    contact_height_m: float = CONTACT_HEIGHT_M,
    max_vertical_m_per_frame: float = CONTACT_VERTICAL_M_PER_FRAME,
    window_s: float = FLOOR_WINDOW_S,
) -> float:
    """Foot-skate (m/s): mean horizontal (x, z) foot speed over the contact frames of all feet
    (``foot_contacts``); speed at frame t = |xz_t − xz_{t−1}|·fps. NaN if no frame is in contact."""
    f = _feet(feet_world)
    contact = foot_contacts(f, fps, contact_height_m, max_vertical_m_per_frame, window_s)
    d = f[1:] - f[:-1]
    speed = np.hypot(d[..., 0], d[..., 2]) * fps  # (N − 1, F) m/s
    on = contact[1:]
    return float(speed[on].mean()) if on.any() else float("nan")


# -- penetration ---------------------------------------------------------------------------------------------


def nearest_layer(layers: ArrayLike, ref_y: ArrayLike) -> np.ndarray:
    """Of candidate layer heights (..., L) (m; NaN = no layer), the one nearest ``ref_y`` (...); ties pick
    the lower layer (as ``LayeredField.query`` does); NaN where there is none."""
    h = np.asarray(layers, np.float64)
    ref = np.broadcast_to(np.asarray(ref_y, np.float64), h.shape[:-1])
    dist = np.where(np.isfinite(h), np.abs(h - ref[..., None]), np.inf)
    best = dist.min(axis=-1, keepdims=True)
    cand = np.where(dist == best, h, np.inf)
    out = cand.min(axis=-1)
    return np.where(np.isfinite(out) & np.isfinite(best[..., 0]), out, np.nan)


def clearances(joints_world: ArrayLike, root_y: ArrayLike, surface: Surface | ArrayLike) -> np.ndarray:
    """Signed clearance y_j − H (N, K) (m) of joints (N, K, 3), H the surface layer nearest the entity's
    root height ``root_y`` (N,); NaN where H is unknown.

    ``surface``: a ``Surface`` (``terrain_scan.field.LayeredField``: the project's bilinear, layer-matched
    query, via ``field.joint_clearances``) or an array (N, K, L) of candidate layer heights under each
    joint (NaN = no layer), of which the one nearest the root height is taken."""
    j = _points("joints_world", joints_world, 3)
    ref = np.asarray(root_y, np.float64)
    if ref.shape != (j.shape[0],):
        raise ValueError(f"root_y: shape {ref.shape}, expected ({j.shape[0]},), the root height of each frame")
    if hasattr(surface, "query"):
        from terrain_scan.field import joint_clearances

        return joint_clearances(surface, j, ref)  # type: ignore[arg-type]
    layers = np.asarray(surface, np.float64)
    if layers.ndim != 3 or layers.shape[:2] != j.shape[:2]:
        raise ValueError(f"surface: layer heights of shape {layers.shape}, expected ({j.shape[0]}, {j.shape[1]}, L)")
    return j[..., 1] - nearest_layer(layers, ref[:, None])


def key_joint_clearances(joints_world: ArrayLike, rig: Rig, surface: Surface | ArrayLike) -> np.ndarray:
    """``clearances`` (N, C) of a rig's key ground-contact joints (``rig.contact_joints``, in that order),
    against the layer nearest the root (joint 0) height; ``joints_world`` (N, K, 3) all kept joints and,
    for an array ``surface``, its layers (N, K, L) under all of them."""
    j = _points("joints_world", joints_world, 3)
    if j.shape[1] != rig.n_keep:
        raise ValueError(f"joints_world: {j.shape[1]} joints, rig {rig.name!r} keeps {rig.n_keep}")
    if rig.kind != "articulated" or not rig.contact_joints:
        raise ValueError(f"rig {rig.name!r} has no root and key contact joints; penetration is measured on articulated rigs")
    return clearances(j, j[:, 0, 1], surface)[:, list(rig.contact_index)]


def penetration(clearance: ArrayLike) -> np.ndarray:
    """Penetration max(0, −clearance) (m), elementwise; NaN stays NaN (surface unknown)."""
    c = np.asarray(clearance, np.float64)
    return np.where(np.isfinite(c), np.maximum(0.0, -c), np.nan)


def _known_frames(clearance: ArrayLike) -> np.ndarray:
    c = np.asarray(clearance, np.float64)
    if c.ndim != 2:
        raise ValueError(f"clearance: shape {c.shape}, expected (N, C): frames × key joints")
    return c[np.isfinite(c).any(axis=1)]


def contact_failure_rate(clearance: ArrayLike, margin_m: float = PENETRATION_MARGIN_M) -> float:
    """CFR: share of frames where any key joint lies below H − ``margin_m`` (clearance < −margin), over
    the frames where the surface under at least one key joint is known; NaN if none. ``clearance`` (N, C) m."""
    c = _known_frames(clearance)
    if not len(c):
        return float("nan")
    with np.errstate(invalid="ignore"):
        return float((c < -margin_m).any(axis=1).mean())


def mean_max_penetration(clearance: ArrayLike) -> float:
    """MMP (m): mean over frames of the largest key-joint penetration that frame (0 when none penetrates),
    over the frames where the surface under at least one key joint is known; NaN if none."""
    p = penetration(_known_frames(clearance))
    if not len(p):
        return float("nan")
    return float(np.nanmax(p, axis=1).mean())


# -- the pose-control frame -------------------------------------------------------------------------------


def body_shares(ids: ArrayLike, layout: Layout, include_attachments: bool = False) -> dict[str, np.ndarray]:
    """Share of the frame's pixels that show each entity: pixels whose id is one of its rig's render ids
    (``Rig.bone_ids``) / all pixels. ``ids`` (..., H, W) integer ids as decoded from the G channel (−1
    background, 0 terrain); returns name → (...) float64. ``include_attachments`` counts an attachment's
    pixels for its owner (the weapon with the hunter) and drops the attachment's own entry.

    Ids name a rig's joint, not an instance: entities of one rig (two hunters) get the same value, the
    share of all of them together."""
    a = np.asarray(ids)
    if a.ndim < 2 or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"ids: shape {a.shape} dtype {a.dtype}, expected integer ids (..., H, W)")
    pixels = a.shape[-2] * a.shape[-1]
    if pixels == 0:
        raise ValueError(f"ids: shape {a.shape} holds no pixels")
    own: dict[str, list[int]] = {e.name: list(e.rig.bone_ids()) for e in layout.entities}
    if include_attachments:
        for e in layout.attachments:
            own[e.owner] += own.pop(e.name)  # type: ignore[index]
    return {n: np.isin(a, v).sum(axis=(-2, -1)) / pixels for n, v in own.items()}


# -- validation of real structures ---------------------------------------------------------------------------


def check_rollout_table(table: pa.Table, layout: Layout, where: str = "rollout table") -> None:
    """Fail with a ValueError naming ``where`` unless ``table`` is a state table of ``layout`` (a rollout
    as ``dynamics.rollout`` writes it, or recorded rows): its schema carries ``layout`` and every column
    of ``schema.state_schema(layout)`` is there with its type (the state a fixed list of ``layout.dim``)."""
    if not isinstance(table, pa.Table):
        raise ValueError(f"{where}: a pyarrow Table is expected, not {type(table).__name__}")
    check_layout(table.schema, layout, where)  # SchemaError (a ValueError) naming both layouts
    want = state_schema(layout)
    missing = [f.name for f in want if f.name not in table.schema.names]
    if missing:
        raise ValueError(f"{where}: lacks columns {missing} of layout {layout.scene!r}")
    for f in want:
        got = table.schema.field(f.name).type
        if got != f.type:
            raise ValueError(f"{where}: column {f.name!r} is {got}, layout {layout.scene!r} (dim {layout.dim}) needs {f.type}")
    if table.num_rows == 0:
        raise ValueError(f"{where}: holds no rows")


def check_skeletons(skeletons: Mapping[str, ArrayLike], layout: Layout, where: str = "skeletons") -> int:
    """Fail with a ValueError unless ``skeletons`` (name → (N, K, 3) world joints) holds every entity of
    ``layout`` with its rig's joint count and one frame count N; returns N."""
    names = [e.name for e in layout.entities]
    if missing := [n for n in names if n not in skeletons]:
        raise ValueError(f"{where}: lacks entities {missing} of layout {layout.scene!r}")
    if extra := sorted(set(skeletons) - set(names)):
        raise ValueError(f"{where}: entities {extra} are not in layout {layout.scene!r} ({names})")
    frames = {}
    for e in layout.entities:
        shape = np.shape(skeletons[e.name])
        if len(shape) != 3 or shape[1:] != (e.rig.n_keep, 3):
            raise ValueError(f"{where}[{e.name!r}]: shape {shape}, rig {e.rig.name!r} needs (N, {e.rig.n_keep}, 3)")
        frames[e.name] = shape[0]
    if len(set(frames.values())) > 1:
        raise ValueError(f"{where}: entities have different frame counts {frames}")
    return next(iter(frames.values()), 0)


def check_window(segment_rows: pa.Table, start: int, length: int, where: str = "window") -> None:
    """Fail with a ValueError unless frames [start, start + length) lie inside ``segment_rows`` — one
    segment's rows (``Corpus.dynamics_segment`` or ``read_segment``), which must hold one segment."""
    if "segment" not in segment_rows.column_names:
        raise ValueError(f"{where}: the segment table has no 'segment' column (columns {segment_rows.column_names[:6]}...)")
    segs = pc.unique(segment_rows["segment"]).to_pylist()
    if len(segs) != 1:
        raise ValueError(f"{where}: expected the rows of one segment, got {len(segs)} segments {segs[:5]}")
    n = segment_rows.num_rows
    if length < 1 or start < 0 or start + length > n:
        raise ValueError(
            f"{where}: frames [{start}, {start + length}) ({length} frames from frame {start}) do not fit in segment "
            f"{segs[0]!r}, which has {n} frames"
        )
