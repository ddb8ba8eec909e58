"""What a WildWorld recording tree holds, read without building anything, and rigs drafted from it.

``survey(source)`` reads each sample's state.csv type, camera and count columns, its skeleton.npz
directory and .npy headers and its videos' headers (no frame is decoded, no skeleton inflated) and
reports samples, hours, species / players / weapons with their frames, skeleton keys with joint
counts, invalid-camera rows, absent-monster frames and the files that are missing or unreadable.

``draft_rigs(source, report)`` then drafts a rig for every skeleton type seen (``draft_rig``): parents
from ``skeleton_edges.json``; the root (the one joint without a parent); the forward axis from the
root's motion taken into the entity's frame by its recorded rotation; the ground-contact joints (the
joints lowest while the body is lowest); a capsule radius from the bone lengths; every joint kept
unless a rule drops helpers (joints that sit on their parent, ``drop_shorter_than``). Joint names are
``j<index>``: the tree names none. It reads at most ``frames_per_type`` frames of each type. And a
scene per combination the samples hold (monster species, player, weapon), named
``<monster rig>_<weapon rig>`` (``em_29_wp_3``). Drafts are written in the layout of ``schemas/``
(``rigs/``, ``scenes/``) so ``--rigs DIR`` adds them to the built-in ones.

Render ids (the bridge's identity channel) are allotted by kind so drafted rigs never share one:
weapons 1–59, monsters 60–164, players 165–254 (WildWorld's largest types, 48 / 80 / 62 joints, fit).
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.compute as pc

from marionette.geometry import quat_to_matrix
from marionette.io import write_json
from marionette.recordings.errors import SampleError
from marionette.recordings.skeleton_archive import MAX_MEMBER_BYTES, SkeletonArchive
from marionette.recordings.wildworld import (
    DEPTH_FILE,
    REQUIRED_FILES,
    RGB_FILE,
    SKELETON_FILE,
    STATE_FILE,
    SampleRef,
    check_in_tree,
    csv_header,
    discover,
    load_edges,
    mode_type,
    read_state_csv,
    scalar_column,
    tuple_column,
    video_info,
)
from marionette.schema import (
    NAME_PATTERN,
    SCHEMA_DIR,
    Entity,
    Layout,
    Rig,
    SchemaError,
    build_layout,
    load_rig,
    load_scene,
    rig_from_json,
    scene_names,
)

Progress = Callable[[str, int, int], None]
SKELETON_KEY = re.compile(r"([mnw])([1-9][0-9]{0,2})_([0-9]{1,6})")
KIND_NAME = {"m": "monster", "n": "player", "w": "weapon"}
ID_BANDS = {"w": (1, 59), "m": (60, 164), "n": (165, 254)}
CONTACT_FRACTION = 0.25  # a leaf this share of the root's height above the lowest leaf still touches the ground
MOVING_M = 0.01  # root displacement per frame above which a frame says which way the body faces
JUMP_M = 1.0  # … and below which it is motion (above: a cut or a teleport)
RADIUS_PER_BONE = 0.5  # capsule radius = this × the median bone length (drake 0.22 m, hunter 0.07 m measured ≈ 0.5×)


def edges_key(kind: str, type_id: int) -> str:
    """The ``skeleton_edges.json`` key of a skeleton type: ``em_<id>``, ``npc`` (every player), ``wp_<id>``."""
    return {"m": f"em_{type_id}", "n": "npc", "w": f"wp_{type_id}"}[kind]


def _list_prefix(kind: str, index: int) -> str:
    return f"{'monster' if kind == 'm' else 'npc'}.list.{index - 1}."


@dataclass
class Survey:
    """What a tree holds (``survey``); ``to_json`` for the report file, ``lines`` for the terminal."""

    source: str
    samples: list[dict] = field(default_factory=list)  # per readable sample: id, frames, fps, keys (mode types)
    skipped: list[tuple[str, str]] = field(default_factory=list)  # entries that are not samples, and why
    problems: dict[str, list[str]] = field(default_factory=dict)  # sample → missing or unreadable files
    species: Counter = field(default_factory=Counter)  # monster type id → frames present
    players: Counter = field(default_factory=Counter)
    weapons: Counter = field(default_factory=Counter)
    skeletons: dict[str, dict] = field(default_factory=dict)  # "m_29" → {"edges_key", "joints", "frames", "samples"}
    invalid_camera_rows: int = 0
    absent_monster_frames: int = 0

    @property
    def frames(self) -> int:
        return sum(s["frames"] for s in self.samples)

    @property
    def hours(self) -> float:
        return sum(s["frames"] / s["fps"] for s in self.samples) / 3600.0

    def to_json(self) -> dict:
        return {
            "source": self.source,
            "samples": len(self.samples),
            "frames": self.frames,
            "hours": self.hours,
            "species": {str(k): v for k, v in sorted(self.species.items())},
            "players": {str(k): v for k, v in sorted(self.players.items())},
            "weapons": {str(k): v for k, v in sorted(self.weapons.items())},
            "skeletons": dict(sorted(self.skeletons.items())),
            "invalid_camera_rows": self.invalid_camera_rows,
            "absent_monster_frames": self.absent_monster_frames,
            "problems": self.problems,
            "skipped": [list(s) for s in self.skipped],
            "per_sample": self.samples,
        }

    def lines(self) -> list[str]:
        out = [
            f"{self.source}: {len(self.samples)} readable samples, {self.frames:,} frames, {self.hours:.2f} h"
            + (f"; {len(self.problems)} with missing or unreadable files" if self.problems else ""),
        ]
        for name, counts in (("species", self.species), ("players", self.players), ("weapons", self.weapons)):
            listed = ", ".join(f"{t} ({n:,} frames)" for t, n in sorted(counts.items())) or "none"
            out.append(f"{name:<8} {listed}")
        for key, s in sorted(self.skeletons.items()):
            out.append(
                f"skeleton {key:<8} {s['joints']:>3} joints  edges {s['edges_key']:<8} {s['frames']:>9,} frames in {s['samples']} samples"
            )
        total = max(1, self.frames)
        out.append(f"invalid camera rows {self.invalid_camera_rows:,} ({100 * self.invalid_camera_rows / total:.1f} %)")
        out.append(f"frames without a monster {self.absent_monster_frames:,} ({100 * self.absent_monster_frames / total:.1f} %)")
        for sample, reasons in sorted(self.problems.items()):
            for r in reasons:
                out.append(f"problem  {sample}: {r}")
        for path, reason in self.skipped:
            out.append(f"skipped  {path}: {reason}")
        return out


def survey(source: Path, progress: Progress | None = None, max_member_bytes: int = MAX_MEMBER_BYTES) -> Survey:
    """Read what every sample under ``source`` holds (headers and the type, camera and count columns only)."""
    out = Survey(source=str(source))
    refs = discover(Path(source), out.skipped)
    seen_samples: dict[str, set[str]] = defaultdict(set)
    for i, ref in enumerate(refs):
        try:
            info = _survey_sample(ref, out, max_member_bytes)
        except SampleError as exc:
            out.problems.setdefault(ref.name, []).append(str(exc))
        else:
            out.samples.append(info)
            for key in info["skeleton_keys"]:
                seen_samples[key].add(ref.name)
        if progress is not None:
            progress("survey", i + 1, len(refs))
    for key, names in seen_samples.items():
        out.skeletons[key]["samples"] = len(names)
    _check_edges(refs, out)
    return out


def _check_edges(refs: list[SampleRef], out: Survey) -> None:
    """Each part's skeleton_edges.json against the skeleton types its samples hold: a type without edges, or with
    a number of edges other than its joints less one, is a problem named with the file."""
    parts = {}
    for ref in refs:
        parts.setdefault(ref.part, ref.edges_path)
    for part, path in sorted(parts.items()):
        held = {k for s in out.samples if s["sample"].startswith(part + "/") for k in s["skeleton_keys"]}
        try:
            edges = load_edges(path)
        except SampleError as exc:
            out.problems.setdefault(f"{part}/skeleton_edges.json", []).append(str(exc))
            continue
        for key in sorted(held):
            s = out.skeletons[key]
            got = edges.get(s["edges_key"])
            if not isinstance(got, list):
                out.problems.setdefault(f"{part}/skeleton_edges.json", []).append(
                    f"{path}: no edges for {s['edges_key']!r} ({key} is recorded)"
                )
            elif len(got) != s["joints"] - 1:
                out.problems.setdefault(f"{part}/skeleton_edges.json", []).append(
                    f"{path}: {s['edges_key']!r} has {len(got)} edges; {key}'s {s['joints']} joints need {s['joints'] - 1}"
                )


def _survey_sample(ref: SampleRef, out: Survey, max_member_bytes: int) -> dict:
    check_in_tree(ref)
    missing = [f for f in REQUIRED_FILES if not (ref.path / f).is_file()]
    if missing:
        raise SampleError(f"{ref.path}: missing {', '.join(missing)}")
    n_video, fps, h, w = video_info(ref.path / RGB_FILE)
    video_info(ref.path / DEPTH_FILE)  # opens, or names the file
    csv_path = ref.path / STATE_FILE
    header = csv_header(csv_path)
    lists = {
        kind: sorted({int(m.group(1)) for c in header if (m := re.fullmatch(rf"{kind}\.list\.([0-9]+)\.type_id", c))})
        for kind in ("monster", "npc")
    }
    cols = ["camera.pos"] + [f"{k}.list.{i}.type_id" for k, idx in lists.items() for i in idx]
    cols += [f"npc.list.{i}.weapon_id" for i in lists["npc"] if f"npc.list.{i}.weapon_id" in header]
    raw, n = read_state_csv(csv_path, cols)
    cam_ok = pc.not_equal(pc.utf8_trim_whitespace(raw["camera.pos"]), "nan").to_numpy(zero_copy_only=False)
    out.invalid_camera_rows += int(n - cam_ok.sum())
    types: dict[str, np.ndarray] = {}
    for i in lists["monster"]:
        types[f"m{i + 1}"] = scalar_column(raw[f"monster.list.{i}.type_id"], csv_path, f"monster.list.{i}.type_id")
    for i in lists["npc"]:
        types[f"n{i + 1}"] = scalar_column(raw[f"npc.list.{i}.type_id"], csv_path, f"npc.list.{i}.type_id")
        if f"npc.list.{i}.weapon_id" in raw:
            types[f"w{i + 1}"] = scalar_column(raw[f"npc.list.{i}.weapon_id"], csv_path, f"npc.list.{i}.weapon_id")
    any_monster = np.zeros(n, bool)
    for slot, v in types.items():
        counts = Counter(int(t) for t in v[np.isfinite(v)])
        {"m": out.species, "n": out.players, "w": out.weapons}[slot[0]].update(counts)
        if slot[0] == "m":
            any_monster |= np.isfinite(v)
    out.absent_monster_frames += int(n - any_monster.sum())

    archive = SkeletonArchive(ref.path / SKELETON_FILE, max_member_bytes)
    keys = []
    for key in archive.keys:
        m = SKELETON_KEY.fullmatch(key)
        if m is None:
            out.problems.setdefault(ref.name, []).append(f"{archive.path}: key {key!r} is not <m|n|w><index>_<type id>")
            continue
        shape, _ = archive.header(key)
        if len(shape) != 3 or shape[2] != 3:
            raise SampleError(f"{archive.path}: key {key!r} has shape {shape}, not (frames, joints, 3)")
        kind, type_id = m.group(1), int(m.group(3))
        name = f"{kind}_{type_id}"
        s = out.skeletons.setdefault(name, {"edges_key": edges_key(kind, type_id), "joints": shape[1], "frames": 0, "samples": 0})
        if s["joints"] != shape[1]:
            out.problems.setdefault(ref.name, []).append(
                f"{archive.path}: key {key!r} has {shape[1]} joints where other samples' {name} have {s['joints']}"
            )
        slot = types.get(f"{kind}{m.group(2)}")
        s["frames"] += int(np.sum(slot == type_id)) if slot is not None else shape[0]
        keys.append(name)
    counts = {"state.csv rows": n, "rgb.mp4 frames": n_video}
    if len(set(counts.values())) != 1:
        out.problems.setdefault(ref.name, []).append(f"{ref.path}: frame counts disagree: state.csv {n}, rgb.mp4 {n_video}")
    return {
        "sample": ref.name,
        "frames": n,
        "fps": fps,
        "size": [h, w],
        "skeleton_keys": sorted(set(keys)),
        "types": {slot: mode_type(v) for slot, v in types.items()},
    }


# ------------------------------------------------------------------------------------------------ drafting


@dataclass(frozen=True)
class DraftRules:
    """How a draft keeps joints: all of them, less the helpers that sit on their parent."""

    drop_shorter_than: float = 0.0  # drop a joint whose median distance to its parent is below this (m); 0 keeps all
    frames_per_type: int = 3000  # frames of each skeleton type read to draft it

    def __post_init__(self) -> None:
        if not (np.isfinite(self.drop_shorter_than) and self.drop_shorter_than >= 0):
            raise ValueError(f"drop_shorter_than must be a length ≥ 0 m, not {self.drop_shorter_than}")
        if self.frames_per_type < 10:
            raise ValueError(f"frames_per_type must be at least 10, not {self.frames_per_type}")


def parents_from_edges(edges: list, n_joints: int, where: str) -> list[int]:
    """Each joint's parent (−1 at the root) from [[parent, child], ...]: one root, one parent per joint, no cycle."""
    parents = [-2] * n_joints
    for k, e in enumerate(edges):
        if not (isinstance(e, list | tuple) and len(e) == 2 and all(isinstance(v, int) and 0 <= v < n_joints for v in e)):
            raise SchemaError(f"{where}: edge {k} {e!r} is not [parent, child] with joints in 0..{n_joints - 1}")
        p, c = e
        if parents[c] != -2:
            raise SchemaError(f"{where}: joint {c} has two parents ({parents[c]} and {p})")
        parents[c] = p
    roots = [j for j, p in enumerate(parents) if p == -2]
    if len(roots) != 1:
        raise SchemaError(f"{where}: {len(roots)} joints without a parent ({roots[:8]}); a skeleton has one root")
    parents[roots[0]] = -1
    for j in range(n_joints):
        seen, p = 0, j
        while p != -1:
            p, seen = parents[p], seen + 1
            if seen > n_joints:
                raise SchemaError(f"{where}: joint {j} is on a cycle")
    return parents


