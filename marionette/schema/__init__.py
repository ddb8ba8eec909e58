"""The shared state schema: rigs, scene layouts and the Arrow schema of state shards.

Everything is generated from the declarative files under ``schemas/``: a rig names a skeleton's
joints and says which of them the state keeps; a scene is an ordered list of entities, each with
a rig; the layout of the state vector is derived from the scene in one generic order
(every articulated entity's [root, joints], then attachments, then every articulated entity's
6D rotation). Nothing downstream hard-codes a width or an index.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa

from marionette.io import read_json

SCHEMA_DIR = Path(os.environ.get("MARIONETTE_SCHEMAS", Path(__file__).resolve().parents[2] / "schemas"))
LAYOUT_METADATA_KEY = b"marionette.layout"
LAYOUT_HASH_METADATA_KEY = b"marionette.layout_hash"


class SchemaError(ValueError):
    """A schema file, or data checked against a schema, is inconsistent."""


@dataclass(frozen=True)
class Rig:
    """A skeleton: the source joints of a WildWorld type and the subset the state keeps."""

    name: str
    kind: str  # "articulated" (has a root and a rotation) or "attachment" (points only)
    edges_key: str  # key in skeleton_edges.json ("em_25", "npc", "wp_3")
    type_ids: tuple[int, ...]
    source_joints: tuple[str, ...]
    source_parents: tuple[int, ...]  # -1 for the source root
    keep: tuple[str, ...]  # kept joint names, in state order; for articulated rigs keep[0] is the root
    root: str
    forward_axis: tuple[float, float, float]  # in the entity's local frame
    contact_joints: tuple[str, ...]
    capsule_radius_m: float
    description: str = ""
    id_band: tuple[int, int] | None = None  # [first, last] render ids of its bones (the bridge's G channel)

    @cached_property
    def keep_source_index(self) -> tuple[int, ...]:
        """Index into the source joint axis of each kept joint."""
        return tuple(self.source_joints.index(n) for n in self.keep)

    @cached_property
    def parents(self) -> tuple[int, ...]:
        """Parent of each kept joint as an index into ``keep`` (nearest kept ancestor; -1 at the top)."""
        kept = {self.source_joints.index(n): i for i, n in enumerate(self.keep)}
        out = []
        for name in self.keep:
            p = self.source_parents[self.source_joints.index(name)]
            while p != -1 and p not in kept:
                p = self.source_parents[p]
            out.append(kept.get(p, -1))
        return tuple(out)

    @cached_property
    def contact_index(self) -> tuple[int, ...]:
        """Index into ``keep`` of each key ground-contact joint."""
        return tuple(self.keep.index(n) for n in self.contact_joints)

    @property
    def n_keep(self) -> int:
        return len(self.keep)

    @cached_property
    def bones(self) -> tuple[tuple[int, int], ...]:
        """(child, parent) kept-joint indices of every bone, children in breadth-first order from the top."""
        par = self.parents
        order, frontier = [], [i for i, p in enumerate(par) if p == -1]
        while frontier:
            nxt = [c for f in frontier for c in range(len(par)) if par[c] == f]
            order += nxt
            frontier = nxt
        return tuple((c, par[c]) for c in order)

    def bone_ids(self) -> tuple[int, ...]:
        """Render id of each bone of ``bones``: id_band[0] + its breadth-first rank."""
        if self.id_band is None:
            raise SchemaError(f"rig {self.name!r} has no id_band: it cannot be rendered")
        return tuple(range(self.id_band[0], self.id_band[0] + len(self.bones)))

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "kind": self.kind,
            "edges_key": self.edges_key,
            "type_ids": list(self.type_ids),
            "source_joints": list(self.source_joints),
            "source_parents": list(self.source_parents),
            "keep": list(self.keep),
            "root": self.root,
            "forward_axis": list(self.forward_axis),
            "contact_joints": list(self.contact_joints),
            "capsule_radius_m": self.capsule_radius_m,
            **({"id_band": list(self.id_band)} if self.id_band is not None else {}),
        }


@dataclass(frozen=True)
class Entity:
    """One entity of a scene: a rig, where it comes from in a recording, and an optional owner."""

    name: str
    rig: Rig
    source_kind: str  # "m", "n" or "w"
    source_index: int  # 1-based, as in skeleton.npz keys
    owner: str | None = None

    @property
    def articulated(self) -> bool:
        return self.rig.kind == "articulated"


@dataclass(frozen=True)
class Layout:
    """The state vector of a scene: ordered entities and named slices [start, stop)."""

    scene: str
    entities: tuple[Entity, ...]
    slices: dict[str, tuple[int, int]] = field(hash=False)
    dim: int = 0

    def slice(self, name: str) -> slice:
        """The named slice of the state vector, e.g. ``layout.slice("hunter.rot6d")``."""
        try:
            a, b = self.slices[name]
        except KeyError:
            raise SchemaError(f"layout {self.scene!r} has no slice {name!r}; it has {sorted(self.slices)}") from None
        return slice(a, b)

    def entity(self, name: str) -> Entity:
        for e in self.entities:
            if e.name == name:
                return e
        raise SchemaError(f"layout {self.scene!r} has no entity {name!r}")

    @property
    def articulated(self) -> tuple[Entity, ...]:
        return tuple(e for e in self.entities if e.articulated)

    @property
    def attachments(self) -> tuple[Entity, ...]:
        return tuple(e for e in self.entities if not e.articulated)

    def dim_names(self) -> list[str]:
        """A name for every dimension of the state vector, e.g. ``hunter.head.y``, ``monster.rot6d.2``."""
        names = [""] * self.dim
        for e in self.entities:
            for part in ("root", "joints", "points", "rot6d"):
                key = f"{e.name}.{part}"
                if key not in self.slices:
                    continue
                a, b = self.slices[key]
                if part == "rot6d":
                    labels = [f"{key}.{i}" for i in range(6)]
                elif part == "root":
                    labels = [f"{key}.{ax}" for ax in "xyz"]
                else:
                    joints = e.rig.keep[1:] if part == "joints" else e.rig.keep
                    labels = [f"{e.name}.{j}.{ax}" for j in joints for ax in "xyz"]
                names[a:b] = labels
        return names

    def to_json(self) -> dict:
        """The layout as JSON: name, dim, slices and each entity with its rig."""
        return {
            "name": self.scene,
            "dim": self.dim,
            "slices": {k: list(v) for k, v in self.slices.items()},
            "entities": [
                {
                    "name": e.name,
                    "rig": e.rig.to_json(),
                    "source": {"kind": e.source_kind, "index": e.source_index},
                    "owner": e.owner,
                }
                for e in self.entities
            ],
        }

    @property
    def hash(self) -> str:
        """sha256 (hex, 16 chars) of the canonical layout JSON."""
        blob = json.dumps(self.to_json(), sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


@dataclass(frozen=True)
class FieldRange:
    """The values a recorded field may take: ``low`` ≤ v ≤ ``high`` where it is finite (nan marks an invalid frame)."""

    low: float
    high: float
    unit: str

    def first_outside(self, values: np.ndarray) -> tuple[int, ...] | None:
        """The index of the first finite value of ``values`` outside the range, or None."""
        v = np.asarray(values, dtype=np.float64)
        bad = np.isfinite(v) & ((v < self.low) | (v > self.high))
        return tuple(int(i) for i in np.argwhere(bad)[0]) if bad.any() else None


INT32_MAX = 2**31 - 1
# Every recorded field's physical range; a sample holding a finite value outside it is quarantined, naming the file,
# field, frame and value. Negative motion ids mean "no action" (the composite id 0).
FIELD_RANGES: dict[str, FieldRange] = {
    "position": FieldRange(-1e6, 1e6, "m (joints, entity positions, the camera: within 1,000 km of the origin)"),
    "focal": FieldRange(1e-3, 1e6, "px (camera fx, fy: positive)"),
    "principal": FieldRange(-1e6, 1e6, "px (camera cx, cy)"),
    "quaternion": FieldRange(-1.1, 1.1, "(each rotation component; the norm is checked on its own)"),
    "motion_bank_id": FieldRange(-INT32_MAX, INT32_MAX // 1000 - 1, "(bank × 1000 + motion + 1 stays within int32)"),
    "motion_id": FieldRange(-INT32_MAX, 999, "(the composite action id bank × 1000 + motion + 1 needs motion < 1000)"),
    "motion_frame": FieldRange(-INT32_MAX, INT32_MAX, "frames (stored as int32)"),
    "hp": FieldRange(-1e7, 1e7, "hit points"),
}


MAX_SCHEMA_BYTES = 16 << 20  # a rig or scene file: a few kilobytes; a generated species' rig, tens


def _read_json(path: Path) -> dict:
    try:
        return read_json(path, max_bytes=MAX_SCHEMA_BYTES)
    except FileNotFoundError:
        raise SchemaError(f"{path}: no such schema file") from None
    except ValueError as exc:
        raise SchemaError(f"invalid JSON: {exc}") from None


def rig_from_json(d: dict, where: str = "<rig>") -> Rig:
    """Build and validate a Rig from its JSON form (schema file or embedded layout)."""
    if "source_joints" in d and d["source_joints"] and isinstance(d["source_joints"][0], dict):
        names = [j["name"] for j in d["source_joints"]]
        parent_names = [j["parent"] for j in d["source_joints"]]
        if len(set(names)) != len(names):
            raise SchemaError(f"{where}: duplicate joint names")
        idx = {n: i for i, n in enumerate(names)}
        for n, p in zip(names, parent_names, strict=True):
            if p is not None and p not in idx:
                raise SchemaError(f"{where}: joint {n!r} has unknown parent {p!r}")
        parents = [-1 if p is None else idx[p] for p in parent_names]
    else:
        names = list(d["source_joints"])
        parents = list(d["source_parents"])
    rig = Rig(
        name=d["name"],
        kind=d["kind"],
        edges_key=d["edges_key"],
        type_ids=tuple(int(t) for t in d["type_ids"]),
        source_joints=tuple(names),
        source_parents=tuple(parents),
        keep=tuple(d["keep"]),
        root=d["root"],
        forward_axis=tuple(float(v) for v in d["forward_axis"]),
        contact_joints=tuple(d.get("contact_joints", ())),
        capsule_radius_m=float(d["capsule_radius_m"]),
        description=d.get("description", ""),
        id_band=tuple(int(v) for v in d["id_band"]) if d.get("id_band") is not None else None,
    )
    if rig.kind not in ("articulated", "attachment"):
        raise SchemaError(f"{where}: kind must be 'articulated' or 'attachment', not {rig.kind!r}")
    missing = [n for n in rig.keep + rig.contact_joints + (rig.root,) if n not in names]
    if missing:
        raise SchemaError(f"{where}: joints {missing} are not among the source joints")
    if rig.kind == "articulated" and rig.keep[0] != rig.root:
        raise SchemaError(f"{where}: the root {rig.root!r} must be the first kept joint")
    if len(set(rig.keep)) != len(rig.keep):
        raise SchemaError(f"{where}: duplicate kept joints")
    if rig.id_band is not None:
        a, b = rig.id_band
        if not (1 <= a <= b <= 254) or b - a + 1 < len(rig.bones):
            raise SchemaError(f"{where}: id_band {list(rig.id_band)} must lie in [1, 254] and hold its {len(rig.bones)} bones")
    return rig


NAME_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,100}")


def _schema_file(kind: str, name: str, schema_dir: Path, rigs: Path | None) -> Path:
    """``<rigs>/<kind>/<name>.json`` when a user's directory holds it, else ``<schema_dir>/<kind>/<name>.json``."""
    if not NAME_PATTERN.fullmatch(name):
        raise SchemaError(f"{name!r} is not a {kind[:-1]} name (letters, digits, '_' and '-', at most 100)")
    if rigs is not None and (Path(rigs) / kind / f"{name}.json").is_file():
        return Path(rigs) / kind / f"{name}.json"
    return Path(schema_dir) / kind / f"{name}.json"


