"""Cameras of the bridge: the recorded camera of corpus rows, and a deterministic follow camera.

A camera is a pinhole in the OpenGL convention the recordings use: ``rot`` is camera-to-world, the
camera looks down its −Z axis with +Y up and +X right; intrinsics (fx, fy, cx, cy) are in output
pixels with pixel (row i, column j) centred at (u, v) = (j + ½, i + ½), v growing downwards. A camera
point p_cam = Rᵀ (p_world − pos) projects to u = cx + fx · x / (−z), v = cy − fy · y / (−z).

**Follow camera** (``follow_cameras``), a closed-form function of the roots, causal: the game's
third-person view, riding behind the player and framing the other entity. Per frame t with the followed
entity A (the player; ``targets.followed_entities`` picks it) at a_t and the other B at b_t (horizontal
unit vector f_t from A to B; with one entity or coincident roots, A's forward axis):

- distance back D_t = max(3.5, 9.5 − s_t) m with s_t the horizontal A–B distance: the eye stays 3.5 m
  behind A and at least 9.5 m (horizontally) from B; D_t = 3.5 m with one entity;
- wanted eye e*_t = a_t − D_t·f_t + (0, 0.2·D_t + 0.8, 0); wanted target g*_t = a_t + min(s_t / 2, 3)·f_t
  + (0, 0.25, 0), the A–B midpoint but at most 3 m ahead of A (2 m ahead with one entity);
- smoothing, using no future frame, that rides with A: with m_t = a_t − a_{t−1} with its vertical part
  zeroed (A's horizontal motion), e_0 = e*_0, e_t = ẽ_t + α (e*_t − ẽ_t) where ẽ_t = e_{t−1} + m_t, and
  α = 1 − exp(−Δt / τ), τ = ``FOLLOW_TAU_S`` (0.4 s), Δt the frame interval; the same for g. Running
  never leaves the camera behind (a 3.5 m camera lagging v·τ would lose a player running toward it);
  turning, height and distance ease;
- rotation: look from e_t at g_t with world +Y up (``look_at``); vertical field of view 60°, square
  pixels, principal point at the image centre.

Measured on recorded state of the synthetic duel (the eval's ``body_share``: 72 × 128, the weapon counted
for the hunter): the hunter covers ~1.5 % of the frame and the drake ~2.6 % on average, 1.1–1.3 % and
4–4.7 % while the roots are under 8 m apart. No camera behind the player brings both near 1.5 % there:
the drake's frontal area is 10–15× the hunter's.

Invalid (absent) entities hold their last valid root; before the first valid root the other
entity alone is framed (m_t = 0 where the framed entity changes).

**Seeded start** (``start``, a camera of one frame, e.g. the recorded camera where a rollout begins):
the smoothing state is seeded from it instead of from the wanted pose, so the first framed frame *is*
that camera and the follow camera eases away from it with the same α: e_0 = the start position;
g_0 = e_0 + d·(its −Z axis) with d = max(1, |g*_0 − e_0|) (its view ray, as far as the wanted target);
an up vector u_0 = its +Y axis eases to world +Y (u_t = u_{t−1} + α (Y − u_{t−1}), so a rolled start
unrolls); the intrinsics ease from its (fx, fy, cx, cy) to the follow camera's. Without ``start`` the
camera is exactly the unseeded one above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marionette.geometry import quat_to_matrix

FOLLOW_TAU_S = 0.4
FOLLOW_VFOV_DEG = 60.0


@dataclass(frozen=True)
class Cameras:
    """Per-frame cameras: K (N, 4) fx, fy, cx, cy in pixels; pos (N, 3) world metres; rot (N, 3, 3) camera-to-world;
    valid (N,); the output size and the depth range of the render."""

    K: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    valid: np.ndarray
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.pos)

    def project(self, points_world: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (u, v) (P, 2) and view depth (P,) (metres along −Z) of world points at frame ``i``."""
        p = (np.asarray(points_world, np.float64) - self.pos[i]) @ self.rot[i]  # Rᵀ (p − pos), row form
        depth = -p[:, 2]
        fx, fy, cx, cy = self.K[i]
        return np.stack([cx + fx * p[:, 0] / depth, cy - fy * p[:, 1] / depth], -1), depth

    def boxes_in_view(self, i: int, lo: np.ndarray, hi: np.ndarray, z_near: float, z_far: float) -> np.ndarray:
        """Which axis-aligned world boxes (corners ``lo``, ``hi`` (B, 3)) may meet frame ``i``'s view between view
        depths ``z_near`` and ``z_far``: (B,) bool, False only where all eight corners lie beyond one of the
        frustum's six planes (a conservative test: a box it keeps may still be unseen)."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        corners = np.stack([np.where(np.array(bits, bool), hi, lo) for bits in np.ndindex(2, 2, 2)], 1)  # (B, 8, 3)
        p = (corners - self.pos[i]) @ self.rot[i]  # camera frame, row form of Rᵀ (c − pos)
        x, y, d = p[..., 0], p[..., 1], -p[..., 2]
        fx, fy, cx, cy = self.K[i]
        outside = (
            d < z_near,
            d > z_far,
            fx * x + cx * d < 0,  # left of u = 0
            fx * x + (cx - self.width) * d > 0,  # right of u = W
            cy * d - fy * y < 0,  # above v = 0
            cy * d - fy * y - self.height * d > 0,  # below v = H
        )
        return ~np.any([o.all(axis=1) for o in outside], axis=0)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world rotation (…, 3, 3) looking from ``eye`` at ``target`` (−Z forward, +Y up-ish)."""
    up = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, np.float64)
    fwd = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    fwd = fwd / np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-12)
    right = np.cross(fwd, up)
    n = np.linalg.norm(right, axis=-1, keepdims=True)
    # looking straight up or down: any right vector perpendicular to fwd
    right = np.where(n > 1e-9, right / np.maximum(n, 1e-12), np.array([1.0, 0.0, 0.0]))
    cam_up = np.cross(right, fwd)
    return np.stack([right, cam_up, -fwd], axis=-1)