def draft_rig(
    kind: str,
    type_ids: list[int],
    edges: list,
    joints: np.ndarray,
    rot: np.ndarray | None = None,
    rules: DraftRules | None = None,
    where: str = "<edges>",
) -> tuple[dict, dict]:
    """A rig (its JSON) for a skeleton type from its edges and recorded frames: ``joints`` (F, J, 3) world metres,
    ``rot`` (F, 4) the recorded rotation (x, y, z, w) of an articulated entity; a row of nan separates recordings.
    Returns (rig JSON, what was
    measured: forward agreement, contact shares, bone lengths)."""

    rules = rules or DraftRules()
    J = joints.shape[1]
    parents = parents_from_edges(edges, J, where)
    names = [f"j{j:02d}" for j in range(J)]
    root = parents.index(-1)
    ok = np.isfinite(joints).all(axis=(1, 2))
    if rot is not None:
        ok &= np.isfinite(rot).all(1)
    X = joints[ok].astype(np.float64)
    if len(X) < 2:
        raise SchemaError(f"{where}: fewer than 2 frames with every joint finite: nothing to measure")
    bone = np.array([np.median(np.linalg.norm(X[:, j] - X[:, p], axis=-1)) if p >= 0 else 0.0 for j, p in enumerate(parents)])
    lengths = bone[[j for j, p in enumerate(parents) if p >= 0]]
    radius = float(np.round(RADIUS_PER_BONE * np.median(lengths[lengths > 1e-3]) if (lengths > 1e-3).any() else 0.05, 3))
    keep_idx = [root] + [j for j in range(J) if j != root and not (bone[j] < rules.drop_shorter_than)]
    measured: dict = {"frames": int(len(X)), "median_bone_m": float(np.median(lengths)) if len(lengths) else 0.0}
    forward, contacts = [0.0, 0.0, 1.0], []
    if kind != "w":
        # forward: the root's displacement in the entity's own frame, where it moves (pairs of consecutive valid
        # frames only: a nan row separates samples; a jump of more than JUMP_M is a cut, not motion)
        pair = ok[1:] & ok[:-1]
        d = np.diff(joints[:, root].astype(np.float64), axis=0)[pair]
        R = quat_to_matrix(rot[1:][pair])
        local = np.einsum("fji,fj->fi", R, d)  # Rᵀ d
        speed = np.linalg.norm(local[:, [0, 2]], axis=1)
        moving = (speed > MOVING_M) & (np.linalg.norm(d, axis=1) < JUMP_M)
        if moving.sum() >= 5:
            v = (local[moving][:, [0, 2]] * speed[moving, None]).sum(0)
            v = v / max(np.linalg.norm(v), 1e-12)
            axes = {"+x": (1.0, 0.0), "-x": (-1.0, 0.0), "+z": (0.0, 1.0), "-z": (0.0, -1.0)}
            best = max(axes, key=lambda a: v @ np.array(axes[a]))
            agree = float(v @ np.array(axes[best]))
            measured["forward_agreement"] = agree
            ax = axes[best] if agree > 0.9 else (float(v[0]), float(v[1]))
            forward = [round(ax[0], 4), 0.0, round(ax[1], 4)]
        else:
            measured["forward_agreement"] = None
        # contacts: the ends of chains (leaves) that hang lowest below the root, typically (median over frames,
        # so the slopes a body stands on up and down even out): within CONTACT_FRACTION of the root's height
        # above the lowest of them
        below = np.median(X[..., 1] - X[:, root, None, 1], axis=0)
        leaves = [j for j in range(J) if j not in parents and j in keep_idx]
        lowest = min(below[j] for j in leaves)
        contacts = [names[j] for j in leaves if below[j] <= lowest * (1.0 - CONTACT_FRACTION)]
        measured["lowest_leaves_m"] = {names[j]: round(float(below[j]), 3) for j in sorted(leaves, key=lambda j: below[j])[:8]}
    name = edges_key(kind, type_ids[0])
    band = ID_BANDS[kind]
    rig = {
        "name": name,
        "description": f"drafted by marionette survey from {len(X)} frames of {name} (review before use)",
        "kind": "attachment" if kind == "w" else "articulated",
        "edges_key": name,
        "type_ids": sorted(type_ids),
        "source_joints": names,
        "source_parents": parents,
        "keep": [names[j] for j in keep_idx],
        "root": names[root],
        "forward_axis": forward,
        "contact_joints": contacts,
        "capsule_radius_m": radius if kind != "w" else float(np.round(min(radius, 0.06), 3)),
        "id_band": list(band),
    }
    n_bones = len(keep_idx) - 1
    if n_bones > band[1] - band[0] + 1:
        raise SchemaError(f"{where}: {name} keeps {len(keep_idx)} joints, more than its render ids {list(band)} hold")
    rig_from_json(rig, f"draft {name}")  # a draft is a valid rig
    return rig, measured