@cache
def load_rig(name: str, schema_dir: Path = SCHEMA_DIR, rigs: Path | None = None) -> Rig:
    """Load ``<rigs>/rigs/<name>.json`` (a user's rigs, e.g. drafted by ``marionette survey``) or, without one,
    the built-in ``schemas/rigs/<name>.json``."""
    path = _schema_file("rigs", name, schema_dir, rigs)
    return rig_from_json(_read_json(path), str(path))


def scene_names(schema_dir: Path = SCHEMA_DIR, rigs: Path | None = None) -> list[str]:
    """The scenes there are: the built-in ones and a user's (``<rigs>/scenes/*.json``)."""
    dirs = [Path(schema_dir)] + ([Path(rigs)] if rigs is not None else [])
    return sorted({f.stem for d in dirs for f in (d / "scenes").glob("*.json") if NAME_PATTERN.fullmatch(f.stem)})


def build_layout(scene: str, entities: list[Entity]) -> Layout:
    """Lay out a scene's state vector in the generic order (roots+joints, attachments, rotations)."""
    names = [e.name for e in entities]
    if len(set(names)) != len(names):
        raise SchemaError(f"scene {scene!r}: duplicate entity names {names}")
    for e in entities:
        if e.owner is not None:
            if e.owner not in names or not next(o for o in entities if o.name == e.owner).articulated:
                raise SchemaError(
                    f"scene {scene!r}: entity {e.name!r} is owned by {e.owner!r}, which is not an articulated entity of the scene"
                )
        elif not e.articulated:
            raise SchemaError(f"scene {scene!r}: attachment {e.name!r} needs an owner")
    banded = [e for e in entities if e.rig.id_band is not None]
    for i, a in enumerate(banded):  # two rigs' bones must never share a render id (the bridge's id channel)
        for b in banded[i + 1 :]:
            (a0, a1), (b0, b1) = a.rig.id_band, b.rig.id_band
            if a.rig.name != b.rig.name and a0 <= b1 and b0 <= a1:
                raise SchemaError(
                    f"scene {scene!r}: the render ids of {a.name!r} [{a0}, {a1}] and {b.name!r} [{b0}, {b1}] overlap"
                )
    slices: dict[str, tuple[int, int]] = {}
    at = 0

    def put(name: str, width: int) -> None:
        nonlocal at
        slices[name] = (at, at + width)
        at += width

    for e in entities:
        if e.articulated:
            put(f"{e.name}.root", 3)
            put(f"{e.name}.joints", 3 * (e.rig.n_keep - 1))
    for e in entities:
        if not e.articulated:
            put(f"{e.name}.points", 3 * e.rig.n_keep)
    for e in entities:
        if e.articulated:
            put(f"{e.name}.rot6d", 6)
    return Layout(scene=scene, entities=tuple(entities), slices=slices, dim=at)


