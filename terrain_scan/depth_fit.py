"""Fitting the 8-bit depth mapping to the recorded joints.

WildWorld does not publish how its depth.mkv codes map to metres; every recording carries what is
needed to measure it. At a frame with a valid camera, a recorded joint projects (the recorded
pinhole camera, as the scan back-projects) onto a pixel of the depth frame whose code is the depth
of the body around that joint, nearer than the joint by about the body's radius along the ray: the
joint's camera z-depth times (1 − r / its distance), r the rig's capsule radius. Each such pixel is
one (code, depth) pair; pixels off the body (a thin limb's joint landing on the ground behind it),
behind something (occluded) or on a thicker part of the body than the rig's radius are outliers.

``fit`` finds, for each parametric kind of ``DepthDecoder`` — the code affine in 1/z, in ln z or in
z — the line code = a + b·g(z) by iteratively reweighted least squares with Tukey's biweight
(scale from the residuals' median absolute deviation, in codes), so the outliers get no weight, and
picks the kind whose inliers scatter least (their codes are rounded, so a right kind scatters by
about the ±½ code of rounding). The 256-entry ``table`` is the median depth of each code's inlier
pairs, made monotone (pool-adjacent-violators, weighted by the pairs) and completed from the best
parametric kind where a code has too few pairs. The bias a body's thickness leaves in the fit is
``contact_scale``'s to remove (``Calibration.with_contact_scale``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from marionette.geometry import quat_to_matrix
from marionette.recordings.wildworld import DEPTH_FILE, SampleRef, read_sample
from marionette.schema import Layout
from terrain_scan.contact_scale import ContactScale
from terrain_scan.depth import CODES, PARAMETRIC, DepthDecoder, curve, curve_inverse
from terrain_scan.recording_video import depth_frames

TUKEY_C = 2.0  # the biweight's cut-off in robust standard deviations: tight, as what contaminates is one-sided (another
# part of the body in front of the joint, always nearer); 4.685, the textbook choice, left a 0.7 % bias (docs/tradeoffs.md)
MIN_TABLE_PAIRS = 5  # a code (or a joint's offset) with fewer inlier pairs takes the best parametric fit's
OFFSET_ROUNDS = 8  # rounds of measuring each joint's body offset and fitting the mapping again
MAX_OFFSET_M = 2.0  # no body is thicker than this around a joint
STEADY_SCATTER = 1.25  # a joint whose pairs scatter more than this × the median joint's is left out


@dataclass
class Pairs:
    """(code, joint) pairs: the pixel's code, the joint's camera z-depth and distance (m), which joint (an index into
    ``names``, "entity/joint"), and its body offset ``offset`` (m, per joint: how much nearer the body's surface is
    along the ray; the rig's capsule radius to start with); ``z`` is the reference depth they give."""

    code: np.ndarray
    zj: np.ndarray
    dist: np.ndarray
    joint: np.ndarray
    names: list[str]
    offset: np.ndarray
    frames: int = 0
    recordings: int = 0
    frame: np.ndarray | None = None  # (n,) the frame each pair came from: recording k's frame i is k · 10⁷ + i

    def take(self, keep: np.ndarray) -> Pairs:
        """The pairs where ``keep`` (a (n,) bool) holds."""
        return Pairs(
            self.code[keep],
            self.zj[keep],
            self.dist[keep],
            self.joint[keep],
            self.names,
            self.offset,
            self.frames,
            self.recordings,
            None if self.frame is None else self.frame[keep],
        )

    @property
    def z(self) -> np.ndarray:
        return self.zj * (1.0 - np.minimum(self.offset[self.joint] / self.dist, 0.5))

    def __len__(self) -> int:
        return len(self.code)

    @staticmethod
    def concat(parts: list[Pairs]) -> Pairs:
        names = sorted({n for p in parts for n in p.names})
        at = {n: k for k, n in enumerate(names)}
        offset = np.zeros(len(names))
        for p in parts:
            offset[[at[n] for n in p.names]] = p.offset
        cat = lambda f: np.concatenate([getattr(p, f) for p in parts]) if parts else np.zeros(0)  # noqa: E731
        joint = (
            np.concatenate([np.array([at[n] for n in p.names], np.int64)[p.joint] for p in parts])
            if parts
            else np.zeros(0, np.int64)
        )
        frames, recordings = sum(p.frames for p in parts), sum(p.recordings for p in parts)
        ids = [np.zeros(len(p), np.int64) if p.frame is None else p.frame for p in parts]
        frame = np.concatenate([k * 10_000_000 + f for k, f in enumerate(ids)]) if parts else np.zeros(0, np.int64)
        return Pairs(cat("code"), cat("zj"), cat("dist"), joint, names, offset, frames, recordings, frame)


def recording_pairs(ref: SampleRef, layout: Layout, frame_stride: int = 5) -> Pairs:
    """The (code, depth) pairs of one recording: every kept joint of every entity present at every
    ``frame_stride``-th frame with a valid camera, projected onto its depth frame (module docstring)."""
    sample = read_sample(ref, layout)
    names, offset, first = [], [], {}
    for e in layout.entities:
        first[e.name] = len(names)
        names += [f"{e.rig.name}/{j}" for j in e.rig.keep]  # by rig: recordings of other species never share a name
        offset += [e.rig.capsule_radius_m] * len(e.rig.keep)
    codes, zjs, dists, joints, at, frames = [], [], [], [], [], 0
    for i, img in enumerate(depth_frames(ref.path / DEPTH_FILE, keep=lambda i: i % frame_stride == 0)):
        if i % frame_stride or sample.camera_valid is None or i >= len(sample.camera_valid) or not sample.camera_valid[i]:
            continue
        frames += 1
        H, W = img.shape
        fx, fy, cx, cy = (float(k) for k in sample.camera_K[i])
        R = quat_to_matrix(np.asarray(sample.camera_rot[i], np.float64))  # camera-to-world
        pos = np.asarray(sample.camera_pos[i], np.float64)
        for name, track in sample.entities.items():
            if not track.valid[i]:
                continue
            p = (track.joints_world[i] - pos) @ R  # world → camera (OpenGL: looking down −z)
            z = -p[:, 2]
            ok = z > 0.05
            u = cx + fx * p[ok, 0] / z[ok]
            v = cy - fy * p[ok, 1] / z[ok]
            col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
            inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
            c = img[row[inside], col[inside]].astype(np.float64)
            seen = c > 0
            codes.append(c[seen])
            zjs.append(z[ok][inside][seen])
            dists.append(np.linalg.norm(p[ok][inside][seen], axis=1))
            joints.append(first[name] + np.flatnonzero(ok)[inside][seen])
            at.append(np.full(int(seen.sum()), i, np.int64))
    cat = lambda parts, dt=np.float64: np.concatenate(parts).astype(dt) if parts else np.zeros(0, dt)  # noqa: E731
    return Pairs(cat(codes), cat(zjs), cat(dists), cat(joints, np.int64), names, np.array(offset), frames, 1, cat(at, np.int64))


@dataclass
class FamilyFit:
    """One parametric kind fitted: code = a + b·g(z), its decoder, its inliers' scatter in codes."""

    kind: str
    a: float
    b: float
    decoder: DepthDecoder | None
    scale: float  # robust standard deviation of the residuals (codes): 1.4826 · MAD
    rms_inliers: float  # RMS residual of the inliers (codes)
    inliers: np.ndarray  # (n,) bool
    reason: str = ""  # why there is no decoder

    def summary(self) -> dict:
        d = {"kind": self.kind, "scale_codes": self.scale, "rms_inliers_codes": self.rms_inliers}
        d["inlier_share"] = float(self.inliers.mean()) if len(self.inliers) else 0.0
        if self.decoder is not None:
            d.update(z_near=self.decoder.z_near, z_far=self.decoder.z_far)
        else:
            d["unusable"] = self.reason
        return d


def _biweight_line(x: np.ndarray, y: np.ndarray, iters: int = 30) -> tuple[float, float, float, np.ndarray]:
    """Robust line y = a + b·x: least squares, then Tukey biweight IRLS; (a, b, scale, inliers)."""
    A = np.stack([np.ones_like(x), x], axis=1)
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    scale = 1.0
    for _ in range(iters):
        r = y - A @ coef
        scale = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.3)  # codes are rounded: ≥ ~ their ±½
        u = r / (TUKEY_C * scale)
        w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        if w.sum() < 2:
            break
        sw = np.sqrt(w)
        new = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
        if np.allclose(new, coef, rtol=1e-10, atol=1e-12):
            coef = new
            break
        coef = new
    r = y - A @ coef
    return float(coef[0]), float(coef[1]), scale, np.abs(r) < TUKEY_C * scale