def _entity_frames(ref: SampleRef, key: str, limit: int, max_member_bytes: int) -> tuple[np.ndarray, np.ndarray | None]:
    """A skeleton key's frames in one sample where its entity is present, with its recorded rotation."""
    m = SKELETON_KEY.fullmatch(key)
    kind, index, type_id = m.group(1), int(m.group(2)), int(m.group(3))
    owner = "n" if kind == "w" else kind
    prefix = _list_prefix(owner, index)
    cols = [prefix + ("weapon_id" if kind == "w" else "type_id")] + ([prefix + "rot"] if kind != "w" else [])
    csv_path = ref.path / STATE_FILE
    raw, n = read_state_csv(csv_path, cols)
    present = scalar_column(raw[cols[0]], csv_path, cols[0]) == type_id
    arr = SkeletonArchive(ref.path / SKELETON_FILE, max_member_bytes).read(key, max_frames=n + 64)
    if arr.shape[0] != n:
        raise SampleError(f"{ref.path / SKELETON_FILE}: {key!r} has {arr.shape[0]} frames, state.csv {n} rows")
    rot = None
    if kind != "w":
        rot = tuple_column(raw[cols[1]], 4, csv_path, cols[1])
    at = np.flatnonzero(present)[:limit]
    return arr[at], (rot[at] if rot is not None else None)


