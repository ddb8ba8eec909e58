"""Who plays where: the synthetic game's species, player characters, weapons and stages.

The default cast is the embedded game's: the drake (species 25), player character 0 with the
greatsword (weapon 3), one stage. A larger cast shapes a tree like WildWorld's (``make_cast``):

- **species** with procedurally generated skeletons, 40–80 joints in trees up to 18 deep, recorded in
  a joint order that is neither breadth- nor depth-first. Each is derived from the drake's motion
  (the game has one set of monster clips): its spine, neck and tail are chains of their own length
  laid along the drake's, helper joints ride on body joints at fixed offsets, wings and tongue may be
  absent, and the whole body is scaled about the ground under its root (feet on a slope then sit up
  to a few centimetres off the surface: the scale is 0.8–1.25);
- **player characters** sharing the one ``npc`` skeleton, each its own size;
- **weapons** of 5 points (the greatsword) and 2 points (a short blade along the same grip);
- **stages**: the second and later stages are the first stage's map turned about a vertical axis
  through the arena centre and raised, so their world coordinates overlap the first's while their
  height fields disagree. Rendering happens in the first stage's frame; everything the recording
  states in world coordinates (joints, roots, cameras) is then moved into its stage.

Which recording plays which: ``Cast.role(index)`` (species cycles fastest, then stage; the player and
the weapon alternate on their own periods), so every combination appears once there are
species × stages recordings. ``Role.to_json`` goes to the truth side file.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

from marionette.schema import load_rig

from . import terrain
from .skeletons import HUNTER_PELVIS_H, MONSTER_PELVIS_H
from .terrain import ARENA_CENTER

DRAKE_TYPE, PLAYER_TYPE, GREATSWORD_TYPE = 25, 0, 3
SHORT_BLADE_TYPE = 8
PLAYER_TYPES = (0, 2, 5, 7)
SPECIES_JOINTS = (40, 80)  # joint counts a generated species keeps within
MAX_HELPERS = 12
STAGE_TURN = np.pi / 2  # each further stage turns by this much about the arena centre …
STAGE_LIFT_M = 1.5  # … and rises by this much


def rig_edges(rig) -> np.ndarray:
    """A rig's source edges as [[parent, child], ...] (its skeleton_edges.json entry)."""
    return np.array([(p, c) for c, p in enumerate(rig.source_parents) if p >= 0], dtype=np.int64)


def _drake():
    return load_rig("drake")


@dataclass(frozen=True)
class Species:
    """A monster species: its recorded joints (names, parents in recorded order) and how each is made from the
    drake's source joints (``recipe``), its size and its ground-contact joints (the truth a drafted rig is
    checked against)."""

    type_id: int
    names: tuple[str, ...]
    parents: tuple[int, ...]  # recorded-order index of each joint's parent, -1 at the root
    recipe: tuple[tuple, ...]  # per joint: ("copy", i) | ("chain", (i0, i1, ...), fraction) | ("offset", j, (x, y, z))
    scale: float
    contact: tuple[str, ...]
    radius_m: float

    @property
    def root(self) -> str:
        return self.names[self.parents.index(-1)]

    @property
    def edges(self) -> list[list[int]]:
        return [[p, c] for c, p in enumerate(self.parents) if p >= 0]

    def depth(self) -> int:
        """Joints on the longest root-to-leaf path, less one (a lone root has depth 0)."""
        best = 0
        for j in range(len(self.names)):
            d, p = 0, self.parents[j]
            while p != -1:
                d, p = d + 1, self.parents[p]
            best = max(best, d)
        return best

    def bone_radii(self) -> np.ndarray:
        """Capsule radius of each bone (edge order), the drake's shape: a thick body and neck, a tapering tail."""
        out = []
        n_tail = sum(n.startswith("tail") for n in self.names)
        for _, c in self.edges:
            n = self.names[c]
            k = 3.0 if n.startswith(("spine", "chest")) else 2.0 if n.startswith(("neck", "head")) else 1.0
            if n.startswith("tail"):
                k = max(0.6, 2.2 - 1.7 * int(n[4:]) / n_tail)
            elif n.startswith("plate"):
                k = 0.5
            out.append(self.radius_m * k)
        return np.asarray(out)

    def derive(self, drake_local: np.ndarray) -> np.ndarray:
        """The species' joints (M, J, 3) from the drake's source joints in the root frame (M, 64, 3)."""
        out = np.zeros(drake_local.shape[:1] + (len(self.names), 3))
        done = np.zeros(len(self.names), bool)

        def point(j: int) -> np.ndarray:
            if not done[j]:
                r = self.recipe[j]
                if r[0] == "copy":
                    out[:, j] = drake_local[:, r[1]]
                elif r[0] == "chain":
                    out[:, j] = _along(drake_local[:, list(r[1])], r[2])
                else:
                    out[:, j] = point(r[1]) + np.asarray(r[2])
                done[j] = True
            return out[:, j]

        for j in range(len(self.names)):
            point(j)
        return _scaled(out, self.scale, MONSTER_PELVIS_H)

    def to_json(self) -> dict:
        return {
            "type_id": self.type_id,
            "joints": list(self.names),
            "parents": list(self.parents),
            "root": self.root,
            "contact": list(self.contact),
            "scale": self.scale,
            "depth": self.depth(),
        }


