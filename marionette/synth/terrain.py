"""The synthetic game's stage: an analytic, layered terrain far from the world origin.

World frame: metric, Y up, right-handed. The arena is a 120 m × 120 m square centred on
``ARENA_CENTER`` = (x, z) = (−950, 850). Its walkable surfaces are

- the ground: a tilted base with a broad hill and a basin (slopes up to ~25°), a valley running
  along +Z at x = −980 (5.5 m deep), and a wall block (``WALL``) that raises the ground by 3 m
  with vertical sides (a sharp step, taller than the 1.5 m a character may step up);
- the bridge deck: a second layer over the valley, inside ``DECK`` (x ∈ [−995, −965],
  z ∈ [846, 850]), about 5.3 m above the valley floor at its middle and level with the ground
  at both ends;
- the fight ground east of the bridge: raised ``TERRACES``, each a rectangle whose south part is a
  plateau ``rise`` metres above the ground (1.5 m and 1 m) with vertical sides (ledges), and whose
  north part is a ramp falling linearly to the ground at the north edge (the one way up).

Every function is vectorised over numpy arrays of x and z (world metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ARENA_CENTER = (-950.0, 850.0)  # (x, z), metres
ARENA_HALF = 60.0  # the arena is [cx ± 60] × [cz ± 60]
WALL = (-945.0, -925.0, 862.0, 866.0)  # x0, x1, z0, z1 of the wall block
WALL_HEIGHT = 3.0
DECK = (-995.0, -965.0, 846.0, 850.0)  # x0, x1, z0, z1 of the bridge deck
DECK_THICKNESS = 0.5
VALLEY_X, VALLEY_DEPTH, VALLEY_SIGMA = -980.0, 5.5, 6.0


@dataclass(frozen=True)
class Terrace:
    """A raised block: plateau over z ∈ [z0, z_ramp], ramp down to the ground over [z_ramp, z1] (metres)."""

    x0: float
    x1: float
    z0: float
    z_ramp: float
    z1: float
    rise: float  # plateau height above the ground (m)

    def height(self, x, z) -> np.ndarray:
        """Height (m) the terrace adds to the ground at (x, z): rise on the plateau, linear on the ramp, 0 outside."""
        x = np.asarray(x, dtype=np.float64)
        z = np.asarray(z, dtype=np.float64)
        inside = (x >= self.x0) & (x < self.x1) & (z >= self.z0) & (z < self.z1)
        ramp = np.clip((self.z1 - z) / (self.z1 - self.z_ramp), 0.0, 1.0)
        return np.where(inside, self.rise * ramp, 0.0)


# Edges on integer metres (grid lines of the mesh and of 1 m terrain cells); ramps of 10–11°.
TERRACES = (
    Terrace(-958.0, -942.0, 822.0, 834.0, 842.0, 1.5),
    Terrace(-934.0, -922.0, 832.0, 842.0, 848.0, 1.0),
)


def _valley(x: np.ndarray) -> np.ndarray:
    return -VALLEY_DEPTH * np.exp(-((x - VALLEY_X) ** 2) / (2 * VALLEY_SIGMA**2))


# The deck is level with the ground at both ends: the valley term at the deck's end points.
_DECK_OFFSET = float(_valley(np.array(DECK[0])))


def base_height(x, z) -> np.ndarray:
    """Ground height (m) before the valley and the wall: tilt + hill + basin."""
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    cx, cz = ARENA_CENTER
    tilt = 0.04 * (x - cx) - 0.03 * (z - cz)
    hill = 14.0 * np.exp(-((x + 925.0) ** 2 + (z - 888.0) ** 2) / (2 * 22.0**2))
    basin = -8.0 * np.exp(-((x + 915.0) ** 2 + (z - 810.0) ** 2) / (2 * 18.0**2))
    return 30.0 + tilt + hill + basin


def in_wall(x, z, margin: float = 0.0) -> np.ndarray:
    """True where (x, z) lies inside the wall block grown by ``margin`` metres."""
    x0, x1, z0, z1 = WALL
    return (x >= x0 - margin) & (x < x1 + margin) & (z >= z0 - margin) & (z < z1 + margin)


def in_deck(x, z, margin: float = 0.0) -> np.ndarray:
    """True where (x, z) lies over the bridge deck grown by ``margin`` metres."""
    x0, x1, z0, z1 = DECK
    return (x >= x0 - margin) & (x <= x1 + margin) & (z >= z0 - margin) & (z <= z1 + margin)


def in_arena(x, z, margin: float = 0.0) -> np.ndarray:
    """True where (x, z) lies inside the arena shrunk by ``margin`` metres."""
    cx, cz = ARENA_CENTER
    h = ARENA_HALF - margin
    return (np.abs(np.asarray(x) - cx) <= h) & (np.abs(np.asarray(z) - cz) <= h)


def terrace_height(x, z) -> np.ndarray:
    """Height (m) the terraces add to the ground at (x, z)."""
    return sum(t.height(x, z) for t in TERRACES)


def in_terrace(x, z, margin: float = 0.0) -> np.ndarray:
    """True where (x, z) lies inside a terrace (plateau or ramp) grown by ``margin`` metres."""
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    out = np.zeros(np.broadcast_shapes(x.shape, z.shape), bool)
    for t in TERRACES:
        out |= (x >= t.x0 - margin) & (x < t.x1 + margin) & (z >= t.z0 - margin) & (z < t.z1 + margin)
    return out


def near_step(x, z, margin: float = 0.6) -> np.ndarray:
    """True within ``margin`` metres of a vertical step: the wall's sides, the deck's edges, a terrace's ledges."""
    step = (in_wall(x, z, margin) & ~in_wall(x, z, -margin)) | (in_deck(x, z, margin) & ~in_deck(x, z, -margin))
    return step | (in_terrace(x, z, margin) & ~in_terrace(x, z, -margin))


