"""The rasterizer: terrain mesh + bone capsules → the G-buffer's 10-bit codes, with moderngl on headless EGL.

OpenGL through moderngl, on EGL with no display (Mesa llvmpipe on a CPU, the vendor driver on a GPU).
One 32-bit unsigned-integer colour target and a depth buffer; depth test on; background cleared to 0. The
vertex shaders compute each channel's value before its clamp (affine in the vertex's position, so interpolating
it is exact), the fragment shader clamps and rounds each to its code round(1023 · v) (``gbuffer``'s module
docstring) and writes the pixel's three codes packed in one word (``gbuffer.pack_planes``: G | B << 10 |
R << 20): the frame is read back as the words a ``.gbz`` file stores, with nothing to convert, and one
target costs llvmpipe less to clear and to write than one per channel. An id's code is integer arithmetic,
exact on every driver. The projection's y is mirrored so that GL's bottom-up rows land top-down in memory
(row 0 at the top of the image, as ``camera.Cameras.project`` numbers them); the mirror turns the winding
of every triangle, so what is counter-clockwise in the image is clockwise to GL, and front faces are
declared clockwise.

Precision: nothing world-sized reaches float32. The terrain mesh is uploaded relative to an anchor
(float64 subtraction on the CPU, the stage's first vertex); each frame passes the camera position
relative to that anchor, and the bone capsules relative to the camera, so a scene 100 km from the
origin renders like one at the origin. Heights are recovered in the shader from the same relative
coordinates plus a per-draw float offset (anchor or camera height − h_min), small numbers both.

Capsules are traced, not tessellated: each bone is drawn as the box around its capsule (instanced, 12 triangles,
by its far faces, so every pixel it covers is shaded once whether the camera is outside the box or inside it),
and the fragment shader intersects the pixel's ray with the capsule itself (two balls of the bone's radius at its
ends and the cylinder between them), discards a pixel whose ray misses it and writes the hit's depth
(``gl_FragDepth``) for the depth test against the terrain and the other bones: the exact capsule, at a cost of
triangles that does not grow with its size on screen. The surface seen is the nearest the ray meets beyond the near
plane: the capsule's outside, or its inside where the camera is within the capsule. The projection matches
``camera.Cameras.project`` exactly: pixel centres at +½, v down; NDC x = 2u/W − 1, y = 1 − 2v/H. Terrain nearer
than ``cull_m`` (3 m of view depth) is clipped away (a clip distance, not a discard, so llvmpipe keeps its early
depth test); bones never are. The terrain is drawn by tiles (``TERRAIN_TILE_M`` square): a frame draws the tiles
whose box may meet its view, so a frame's cost follows what it sees, not how large its stage has grown.
"""

from __future__ import annotations

import numpy as np

from .camera import Cameras
from .gbuffer import CODE_MAX, unpack_planes

GL_CLIP_DISTANCE0 = 0x3000  # glEnable's name of the first clip distance (moderngl has none)
TERRAIN_CULL_M = 3.0
TERRAIN_TILE_M = 25.0  # side of the squares the terrain's triangles are drawn by (``Rasterizer.set_terrain``)
TILE_PAD_M = 0.01  # a tile's box grown by this on every side: far more than float32's rounding of a stage's vertices

_VS_TERRAIN = """
#version 330
uniform mat4 u_proj;
uniform mat3 u_view;       // world-to-camera rotation (R^T)
uniform vec3 u_cam_rel;    // camera position relative to the anchor
uniform float u_h_off;     // anchor height - h_min
uniform float u_h_scale;   // 1 / (h_max - h_min)
uniform float u_z_near;
uniform float u_z_scale;   // 1 / (z_far - z_near)
uniform float u_cull;      // terrain nearer than this (m of view depth) is clipped away
in vec3 in_pos;            // vertex relative to the anchor
out float v_r;             // 0.5 + 0.5 ĥ
out float v_b;             // inverse depth
void main() {
    vec3 p = u_view * (in_pos - u_cam_rel);
    v_r = 0.5 + 0.5 * (in_pos.y + u_h_off) * u_h_scale;
    v_b = 1.0 - (-p.z - u_z_near) * u_z_scale;
    gl_ClipDistance[0] = -p.z - u_cull;
    gl_Position = u_proj * vec4(p, 1.0);
}
"""