def draft_rigs(
    source: Path, report: Survey, rules: DraftRules | None = None, progress: Progress | None = None
) -> tuple[dict[str, dict], dict[str, dict], dict[str, str]]:
    """Draft a rig per skeleton type the survey saw and a scene per combination its samples hold.

    Returns (rigs by name, scenes by name, problems by skeleton type)."""
    rules = rules or DraftRules()
    refs = {r.name: r for r in discover(Path(source))}
    by_type: dict[tuple[str, str], list[tuple[str, str]]] = defaultdict(list)  # (kind, edges key) → [(sample, npz key)]
    type_ids: dict[tuple[str, str], set[int]] = defaultdict(set)
    for s in report.samples:
        for slot, t in s["types"].items():
            if t is not None:
                key = (slot[0], edges_key(slot[0], t))
                by_type[key].append((s["sample"], f"{slot}_{t}"))
                type_ids[key].add(t)
    rigs, problems = {}, {}
    for i, ((kind, ekey), where) in enumerate(sorted(by_type.items())):
        frames, rots = [], []
        budget = rules.frames_per_type
        edges = None
        try:
            for sample, npz_key in where:
                if budget <= 0:
                    break
                ref = refs[sample]
                all_edges = load_edges(ref.edges_path)
                if ekey not in all_edges:
                    raise SampleError(f"{ref.edges_path}: no edges for {ekey!r} (keys: {sorted(all_edges)})")
                if edges is not None and sorted(map(tuple, all_edges[ekey])) != sorted(map(tuple, edges)):
                    raise SampleError(f"{ref.edges_path}: {ekey!r} edges differ from another part's")
                edges = all_edges[ekey]
                x, r = _entity_frames(ref, npz_key, budget, MAX_MEMBER_BYTES)
                frames += [x, np.full((1, *x.shape[1:]), np.nan, x.dtype)]
                if r is not None:
                    rots += [r, np.full((1, 4), np.nan)]
                budget -= len(x)
            X = np.concatenate(frames)
            rig, measured = draft_rig(
                kind, sorted(type_ids[(kind, ekey)]), edges, X, np.concatenate(rots) if rots else None, rules, where=ekey
            )
            rig["measured"] = measured
            rigs[rig["name"]] = rig
        except (SampleError, SchemaError, ValueError, TypeError) as exc:  # TypeError: edges that are not pairs
            problems[ekey] = str(exc)
        if progress is not None:
            progress("draft rigs", i + 1, len(by_type))
    scenes = {}
    for s in report.samples:
        t = s["types"]
        m, n, w = (t.get(k) for k in ("m1", "n1", "w1"))
        if None in (m, n, w):
            continue
        names = (edges_key("m", m), edges_key("n", n), edges_key("w", w))
        if not all(x in rigs for x in names):
            continue
        scene = f"{names[0]}_{names[2]}"
        scenes[scene] = {
            "name": scene,
            "description": f"drafted by marionette survey: monster {m}, a player, weapon {w}",
            "entities": [
                {"name": "monster", "rig": names[0], "source": {"kind": "m", "index": 1}},
                {"name": "hunter", "rig": names[1], "source": {"kind": "n", "index": 1}},
                {"name": "weapon", "rig": names[2], "source": {"kind": "w", "index": 1}, "owner": "hunter"},
            ],
        }
    return rigs, scenes, problems


