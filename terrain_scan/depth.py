"""Decoding 8-bit depth codes into metres: a configurable mapping.

WildWorld's depth.mkv stores 8-bit codes whose mapping to metres is not published, so the mapping
is data (``DepthDecoder.to_json()``), never a constant in the scanner, and ``terrain_scan.calibrate``
recovers it from the recordings themselves. Code 0 always means "no depth" (nothing hit, or beyond
the far plane) and decodes to NaN. Kinds (the parametric ones: the code affine in g(z) between
``z_near`` and ``z_far``):

- ``"inverse"``: g = 1/z, code 255 at ``z_near`` and 1 at ``z_far`` —
  ``code = 1 + 254 (1/z − 1/z_far) / (1/z_near − 1/z_far)`` — the synthetic game's default mapping
  (``SYNTHETIC_DEPTH_ENCODING``, also stored in its truth JSON as ``depth_encoding``);
- ``"linear"``: g = z, code 1 at ``z_near`` and 255 at ``z_far``;
- ``"log"``: g = ln z, code 1 at ``z_near`` and 255 at ``z_far`` (a constant share of z per code);
- ``"table"``: any monotone mapping, given as the depth of each code 1..255 (``table``; fractional
  codes interpolate linearly between their neighbours).

The decoded value is the z-depth along the camera's optical axis (m), as the synthetic game stores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

KINDS = ("inverse", "linear", "log", "table")
PARAMETRIC = ("inverse", "linear", "log")
# the names the synthetic game (and possibly other writers) use for the kinds above
_ALIASES = {"inverse_depth_u8": "inverse", "linear_depth_u8": "linear", "log_depth_u8": "log", **{k: k for k in KINDS}}
CODES = np.arange(1, 256, dtype=np.float64)  # the codes that carry a depth


# The synthetic game's 8-bit depth mapping: ``marionette.synth`` renders with it and records it in its truth JSON.
SYNTHETIC_Z_NEAR, SYNTHETIC_Z_FAR = 2.0, 300.0
SYNTHETIC_DEPTH_ENCODING = {
    "kind": "inverse_depth_u8",
    "z_near_m": SYNTHETIC_Z_NEAR,
    "z_far_m": SYNTHETIC_Z_FAR,
    "formula": "code = 0 if no hit or z > z_far else clip(round(1 + 254 * (1/z - 1/z_far) / (1/z_near - 1/z_far)), 1, 255)",
    "depth": "z-depth along the camera's viewing axis (m), characters included",
}


def curve(kind: str, z):
    """g(z) of a parametric kind: the quantity its code is affine in (1/z, ln z or z)."""
    return 1.0 / z if kind == "inverse" else np.log(z) if kind == "log" else z


def curve_inverse(kind: str, g):
    """z of g(z) for a parametric kind."""
    return 1.0 / g if kind == "inverse" else np.exp(g) if kind == "log" else g


@dataclass(frozen=True)
class DepthDecoder:
    """An 8-bit depth mapping: ``kind`` in KINDS over [z_near, z_far] metres (inverse: code 255 = z_near, 1 = z_far;
    linear and log: code 1 = z_near, 255 = z_far; table: ``table[c − 1]`` is the depth of code c, monotone)."""

    kind: str = "inverse"
    z_near: float = 2.0
    z_far: float = 300.0
    table: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"depth kind {self.kind!r}: expected one of {KINDS}")
        if self.kind == "table":
            t = np.asarray(self.table if self.table is not None else (), dtype=np.float64)
            d = np.diff(t)
            if t.shape != (255,) or not np.isfinite(t).all() or not (t > 0).all() or not ((d > 0).all() or (d < 0).all()):
                raise ValueError("depth table: need 255 finite positive depths (codes 1..255), strictly monotone")
            object.__setattr__(self, "table", tuple(float(v) for v in t))
            object.__setattr__(self, "z_near", float(t.min()))
            object.__setattr__(self, "z_far", float(t.max()))
        elif self.table is not None:
            raise ValueError(f"depth kind {self.kind!r} takes no table")
        if not (0 < self.z_near < self.z_far):
            raise ValueError(f"depth range: need 0 < z_near < z_far, got {self.z_near}, {self.z_far}")

    @staticmethod
    def from_json(d: dict) -> DepthDecoder:
        """From ``to_json()`` or from the synthetic game's ``depth_encoding`` dict (``z_near_m``, ``z_far_m``)."""
        if not isinstance(d, dict):
            raise ValueError(f"depth mapping {d!r}: expected a JSON object")
        kind = _ALIASES.get(d.get("kind", ""), d.get("kind", ""))
        if kind == "table":
            table = d.get("table")
            if not isinstance(table, list) or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in table):
                raise ValueError("depth mapping of kind 'table': needs 'table', a list of 255 depths (codes 1..255)")
            return DepthDecoder("table", table=tuple(table))
        z_near = d.get("z_near", d.get("z_near_m"))
        z_far = d.get("z_far", d.get("z_far_m"))
        if z_near is None or z_far is None:
            raise ValueError(f"depth mapping {d!r}: needs z_near and z_far")
        return DepthDecoder(kind, float(z_near), float(z_far))

    def to_json(self) -> dict:
        if self.kind == "table":
            return {"kind": "table", "table": list(self.table)}
        return {"kind": self.kind, "z_near": self.z_near, "z_far": self.z_far}

    @staticmethod
    def synthetic() -> DepthDecoder:
        """The synthetic game's mapping (``SYNTHETIC_DEPTH_ENCODING``, the one its renderer encodes with)."""
        return DepthDecoder.from_json(SYNTHETIC_DEPTH_ENCODING)

    def scaled(self, s: float) -> DepthDecoder:
        """This mapping with every depth multiplied by ``s`` > 0 (exact for every kind: each is affine in a g(z) with
        g(s·z) affine in g(z), and a table's entries scale)."""
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"depth scale must be a positive number, not {s!r}")
        if self.kind == "table":
            return DepthDecoder("table", table=tuple(float(v) * s for v in self.table))
        return DepthDecoder(self.kind, self.z_near * s, self.z_far * s)

    def code_of(self, z: np.ndarray) -> np.ndarray:
        """The unrounded code (float64) of depths z (m) within [z_near, z_far]: the mapping's inverse."""
        z = np.asarray(z, dtype=np.float64)
        if self.kind == "table":
            t = np.asarray(self.table)
            return np.interp(z, t, CODES) if t[0] < t[-1] else np.interp(z, t[::-1], CODES[::-1])
        gn, gf = curve(self.kind, self.z_near), curve(self.kind, self.z_far)
        if self.kind == "inverse":
            return 1 + 254 * (curve(self.kind, z) - gf) / (gn - gf)
        return 1 + 254 * (curve(self.kind, z) - gn) / (gf - gn)

    def encode(self, z: np.ndarray) -> np.ndarray:
        """z-depth (m; inf/nan = nothing) → uint8 code; 0 where nothing or beyond z_far (for tests and tools)."""
        z = np.asarray(z, dtype=np.float64)
        ok = np.isfinite(z) & (z > 0) & (z <= self.z_far)
        c = self.code_of(np.clip(np.where(ok, z, self.z_far), self.z_near, self.z_far))
        return np.where(ok, np.clip(np.round(c), 1, 255), 0).astype(np.uint8)

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """uint8 codes (H, W) → z-depth (H, W) float32 in metres, NaN where the code is 0.

        Fractional codes (e.g. smoothed ones) decode along the same curve.
        """
        c = np.asarray(codes, dtype=np.float64)
        return np.where(c > 0, self.depth_of(c), np.nan).astype(np.float32)

    def depth_of(self, c: np.ndarray) -> np.ndarray:
        """The depth (float64, m) of codes c in [1, 255], fractional ones along the curve."""
        c = np.asarray(c, dtype=np.float64)
        if self.kind == "table":
            return np.interp(c, CODES, np.asarray(self.table))
        t = (c - 1) / 254  # 0 at code 1, 1 at code 255
        gn, gf = curve(self.kind, self.z_near), curve(self.kind, self.z_far)
        if self.kind == "inverse":
            return 1.0 / np.maximum(t * (gn - gf) + gf, 1e-12)
        return curve_inverse(self.kind, gn + t * (gf - gn))