def fit_kind(pairs: Pairs, kind: str) -> FamilyFit:
    """Fit one parametric kind to the pairs (module docstring)."""
    x = curve(kind, pairs.z)
    a, b, scale, inl = _biweight_line(x, pairs.code)
    rms = float(np.sqrt(np.mean((pairs.code[inl] - a - b * x[inl]) ** 2))) if inl.any() else float("inf")
    # the decoder's planes: the depths of codes 1 and 255 (inverse: 255 is the near plane)
    with np.errstate(all="ignore"):
        z1, z255 = (float(curve_inverse(kind, (c - a) / b)) if b != 0 else float("nan") for c in (1.0, 255.0))
    near, far = (z255, z1) if kind == "inverse" else (z1, z255)
    try:
        return FamilyFit(kind, a, b, DepthDecoder(kind, near, far), scale, rms, inl)
    except ValueError as exc:
        return FamilyFit(kind, a, b, None, scale, rms, inl, f"its planes are not a depth range ({exc})")


def refine_offsets(pairs: Pairs, best: FamilyFit) -> None:
    """Each joint's body offset (m, in place) from its inlier pairs under ``best``'s mapping: the median of
    distance × (1 − decoded depth / joint depth), kept within [0, ``MAX_OFFSET_M``]; joints with fewer than
    ``MIN_TABLE_PAIRS`` inliers keep theirs. A joint's offset is a constant in metres at every depth it is seen
    at, which a mapping's error (a share of the depth) is not, so the two separate over a range of depths."""
    inl = best.inliers
    dec = best.decoder.depth_of(np.clip(pairs.code[inl], 1, 255))
    off = pairs.dist[inl] * (1.0 - dec / pairs.zj[inl])
    joint = pairs.joint[inl]
    order = np.argsort(joint, kind="stable")
    bounds = np.searchsorted(joint[order], np.arange(len(pairs.names) + 1))
    for j in range(len(pairs.names)):
        seg = order[bounds[j] : bounds[j + 1]]
        if len(seg) >= MIN_TABLE_PAIRS:
            pairs.offset[j] = float(np.clip(np.median(off[seg]), 0.0, MAX_OFFSET_M))