def _along(poly: np.ndarray, fraction: float) -> np.ndarray:
    """The point at ``fraction`` of the arc length along polylines (M, P, 3), per row."""
    seg = np.linalg.norm(np.diff(poly, axis=1), axis=-1)  # (M, P-1)
    cum = np.concatenate([np.zeros((len(poly), 1)), np.cumsum(seg, axis=1)], axis=1)
    s = fraction * cum[:, -1]
    k = np.clip((cum[:, 1:] < s[:, None]).sum(axis=1), 0, poly.shape[1] - 2)
    rows = np.arange(len(poly))
    w = np.clip((s - cum[rows, k]) / np.maximum(seg[rows, k], 1e-12), 0.0, 1.0)
    return poly[rows, k] + w[:, None] * (poly[rows, k + 1] - poly[rows, k])


def _scaled(local: np.ndarray, scale: float, pelvis_h: float) -> np.ndarray:
    """Joints in the root frame scaled by ``scale`` about the ground point under the root."""
    if scale == 1.0:
        return local
    g = np.array([0.0, -pelvis_h, 0.0])
    return g + scale * (local - g)


def make_species(type_id: int, rng: np.random.Generator, deep: bool = False) -> Species:
    """A species drawn by ``rng``: chain lengths, helpers, optional wings and tongue, size, joint order."""
    drake = _drake()
    di = {n: i for i, n in enumerate(drake.source_joints)}
    dpar = drake.source_parents
    n_tail = int(rng.integers(15, 17)) if deep else int(rng.integers(4, 13))
    n_spine, n_neck = int(rng.integers(2, 6)), int(rng.integers(2, 7))
    wings, tongue = bool(rng.random() < 0.6), bool(rng.random() < 0.5)

    names: list[str] = []
    parent_of: dict[str, str | None] = {}
    recipe: dict[str, tuple] = {}

    def add(name: str, parent: str | None, how: tuple) -> None:
        names.append(name)
        parent_of[name] = parent
        recipe[name] = how

    def chain(prefix: str, anchor: str, drake_chain: list[str], n: int, include_end: bool) -> str:
        poly = tuple(di[x] for x in [anchor, *drake_chain])
        last = anchor
        for k in range(1, n + 1):
            f = k / n if include_end else k / (n + 1)
            add(f"{prefix}{k}", last, ("chain", poly, f))
            last = f"{prefix}{k}"
        return last

    add("pelvis", None, ("copy", di["pelvis"]))
    top = chain("spine", "pelvis", ["spine1", "spine2", "spine3", "chest"], n_spine, include_end=False)
    add("chest", top, ("copy", di["chest"]))
    top = chain("neck", "chest", ["neck1", "neck2", "neck3", "head"], n_neck, include_end=False)
    add("head", top, ("copy", di["head"]))
    chain("tail", "pelvis", [f"tail{k}" for k in range(1, 11)], n_tail, include_end=True)
    skip = {"pelvis", "chest", "head"} | {f"spine{k}" for k in (1, 2, 3)} | {f"neck{k}" for k in (1, 2, 3)}
    skip |= {f"tail{k}" for k in range(1, 11)}
    if not wings:
        skip |= {n for n in drake.source_joints if n.startswith("wing")}
    if not tongue:
        skip |= {"tongue1", "tongue2"}
    for i, n in enumerate(drake.source_joints):  # the rest as the drake has them, parents re-pointed to copies
        if n in skip:
            continue
        p = drake.source_joints[dpar[i]]
        add(n, {"spine3": "chest", "neck3": "head"}.get(p, p), ("copy", i))
    room = SPECIES_JOINTS[1] - len(names)
    want = int(rng.integers(SPECIES_JOINTS[0], SPECIES_JOINTS[1] + 1)) - len(names)
    for k in range(max(int(deep), min(MAX_HELPERS, room, want))):  # helpers (armour plates, spikes) ride on body joints
        on = [n for n in names if n.startswith(("spine", "neck", "tail", "head", "chest"))]
        base = on[int(rng.integers(len(on)))] if not (deep and k == 0) else f"tail{n_tail}"
        offset = tuple(float(v) for v in rng.normal(0.0, 0.12, 3) + np.array([0.0, 0.18, 0.0]))
        add(f"plate{k + 1}", base, ("offset", base, offset))

    order = _unordered(names, parent_of, rng)
    pos = {n: k for k, n in enumerate(order)}
    parents = tuple(-1 if parent_of[n] is None else pos[parent_of[n]] for n in order)

    def remap(how: tuple) -> tuple:
        return ("offset", pos[how[1]], how[2]) if how[0] == "offset" else how

    scale = round(float(rng.uniform(0.8, 1.25)), 3)
    contact = ("claw_fl", "claw_fr", "claw_hl", "claw_hr")
    return Species(
        type_id=type_id,
        names=tuple(order),
        parents=parents,
        recipe=tuple(remap(recipe[n]) for n in order),
        scale=scale,
        contact=contact,
        radius_m=round(drake.capsule_radius_m * scale, 4),
    )