def intrinsics_for(width: int, height: int, vfov_deg: float = FOLLOW_VFOV_DEG) -> np.ndarray:
    """(4,) fx, fy, cx, cy of a centred pinhole with square pixels and the given vertical field of view."""
    fy = 0.5 * height / np.tan(np.radians(vfov_deg) / 2)
    return np.array([fy, fy, width / 2, height / 2])


def recorded_cameras(
    K: np.ndarray, pos: np.ndarray, rot_xyzw: np.ndarray, valid: np.ndarray, width: int, height: int, crop=None
) -> Cameras:
    """Cameras from recorded rows: K (N, 4) source pixels, pos (N, 3), rot (N, 4) xyzw camera-to-world.

    ``crop`` (a ``marionette.video.CropResize``) maps the source intrinsics to the output the
    video chunk applied; its output size must be (height, width).
    """

    K = np.asarray(K, np.float64)
    if crop is not None:
        if (crop.out_h, crop.out_w) != (height, width):
            raise ValueError(f"crop outputs {crop.out_h}×{crop.out_w}, the render is {height}×{width}")
        K = crop.intrinsics(K)
    rot = np.asarray(rot_xyzw, np.float64)
    ok = np.asarray(valid, bool) & np.isfinite(K).all(-1) & np.isfinite(pos).all(-1) & np.isfinite(rot).all(-1)
    ok &= (K[:, 0] > 0) & (K[:, 1] > 0) & (np.linalg.norm(np.nan_to_num(rot), axis=-1) > 1e-6)
    R = np.where(ok[:, None, None], quat_to_matrix(np.where(ok[:, None], rot, [0.0, 0.0, 0.0, 1.0])), np.eye(3))
    return Cameras(K, np.asarray(pos, np.float64), R, ok, int(width), int(height))