@cache
def load_scene(name: str, schema_dir: Path = SCHEMA_DIR, rigs: Path | None = None) -> Layout:
    """Load ``schemas/scenes/<name>.json`` — or ``<rigs>/scenes/<name>.json``, its rigs looked up in ``<rigs>/rigs/``
    before the built-in ones — and generate its layout."""
    path = _schema_file("scenes", name, schema_dir, rigs)
    if not path.is_file():
        names = scene_names(schema_dir, rigs)
        raise SchemaError(f"no scene {name!r} in {path.parent} (scenes: {', '.join(names)})")
    d = _read_json(path)
    ents = []
    for i, ed in enumerate(d["entities"]):
        try:
            ents.append(
                Entity(
                    name=ed["name"],
                    rig=load_rig(ed["rig"], schema_dir, rigs),
                    source_kind=ed["source"]["kind"],
                    source_index=int(ed["source"]["index"]),
                    owner=ed.get("owner"),
                )
            )
        except KeyError as exc:
            raise SchemaError(f"{path}: entity {i} lacks {exc}") from None
    return build_layout(d["name"], ents)


def layout_from_json(d: dict) -> Layout:
    """Rebuild a Layout from ``Layout.to_json()`` (as stored in shard metadata and info.json)."""
    ents = [
        Entity(
            name=e["name"],
            rig=rig_from_json(e["rig"], f"layout {d['name']}"),
            source_kind=e["source"]["kind"],
            source_index=int(e["source"]["index"]),
            owner=e.get("owner"),
        )
        for e in d["entities"]
    ]
    layout = build_layout(d["name"], ents)
    if layout.dim != d["dim"] or {k: tuple(v) for k, v in d["slices"].items()} != layout.slices:
        raise SchemaError(f"layout {d['name']!r}: stored slices disagree with the ones its entities generate")
    return layout