def steady_joints(pairs: Pairs, best: FamilyFit) -> np.ndarray:
    """(joints,) bool: the joints whose inlier pairs scatter (robust scale, codes) at most ``STEADY_SCATTER`` × the
    median joint's, with ``MIN_TABLE_PAIRS`` inliers or more. A joint inside a thick body whose depth toward the
    camera changes with the view (a torso seen from the front, then the side) scatters more than its mapping does:
    its offset is no constant, and it would bend the fit."""
    resid = pairs.code - best.a - best.b * curve(best.kind, pairs.z)
    scale = np.full(len(pairs.names), np.inf)
    for j in range(len(pairs.names)):
        r = resid[(pairs.joint == j) & best.inliers]
        if len(r) >= MIN_TABLE_PAIRS:
            scale[j] = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    finite = scale[np.isfinite(scale)]
    if not len(finite):
        return np.ones(len(pairs.names), bool)
    return scale <= STEADY_SCATTER * max(float(np.median(finite)), 0.3)


def monotone(y: np.ndarray, w: np.ndarray, increasing: bool) -> np.ndarray:
    """Weighted isotonic regression (pool adjacent violators) of ``y``, non-decreasing or non-increasing."""
    if not increasing:
        return -monotone(-y, w, True)
    blocks: list[list[float]] = []  # [value, weight, count]
    for v, wt in zip(y.tolist(), w.tolist()):
        blocks.append([v, wt, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            v2, w2, n2 = blocks.pop()
            v1, w1, n1 = blocks.pop()
            tot = w1 + w2
            blocks.append([(v1 * w1 + v2 * w2) / tot if tot > 0 else (v1 + v2) / 2, tot, n1 + n2])
    return np.concatenate([np.full(n, v) for v, _, n in blocks])


def table_fit(pairs: Pairs, best: FamilyFit) -> DepthDecoder:
    """The 256-entry table: each code's median inlier depth, monotone in the best fit's direction, completed from
    it where a code has fewer than ``MIN_TABLE_PAIRS`` inliers (module docstring)."""
    base = best.decoder.depth_of(CODES)
    code, z = pairs.code[best.inliers].astype(np.int64), pairs.z[best.inliers]
    med = base.copy()
    count = np.bincount(code, minlength=256)[1:].astype(np.float64)
    order = np.argsort(code, kind="stable")
    starts = np.searchsorted(code[order], np.arange(1, 257))
    for c in range(1, 256):
        if count[c - 1] >= MIN_TABLE_PAIRS:
            med[c - 1] = float(np.median(z[order[starts[c - 1] : starts[c]]]))
    w = np.where(count >= MIN_TABLE_PAIRS, count, 1.0)
    increasing = base[-1] > base[0]
    t = monotone(med, w, increasing)
    # strictly monotone: a flat run rises by a millionth a step (far below any code's spacing)
    step = 1e-6 * np.abs(t) if increasing else -1e-6 * np.abs(t)
    for k in range(1, len(t)):
        if (t[k] <= t[k - 1]) if increasing else (t[k] >= t[k - 1]):
            t[k] = t[k - 1] + step[k - 1]
    return DepthDecoder("table", table=tuple(t))


@dataclass
class Calibration:
    """The result: every kind's fit, the chosen decoder, the table, the pairs it came from, and the contact scale
    applied to the chosen decoder and the table (``with_contact_scale``; the fits keep the joints' planes)."""

    fits: dict[str, FamilyFit]
    chosen: DepthDecoder
    table: DepthDecoder | None
    pairs: Pairs
    best: str
    notes: list[str] = field(default_factory=list)
    contact: ContactScale | None = None

    def with_contact_scale(self, cs: ContactScale) -> Calibration:
        """This calibration with ``cs`` recorded and, where it was applied, its scale on the chosen decoder and the
        table."""
        if not cs.applied:
            return replace(self, contact=cs)
        table = None if self.table is None else self.table.scaled(cs.scale)
        return replace(self, chosen=self.chosen.scaled(cs.scale), table=table, contact=cs)

    def report(self) -> dict:
        return {
            "pairs": len(self.pairs),
            "frames": self.pairs.frames,
            "recordings": self.pairs.recordings,
            "fits": {k: f.summary() for k, f in self.fits.items()},
            "best_parametric": self.best,
            "chosen": self.chosen.to_json(),
            "notes": self.notes,
            **({} if self.contact is None else {"contact_scale": self.contact.summary()}),
        }

    def lines(self) -> list[str]:
        out = [
            f"{len(self.pairs):,} (code, joint) pairs from {self.pairs.frames:,} frames of {self.pairs.recordings} recording(s)"
        ]
        for k, f in self.fits.items():
            s = f.summary()
            planes = f"near {s['z_near']:.3f} m, far {s['z_far']:.1f} m" if "z_near" in s else s["unusable"]
            out.append(
                f"  {k:<8} {planes}; inliers {100 * s['inlier_share']:.1f} %, their RMS residual "
                f"{s['rms_inliers_codes']:.3f} codes (robust scale {s['scale_codes']:.3f})"
                + ("  <- best" if k == self.best else "")
            )
        out += [f"  note: {n}" for n in self.notes]
        if self.contact is not None:
            out.append(self.contact.line())
        kind = self.chosen.kind
        out.append(
            f"chosen: {kind}" + ("" if kind == "table" else f", near {self.chosen.z_near:.3f} m, far {self.chosen.z_far:.1f} m")
        )
        return out


def _fit_every_kind(pairs: Pairs, when: str) -> tuple[dict[str, FamilyFit], dict[str, FamilyFit], str]:
    """Every parametric kind fitted, those that give a depth range, and the one whose inliers scatter least."""
    fits = {k: fit_kind(pairs, k) for k in PARAMETRIC}
    usable = {k: f for k, f in fits.items() if f.decoder is not None}
    if not usable:
        why = "; ".join(f"{k}: {f.reason}" for k, f in fits.items())
        raise ValueError(f"no parametric depth mapping fits the pairs{when}: {why}")
    return fits, usable, min(usable, key=lambda k: usable[k].rms_inliers)


def fit(pairs: Pairs, family: str = "auto") -> Calibration:
    """Fit every parametric kind, pick the best (``family`` "auto") or the one asked for (a kind, or "table")."""
    if len(pairs) < 50:
        raise ValueError(
            f"{len(pairs)} (code, joint) pairs: too few to calibrate (need 50; more recordings, a smaller "
            "--frame-stride, or recordings whose characters are in view)"
        )
    fits, usable, best = _fit_every_kind(pairs, "")
    notes = []
    for round_ in range(2 * OFFSET_ROUNDS):  # each joint's body offset from the mapping, then the mapping again
        if round_ == OFFSET_ROUNDS:  # halfway: keep the joints whose pairs agree (a thin, rigid part of a body)
            steady = steady_joints(pairs, usable[best])
            notes.append(f"{int(steady.sum())} of {len(pairs.names)} joints kept: those whose pairs scatter least")
            pairs = pairs.take(steady[pairs.joint])
        refine_offsets(pairs, usable[best] if round_ != OFFSET_ROUNDS else fit_kind(pairs, best))
        fits, usable, best = _fit_every_kind(pairs, " once the body offsets are measured")
    if usable[best].inliers.mean() < 0.5:
        notes.append(f"only {100 * usable[best].inliers.mean():.0f} % of the pairs are inliers: check the rigs and the cameras")
    table = table_fit(pairs, usable[best])
    if family == "auto":
        chosen = usable[best].decoder
    elif family == "table":
        chosen = table
    elif family in usable:
        chosen = usable[family].decoder
    else:
        raise ValueError(
            f"family {family!r}: " + (fits[family].reason if family in fits else f"expected auto, table or one of {PARAMETRIC}")
        )
    return Calibration(fits, chosen, table, pairs, best, notes)
