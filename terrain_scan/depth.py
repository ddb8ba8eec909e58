"""Decoding 8-bit depth codes into metres: a configurable mapping.

WildWorld's depth.mkv stores 8-bit codes whose mapping to metres is not published, so the mapping
is data (``DepthDecoder.to_json()``), never a constant in the scanner. Code 0 always means "no
depth" (nothing hit, or beyond the far plane) and decodes to NaN. Kinds:

- ``"inverse"``: the code is affine in inverse depth between ``z_near`` and ``z_far`` —
  ``code = 1 + 254 (1/z − 1/z_far) / (1/z_near − 1/z_far)`` — the synthetic game's mapping
  (``marionette.synth.render.DEPTH_ENCODING``, also stored in its truth JSON as ``depth_encoding``);
- ``"linear"``: the code is affine in depth — ``code = 1 + 254 (z − z_near) / (z_far − z_near)``.

The decoded value is the z-depth along the camera's optical axis (m), as the synthetic game stores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

KINDS = ("inverse", "linear")
# the names the synthetic game (and possibly other writers) use for the kinds above
_ALIASES = {"inverse_depth_u8": "inverse", "linear_depth_u8": "linear", "inverse": "inverse", "linear": "linear"}


@dataclass(frozen=True)
class DepthDecoder:
    """An 8-bit depth mapping: ``kind`` in KINDS over [z_near, z_far] metres (inverse: code 255 = z_near, 1 = z_far;
    linear: code 1 = z_near, 255 = z_far)."""

    kind: str = "inverse"
    z_near: float = 2.0
    z_far: float = 300.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"depth kind {self.kind!r}: expected one of {KINDS}")
        if not (0 < self.z_near < self.z_far):
            raise ValueError(f"depth range: need 0 < z_near < z_far, got {self.z_near}, {self.z_far}")

    @staticmethod
    def from_json(d: dict) -> DepthDecoder:
        """From ``to_json()`` or from the synthetic game's ``depth_encoding`` dict (``z_near_m``, ``z_far_m``)."""
        kind = _ALIASES.get(d.get("kind", ""), d.get("kind", ""))
        z_near = d.get("z_near", d.get("z_near_m"))
        z_far = d.get("z_far", d.get("z_far_m"))
        if z_near is None or z_far is None:
            raise ValueError(f"depth mapping {d!r}: needs z_near and z_far")
        return DepthDecoder(kind, float(z_near), float(z_far))

    def to_json(self) -> dict:
        return {"kind": self.kind, "z_near": self.z_near, "z_far": self.z_far}

    @staticmethod
    def synthetic() -> DepthDecoder:
        """The synthetic game's mapping (read from its renderer, so the two cannot drift apart)."""
        from marionette.synth.render import DEPTH_ENCODING

        return DepthDecoder.from_json(DEPTH_ENCODING)

    def encode(self, z: np.ndarray) -> np.ndarray:
        """z-depth (m; inf/nan = nothing) → uint8 code; 0 where nothing or beyond z_far (for tests and tools)."""
        z = np.asarray(z, dtype=np.float64)
        ok = np.isfinite(z) & (z > 0) & (z <= self.z_far)
        zz = np.where(ok, z, self.z_far)
        if self.kind == "inverse":
            c = 1 + 254 * (1 / zz - 1 / self.z_far) / (1 / self.z_near - 1 / self.z_far)
        else:
            c = 1 + 254 * (zz - self.z_near) / (self.z_far - self.z_near)
        return np.where(ok, np.clip(np.round(c), 1, 255), 0).astype(np.uint8)

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """uint8 codes (H, W) → z-depth (H, W) float32 in metres, NaN where the code is 0.

        Fractional codes (e.g. smoothed ones) decode along the same curve.
        """
        c = np.asarray(codes, dtype=np.float64)
        t = (c - 1) / 254  # 0 at code 1, 1 at code 255
        if self.kind == "inverse":
            inv = t * (1 / self.z_near - 1 / self.z_far) + 1 / self.z_far
            z = 1.0 / np.maximum(inv, 1e-12)
        else:
            z = self.z_near + t * (self.z_far - self.z_near)
        return np.where(c > 0, z, np.nan).astype(np.float32)


def smooth_codes(codes: np.ndarray, radius: int = 3, tol: float = 1.0) -> np.ndarray:
    """Sub-code depth from 8-bit codes: each valid code replaced by the mean of the valid codes within
    ``tol`` of it in its (2·radius + 1)² window (float64, 0 stays 0).

    Under the inverse mapping a code is affine in 1/z, and 1/z is affine in the pixel coordinates over
    a plane, so on a planar patch the window mean is the unquantised code at the centre; a window that
    straddles a depth edge only averages the side the centre lies on (codes further than ``tol`` away
    are left out). Where codes change by more than ``tol`` per pixel (near surfaces, whose quantisation
    is fine anyway) the mean keeps roughly the centre's own code.
    """
    c = np.asarray(codes, dtype=np.float64)
    if radius <= 0:
        return c
    if c.ndim == 2 and np.asarray(codes).dtype == np.uint8:
        return _smooth_u8(np.ascontiguousarray(codes), int(radius), float(tol))
    return smooth_codes_reference(c, radius, tol)


def smooth_codes_reference(c: np.ndarray, radius: int, tol: float) -> np.ndarray:
    """``smooth_codes`` in plain numpy over float codes: the definition the compiled kernel equals bit for bit."""
    H, W = c.shape
    pad = np.pad(c, radius, mode="constant")  # padding is 0: invalid, never averaged
    total = np.zeros_like(c)
    count = np.zeros_like(c)
    for di in range(2 * radius + 1):
        for dj in range(2 * radius + 1):
            nb = pad[di : di + H, dj : dj + W]
            ok = (nb > 0) & (np.abs(nb - c) <= tol)
            total += np.where(ok, nb, 0.0)
            count += ok
    return np.where(c > 0, total / np.maximum(count, 1), 0.0)


@numba.njit(cache=True, nogil=True)
def _smooth_u8(codes: np.ndarray, radius: int, tol: float) -> np.ndarray:  # pragma: no cover - compiled
    """``smooth_codes`` of 8-bit codes, per pixel over its window: the sums are of integers, so exact in any
    order, and the one division per pixel is the reference's."""
    H, W = codes.shape
    out = np.zeros((H, W))
    for i in range(H):
        for j in range(W):
            c = codes[i, j]
            if c == 0:
                continue
            total = 0.0
            count = 0.0
            for a in range(max(i - radius, 0), min(i + radius + 1, H)):
                for b in range(max(j - radius, 0), min(j + radius + 1, W)):
                    nb = codes[a, b]
                    if nb > 0 and abs(float(nb) - float(c)) <= tol:
                        total += nb
                        count += 1.0
            out[i, j] = total / max(count, 1.0)
    return out


def depth_edges(z: np.ndarray, rel: float = 0.1) -> np.ndarray:
    """(H, W) bool: pixels next to a depth discontinuity (a 4-neighbour nearer or farther by > ``rel`` · z, or invalid)."""
    zz = np.where(np.isfinite(z), z, np.inf)
    edge = np.zeros(z.shape, bool)
    for a, b in ((zz[1:], zz[:-1]), (zz[:, 1:], zz[:, :-1])):
        with np.errstate(invalid="ignore"):
            jump = ~(np.abs(a - b) <= rel * np.minimum(a, b))
        if a.shape[0] != zz.shape[0]:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    return edge
