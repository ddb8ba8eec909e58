"""Reading one WildWorld-format sample (the public layout) into arrays a scene layout asks for.

A sample is ``data_part<x>/<id>/`` with ``rgb.mp4``, ``depth.mkv``, ``state.csv`` and
``skeleton.npz``; ``data_part<x>/skeleton_edges.json`` gives each skeleton type's edges. Columns of
state.csv hold scalars or Python tuple literals; invalid values are ``nan``. List columns are
0-based (``npc.list.0.*``), skeleton keys 1-based (``n1_<type_id>``).

Every error names the file and, where there is one, the row (1-based data row, header excluded)
and column, and is raised as ``SampleError`` so the caller can quarantine the sample.

Nothing is trusted: a sample directory, part or input file that is a symlink resolving outside the
source root is refused; a skeleton.npz member is inflated only after the zip directory and its .npy
header declare a float (N, J, 3) array the sample can need (N at most the state.csv rows plus
``FRAME_SLACK``, J at most ``MAX_JOINTS``) within the per-member byte cap; depth.mkv must open as a
video with as many frames as rgb.mp4, of the same size, within ``MAX_FRAME_PIXELS``, both
read from the headers before any frame is decoded.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv

from marionette.io import read_json
from marionette.recordings.errors import SampleError, SampleSkipped, regular_input
from marionette.recordings.skeleton_archive import MAX_MEMBER_BYTES, SkeletonArchive
from marionette.schema import FIELD_RANGES, Entity, Layout

RGB_FILE = "rgb.mp4"  # a sample's files
DEPTH_FILE = "depth.mkv"
STATE_FILE = "state.csv"
SKELETON_FILE = "skeleton.npz"
EDGES_FILE = "skeleton_edges.json"  # beside the samples of a part
STAGES_FILE = "stages.json"  # a tree's own stage map, at its root
REQUIRED_FILES = (RGB_FILE, DEPTH_FILE, STATE_FILE, SKELETON_FILE)
MAX_EDGES_BYTES = 16 << 20  # a skeleton_edges.json (a few KiB for WildWorld's 38 types) larger than this is refused unread
MAX_FRAME_PIXELS = 3840 * 2160  # default cap on a sample's video frame (IngestOptions.max_frame_pixels): 4K UHD
FRAME_SLACK = 64  # a member may declare this many frames beyond the state.csv rows (and is then reported as a count mismatch)


@dataclass(frozen=True)
class SampleRef:
    """Where a sample lives: ``root/part/sample_id``."""

    root: Path
    part: str
    sample_id: str

    @property
    def path(self) -> Path:
        return self.root / self.part / self.sample_id

    @property
    def name(self) -> str:
        """Recording id used throughout the corpus: ``<part>/<id>``."""
        return f"{self.part}/{self.sample_id}"

    @property
    def edges_path(self) -> Path:
        return self.root / self.part / EDGES_FILE


_KNOWN_FILES = {STAGES_FILE, EDGES_FILE}  # files of the layout that are not samples


def discover(source: Path, skipped: list | None = None) -> list[SampleRef]:
    """All sample directories under ``source`` (a root holding ``data_part*/`` or one part), sorted.

    Entries passed over (hidden names, files, directories that are not ``data_part<x>``) are appended
    to ``skipped`` as (path, reason) pairs when a list is given.
    """
    source = Path(source)
    if not source.is_dir():
        raise FileNotFoundError(f"{source}: source directory does not exist")

    def skip(p: Path, reason: str) -> None:
        if skipped is not None:
            skipped.append((str(p), reason))

    def why_not(p: Path, what: str) -> str | None:
        """Why ``p`` is not a ``what`` directory, or None when it is one."""
        if p.name.startswith("."):
            return f"hidden name (starts with '.'): not read as a {what}"
        if p.is_symlink() and not p.exists():
            return f"broken symlink (→ {p.readlink()})"
        if not p.is_dir():
            return f"not a directory: not read as a {what}"
        return None

    entries = sorted(source.iterdir())
    parts = [p for p in entries if why_not(p, "part") is None and p.name.startswith("data_part")]
    if not parts and source.name.startswith("data_part"):
        parts, source = [source], source.parent
    else:
        for p in entries:
            if p not in parts and p.name not in _KNOWN_FILES:
                skip(p, why_not(p, "part") or "not named data_part<x>: not read as a part")
    refs = []
    for part in parts:
        for d in sorted(part.iterdir()):
            reason = why_not(d, "sample")
            if reason is None:
                refs.append(SampleRef(source, part.name, d.name))
            elif d.name not in _KNOWN_FILES:
                skip(d, reason)
    return refs


def check_in_tree(ref: SampleRef) -> None:
    """Refuse a sample whose part, directory or input files are symlinks resolving outside the source root, or whose
    input files are not regular files."""
    root = Path(ref.root).resolve()
    for p in (ref.root / ref.part, ref.path, ref.edges_path, *(ref.path / f for f in REQUIRED_FILES)):
        if p.is_symlink():
            try:
                target = p.resolve()
            except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop
                raise SampleError(f"{p}: symlink cannot be resolved ({exc})") from None
            if not target.is_relative_to(root):
                raise SampleError(f"symlink leaves the source tree: {p} → {target}")
    for p in (ref.edges_path, *(ref.path / f for f in REQUIRED_FILES)):
        if p.exists():
            regular_input(p)


@dataclass
class EntityTrack:
    """One entity's recorded arrays over a sample's frames (float64 positions)."""

    type_id: np.ndarray  # (N,) float64, nan where absent
    joints_world: np.ndarray  # (N, K, 3) kept joints in rig keep order, float64
    valid: np.ndarray  # (N,) bool
    rot: np.ndarray | None = None  # (N, 4) xyzw (articulated only)
    pos: np.ndarray | None = None  # (N, 3)
    action: np.ndarray | None = None  # (N,) int32 composite id, 0 = no valid action
    motion_frame: np.ndarray | None = None  # (N,) int32, -1 where invalid
    hp: np.ndarray | None = None  # (N,) float32


@dataclass
class RecordedSample:
    """A sample read for one layout: per-entity tracks and the camera, all over N frames."""

    ref: SampleRef
    n_frames: int
    fps: float
    entities: dict[str, EntityTrack] = field(default_factory=dict)
    camera_K: np.ndarray | None = None  # (N, 4)
    camera_pos: np.ndarray | None = None  # (N, 3)
    camera_rot: np.ndarray | None = None  # (N, 4) camera-to-world xyzw, OpenGL camera frame
    camera_valid: np.ndarray | None = None  # (N,)
    video_size: tuple[int, int] = (0, 0)  # (height, width)

    @property
    def valid(self) -> np.ndarray:
        """Frames where every entity of the layout and the camera are valid."""
        v = self.camera_valid.copy()
        for t in self.entities.values():
            v &= t.valid
        return v


# ------------------------------------------------------------------------------------------------
# state.csv


def _list_prefix(kind: str, index: int) -> str:
    return {"m": "monster", "n": "npc"}[kind] + f".list.{index - 1}."


def _entity_columns(e: Entity, layout: Layout) -> dict[str, str]:
    """Column name (in state.csv) for each field an entity needs."""
    if e.articulated:
        p = _list_prefix(e.source_kind, e.source_index)
        return {f: p + f for f in ("type_id", "pos", "rot", "motion_bank_id", "motion_id", "motion_frame", "hp")}
    # an attachment (weapon): its type is the owner player's weapon_id
    owner = layout.entity(e.owner)
    return {"type_id": _list_prefix(owner.source_kind, owner.source_index) + "weapon_id"}


def _find_bad_row(path: Path, n_cols: int) -> str:
    """Locate the first row whose field count differs from the header (slow path, errors only)."""
    with open(path, newline="") as fh:
        for i, row in enumerate(csv.reader(fh)):
            if i and len(row) != n_cols:
                return f"row {i} (line {i + 1}) has {len(row)} fields, the header has {n_cols}"
    return "a row has the wrong number of fields"


def tuple_column(col: pa.ChunkedArray, width: int, path: Path, name: str) -> np.ndarray:
    """Parse a column of tuple literals '(a, b, c)' (or 'nan') into (N, width) float64, nan where invalid."""
    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    if pa.types.is_floating(col.type) or pa.types.is_integer(col.type) or pa.types.is_null(col.type):
        # a column with no valid tuple at all is read as numbers/nulls
        vals = col.cast(pa.float64()).to_numpy(zero_copy_only=False)
        if np.isfinite(vals).any():
            raise SampleError(f"{path}: column {name!r} holds scalars, expected {width}-tuples")
        return np.full((len(col), width), np.nan)
    stripped = pc.utf8_trim(col.fill_null("nan"), "() ")
    parts = pc.split_pattern(stripped, ",")
    lens = pc.list_value_length(parts).to_numpy(zero_copy_only=False)
    low = pc.utf8_lower(stripped).to_numpy(zero_copy_only=False)
    invalid = (lens == 1) & np.isin(low, ["nan", ""])
    bad = ~invalid & (lens != width)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise SampleError(f"{path}: row {r + 1}, column {name!r}: expected a {width}-tuple, got {col[r].as_py()!r}")
    out = np.full((len(col), width), np.nan)
    ok = np.flatnonzero(~invalid)
    if len(ok):
        flat = pc.utf8_trim_whitespace(pc.list_flatten(parts.take(pa.array(ok))))
        try:
            vals = flat.cast(pa.float64()).to_numpy(zero_copy_only=False)
        except pa.ArrowInvalid:
            strs = flat.to_numpy(zero_copy_only=False)
            for j, s in enumerate(strs):
                try:
                    float(s)
                except ValueError:
                    r = int(ok[j // width])
                    raise SampleError(f"{path}: row {r + 1}, column {name!r}: cannot parse {col[r].as_py()!r}") from None
            raise
        out[ok] = vals.reshape(-1, width)
    return out


def scalar_column(col: pa.ChunkedArray, path: Path, name: str) -> np.ndarray:
    """A numeric column as float64 (nan where invalid), naming the row of an unparsable cell."""
    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    if pa.types.is_null(col.type):
        return np.full(len(col), np.nan)
    if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
        try:
            return pc.utf8_trim_whitespace(col.fill_null("nan")).cast(pa.float64()).to_numpy(zero_copy_only=False)
        except pa.ArrowInvalid:
            for r, s in enumerate(col.to_pylist()):
                try:
                    float(s if s is not None else "nan")
                except ValueError:
                    raise SampleError(f"{path}: row {r + 1}, column {name!r}: not a number: {s!r}") from None
            raise
    return col.cast(pa.float64()).to_numpy(zero_copy_only=False)


def csv_header(path: Path) -> list[str]:
    """The column names of a state.csv (its first line only)."""
    try:
        with open(path, "rb") as fh:
            return next(csv.reader([fh.readline().decode("utf-8", "replace")]), [])
    except OSError as exc:
        raise SampleError(f"{path}: unreadable ({exc})") from None


def read_state_csv(path: Path, columns: list[str]) -> tuple[dict[str, pa.ChunkedArray], int]:
    """Read the named columns of a state.csv with pyarrow; malformed rows raise SampleError."""
    path = Path(path)
    if not path.exists():
        raise SampleError(f"{path}: missing")
    bad_rows: list[str] = []

    def on_bad(row):  # noqa: ANN001 — pyarrow's InvalidRow
        bad_rows.append(row.text)
        return "skip"

    header = csv_header(path)
    missing = [c for c in columns if c not in header]
    if missing:
        raise SampleError(f"{path}: header lacks columns {missing[:6]}{' ...' if len(missing) > 6 else ''}")
    tuple_like = {c: pa.string() for c in columns}
    try:
        table = pacsv.read_csv(
            path,
            parse_options=pacsv.ParseOptions(invalid_row_handler=on_bad),
            convert_options=pacsv.ConvertOptions(include_columns=columns, column_types=tuple_like, strings_can_be_null=False),
        )
    except pa.ArrowInvalid as exc:
        raise SampleError(f"{path}: not a readable CSV ({exc})") from None
    if bad_rows:
        raise SampleError(f"{path}: {_find_bad_row(path, len(header))}")
    return {c: table.column(c) for c in columns}, table.num_rows


# ------------------------------------------------------------------------------------------------
# edges, video (skeleton.npz: ``recordings.skeleton_archive``)


def load_edges(path: Path) -> dict[str, list[list[int]]]:
    """skeleton_edges.json: skeleton type key → [[parent, child], ...] (its size checked before it is read)."""

    try:
        d = read_json(Path(path), MAX_EDGES_BYTES)
    except FileNotFoundError:
        raise SampleError(f"{path}: missing") from None
    except ValueError as exc:  # too large, or not JSON: the message names the file
        raise SampleError(str(exc)) from None
    if not isinstance(d, dict):
        raise SampleError(f"{path}: not an object of skeleton type → edges")
    return d


def video_info(path: Path) -> tuple[int, float, int, int]:
    """(frame count, fps, height, width) of a video, counting packets (no decoding)."""
    path = Path(path)
    if not path.exists():
        raise SampleError(f"{path}: missing")
    regular_input(path)
    try:
        with av.open(str(path)) as c:
            s = c.streams.video[0]
            fps = float(s.average_rate or s.guessed_rate or 30)
            # MP4 headers carry the frame count; containers without one (e.g. Matroska) are counted
            # packet by packet. A header that overstates the frames is caught when chunks are decoded.
            n = s.frames or sum(1 for p in c.demux(s) if p.size > 0)
            return n, fps, s.codec_context.height, s.codec_context.width
    except (av.error.FFmpegError, IndexError) as exc:
        raise SampleError(f"{path}: unreadable video ({exc})") from None


# ------------------------------------------------------------------------------------------------


def _check_edges(path: Path, edges: dict, e: Entity) -> None:
    """The recording's skeleton edges must be exactly the rig's source tree (same joint order)."""
    key = e.rig.edges_key
    if key not in edges:
        raise SampleError(f"{path}: no edges for {key!r} (entity {e.name!r}, rig {e.rig.name!r}); keys: {sorted(edges)}")
    want = sorted((p, c) for c, p in enumerate(e.rig.source_parents) if p >= 0)
    try:
        got = sorted((int(p), int(c)) for p, c in edges[key])
    except (TypeError, ValueError):
        raise SampleError(f"{path}: {key!r} is not a list of [parent, child] index pairs") from None
    if got != want:
        diff = sorted(set(got) ^ set(want))[:4]
        raise SampleError(
            f"{path}: {key!r} edges differ from rig {e.rig.name!r} ({len(got)} vs {len(want)} edges; first differences {diff}): "
            "the joint order is not the one the rig declares"
        )


def check_range(values: np.ndarray, field: str, where: str, column: str = "") -> None:
    """A SampleError naming ``where``, the row (or frame and joint) and the value when a finite value of ``values`` lies
    outside its field's declared range (``schema.FIELD_RANGES``); ``column`` names a state.csv column (rows are
    1-based there), else ``values`` are a skeleton.npz member's (N, J, 3) joints."""
    rng = FIELD_RANGES[field]
    at = rng.first_outside(values)
    if at is None:
        return
    place = f"row {at[0] + 1}, column {column!r}" if column else f"frame {at[0]}, joint {at[1]}"
    raise SampleError(f"{where}: {place}: {values[at]:g} is outside the {field} range [{rng.low:g}, {rng.high:g}] {rng.unit}")


