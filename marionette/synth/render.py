"""Ray-cast rendering of the synthetic game: a follow camera, shaded RGB and an 8-bit depth map.

Cameras are pinhole, OpenGL frame (looks down its local −Z, +Y up), camera-to-world rotation R_cw
and position in the world. One ray per pixel centre; with the ray direction written as
R_cw · ((u + ½ − cx)/fx, −(v + ½ − cy)/fy, −1) the ray parameter at a hit is the z-depth (m).

Depth encoding (8-bit, inverse depth): code = 0 where nothing is hit or z > Z_FAR, else
code = clip(round(1 + 254 · (1/z − 1/Z_FAR) / (1/Z_NEAR − 1/Z_FAR)), 1, 255); decoding inverts it.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import open3d as o3d

from terrain_scan.depth import SYNTHETIC_Z_FAR as Z_FAR
from terrain_scan.depth import SYNTHETIC_Z_NEAR as Z_NEAR

from . import terrain as ter

RENDER_PIXELS = 1 << 16  # the pixels of the frames one render call takes (``Renderer.frames``): a few MB
VFOV_DEG = 60.0


def encode_depth(z: np.ndarray) -> np.ndarray:
    """z-depth (m, inf = no hit) → uint8 code (0 = no hit / beyond Z_FAR)."""
    z = np.asarray(z, dtype=np.float64)
    ok = np.isfinite(z) & (z <= Z_FAR) & (z > 0)
    inv = 1.0 / np.where(ok, z, 1.0)
    code = np.clip(np.round(1 + 254 * (inv - 1 / Z_FAR) / (1 / Z_NEAR - 1 / Z_FAR)), 1, 255)
    return np.where(ok, code, 0).astype(np.uint8)


def decode_depth(code: np.ndarray) -> np.ndarray:
    """uint8 code → z-depth (m); nan where the code is 0. Codes may be fractional (bin edges)."""
    c = np.asarray(code, dtype=np.float64)
    inv = (c - 1) / 254 * (1 / Z_NEAR - 1 / Z_FAR) + 1 / Z_FAR
    return np.where(c > 0, 1.0 / np.maximum(inv, 1e-12), np.nan)


def intrinsics(width: int, height: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels for the fixed vertical field of view."""
    f = (height / 2) / np.tan(np.radians(VFOV_DEG) / 2)
    return f, f, width / 2, height / 2


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation (3, 3), OpenGL frame, looking from ``eye`` at ``target`` with world +Y up."""
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross([0.0, 1.0, 0.0], back)
    right = right / np.linalg.norm(right)
    up = np.cross(back, right)
    return np.stack([right, up, back], axis=1)


def follow_camera(
    hunter_root: np.ndarray,
    hunter_yaw: np.ndarray,
    monster_root: np.ndarray,
    present: np.ndarray,
    pan: np.ndarray | None = None,
):
    """Smoothed third-person camera per frame: positions (N, 3) and camera-to-world rotations (N, 3, 3).
    ``pan`` (N,): the camera's look turned about its own vertical axis (rad; a player looking around, the
    characters leaving the view and coming back), during which it stops turning to the monster."""
    N = len(hunter_root)
    pos, rot = np.zeros((N, 3)), np.zeros((N, 3, 3))
    eye = look = None
    for i in range(N):
        fwd = np.array([np.sin(hunter_yaw[i]), 0.0, np.cos(hunter_yaw[i])])
        want_eye = hunter_root[i] - 6.0 * fwd + np.array([0.0, 3.0, 0.0])
        want_look = hunter_root[i] + np.array([0.0, 0.6, 0.0]) + 2.0 * fwd
        turned = pan is not None and abs(pan[i]) > 0.2
        if present[i] and not turned and np.linalg.norm(monster_root[i] - hunter_root[i]) < 25.0:
            want_look = 0.65 * want_look + 0.35 * monster_root[i]
        if pan is not None and pan[i]:
            c, s = np.cos(pan[i]), np.sin(pan[i])
            d = want_look - want_eye
            want_look = want_eye + np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])
        eye = want_eye if eye is None else eye + 0.12 * (want_eye - eye)
        look = want_look if look is None else look + 0.2 * (want_look - look)
        floor = float(ter.ground_height(eye[0], eye[2])) + 1.5
        eye = np.array([eye[0], max(eye[1], floor), eye[2]])
        pos[i], rot[i] = eye, look_at(eye, look)
    return pos, rot


def camera_pans(seed: int, index: int, n_frames: int, fps: float) -> np.ndarray:
    """(N,) angles of a camera a player turns to look around now and then (``follow_camera``'s ``pan``), drawn by
    (seed, index): every 2–5 s a swing of 2.5–4 s that eases out to 120–180° either way and back (raised cosine)."""
    rng = np.random.default_rng([seed, 0x0CB, index])
    out = np.zeros(n_frames)
    t = rng.uniform(1.0, 3.0)
    while t * fps < n_frames:
        length, angle = rng.uniform(2.5, 4.0), np.radians(rng.uniform(120.0, 180.0)) * rng.choice([-1.0, 1.0])
        a, b = int(t * fps), min(n_frames, int((t + length) * fps))
        u = (np.arange(a, b) - a) / max(b - a, 1)
        out[a:b] = angle * 0.5 * (1.0 - np.cos(2.0 * np.pi * u))
        t += length + rng.uniform(2.0, 5.0)
    return out


def _capsules(points: np.ndarray, edges: np.ndarray, radius: np.ndarray, sides: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Prisms along bones plus octahedra at joints: vertices (..., V, 3) float32 of ``points`` (..., J, 3), one mesh
    per leading index (every frame of a recording at once: the arithmetic per vertex is the same as one frame's), and
    the triangles (T, 3) uint32 they share."""
    a, b = points[..., edges[:, 0], :], points[..., edges[:, 1], :]  # (..., E, 3)
    r = radius[:, None, None]
    axis = b - a
    axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
    helper = np.where(np.abs(axis[..., 1:2]) < 0.9, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    u = np.cross(axis, helper)
    u /= np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-9)
    v = np.cross(axis, u)
    th = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(th)[:, None] * u[..., None, :] + np.sin(th)[:, None] * v[..., None, :]  # (..., E, S, 3)
    V = np.concatenate([a[..., None, :] + r * ring, b[..., None, :] + r * ring], axis=-2)  # (..., E, 2S, 3)
    j = np.arange(sides)
    k = (j + 1) % sides
    quad = np.concatenate([np.stack([j, k, j + sides], -1), np.stack([k, k + sides, j + sides], -1)])  # (2S, 3)
    T = (quad[None] + (2 * sides * np.arange(len(edges)))[:, None, None]).reshape(-1, 3)
    V = V.reshape(*V.shape[:-3], -1, 3)
    # Joint blobs.
    octa = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    of = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    J = points.shape[-2]
    jr = np.zeros(J)
    np.maximum.at(jr, edges[:, 0], radius)
    np.maximum.at(jr, edges[:, 1], radius)
    BV = (points[..., None, :] + 1.3 * jr[:, None, None] * octa).reshape(*points.shape[:-2], -1, 3)
    BT = (of[None] + 6 * np.arange(J)[:, None, None]).reshape(-1, 3) + V.shape[-2]
    return np.concatenate([V, BV], axis=-2).astype(np.float32), np.concatenate([T, BT]).astype(np.uint32)


class Renderer:
    """Renders frames of the stage with characters; the terrain scene is built once."""

    MATERIALS = ("ground", "wall", "deck", "monster", "hunter", "weapon")

    def __init__(
        self,
        width: int,
        height: int,
        edges: dict[str, np.ndarray],
        radii: dict[str, np.ndarray],
        colours: dict[str, tuple[float, float, float]] | None = None,
        threads: int = 0,
    ):
        """``threads``: open3d's ray-casting threads (0: every core); the pixels are the same at any count."""
        self.width, self.height = width, height
        self.threads = int(threads)
        self.colours = dict(colours or {})  # a recording's own albedo of a character (cast.Skin), else the game's
        self.K = intrinsics(width, height)
        self.edges, self.radii = edges, radii
        self.terrain = o3d.t.geometry.RaycastingScene()
        self.terrain_ids = {}
        for name, V, T in ter.terrain_mesh():
            self.terrain_ids[self.terrain.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(T))] = self.MATERIALS.index(name)
        fx, fy, cx, cy = self.K
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        self.dirs_cam = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones_like(u)], -1)  # (H, W, 3)

    def rays(self, pos: np.ndarray, R_cw: np.ndarray) -> np.ndarray:
        """(H, W, 3) world ray directions whose parameter is the z-depth."""
        return self.dirs_cam @ R_cw.T

    def meshes(self, name: str, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body ``name``'s capsule mesh at joints ``points`` (J, 3), or at every frame's of (N, J, 3): vertices
        (..., V, 3) float32 and the triangles (T, 3) uint32."""
        return _capsules(points, self.edges[name], self.radii[name])

    def render(
        self, pos: np.ndarray, R_cw: np.ndarray, bodies: dict[str, tuple[np.ndarray, np.ndarray]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8 and z-depth (H, W) float64 (inf where nothing is hit) of the terrain and ``bodies``:
        name → this frame's mesh (``meshes``), a body not shown left out."""
        rgb, z = self.render_frames(pos[None], R_cw[None], [bodies])
        return rgb[0], z[0]

    def frames(
        self, pos: np.ndarray, R_cw: np.ndarray, bodies: list[dict[str, tuple[np.ndarray, np.ndarray]]]
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Each frame's ``render`` (cameras ``pos`` (N, 3), ``R_cw`` (N, 3, 3), ``bodies[i]`` frame i's), in order,
        rendered ``RENDER_PIXELS`` of frames at a call (``render_frames``)."""
        per_call = max(1, RENDER_PIXELS // (self.width * self.height))
        for a in range(0, len(pos), per_call):
            rgb, z = self.render_frames(pos[a : a + per_call], R_cw[a : a + per_call], bodies[a : a + per_call])
            yield from zip(rgb, z, strict=True)

    def render_frames(
        self, pos: np.ndarray, R_cw: np.ndarray, bodies: list[dict[str, tuple[np.ndarray, np.ndarray]]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``render`` of K frames at once (cameras ``pos`` (K, 3), ``R_cw`` (K, 3, 3), ``bodies[k]`` frame k's): RGB
        (K, H, W, 3) and z-depth (K, H, W), each frame's the bytes ``render`` gives it alone. The terrain's rays are
        cast and the pixels shaded for every frame in one call (the arithmetic per ray and per pixel is the same);
        the characters, posed anew each frame, are a scene per frame."""
        d = np.stack([self.rays(p, R) for p, R in zip(pos, R_cw, strict=True)])  # (K, H, W, 3)
        rays = np.concatenate([np.broadcast_to(pos[:, None, None, :], d.shape), d], -1).astype(np.float32)
        hit = self.terrain.cast_rays(o3d.core.Tensor(rays), nthreads=self.threads)
        t = hit["t_hit"].numpy().astype(np.float64)
        n = hit["primitive_normals"].numpy().astype(np.float64)
        gid = hit["geometry_ids"].numpy()
        mat = np.full(t.shape, -1, dtype=np.int64)
        for g, m in self.terrain_ids.items():
            mat[gid == g] = m
        mat[~np.isfinite(t)] = -1
        for k, shown in enumerate(bodies):
            chars = o3d.t.geometry.RaycastingScene()
            char_ids = {}
            for name, (V, T) in shown.items():
                char_ids[chars.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(T))] = self.MATERIALS.index(name)
            if not char_ids:
                continue
            ch = chars.cast_rays(o3d.core.Tensor(rays[k]), nthreads=self.threads)
            tc = ch["t_hit"].numpy().astype(np.float64)
            nearer = np.isfinite(tc) & (tc < t[k])
            t[k] = np.where(nearer, tc, t[k])
            n[k] = np.where(nearer[..., None], ch["primitive_normals"].numpy(), n[k])
            cg = ch["geometry_ids"].numpy()
            for g, m in char_ids.items():
                mat[k][nearer & (cg == g)] = m
        return self._shade(pos, d, t, n, mat), t

    def _shade(self, pos, d, t, n, mat) -> np.ndarray:
        """Sky where nothing is hit; elsewhere each material's albedo, sun-lit and fogged, of K frames: ``pos`` (K, 3)
        their cameras, ``d`` (K, H, W, 3) their rays. Shading runs over the hit pixels only, with each material's albedo
        computed over its own pixels (the arithmetic per pixel is the same as over one whole image)."""
        dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
        sky = np.clip(0.5 + 0.5 * dn[..., 1:2], 0, 1)
        img = (1 - sky) * np.array([0.85, 0.9, 1.0]) + sky * np.array([0.35, 0.55, 0.9])
        hitm = mat >= 0
        if hitm.any():
            m_hit, tt, dh, nh = mat[hitm], t[hitm], d[hitm], n[hitm]  # (N,), (N,), (N, 3), (N, 3)
            p = pos[np.nonzero(hitm)[0]] + tt[..., None] * dh
            nh = np.where(np.sum(nh * dh, -1, keepdims=True) > 0, -nh, nh)
            sun = np.array([0.4, 0.8, 0.3]) / np.linalg.norm([0.4, 0.8, 0.3])
            lam = 0.35 + 0.65 * np.clip(np.sum(nh * sun, -1), 0, 1)
            col = np.zeros((len(tt), 3))
            for m in np.unique(m_hit):
                sel = m_hit == m
                col[sel] = self._albedo(int(m), p[sel], nh[sel])
            fog = np.clip(tt / 250.0, 0, 1)[..., None] ** 2
            shaded = col * lam[..., None]
            img[hitm] = shaded * (1 - fog) + img[hitm] * fog
        return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)

    def _albedo(self, m: int, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(N, 3) albedo of material ``m`` at world points ``p`` (N, 3) with normals ``n`` (N, 3)."""
        if m in (0, 1):
            fine = (0.5 + 0.5 * np.sin(p[..., 0] * 3.1) * np.sin(p[..., 2] * 2.7))[..., None]
            rock = np.array([0.50, 0.47, 0.44]) * (0.85 + 0.15 * fine)
            if m == 1:
                return rock * (0.8 + 0.2 * (np.floor(p[..., 1:2] * 2) % 2))
            check = ((np.floor(p[..., 0] / 2) + np.floor(p[..., 2] / 2)) % 2)[..., None]
            grass = np.array([0.30, 0.55, 0.22]) * (0.85 + 0.15 * check) * (0.9 + 0.1 * fine)
            steep = (n[..., 1:2] < 0.88).astype(np.float64)
            return grass * (1 - steep) + rock * steep
        if m == 2:
            return np.array([0.55, 0.38, 0.2]) * (0.8 + 0.2 * (np.floor(p[..., 0:1] * 3) % 2))
        fixed = {
            3: self.colours.get("monster", (0.6, 0.15, 0.1)),
            4: self.colours.get("hunter", (0.15, 0.3, 0.75)),
            5: (0.85, 0.85, 0.9),
        }
        return np.broadcast_to(np.array(fixed[m]), (len(p), 3))