def smooth_codes(codes: np.ndarray, radius: int = 3, tol: float = 1.0) -> np.ndarray:
    """Sub-code depth from 8-bit codes: each valid code replaced by the mean of the valid codes within
    ``tol`` of it in its (2·radius + 1)² window (float64, 0 stays 0).

    Under the inverse mapping a code is affine in 1/z, and 1/z is affine in the pixel coordinates over
    a plane, so on a planar patch the window mean is the unquantised code at the centre; a window that
    straddles a depth edge only averages the side the centre lies on (codes further than ``tol`` away
    are left out). Where codes change by more than ``tol`` per pixel (near surfaces, whose quantisation
    is fine anyway) the mean keeps roughly the centre's own code.
    """
    codes = np.asarray(codes)
    if radius > 0 and codes.ndim == 2 and codes.dtype == np.uint8:
        return _smooth_u8(np.ascontiguousarray(codes), int(radius), float(tol))
    c = codes.astype(np.float64)
    return c if radius <= 0 else smooth_codes_reference(c, radius, tol)


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
    """``smooth_codes`` of 8-bit codes with a histogram of the window's codes that slides along each row: a step
    right adds the column entering the window and removes the one leaving it, and a pixel of code c reads the
    bins c − ⌊tol⌋ … c + ⌊tol⌋ (the integer codes within ``tol`` of c). The sums are of integers, so exact in any
    order, and the one division per pixel is the reference's. Rows alternate between two histograms (by row
    parity), so the increments of a column of equal codes do not wait on one another."""
    H, W = codes.shape
    out = np.zeros((H, W))
    if tol < 0:
        return out  # no code lies within a negative tolerance, not even its own: the reference's 0 / max(0, 1)
    k = int(np.floor(tol))
    hist = np.zeros((2, 256), np.int32)
    for i in range(H):
        a0 = max(i - radius, 0)
        a1 = min(i + radius + 1, H)
        hist[:] = 0
        for b in range(min(radius + 1, W)):
            for a in range(a0, a1):
                hist[a & 1, codes[a, b]] += 1
        for j in range(W):
            c = np.int64(codes[i, j])
            if c > 0:
                total = 0
                count = 0
                for v in range(max(c - k, 1), min(c + k, 255) + 1):
                    n = np.int64(hist[0, v] + hist[1, v])
                    total += n * v
                    count += n
                out[i, j] = float(total) / max(float(count), 1.0)
            enter = j + radius + 1
            if enter < W:
                for a in range(a0, a1):
                    hist[a & 1, codes[a, enter]] += 1
            leave = j - radius
            if leave >= 0:
                for a in range(a0, a1):
                    hist[a & 1, codes[a, leave]] -= 1
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
