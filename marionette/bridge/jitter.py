"""Jittered state: the recorded skeletons moved a set amount before the bridge renders them.

The observation model is trained on pose-control targets rendered from recorded state but is used on
targets rendered from the dynamics model's rollouts, which are never quite the recording (the paper's
limitations name this shift). Rendering training targets from jittered state teaches it the neighbourhood
of the recorded poses instead. Three moves, each with its magnitude in ``Jitter``, drawn once per clip from
a generator seeded by (``seed``, the clip's key), so a clip's jitter is reproducible and clips differ:

- **root** (``root_m``): every articulated entity is shifted by a horizontal vector of exactly that length
  (a random direction, constant over the clip); what it carries (its attachments) moves with it;
- **joints** (``joint_deg``): every bone of an articulated entity is turned about its parent joint by an
  angle drawn uniformly in [0, ``joint_deg``] about a random axis, parent before child (breadth first),
  so each bone keeps its length exactly and the pose changes by at most that much per joint;
- **time** (``time_s``): the clip is sampled at warped times t + A·sin(2πt / P + φ), A = ``time_s``,
  P = max(4πA, 2 s) (so the warp never runs time backwards: its rate stays within [½, 3⁄2]), clamped to
  the clip's span.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from marionette.bridge.kinematics import Skeletons
from marionette.schema import Layout


@dataclass(frozen=True)
class Jitter:
    """Magnitudes of the three moves (module docstring); all 0 is no jitter."""

    root_m: float = 0.0
    joint_deg: float = 0.0
    time_s: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("root_m", "joint_deg", "time_s"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                raise ValueError(f"jitter {name} must be a finite number ≥ 0, not {v!r}")
        if self.joint_deg > 45:
            raise ValueError(f"jitter joint_deg {self.joint_deg} is more than 45°: that is another pose, not a neighbour")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"jitter seed must be an integer ≥ 0, not {self.seed!r}")

    @property
    def active(self) -> bool:
        return bool(self.root_m or self.joint_deg or self.time_s)

    def key(self) -> str:
        """16 hex digits naming this jitter's targets (``corpus.paths.jitter_dir``)."""
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:16]

    def rng(self, key: str) -> np.random.Generator:
        """The clip's generator: seeded by ``seed`` and a hash of ``key``."""
        return np.random.default_rng([self.seed, int(hashlib.sha256(key.encode()).hexdigest()[:15], 16)])

    def times(self, t: np.ndarray, key: str) -> np.ndarray:
        """The warped sampling times of a clip sampled at ``t`` (increasing, seconds)."""
        t = np.asarray(t, np.float64)
        if not self.time_s or len(t) < 2:
            return t
        period = max(4 * math.pi * self.time_s, 2.0)
        phase = self.rng(key + "/time").uniform(0, 2 * math.pi)
        return np.clip(t + self.time_s * np.sin(2 * math.pi * t / period + phase), t[0], t[-1])

    def apply(self, layout: Layout, skel: Skeletons, key: str) -> Skeletons:
        """``skel`` with the root and joint moves of the clip ``key`` (the time warp is ``times``, applied where the
        state is sampled)."""
        if not (self.root_m or self.joint_deg):
            return skel
        rng = self.rng(key)
        joints = dict(skel.joints)
        for e in layout.articulated:
            J = np.array(skel.joints[e.name], np.float64)
            angle = rng.uniform(0.0, math.radians(self.joint_deg), len(e.rig.bones))
            axes = rng.normal(size=(len(e.rig.bones), 3))
            axes /= np.linalg.norm(axes, axis=1, keepdims=True)
            if self.joint_deg:
                old = J.copy()
                for (child, parent), theta, axis in zip(e.rig.bones, angle, axes):
                    J[:, child] = J[:, parent] + (old[:, child] - old[:, parent]) @ rotation(axis, theta).T
            heading = rng.uniform(0.0, 2 * math.pi)
            shift = self.root_m * np.array([math.cos(heading), 0.0, math.sin(heading)])
            joints[e.name] = J + shift
            for a in layout.attachments:
                if a.owner == e.name:
                    joints[a.name] = np.asarray(skel.joints[a.name], np.float64) + shift
        return replace(skel, joints=joints)


def rotation(axis: np.ndarray, theta: float) -> np.ndarray:
    """The rotation by ``theta`` (radians) about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * (K @ K)