def _unordered(names: list[str], parent_of: dict, rng: np.random.Generator) -> list[str]:
    """A random joint order that is neither a breadth-first nor a depth-first order of the tree."""
    while True:
        order = [names[i] for i in rng.permutation(len(names))]
        if not _tree_order(order, parent_of):
            return order


def _tree_order(order: list[str], parent_of: dict) -> bool:
    """Whether every joint comes after its parent (which every BFS and DFS order has)."""
    seen: set[str] = set()
    for n in order:
        if parent_of[n] is not None and parent_of[n] not in seen:
            return False
        seen.add(n)
    return True


@dataclass(frozen=True)
class Player:
    """A player character: its type id on the one ``npc`` skeleton and its size."""

    type_id: int
    scale: float = 1.0

    def derive(self, hunter_local: np.ndarray) -> np.ndarray:
        return _scaled(hunter_local, self.scale, HUNTER_PELVIS_H)


@dataclass(frozen=True)
class Weapon:
    """A weapon type: its points from the greatsword's five (base, grip, guard, mid, tip) as fractions of the way
    from the base to the tip."""

    type_id: int
    name: str
    fractions: tuple[float, ...]

    @property
    def edges(self) -> list[list[int]]:
        return [[k - 1, k] for k in range(1, len(self.fractions))]

    def derive(self, sword: np.ndarray) -> np.ndarray:
        """Points (M, P, 3) from the greatsword's (M, 5, 3)."""
        base, tip = sword[:, :1], sword[:, 4:5]
        if self.type_id == GREATSWORD_TYPE:
            return sword
        return base + np.asarray(self.fractions)[None, :, None] * (tip - base)