_VS_BONE = """
#version 330
uniform mat4 u_proj;
uniform mat3 u_view;
in vec3 in_corner;         // unit box corner: (±1, ±1) across the bone, ±1 along it
in vec3 in_a;              // bone end at the parent, relative to the camera
in vec3 in_b;              // bone end at the child, relative to the camera
in float in_r;
in float in_id;
out vec3 v_q;              // the box's surface point, relative to the camera (world axes)
flat out vec4 v_ball_a;    // the ball at a: its centre, |a|² − r²
flat out vec4 v_ball_b;    // the ball at b: its centre, |b|² − r²
flat out vec4 v_axis;      // the axis's unit vector n, the camera's place along it from a (−a · n)
flat out vec4 v_across;    // the camera's offset from the axis (−a − (−a · n) n), its squared length − r²
flat out float v_len;      // |b − a|; −1: no cylinder (a and b one point)
flat out uint v_g;         // the id's code
void main() {
    vec3 axis = in_b - in_a;
    float len = length(axis);
    vec3 n = len > 1e-6 ? axis / len : vec3(0.0, 1.0, 0.0);
    vec3 helper = abs(n.y) < 0.9 ? vec3(0.0, 1.0, 0.0) : vec3(1.0, 0.0, 0.0);
    vec3 u = normalize(cross(n, helper));
    vec3 w = cross(n, u);
    vec3 q = mix(in_a - in_r * n, in_b + in_r * n, 0.5 + 0.5 * in_corner.z) + in_r * (u * in_corner.x + w * in_corner.y);
    float r2 = in_r * in_r;
    float an = dot(-in_a, n);
    vec3 ap = -in_a - an * n;
    v_q = q;
    v_ball_a = vec4(in_a, dot(in_a, in_a) - r2);
    v_ball_b = vec4(in_b, dot(in_b, in_b) - r2);
    v_axis = vec4(n, an);
    v_across = vec4(ap, dot(ap, ap) - r2);
    v_len = len > 1e-6 ? len : -1.0;
    v_g = (uint(in_id + 0.5) * 2046u + 255u) / 510u;  // round(1023 · id / 255), never a tie
    gl_Position = u_proj * vec4(u_view * q, 1.0);
}
"""