def ground_height(x, z) -> np.ndarray:
    """Height (m) of the ground layer at (x, z): base + valley + terraces, +3 m on the wall block."""
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    return base_height(x, z) + _valley(x) + terrace_height(x, z) + np.where(in_wall(x, z), WALL_HEIGHT, 0.0)


def deck_height(x, z) -> np.ndarray:
    """Height (m) of the bridge deck's top at (x, z), extended analytically outside the deck."""
    return base_height(x, z) + _DECK_OFFSET


def layers(x, z) -> list[np.ndarray]:
    """Walkable surfaces at (x, z): [ground, deck], the deck nan where there is no bridge."""
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    deck = np.where(in_deck(x, z), deck_height(x, z), np.nan)
    return [ground_height(x, z), deck]


def surface_height(x, z, ref_y) -> np.ndarray:
    """Height (m) of the walkable layer at (x, z) nearest to the height ``ref_y`` (m)."""
    ground, deck = layers(x, z)
    ref_y = np.asarray(ref_y, dtype=np.float64)
    use_deck = np.isfinite(deck) & (np.abs(np.nan_to_num(deck) - ref_y) < np.abs(ground - ref_y))
    return np.where(use_deck, deck, ground)


def ground_normal(x, z, eps: float = 0.05) -> np.ndarray:
    """Unit normal (..., 3) of the ground layer by central differences (ignores the wall step; a terrace's
    ledge tilts it only within ``eps`` of the edge)."""
    x = np.asarray(x, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)

    def h(a, b):
        return base_height(a, b) + _valley(a) + terrace_height(a, b)

    dx = (h(x + eps, z) - h(x - eps, z)) / (2 * eps)
    dz = (h(x, z + eps) - h(x, z - eps)) / (2 * eps)
    n = np.stack([-dx, np.ones_like(dx), -dz], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


class StageTerrain:
    """The stage as an object: the module's analytic functions plus its bounds."""

    center = ARENA_CENTER
    half_size = ARENA_HALF
    wall = WALL
    deck = DECK

    @staticmethod
    def layers(x, z) -> list[np.ndarray]:
        """Walkable surfaces at (x, z): [ground, deck], the deck nan where there is no bridge."""
        return layers(x, z)

    @staticmethod
    def surface_height(x, z, ref_y) -> np.ndarray:
        """Height (m) of the walkable layer at (x, z) nearest to ``ref_y``."""
        return surface_height(x, z, ref_y)

    @staticmethod
    def ground_height(x, z) -> np.ndarray:
        """Height (m) of the ground layer at (x, z)."""
        return ground_height(x, z)


def terrain_mesh(cell_m: float = 1.0, extent_m: float = 80.0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Triangle meshes of the stage: [(material, vertices (V, 3) float32, triangles (T, 3) uint32)].

    The ground is a height-field grid over the arena ± ``extent_m`` (the wall and terrace footprints
    are covered by their blocks); the wall is a block whose top follows the ground + 3 m; each
    terrace a block whose top is the ground plus the terrace; the deck a slab of ``DECK_THICKNESS``.
    Grid lines fall on the wall, terrace and deck edges (integer metres).
    """
    cx, cz = ARENA_CENTER
    out = []
    xs = np.arange(cx - extent_m, cx + extent_m + 1e-9, cell_m)
    zs = np.arange(cz - extent_m, cz + extent_m + 1e-9, cell_m)
    out.append(("ground", *_grid(xs, zs, lambda x, z: base_height(x, z) + _valley(x))))

    x0, x1, z0, z1 = WALL
    top = lambda x, z: base_height(x, z) + _valley(x) + WALL_HEIGHT  # noqa: E731
    low = lambda x, z: base_height(x, z) + _valley(x) - 0.5  # noqa: E731
    out.append(("wall", *_block(np.arange(x0, x1 + 1e-9, 0.5), np.arange(z0, z1 + 1e-9, 0.5), top, low)))
    for t in TERRACES:
        # Inside the block (x < x1, z < z1) the terrace's own height: evaluated a hair inside its far edges.
        def top(x, z, t=t):
            return base_height(x, z) + _valley(x) + t.height(np.minimum(x, t.x1 - 1e-6), np.minimum(z, t.z1 - 1e-6))

        xs_t, zs_t = np.arange(t.x0, t.x1 + 1e-9, 0.5), np.arange(t.z0, t.z1 + 1e-9, 0.5)
        out.append(("wall", *_block(xs_t, zs_t, top, low)))

    x0, x1, z0, z1 = DECK
    top = deck_height
    low = lambda x, z: deck_height(x, z) - DECK_THICKNESS  # noqa: E731
    out.append(("deck", *_block(np.arange(x0, x1 + 1e-9, 1.0), np.arange(z0, z1 + 1e-9, 1.0), top, low)))
    return out


def _grid(xs: np.ndarray, zs: np.ndarray, height, flip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    X, Z = np.meshgrid(xs, zs)  # (nz, nx)
    V = np.stack([X, height(X, Z), Z], axis=-1).reshape(-1, 3)
    nz, nx = X.shape
    i = np.arange(nz * nx).reshape(nz, nx)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    # Counter-clockwise seen from above (+Y): (a, c, b) and (b, c, d) with z growing along rows.
    T = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    if flip:
        T = T[:, ::-1]
    return V.astype(np.float32), T.astype(np.uint32)


def _block(xs: np.ndarray, zs: np.ndarray, top, low) -> tuple[np.ndarray, np.ndarray]:
    """A slab between two height functions over a rectangle: top and bottom grids plus four sides."""
    verts, tris, n = [], [], 0
    for V, T in (_grid(xs, zs, top), _grid(xs, zs, low, flip=True)):
        verts.append(V)
        tris.append(T + n)
        n += len(V)
    # Perimeter, counter-clockwise seen from above.
    px = np.concatenate([xs, np.full(len(zs) - 1, xs[-1]), xs[::-1][1:], np.full(len(zs) - 2, xs[0])])
    pz = np.concatenate([np.full(len(xs), zs[0]), zs[1:], np.full(len(xs) - 1, zs[-1]), zs[::-1][1:-1]])
    m = len(px)
    up = np.stack([px, top(px, pz), pz], -1)
    dn = np.stack([px, low(px, pz), pz], -1)
    verts.append(np.concatenate([up, dn]).astype(np.float32))
    j = np.arange(m)
    k = (j + 1) % m
    side = np.concatenate([np.stack([j, k, j + m], -1), np.stack([k, k + m, j + m], -1)]) + n
    tris.append(side.astype(np.uint32))
    return np.concatenate(verts), np.concatenate(tris)
