"""What a play page shows of one frame: the bridge's G-buffer through a follow or orbit camera, and the stage's map.

A frame is rendered by the bridge's rasterizer (``bridge.render.Rasterizer``) exactly as a pose-control target
is: terrain mesh plus bone capsules, the same G-buffer channels (R height, G render id, B inverse depth). The
page gets those channels as 8-bit RGB (``to_bytes``); the render id survives exactly (G = id / 255) and the page
colours by it. The stage map is the terrain mesh's vertices binned on a grid of at most ``MAP_CELLS`` cells a side,
the highest per cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marionette.bridge.camera import Cameras, FollowCamera, intrinsics_for, look_at
from marionette.bridge.kinematics import Skeletons, bone_segments
from marionette.bridge.render import Rasterizer
from marionette.bridge.targets import RenderSettings, TerrainScene, followed_entities, height_range
from marionette.schema import Layout

MAP_CELLS = 160
ORBIT_PITCH_DEG = (-10.0, 85.0)  # the orbit camera's pitch range (degrees above the horizon)
ORBIT_DISTANCE_M = (2.0, 80.0)


@dataclass
class Orbit:
    """A free camera circling the midpoint of the articulated roots: yaw (degrees, 0 = looking along +Z), pitch
    (degrees above the horizon), distance (m)."""

    yaw: float = 0.0
    pitch: float = 25.0
    distance: float = 14.0

    def checked(self) -> Orbit:
        """This orbit with pitch and distance clipped to their ranges; a non-finite value is a ValueError."""
        if not all(np.isfinite([self.yaw, self.pitch, self.distance])):
            raise ValueError(f"orbit camera: yaw, pitch and distance are finite numbers, not {self}")
        return Orbit(
            float(self.yaw) % 360.0,
            float(np.clip(self.pitch, *ORBIT_PITCH_DEG)),
            float(np.clip(self.distance, *ORBIT_DISTANCE_M)),
        )

    def camera(self, target: np.ndarray, width: int, height: int) -> Cameras:
        yaw, pitch = np.radians(self.yaw), np.radians(self.pitch)
        back = np.array([-np.sin(yaw) * np.cos(pitch), np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])
        eye = np.asarray(target, np.float64) + self.distance * back
        R = look_at(eye, target)
        return Cameras(intrinsics_for(width, height)[None], eye[None], R[None], np.array([True]), width, height)


def frame_skeletons(layout: Layout, world: dict[str, np.ndarray]) -> Skeletons:
    """One frame's world joints (entity → (K, 3)) as a one-frame ``Skeletons`` (an entity with a non-finite joint is
    absent)."""
    joints = {e.name: np.asarray(world[e.name], np.float64)[None] for e in layout.entities}
    valid = {n: np.array([bool(np.isfinite(j).all())]) for n, j in joints.items()}
    return Skeletons(np.zeros(1), joints, {n: np.tile(np.eye(3), (1, 1, 1)) for n in joints}, valid)


class FrameView:
    """Renders a scene frame by frame on one stage: ``render(world, R)`` → the G-buffer as (H, W, 3) uint8."""

    def __init__(self, layout: Layout, terrain: TerrainScene, size: tuple[int, int], fps: float, roots_y: np.ndarray):
        self.layout, self.terrain, self.fps = layout, terrain, float(fps)
        self.height, self.width = size
        self.settings = RenderSettings()
        self.h = height_range(terrain, np.asarray(roots_y, np.float64), self.settings)
        self.rast = Rasterizer(self.width, self.height)
        self.rast.set_terrain(terrain.vertices, terrain.faces)
        self.followed = followed_entities(layout)
        self.last_float: np.ndarray | None = None
        self.reset_camera()

    def reset_camera(self, start: Cameras | None = None) -> None:
        """The follow camera starts over (a new scene), seeded at ``start`` (a camera of the view's size) if given."""
        self.follow = FollowCamera(self.fps, self.width, self.height, start)

    def release(self) -> None:
        self.rast.release()

    def camera(self, world: dict[str, np.ndarray], rot: dict[str, np.ndarray], mode: str, orbit: Orbit) -> Cameras:
        """This frame's camera; the follow camera advances every frame (also while the orbit camera is shown), so
        switching back to it finds it where a recording's render has it."""
        ents = self.followed
        roots = [np.asarray(world[e.name][0], np.float64) for e in ents]
        valid = [bool(np.isfinite(r).all()) for r in roots]
        fwd = np.asarray(rot[ents[0].name], np.float64) @ np.asarray(ents[0].rig.forward_axis, np.float64)
        follow = self.follow.camera(roots, fwd, valid)
        if mode == "follow":
            return follow
        seen = [r for r, v in zip(roots, valid) if v]
        target = np.mean(seen, axis=0) + np.array([0.0, 1.0, 0.0]) if seen else np.zeros(3)
        return orbit.camera(target, self.width, self.height)

    def render(
        self, world: dict[str, np.ndarray], rot: dict[str, np.ndarray], mode: str = "follow", orbit: Orbit | None = None
    ) -> np.ndarray:
        """The G-buffer of one frame (entity → (K, 3) world joints; articulated entity → (3, 3) root rotation) as
        (H, W, 3) uint8: R height, G render id, B inverse depth."""
        return self.render_with(self.camera(world, rot, mode, orbit or Orbit()), 0, world)

    def render_with(self, cams: Cameras, i: int, world: dict[str, np.ndarray]) -> np.ndarray:
        """``render`` through frame ``i`` of given cameras (a replay's follow camera, run over the whole segment)."""
        s = self.settings
        bones = bone_segments(self.layout, frame_skeletons(self.layout, world), 0)
        rgb = self.rast.render(cams, i, bones, self.h[0], self.h[1], s.z_near, s.z_far, s.cull_m)
        self.last_float = rgb  # (H, W, 3) float32, the channels a pose target encodes
        return np.rint(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def stage_map(terrain: TerrainScene, cells: int = MAP_CELLS) -> dict:
    """The stage seen from above: {"x0", "z0", "cell" (m), "nx", "nz", "heights": row-major nz × nx (None where no
    terrain), "h_min", "h_max"}; an empty dict without terrain."""
    V = np.asarray(terrain.vertices, np.float64)
    if not len(V):
        return {}
    lo, hi = V[:, [0, 2]].min(0), V[:, [0, 2]].max(0)
    cell = max(float((hi - lo).max()) / cells, 0.25)
    n = np.minimum(np.floor((hi - lo) / cell).astype(int) + 1, cells)
    ix = np.minimum(((V[:, 0] - lo[0]) / cell).astype(int), n[0] - 1)
    iz = np.minimum(((V[:, 2] - lo[1]) / cell).astype(int), n[1] - 1)
    grid = np.full(n[1] * n[0], -np.inf)
    np.maximum.at(grid, iz * n[0] + ix, V[:, 1])
    grid = _fill_gaps(grid.reshape(n[1], n[0])).reshape(-1)
    heights = [None if not np.isfinite(h) else round(float(h), 2) for h in grid]
    return {
        "x0": float(lo[0]),
        "z0": float(lo[1]),
        "cell": cell,
        "nx": int(n[0]),
        "nz": int(n[1]),
        "heights": heights,
        "h_min": float(V[:, 1].min()),
        "h_max": float(V[:, 1].max()),
    }


def _fill_gaps(grid: np.ndarray, passes: int = 2) -> np.ndarray:
    """Empty (−inf) cells of a height grid next to filled ones take their highest neighbour (the mesh's vertices are
    sparser than a fine map grid), ``passes`` times."""
    g = grid.copy()
    for _ in range(passes):
        p = np.pad(g, 1, constant_values=-np.inf)
        near = np.max(
            [p[1 + dz : 1 + dz + g.shape[0], 1 + dx : 1 + dx + g.shape[1]] for dz in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0
        )
        g = np.where(np.isfinite(g), g, near)
    return g