GREATSWORD = Weapon(GREATSWORD_TYPE, "greatsword", (0.0, 0.1, 0.2, 0.6, 1.0))
SHORT_BLADE = Weapon(SHORT_BLADE_TYPE, "short blade", (0.0, 0.55))


@dataclass(frozen=True)
class Stage:
    """A stage: the first stage's map turned by ``turn`` radians about the vertical through the arena centre and
    raised by ``lift`` metres (the first stage: neither)."""

    name: str
    turn: float = 0.0
    lift: float = 0.0

    @property
    def identity(self) -> bool:
        return self.turn == 0.0 and self.lift == 0.0

    @property
    def rotation(self) -> np.ndarray:
        c, s = np.cos(self.turn), np.sin(self.turn)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])

    def points(self, p: np.ndarray) -> np.ndarray:
        """World points of the first stage's frame (…, 3) in this stage."""
        if self.identity:
            return p
        pivot = np.array([ARENA_CENTER[0], 0.0, ARENA_CENTER[1]])
        return (p - pivot) @ self.rotation.T + pivot + np.array([0.0, self.lift, 0.0])

    def unpoints(self, p: np.ndarray) -> np.ndarray:
        """This stage's world points (…, 3) in the first stage's frame."""
        if self.identity:
            return p
        pivot = np.array([ARENA_CENTER[0], 0.0, ARENA_CENTER[1]])
        return (p - pivot - np.array([0.0, self.lift, 0.0])) @ self.rotation + pivot

    def rotations(self, R: np.ndarray) -> np.ndarray:
        """Rotation matrices (…, 3, 3) of the first stage's frame in this stage."""
        return R if self.identity else self.rotation @ R

    def layers(self, x, z) -> list[np.ndarray]:
        """The stage's walkable surfaces at its own world (x, z): [ground, deck], nan where there is none."""

        x, z = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(z, np.float64))
        q = self.unpoints(np.stack([x, np.zeros_like(x), z], -1))
        return [h + self.lift for h in terrain.layers(q[..., 0], q[..., 2])]

    def to_json(self) -> dict:
        return {"name": self.name, "turn": self.turn, "lift": self.lift}


@dataclass(frozen=True)
class Skin:
    """What the monster and the player look like in one recording (RGB albedo in [0, 1]): in the real game a
    species' variants and a player's armour differ between recordings, so appearance cannot be learnt once."""

    monster: tuple[float, float, float]
    hunter: tuple[float, float, float]

    def colours(self) -> dict[str, tuple[float, float, float]]:
        return {"monster": self.monster, "hunter": self.hunter}

    def to_json(self) -> dict:
        return {"monster": list(self.monster), "hunter": list(self.hunter)}


def draw_skin(seed: int, index: int) -> Skin:
    """Recording ``index``'s skin, drawn by (seed, index): two colours of any hue, mid saturation and value."""

    rng = np.random.default_rng([seed, 0x5C1, index])

    def colour() -> tuple[float, float, float]:
        h, s, v = rng.uniform(0.0, 1.0), rng.uniform(0.5, 0.9), rng.uniform(0.45, 0.9)
        return tuple(round(float(c), 4) for c in colorsys.hsv_to_rgb(h, s, v))

    return Skin(monster=colour(), hunter=colour())


@dataclass(frozen=True)
class Role:
    """Who plays in one recording and where."""

    species: Species | None  # None: the drake
    player: Player
    weapon: Weapon
    stage: Stage
    skin: Skin | None = None  # None: the game's one look (a red monster, a blue player)
    camera_pans: bool = False  # whether the player looks around now and then (render.camera_pans)

    @property
    def monster_type(self) -> int:
        return DRAKE_TYPE if self.species is None else self.species.type_id

    @property
    def default(self) -> bool:
        return (
            self.species is None
            and self.player.scale == 1.0
            and self.weapon == GREATSWORD
            and self.stage.identity
            and self.skin is None
            and not self.camera_pans
        )

    def to_json(self) -> dict:
        return {
            "species": None if self.species is None else self.species.to_json(),
            "monster_type": self.monster_type,
            "player": {"type_id": self.player.type_id, "scale": self.player.scale},
            "weapon": {"type_id": self.weapon.type_id, "name": self.weapon.name, "points": len(self.weapon.fractions)},
            "stage": self.stage.to_json(),
            **({"skin": self.skin.to_json()} if self.skin is not None else {}),
            **({"camera_pans": True} if self.camera_pans else {}),
        }