# The capsule itself, traced along the pixel's ray t·d from the camera (the origin, |d| = 1): the ray meets the
# convex capsule (two balls and the solid cylinder between them) in one interval [t_in, t_out], the union of the
# three parts' intervals. The nearest end of it beyond the camera and within [z_near, z_far] is the surface seen:
# t_in from outside, t_out (the inside of the capsule) from within it or where t_in is nearer than z_near. Every
# term that does not depend on the ray is the bone's, computed once by its vertices (flat inputs): a pixel pays for
# a dot product and a square root per ball, and the cylinder's quadratic and slab along its ray.
_FS_BONE = """
#version 330
uniform mat3 u_view;
uniform float u_h_off;     // camera height - h_min
uniform float u_h_scale;   // 1 / (h_max - h_min)
uniform float u_z_near;
uniform float u_z_far;
uniform float u_z_scale;   // 1 / (z_far - z_near)
in vec3 v_q;
flat in vec4 v_ball_a;
flat in vec4 v_ball_b;
flat in vec4 v_axis;
flat in vec4 v_across;
flat in float v_len;
flat in uint v_g;
layout(location = 0) out uint o_codes;   // G | B << 10 | R << 20
const float FAR = 1e30;

void main() {
    vec3 d = normalize(v_q);
    float t_in = FAR, t_out = -FAR;
    float h = dot(v_ball_a.xyz, d), disc = h * h - v_ball_a.w;
    if (disc >= 0.0) { float s = sqrt(disc); t_in = h - s; t_out = h + s; }
    h = dot(v_ball_b.xyz, d);
    disc = h * h - v_ball_b.w;
    if (disc >= 0.0) { float s = sqrt(disc); t_in = min(t_in, h - s); t_out = max(t_out, h + s); }
    if (v_len > 0.0) {                      // the cylinder: across the axis a quadratic in t, along it a slab
        float dn = dot(d, v_axis.xyz), an = v_axis.w;
        vec3 dp = d - dn * v_axis.xyz;
        float qa = dot(dp, dp), qb = dot(v_across.xyz, dp), qc = v_across.w;
        vec2 iv = vec2(FAR, -FAR);
        if (qa < 1e-12) {                   // the ray along the axis: inside the cylinder's radius or never
            if (qc <= 0.0) iv = vec2(-FAR, FAR);
        } else {
            float dq = qb * qb - qa * qc;
            if (dq >= 0.0) { float s = sqrt(dq); iv = vec2(-qb - s, -qb + s) / qa; }
        }
        if (abs(dn) < 1e-12) {
            if (an < 0.0 || an > v_len) iv = vec2(FAR, -FAR);
        } else {
            float t0 = -an / dn, t1 = (v_len - an) / dn;
            iv = vec2(max(iv.x, min(t0, t1)), min(iv.y, max(t0, t1)));
        }
        if (iv.x <= iv.y) { t_in = min(t_in, iv.x); t_out = max(t_out, iv.y); }
    }
    if (t_in > t_out) discard;
    float dz = -dot(vec3(u_view[0][2], u_view[1][2], u_view[2][2]), d);   // view depth per unit of t
    float t = t_in;
    if (t <= 0.0 || t * dz < u_z_near) t = t_out;
    float z = t * dz;
    if (t <= 0.0 || z < u_z_near || z > u_z_far) discard;
    gl_FragDepth = u_z_far * u_z_scale * (1.0 - u_z_near / z);   // the projection's window depth of view depth z
    uint b = uint(floor(clamp(1.0 - (z - u_z_near) * u_z_scale, 0.0, 1.0) * 1023.0 + 0.5));
    uint r = uint(floor(clamp(0.2 * (t * d.y + u_h_off) * u_h_scale, 0.0, 0.2) * 1023.0 + 0.5));
    o_codes = v_g | (b << 10) | (r << 20);
}
"""

