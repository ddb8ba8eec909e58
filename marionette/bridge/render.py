"""The rasterizer: terrain mesh + bone capsules → the G-buffer floats, with moderngl on headless EGL.

OpenGL through moderngl, on EGL with no display (Mesa llvmpipe on a CPU, the vendor driver on a GPU).
One half-float RGBA colour target and a depth buffer; depth test on; background cleared to 0.

Precision: nothing world-sized reaches float32. The terrain mesh is uploaded relative to an anchor
(float64 subtraction on the CPU, the stage's first vertex); each frame passes the camera position
relative to that anchor, and the bone capsules relative to the camera, so a scene 100 km from the
origin renders like one at the origin. Heights are recovered in the shader from the same relative
coordinates plus a per-draw float offset (anchor or camera height − h_min), small numbers both.

Capsules are instanced: one unit capsule (two hemispheres joined by a cylinder, ``CAPSULE_SIDES``
around, ``CAPSULE_RINGS`` per hemisphere) is placed per bone by the vertex shader from the bone's two
end points and radius. The projection matches ``camera.Cameras.project`` exactly: pixel centres at
+½, v down; NDC x = 2u/W − 1, y = 1 − 2v/H. Terrain fragments nearer than ``cull_m`` (3 m) are
discarded; bones never are.

A capsule is a closed convex mesh wound outwards, so behind the near plane's reach only its front faces can be
seen: where every capsule of a frame lies beyond the near plane (``capsules_beyond``) the bones are drawn with back
faces culled (llvmpipe renders such a frame 1.4–1.6× as fast up to 352×640: ``benchmarks/bench_bridge.py --part
faces``). The picture is the same but for a pixel whose centre lies exactly on a silhouette edge, which the
rasterizer's fill rule may give to the back face.
A frame with a capsule at the near plane or behind the camera (the camera inside a body) draws both faces.
"""

from __future__ import annotations

import numpy as np

from .camera import Cameras
from .gbuffer import HALF_TO_CODE

CAPSULE_SIDES = 12
CAPSULE_RINGS = 4
TERRAIN_CULL_M = 3.0

_VS_TERRAIN = """
#version 330
uniform mat4 u_proj;
uniform mat3 u_view;       // world-to-camera rotation (R^T)
uniform vec3 u_cam_rel;    // camera position relative to the anchor
uniform float u_h_off;     // anchor height - h_min
in vec3 in_pos;            // vertex relative to the anchor
out float v_y;             // world height - h_min
out float v_depth;         // view depth (m)
void main() {
    vec3 p = u_view * (in_pos - u_cam_rel);
    v_y = in_pos.y + u_h_off;
    v_depth = -p.z;
    gl_Position = u_proj * vec4(p, 1.0);
}
"""

_VS_BONE = """
#version 330
uniform mat4 u_proj;
uniform mat3 u_view;
uniform float u_h_off;     // camera height - h_min
in vec4 in_unit;           // unit capsule: (cos, sin) around, axial offset, end (0 = a, 1 = b)
in vec3 in_a;              // bone end at the parent, relative to the camera
in vec3 in_b;              // bone end at the child, relative to the camera
in float in_r;
in float in_id;
out float v_y;
out float v_depth;
flat out float v_id;
void main() {
    vec3 axis = in_b - in_a;
    float len = length(axis);
    vec3 n = len > 1e-6 ? axis / len : vec3(0.0, 1.0, 0.0);
    vec3 helper = abs(n.y) < 0.9 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);
    vec3 u = normalize(cross(n, helper));
    vec3 w = cross(n, u);
    vec3 q = mix(in_a, in_b, in_unit.w) + in_r * (u * in_unit.x + w * in_unit.y + n * in_unit.z);
    vec3 p = u_view * q;
    v_y = q.y + u_h_off;
    v_depth = -p.z;
    v_id = in_id;
    gl_Position = u_proj * vec4(p, 1.0);
}
"""

_FS = """
#version 330
uniform float u_h_scale;   // 1 / (h_max - h_min)
uniform float u_z_near;
uniform float u_z_far;
uniform float u_cull;      // terrain: discard nearer than this; bones: 0
uniform int u_terrain;
in float v_y;
in float v_depth;
%s
out vec4 f_color;
void main() {
    if (v_depth < u_cull) discard;
    float h = clamp(v_y * u_h_scale, 0.0, 1.0);
    float inv = clamp(1.0 - (v_depth - u_z_near) / (u_z_far - u_z_near), 0.0, 1.0);
    if (u_terrain == 1) f_color = vec4(0.5 + 0.5 * h, 0.0, inv, 1.0);
    else f_color = vec4(0.2 * h, %s / 255.0, inv, 1.0);
}
"""