@dataclass(frozen=True)
class Cast:
    """Everything the game can put in a recording; ``role(index)`` picks one recording's."""

    species: tuple[Species, ...] = ()
    players: tuple[Player, ...] = (Player(PLAYER_TYPE),)
    weapons: tuple[Weapon, ...] = (GREATSWORD,)
    stages: tuple[Stage, ...] = field(default_factory=lambda: (Stage("a"),))
    skins: int | None = None  # the seed of each recording's skin (draw_skin); None: one look for all
    camera_pans: bool = False  # the player looks around now and then (render.camera_pans)

    def role(self, index: int) -> Role:
        n_species = max(1, len(self.species))
        return Role(
            species=self.species[index % n_species] if self.species else None,
            player=self.players[index % len(self.players)],
            weapon=self.weapons[(index // 2) % len(self.weapons)],
            stage=self.stages[(index // n_species) % len(self.stages)],
            skin=draw_skin(self.skins, index) if self.skins is not None else None,
            camera_pans=self.camera_pans,
        )

    def edges(self) -> dict[str, list[list[int]]]:
        """``skeleton_edges.json`` of a tree of this cast."""
        out = {}
        if not self.species:
            out[f"em_{DRAKE_TYPE}"] = rig_edges(_drake()).tolist()
        for s in self.species:
            out[f"em_{s.type_id}"] = s.edges
        out["npc"] = rig_edges(load_rig("hunter")).tolist()
        for w in self.weapons:
            out[f"wp_{w.type_id}"] = rig_edges(load_rig("greatsword")).tolist() if w.type_id == GREATSWORD_TYPE else w.edges
        return out


def make_cast(
    seed: int,
    species: int = 0,
    players: int = 1,
    weapons: int = 1,
    stages: int = 1,
    skins: bool = False,
    camera_pans: bool = False,
) -> Cast:
    """A cast drawn by ``seed``: ``species`` generated species (0: the drake alone), ``players`` player
    characters, ``weapons`` weapon types (the greatsword, then the short blade), ``stages`` stages; with
    ``skins`` each recording's monster and player colours drawn by (seed, index); with ``camera_pans`` the
    player looks around now and then (the bodies leave the view and come back)."""
    if not 0 <= species <= 20 or not 1 <= players <= len(PLAYER_TYPES) or not 1 <= weapons <= 2 or not 1 <= stages <= 4:
        raise ValueError(
            f"a cast holds 0–20 species, 1–{len(PLAYER_TYPES)} players, 1–2 weapons and 1–4 stages, "
            f"not {species}, {players}, {weapons}, {stages}"
        )
    rng = np.random.default_rng([seed, 0xCA57])
    types = sorted(int(t) for t in rng.choice(np.arange(26, 100), size=species, replace=False)) if species else []
    return Cast(
        species=tuple(make_species(t, rng, deep=k == 0) for k, t in enumerate(types)),
        players=tuple(
            Player(PLAYER_TYPES[k], 1.0 if k == 0 else round(float(rng.uniform(0.88, 0.96)), 3)) for k in range(players)
        ),
        weapons=(GREATSWORD, SHORT_BLADE)[:weapons],
        stages=tuple(Stage("abcd"[k], STAGE_TURN * k, STAGE_LIFT_M * k) for k in range(stages)),
        skins=int(seed) if skins else None,
        camera_pans=bool(camera_pans),
    )