_FS_TERRAIN = """
#version 330
in float v_r;
in float v_b;
layout(location = 0) out uint o_codes;   // G | B << 10 | R << 20 (G = 0: terrain)
uint code(float v) { return uint(floor(v * 1023.0 + 0.5)); }
void main() {
    o_codes = (code(clamp(v_b, 0.0, 1.0)) << 10) | (code(clamp(v_r, 0.5, 1.0)) << 20);
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


def unit_box() -> tuple[np.ndarray, np.ndarray]:
    """Corners (8, 3) float32 (±1, ±1, ±1) and triangles (12, 3) int32 of the box around a capsule, wound
    counter-clockwise seen from outside (before the projection's mirror)."""
    V = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], np.float32)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    T = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return V, np.array(T, np.int32)


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
        size = (self.width, self.height)
        self._codes = ctx.renderbuffer(size, 1, dtype="u4")  # a pixel's packed codes
        self._depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(color_attachments=[self._codes], depth_attachment=self._depth)
        ctx.front_face = "cw"  # the mirrored projection (module doc)
        ctx.cull_face = "front"  # a capsule's box is drawn by its far faces: every pixel once, the camera inside or out
        self._terrain_prog = ctx.program(vertex_shader=_VS_TERRAIN, fragment_shader=_FS_TERRAIN)
        self._bone_prog = ctx.program(vertex_shader=_VS_BONE, fragment_shader=_FS_BONE)
        V, T = unit_box()
        self._box_vbo = ctx.buffer(V.tobytes())
        self._box_ibo = ctx.buffer(T.tobytes())
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
        """Upload the terrain mesh (vertices (V, 3) float64 world metres, faces (F, 3)); empty = no terrain.

        The triangles are grouped into square tiles of ``TERRAIN_TILE_M`` (by their first vertex), each tile one
        range of the index buffer with the box of its triangles' vertices: a frame draws the tiles whose box may
        meet its view (``Cameras.boxes_in_view``), so its cost follows what it sees, not the stage's size. A
        triangle wholly outside the view draws no pixel, so the frame is the one the whole mesh draws."""
        V = np.asarray(vertices_world, np.float64)
        F = np.asarray(faces, np.int64)
        with self.ctx:  # this rasterizer's context current on this thread (``render_packed``)
            if self._terrain_vao is not None:
                self._terrain_vao.release()
                self._terrain_vao = None
            if not len(V) or not len(F):
                return
            self.anchor = V[0].copy()
            tile = np.floor(V[F[:, 0]][:, [0, 2]] / TERRAIN_TILE_M).astype(np.int64)
            order = np.lexsort((tile[:, 1], tile[:, 0]))
            F, tile = F[order], tile[order]
            first = np.flatnonzero(np.r_[True, np.any(tile[1:] != tile[:-1], axis=1)])
            corners = [V[F[:, k]] for k in range(3)]
            # each box padded by TILE_PAD_M: the GPU clips the float32 vertices, the test reads the float64 ones
            lo = np.minimum.reduceat(np.minimum(np.minimum(*corners[:2]), corners[2]), first)
            hi = np.maximum.reduceat(np.maximum(np.maximum(*corners[:2]), corners[2]), first)
            self._tile_lo, self._tile_hi = lo - TILE_PAD_M, hi + TILE_PAD_M
            self._tile_first = 3 * first  # in indices
            self._tile_count = 3 * np.diff(np.r_[first, len(F)])
            vbo = self.ctx.buffer((V - self.anchor).astype(np.float32).tobytes())
            ibo = self.ctx.buffer(F.astype(np.int32).tobytes())
            self._terrain_vao = self.ctx.vertex_array(self._terrain_prog, [(vbo, "3f", "in_pos")], index_buffer=ibo)

    def terrain_ranges(self, cameras: Cameras, i: int, z_near: float, z_far: float, cull_m: float) -> list[tuple[int, int]]:
        """(first index, index count) of the terrain's tiles frame ``i`` may see, neighbours joined into one range.
        Nothing nearer than the terrain's cull is drawn either."""
        seen = cameras.boxes_in_view(i, self._tile_lo, self._tile_hi, max(z_near, cull_m), z_far)
        ranges: list[tuple[int, int]] = []
        for first, count in zip(self._tile_first[seen].tolist(), self._tile_count[seen].tolist()):
            if ranges and ranges[-1][0] + ranges[-1][1] == first:
                ranges[-1] = (ranges[-1][0], ranges[-1][1] + count)
            else:
                ranges.append((first, count))
        return ranges

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
                [(self._box_vbo, "3f", "in_corner"), (self._inst, "3f 3f 1f 1f/i", "in_a", "in_b", "in_r", "in_id")],
                index_buffer=self._box_ibo,
            )
        self._inst.write(data.tobytes())
        return n

    def _draw(
        self, cameras: Cameras, i: int, bones, h_min: float, h_max: float, z_near: float, z_far: float, cull_m: float
    ) -> bool:
        """Draw frame ``i`` into the codes' target; False (nothing drawn) if the camera is invalid."""
        if (cameras.width, cameras.height) != (self.width, self.height):
            raise ValueError(f"cameras are {cameras.height}×{cameras.width}, the rasterizer {self.height}×{self.width}")
        if not cameras.valid[i]:
            return False
        import moderngl

        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)  # the terrain's triangles face either way
        pos, R = cameras.pos[i], cameras.rot[i]
        proj = projection(cameras.K[i], self.width, self.height, z_near, z_far)
        proj[1] *= -1.0  # image rows top-down in memory (module doc)
        proj = proj.astype(np.float32)
        view = np.ascontiguousarray(R.T.astype(np.float32))
        for prog in (self._terrain_prog, self._bone_prog):
            prog["u_proj"].write(proj.T.tobytes())  # GL matrices are column-major
            prog["u_view"].write(view.T.tobytes())
            prog["u_h_scale"].value = 1.0 / (h_max - h_min)
            prog["u_z_near"].value, prog["u_z_scale"].value = z_near, 1.0 / (z_far - z_near)
        self._bone_prog["u_z_far"].value = z_far
        if self._terrain_vao is not None:
            self._terrain_prog["u_cull"].value = cull_m
            self._terrain_prog["u_cam_rel"].value = tuple(float(v) for v in (pos - self.anchor).astype(np.float32))
            self._terrain_prog["u_h_off"].value = float(self.anchor[1] - h_min)
            self.ctx.enable_direct(GL_CLIP_DISTANCE0)  # the terrain's near cull; the bones' shader writes none
            for first, count in self.terrain_ranges(cameras, i, z_near, z_far, cull_m):
                self._terrain_vao.render(vertices=count, first=first)
            self.ctx.disable_direct(GL_CLIP_DISTANCE0)
        a, b, r, ids = bones
        if len(a):
            a_rel, b_rel = np.asarray(a) - pos, np.asarray(b) - pos
            n = self._instances(a_rel, b_rel, r, ids)
            self._bone_prog["u_h_off"].value = float(pos[1] - h_min)
            self.ctx.enable(moderngl.CULL_FACE)
            self._bone_vao.render(instances=n)
        return True

    def render_packed(
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
        """Render frame ``i`` of ``cameras`` with bone capsules (a, b world (B, 3), radii (B,), ids (B,)): each
        pixel's 10-bit codes packed in one word (H, W) uint32, G | B << 10 | R << 20 (``gbuffer.pack_planes``), row
        0 at the top; all zero where the camera is invalid. The fast path: what a ``.gbz`` file stores."""
        out = np.empty((self.height, self.width), np.uint32)  # every pixel is read back (or zeroed) below
        # A GL call goes to the context current on the calling thread: with two rasterizers on one thread (a pass over
        # chunks of two sizes), the one made last would receive the other's draws. Each frame makes its own current.
        with self.ctx:
            if self._draw(cameras, i, bones, h_min, h_max, z_near, z_far, cull_m):
                self.fbo.read_into(out, components=1, dtype="u4")
            else:
                out[:] = 0
        return out

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
        """``render_packed`` as code planes (3, H, W) uint16 in G, B, R order."""
        return unpack_planes(self.render_packed(cameras, i, bones, h_min, h_max, z_near, z_far, cull_m))

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
        """``render_packed`` as the channels' values (H, W, 3) float32 R, G, B in [0, 1], each its code / 1023
        (``gbuffer.to_codes`` of them gives the codes back)."""
        g, b, r = self.render_planes(cameras, i, bones, h_min, h_max, z_near, z_far, cull_m)
        return np.stack([r, g, b], -1).astype(np.float32) / CODE_MAX


def llvmpipe_threads(cores: int) -> str:
    """Mesa llvmpipe's ``LP_NUM_THREADS`` for a process allotted ``cores`` cores: "0" for one (the thread that draws
    rasterizes, with no hand-off to a rasterizer thread: the least CPU a frame), else the count."""
    return "0" if int(cores) <= 1 else str(int(cores))