def mode_type(type_id: np.ndarray) -> int | None:
    """The type id recorded on most rows (nan rows aside), or None when every row is nan."""
    v = type_id[np.isfinite(type_id)]
    if not len(v):
        return None
    vals, counts = np.unique(v.astype(np.int64), return_counts=True)
    return int(vals[np.argmax(counts)])


def read_sample(
    ref: SampleRef,
    layout: Layout,
    type_filter: dict[str, set[int]] | None = None,
    max_member_bytes: int = MAX_MEMBER_BYTES,
    max_frame_pixels: int = MAX_FRAME_PIXELS,
) -> RecordedSample:
    """Read a sample for ``layout``: every entity's kept joints, rotations, actions, and the camera.

    ``type_filter`` maps an entity name to the type ids to accept (default: its rig's ``type_ids``);
    a sample whose entity has another type raises SampleSkipped. ``max_member_bytes`` caps one
    inflated skeleton.npz member, ``max_frame_pixels`` a video frame; depth.mkv's frames must be
    rgb.mp4's size. Every field's values are checked against its declared range (``schema.FIELD_RANGES``).
    """
    check_in_tree(ref)
    d = ref.path
    for f in REQUIRED_FILES:
        if not (d / f).exists():
            raise SampleError(f"{d / f}: missing")
    cols = ["camera.K", "camera.pos", "camera.rot"]
    per_entity = {e.name: _entity_columns(e, layout) for e in layout.entities}
    for m in per_entity.values():
        cols += list(m.values())
    raw, n = read_state_csv(d / STATE_FILE, cols)
    csv_path = d / STATE_FILE

    def tup(c: str, w: int) -> np.ndarray:
        return tuple_column(raw[c], w, csv_path, c)

    def num(c: str) -> np.ndarray:
        return scalar_column(raw[c], csv_path, c)

    npz = d / SKELETON_FILE
    skel = SkeletonArchive(npz, max_member_bytes)
    edges = load_edges(ref.edges_path)
    n_video, fps, vh, vw = video_info(d / RGB_FILE)
    n_depth, _, dh, dw = video_info(d / DEPTH_FILE)
    if vh * vw > max_frame_pixels:
        raise SampleError(
            f"{d / RGB_FILE}: {vw}×{vh} frames, more than the {max_frame_pixels:,}-pixel limit (--max-frame-pixels)"
        )
    if (dh, dw) != (vh, vw):  # checked from the headers: nothing is decoded
        raise SampleError(f"{d / DEPTH_FILE}: {dw}×{dh} frames; {RGB_FILE}'s are {vw}×{vh} (a depth video matches its RGB)")

    sample = RecordedSample(ref=ref, n_frames=n, fps=fps, video_size=(vh, vw))
    sample.camera_K = tup("camera.K", 4)
    sample.camera_pos = tup("camera.pos", 3)
    sample.camera_rot = tup("camera.rot", 4)
    check_range(sample.camera_K[:, :2], "focal", str(csv_path), "camera.K")
    check_range(sample.camera_K[:, 2:], "principal", str(csv_path), "camera.K")
    check_range(sample.camera_pos, "position", str(csv_path), "camera.pos")
    check_range(sample.camera_rot, "quaternion", str(csv_path), "camera.rot")
    sample.camera_valid = (
        np.isfinite(sample.camera_K).all(1) & np.isfinite(sample.camera_pos).all(1) & np.isfinite(sample.camera_rot).all(1)
    )
    counts = {"state.csv rows": n, "rgb.mp4 frames": n_video, "depth.mkv frames": n_depth}
    for e in layout.entities:
        c = per_entity[e.name]
        type_id = num(c["type_id"])
        t = mode_type(type_id)
        allowed = (type_filter or {}).get(e.name, set(e.rig.type_ids))
        if t is None:
            raise SampleError(f"{csv_path}: column {c['type_id']!r} is nan on every row: entity {e.name!r} never appears")
        if t not in allowed:
            raise SampleSkipped(f"{e.name} type {t} is outside the requested slice {sorted(allowed)}")
        key = f"{e.source_kind}{e.source_index}_{t}"
        if key not in skel:
            raise SampleError(f"{npz}: no key {key!r} for entity {e.name!r} (keys: {skel.keys})")
        shape, _ = skel.header(key)
        if len(shape) != 3 or shape[2] != 3 or shape[1] != len(e.rig.source_joints):
            raise SampleError(
                f"{npz}: key {key!r} has shape {shape}, rig {e.rig.name!r} expects (N, {len(e.rig.source_joints)}, 3)"
            )
        _check_edges(ref.edges_path, edges, e)
        arr = skel.read(key, max_frames=n + FRAME_SLACK)
        check_range(arr, "position", f"{npz}: key {key!r}")
        counts[f"skeleton.npz {key} frames"] = arr.shape[0]
        joints = arr[:, list(e.rig.keep_source_index), :].astype(np.float64) if arr.shape[0] == n else None
        if joints is None:
            continue
        present = np.isfinite(type_id) & (type_id == t)
        track = EntityTrack(type_id=type_id, joints_world=joints, valid=present & np.isfinite(joints).all(axis=(1, 2)))
        if e.articulated:
            track.rot = tup(c["rot"], 4)
            track.pos = tup(c["pos"], 3)
            bank, motion, mf = num(c["motion_bank_id"]), num(c["motion_id"]), num(c["motion_frame"])
            hp = num(c["hp"])
            for name, field, values in (
                ("pos", "position", track.pos),
                ("motion_bank_id", "motion_bank_id", bank),
                ("motion_id", "motion_id", motion),
                ("motion_frame", "motion_frame", mf),
                ("hp", "hp", hp),
            ):
                check_range(values, field, str(csv_path), c[name])
            ok = np.isfinite(bank) & np.isfinite(motion) & (bank >= 0) & (motion >= 0)
            track.action = np.where(ok, np.nan_to_num(bank) * 1000 + np.nan_to_num(motion) + 1, 0).astype(np.int32)
            track.motion_frame = np.where(np.isfinite(mf), np.nan_to_num(mf, nan=-1), -1).astype(np.int32)
            track.hp = hp.astype(np.float32)
            rn = np.linalg.norm(np.nan_to_num(track.rot), axis=1)
            track.valid &= np.isfinite(track.rot).all(1) & (rn > 0.5)
            bad_rot = np.isfinite(track.rot).all(1) & present & ((rn < 0.9) | (rn > 1.1))
            if bad_rot.any():
                r = int(np.flatnonzero(bad_rot)[0])
                raise SampleError(f"{csv_path}: row {r + 1}, column {c['rot']!r}: not a unit quaternion (norm {rn[r]:.3f})")
        sample.entities[e.name] = track
    if len(set(counts.values())) != 1:
        listed = ", ".join(f"{k} {v}" for k, v in counts.items())
        raise SampleError(f"{d}: frame counts disagree: {listed}")
    for e in layout.attachments:  # an attachment is only valid while its owner is
        sample.entities[e.name].valid &= sample.entities[e.owner].valid
    return sample