def write_drafts(out: Path, rigs: dict[str, dict], scenes: dict[str, dict]) -> list[Path]:
    """Write drafted rigs to ``out/rigs/`` and scenes to ``out/scenes/`` (atomically); returns the files."""
    written = []
    for sub, items in (("rigs", rigs), ("scenes", scenes)):
        (Path(out) / sub).mkdir(parents=True, exist_ok=True)
        for name, d in sorted(items.items()):
            path = Path(out) / sub / f"{name}.json"
            write_json(path, d)
            written.append(path)
    return written


# ------------------------------------------------------------------------------------------------ a recording's layout


def rig_index(rigs: Path | None = None) -> dict[str, Rig]:
    """Every rig there is by its edges key: a user's (``<rigs>/rigs/*.json``) over the built-in ones."""

    out: dict[str, Rig] = {}
    for d in [SCHEMA_DIR] + ([Path(rigs)] if rigs is not None else []):
        for f in sorted((Path(d) / "rigs").glob("*.json")):
            if NAME_PATTERN.fullmatch(f.stem):
                rig = load_rig(f.stem, SCHEMA_DIR, None if Path(d) == SCHEMA_DIR else Path(d))
                out[rig.edges_key] = rig
    return out


def recording_layout(ref: SampleRef, rigs: Path | None = None, index: dict[str, Rig] | None = None) -> Layout:
    """The layout of what one recording holds: its monster's, player's and weapon's rigs (by edges key, the type
    recorded most often; ``rig_index``), in the duel's order. A built-in scene of the same rigs keeps its name
    (``duel``); another is named ``<monster rig>_<weapon rig>``, as survey names its drafts. A type no rig
    declares is a SampleError naming it."""

    index = rig_index(rigs) if index is None else index
    cols = {"m": "monster.list.0.type_id", "n": "npc.list.0.type_id", "w": "npc.list.0.weapon_id"}
    csv_path = ref.path / STATE_FILE
    raw, _ = read_state_csv(csv_path, list(cols.values()))
    picked = {}
    for kind, col in cols.items():
        t = mode_type(scalar_column(raw[col], csv_path, col))
        if t is None:
            raise SampleError(f"{csv_path}: column {col!r} is nan on every row")
        key = edges_key(kind, t)
        rig = index.get(key)
        if rig is None or t not in rig.type_ids:
            raise SampleError(
                f"{ref.path}: no rig for {KIND_NAME[kind]} type {t} (edges key {key!r}); draft one with "
                f"`marionette survey {ref.root} --rigs-out DIR` and pass --rigs DIR"
            )
        picked[kind] = rig
    entities = [
        Entity("monster", picked["m"], "m", 1),
        Entity("hunter", picked["n"], "n", 1),
        Entity("weapon", picked["w"], "w", 1, owner="hunter"),
    ]
    for name in scene_names(rigs=rigs):  # a built-in or user scene of exactly these rigs keeps its name
        try:
            known = load_scene(name, rigs=rigs)
        except SchemaError:
            continue
        if [e.rig for e in known.entities] == [e.rig for e in entities]:
            return known
    return build_layout(f"{picked['m'].name}_{picked['w'].name}", entities)