def projection(K: np.ndarray, width: int, height: int, z_near: float, z_far: float) -> np.ndarray:
    """(4, 4) OpenGL clip matrix of pinhole intrinsics (fx, fy, cx, cy) in pixels, pixel centres at +½, v down."""
    fx, fy, cx, cy = (float(k) for k in K)
    n, f = float(z_near), float(z_far)
    return np.array(
        [
            [2 * fx / width, 0.0, 1 - 2 * cx / width, 0.0],
            [0.0, 2 * fy / height, 2 * cy / height - 1, 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


def unit_capsule(sides: int = CAPSULE_SIDES, rings: int = CAPSULE_RINGS) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 4) float32 (cos·ρ, sin·ρ, axial, end) and triangles (T, 3) int32 of the unit capsule."""
    lat = np.concatenate([np.linspace(-np.pi / 2, 0, rings + 1), np.linspace(0, np.pi / 2, rings + 1)])
    end = np.concatenate([np.zeros(rings + 1), np.ones(rings + 1)])
    th = 2 * np.pi * np.arange(sides) / sides
    rho, ax = np.cos(lat), np.sin(lat)
    V = np.stack(
        [
            np.outer(rho, np.cos(th)),
            np.outer(rho, np.sin(th)),
            np.repeat(ax[:, None], sides, 1),
            np.repeat(end[:, None], sides, 1),
        ],
        -1,
    ).reshape(-1, 4)
    L = len(lat)
    i = np.arange(L - 1)[:, None] * sides + np.arange(sides)[None]
    j = np.arange(L - 1)[:, None] * sides + (np.arange(sides)[None] + 1) % sides
    T = np.concatenate([np.stack([i, j, i + sides], -1).reshape(-1, 3), np.stack([j, j + sides, i + sides], -1).reshape(-1, 3)])
    return V.astype(np.float32), T.astype(np.int32)


def capsules_beyond(a_rel: np.ndarray, b_rel: np.ndarray, r: np.ndarray, back: np.ndarray, z_near: float) -> bool:
    """Whether every capsule (ends ``a_rel``, ``b_rel`` (B, 3) relative to the camera, radii ``r``) lies wholly
    beyond the near plane: its view depth (along −``back``, the camera's +Z in the world) at least ``z_near`` plus a
    margin of 1 % and 1 mm. A capsule's depth is least at one of its ends, less its radius."""
    depth = np.minimum(-(np.asarray(a_rel) @ back), -(np.asarray(b_rel) @ back)) - np.asarray(r, np.float64)
    return bool(np.all(depth > z_near * 1.01 + 1e-3))


class Rasterizer:
    """A headless GL context rendering G-buffer frames of one size (``width`` × ``height``)."""

    def __init__(self, width: int, height: int, backend: str = "egl"):
        import moderngl

        self.width, self.height = int(width), int(height)
        try:
            self.ctx = moderngl.create_standalone_context(backend=backend, require=330)
        except Exception as err:  # noqa: BLE001 - any driver failure is reported the same way
            raise RuntimeError(
                f"cannot create a headless OpenGL context ({backend}): {err}. Install Mesa's EGL "
                "(Debian: libegl1 libgl1-mesa-dri) or a GPU driver."
            ) from err
        ctx = self.ctx
        self._color = ctx.renderbuffer((self.width, self.height), 4, dtype="f2")
        self._depth = ctx.depth_renderbuffer((self.width, self.height))
        self.fbo = ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        self._terrain_prog = ctx.program(vertex_shader=_VS_TERRAIN, fragment_shader=_FS % ("", "0.0"))
        self._bone_prog = ctx.program(vertex_shader=_VS_BONE, fragment_shader=_FS % ("flat in float v_id;", "v_id"))
        V, T = unit_capsule()
        self._cap_vbo = ctx.buffer(V.tobytes())
        self._cap_ibo = ctx.buffer(T.tobytes())
        self._inst = None
        self._inst_cap = 0
        self._terrain_vao = None
        self.anchor = np.zeros(3)

    def release(self) -> None:
        """Free the GL context."""
        self.ctx.release()

    def __enter__(self) -> Rasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def set_terrain(self, vertices_world: np.ndarray, faces: np.ndarray) -> None:
        """Upload the terrain mesh (vertices (V, 3) float64 world metres, faces (F, 3)); empty = no terrain."""
        if self._terrain_vao is not None:
            self._terrain_vao.release()
            self._terrain_vao = None
        V = np.asarray(vertices_world, np.float64)
        F = np.asarray(faces, np.int64)
        if not len(V) or not len(F):
            return
        self.anchor = V[0].copy()
        vbo = self.ctx.buffer((V - self.anchor).astype(np.float32).tobytes())
        ibo = self.ctx.buffer(F.astype(np.int32).tobytes())
        self._terrain_vao = self.ctx.vertex_array(self._terrain_prog, [(vbo, "3f", "in_pos")], index_buffer=ibo)

    def _instances(self, a, b, r, ids) -> int:
        n = len(a)
        data = np.empty((n, 8), np.float32)
        data[:, 0:3], data[:, 3:6], data[:, 6], data[:, 7] = a, b, r, ids
        if n > self._inst_cap:
            if self._inst is not None:
                self._inst.release()
            self._inst_cap = max(n, 2 * self._inst_cap, 64)
            self._inst = self.ctx.buffer(reserve=self._inst_cap * 32)
            self._bone_vao = self.ctx.vertex_array(
                self._bone_prog,
                [(self._cap_vbo, "4f", "in_unit"), (self._inst, "3f 3f 1f 1f/i", "in_a", "in_b", "in_r", "in_id")],
                index_buffer=self._cap_ibo,
            )
        self._inst.write(data.tobytes())
        return n

    def _draw(
        self, cameras: Cameras, i: int, bones, h_min: float, h_max: float, z_near: float, z_far: float, cull_m: float
    ) -> np.ndarray | None:
        """Draw frame ``i`` and read back the half-float bits (H, W, 4) uint16, rows bottom-up; None if the camera is invalid."""
        if (cameras.width, cameras.height) != (self.width, self.height):
            raise ValueError(f"cameras are {cameras.height}×{cameras.width}, the rasterizer {self.height}×{self.width}")
        if not cameras.valid[i]:
            return None
        import moderngl

        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        pos, R = cameras.pos[i], cameras.rot[i]
        proj = projection(cameras.K[i], self.width, self.height, z_near, z_far).astype(np.float32)
        view = np.ascontiguousarray(R.T.astype(np.float32))
        scale = 1.0 / (h_max - h_min)
        for prog, cull, terrain in ((self._terrain_prog, cull_m, 1), (self._bone_prog, 0.0, 0)):
            prog["u_proj"].write(proj.T.tobytes())  # GL matrices are column-major
            prog["u_view"].write(view.T.tobytes())
            prog["u_h_scale"].value = scale
            prog["u_z_near"].value, prog["u_z_far"].value = z_near, z_far
            prog["u_cull"].value = cull
            prog["u_terrain"].value = terrain
        if self._terrain_vao is not None:
            self._terrain_prog["u_cam_rel"].value = tuple(float(v) for v in (pos - self.anchor).astype(np.float32))
            self._terrain_prog["u_h_off"].value = float(self.anchor[1] - h_min)
            self._terrain_vao.render()
        a, b, r, ids = bones
        if len(a):
            a_rel, b_rel = np.asarray(a) - pos, np.asarray(b) - pos
            n = self._instances(a_rel, b_rel, r, ids)
            self._bone_prog["u_h_off"].value = float(pos[1] - h_min)
            if capsules_beyond(a_rel, b_rel, r, R[:, 2], z_near):
                self.ctx.enable(moderngl.CULL_FACE)  # front faces alone (module doc); every frame starts with it off
            self._bone_vao.render(instances=n)
        return np.frombuffer(self.fbo.read(components=4, dtype="f2"), np.uint16).reshape(self.height, self.width, 4)

    def render(
        self,
        cameras: Cameras,
        i: int,
        bones: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        h_min: float,
        h_max: float,
        z_near: float,
        z_far: float,
        cull_m: float = TERRAIN_CULL_M,
    ) -> np.ndarray:
        """Render frame ``i`` of ``cameras`` with bone capsules (a, b world (B, 3), radii (B,), ids (B,)):
        the (H, W, 3) float32 R, G, B of the G-buffer (row 0 at the top); all zero where the camera is invalid."""
        bits = self._draw(cameras, i, bones, h_min, h_max, z_near, z_far, cull_m)
        if bits is None:
            return np.zeros((self.height, self.width, 3), np.float32)
        return bits[::-1, :, :3].view(np.float16).astype(np.float32)

    def render_planes(
        self,
        cameras: Cameras,
        i: int,
        bones: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
        h_min: float,
        h_max: float,
        z_near: float,
        z_far: float,
        cull_m: float = TERRAIN_CULL_M,
    ) -> np.ndarray:
        """``render`` straight to 10-bit code planes (3, H, W) uint16 in G, B, R order (the encoder's), through
        one table lookup per channel: equal to ``to_codes(render(...))`` re-ordered, without the float copies."""
        bits = self._draw(cameras, i, bones, h_min, h_max, z_near, z_far, cull_m)
        out = np.zeros((3, self.height, self.width), np.uint16)
        if bits is not None:
            flipped = bits[::-1]
            for k, c in enumerate((1, 2, 0)):
                np.take(HALF_TO_CODE, flipped[:, :, c], out=out[k])
        return out