def _hold(x: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Each row replaced by the last valid row at or before it (rows before the first valid one stay NaN)."""
    idx = np.where(ok, np.arange(len(ok)), -1)
    idx = np.maximum.accumulate(idx) if len(idx) else idx
    out = np.full_like(x, np.nan)
    have = idx >= 0
    out[have] = x[idx[have]]
    return out


class FollowCamera:
    """The follow camera of the module docstring, one frame at a time: ``step`` takes the followed entities' roots, A's
    forward vector and their validity for one frame and gives that frame's camera, so a live rollout is framed exactly as
    ``follow_cameras`` frames the whole sequence afterwards (which runs this stepper over it)."""

    UP = np.array([0.0, 1.0, 0.0])

    def __init__(self, fps: float, width: int, height: int, start: Cameras | None = None) -> None:
        if start is not None and (not len(start) or not start.valid[0] or (start.width, start.height) != (width, height)):
            raise ValueError(f"follow_cameras: the start camera must be a valid camera of the output size {width}×{height}")
        self.width, self.height, self.start = int(width), int(height), start
        self.alpha = 1.0 - np.exp(-1.0 / (float(fps) * FOLLOW_TAU_S))
        self.K_wanted = intrinsics_for(width, height)
        nan = np.full(3, np.nan)
        self._a, self._b, self._fwd = nan, nan, nan  # last valid A, B root and A forward
        self._prev_a: np.ndarray | None = None  # last frame's followed point (B's root before A appears)
        self._prev_only_b = False
        self._e: np.ndarray | None = None  # smoothed eye and target, up vector and intrinsics
        self._g: np.ndarray | None = None
        self._u, self._k = self.UP, self.K_wanted

    def wanted(self, a: np.ndarray, b: np.ndarray, fwd_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The wanted eye and target (3,) of held roots ``a`` (NaN before A appears), ``b`` (NaN without B) and A's
        forward vector; NaN where nothing is framed."""
        have_b = bool(np.isfinite(b).all())
        d = b - a if have_b else np.zeros(3)
        d = d * np.array([1.0, 0.0, 1.0])
        s = float(np.linalg.norm(d))
        f_h = np.nan_to_num(fwd_a * np.array([1.0, 0.0, 1.0]))
        nf = float(np.linalg.norm(f_h))
        f = d / s if have_b and s > 1e-6 else (f_h / nf if nf > 1e-9 else np.array([0.0, 0.0, 1.0]))
        D = max(3.5, 9.5 - s) if have_b else 3.5  # 3.5 m behind A, at least 9.5 m from B
        ahead = min(s / 2, 3.0) if have_b else 2.0
        return a - D * f + (0.2 * D + 0.8) * self.UP, a + ahead * f + 0.25 * self.UP

    def step(
        self, roots: list[np.ndarray], forward: np.ndarray, valid: list[bool]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
        """One frame: roots [(3,)] (A first, then B if any), A's forward (3,), validities → (eye (3,), target (3,),
        up (3,), intrinsics (4,), valid); an invalid frame (nothing framed yet) leaves the smoothing where it was."""
        if valid[0]:
            self._a, self._fwd = np.asarray(roots[0], np.float64), np.asarray(forward, np.float64)
        if len(roots) > 1 and valid[1]:
            self._b = np.asarray(roots[1], np.float64)
        a, b = self._a, self._b
        only_b = not np.isfinite(a).all() and np.isfinite(b).all()
        if only_b:  # before A first appears, frame B alone
            a, b = b, np.full(3, np.nan)
        moved = np.zeros(3)  # A's horizontal motion, carried by the eye and the target
        if self._prev_a is not None and only_b == self._prev_only_b:
            moved = (a - self._prev_a) * np.array([1.0, 0.0, 1.0])
        self._prev_a, self._prev_only_b = a, only_b
        eye_w, tgt_w = self.wanted(a, b, self._fwd)
        if not np.isfinite(eye_w).all():
            return np.full(3, np.nan), np.full(3, np.nan), self.UP, self.K_wanted, False
        if self._e is None and self.start is None:
            self._e, self._g = eye_w, tgt_w
        elif self._e is None:  # the first framed frame is the start camera
            st = self.start
            self._e = st.pos[0].astype(np.float64)
            self._g = self._e - max(1.0, float(np.linalg.norm(tgt_w - self._e))) * st.rot[0][:, 2]
            self._u, self._k = st.rot[0][:, 1].astype(np.float64), st.K[0].astype(np.float64)
        else:
            al = self.alpha
            e, g = self._e + moved, self._g + moved
            self._e, self._g = e + al * (eye_w - e), g + al * (tgt_w - g)
            self._u, self._k = self._u + al * (self.UP - self._u), self._k + al * (self.K_wanted - self._k)
        return self._e, self._g, self._u, self._k, True

    def camera(self, roots: list[np.ndarray], forward: np.ndarray, valid: list[bool]) -> Cameras:
        """``step`` as a one-frame ``Cameras``."""
        e, g, u, k, ok = self.step(roots, forward, valid)
        R = look_at(e, g, u if self.start is not None else None) if ok else np.eye(3)
        return Cameras(k[None].copy(), e[None].copy(), R[None], np.array([ok]), self.width, self.height)


def follow_cameras(
    roots: list[np.ndarray],
    forward: np.ndarray,
    valid: list[np.ndarray],
    fps: float,
    width: int,
    height: int,
    start: Cameras | None = None,
) -> Cameras:
    """The follow camera of the module docstring: roots [(N, 3)] of the articulated entities (A, the player, first),
    A's world forward vectors (N, 3), their validity [(N,)], the frame rate and the output size; ``start``
    (frame 0 of a valid camera of the same output size) seeds the smoothing (module doc, "Seeded start")."""
    cam = FollowCamera(fps, width, height, start)
    n = len(roots[0])
    roots = [np.asarray(r, np.float64) for r in roots[:2]]
    valid = [np.asarray(v, bool) for v in valid[:2]]
    forward = np.asarray(forward, np.float64)
    eye, tgt = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    K = np.tile(cam.K_wanted, (n, 1))
    ups = np.tile(cam.UP, (n, 1))
    for t in range(n):
        e, g, u, k, ok = cam.step([r[t] for r in roots], forward[t], [bool(v[t]) for v in valid])
        if ok:
            eye[t], tgt[t] = e, g
            if start is not None:
                ups[t], K[t] = u, k
    ok = np.isfinite(eye).all(-1)
    R = np.tile(np.eye(3), (n, 1, 1))
    R[ok] = look_at(eye[ok], tgt[ok]) if start is None else look_at(eye[ok], tgt[ok], ups[ok])
    return Cameras(K, eye, R, ok, int(width), int(height))