def state_schema(layout: Layout) -> pa.Schema:
    """Arrow schema of a state shard: one row per source video frame, the layout in the metadata."""
    f64x3 = pa.list_(pa.float64(), 3)
    fields = [
        pa.field("segment", pa.string()),
        pa.field("sample", pa.string()),
        pa.field("frame", pa.int32()),  # source video frame index within the sample
        pa.field("t", pa.float64()),  # seconds since the sample's first frame
        pa.field("state", pa.list_(pa.float32(), layout.dim)),
    ]
    for e in layout.articulated:
        fields += [
            pa.field(f"{e.name}.type_id", pa.int32()),
            pa.field(f"{e.name}.action", pa.int32()),  # composite bank*1000 + motion + 1; 0 = no valid action
            pa.field(f"{e.name}.motion_frame", pa.int32()),
            pa.field(f"{e.name}.hp", pa.float32()),
            pa.field(f"{e.name}.root_world", f64x3),  # recorded root joint, world metres
            pa.field(f"{e.name}.rot_world", pa.list_(pa.float64(), 4)),  # recorded root rotation (x, y, z, w)
            pa.field(f"{e.name}.pos_check_m", pa.float32()),  # |state.csv pos - root joint|
        ]
    for e in layout.attachments:
        fields.append(pa.field(f"{e.name}.type_id", pa.int32()))
    fields += [
        pa.field("camera.K", pa.list_(pa.float64(), 4)),  # fx, fy, cx, cy in source pixels
        pa.field("camera.pos", f64x3),
        pa.field("camera.rot", pa.list_(pa.float64(), 4)),  # camera-to-world (x, y, z, w), OpenGL frame
        pa.field("valid", pa.bool_()),
    ]
    meta = {
        LAYOUT_METADATA_KEY: json.dumps(layout.to_json(), sort_keys=True).encode(),
        LAYOUT_HASH_METADATA_KEY: layout.hash.encode(),
    }
    return pa.schema(fields, metadata=meta)


def layout_of_schema(schema: pa.Schema, where: str = "<table>") -> Layout:
    """The layout a shard schema carries in its metadata."""
    meta = schema.metadata or {}
    if LAYOUT_METADATA_KEY not in meta:
        raise SchemaError(f"{where}: no layout in the schema metadata; not a Marionette state shard")
    return layout_from_json(json.loads(meta[LAYOUT_METADATA_KEY]))


def check_layout(schema: pa.Schema, expected: Layout, where: str = "<table>") -> None:
    """Fail, naming both layouts, unless ``schema`` carries ``expected``."""
    meta = schema.metadata or {}
    got_hash = meta.get(LAYOUT_HASH_METADATA_KEY, b"").decode()
    if got_hash == expected.hash:
        return
    got = layout_of_schema(schema, where)
    raise SchemaError(
        f"{where}: shard layout {got.scene!r} (dim {got.dim}, hash {got.hash}) does not match the expected "
        f"layout {expected.scene!r} (dim {expected.dim}, hash {expected.hash})"
    )
