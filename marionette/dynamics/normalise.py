"""The dynamics models' normalisation of the state, from the corpus's statistics.

**Normalisation** (``Normaliser``). The root stream and the body state are z-scored per dimension,
z = (x − mean) / max(std, std_floor), with mean and std the ``state`` entry of ``meta/stats.json``
(population statistics over the train split's source-rate rows; over all rows when the corpus has no
train split, which ``stats.json`` records as ``"split": "all"``), mapped through the same index lists as
``state.split_state``. ``std_floor`` (default 1e-3, in the dimension's own unit: metres or 6D
entries) keeps dimensions that barely vary from blowing up: a joint rigidly attached to its root
(the synthetic drake's spine, or any 6D entry of a yaw-only rotation) has a std of float32 rounding
noise (~1e-5 m) or exactly 0, and dividing by that would turn rounding noise into unit-scale signal
or divide by zero. The arithmetic runs in float64 and returns the input's dtype.
The statistics are those of the source rate (30 fps): the joints and 6D rotations do not depend on
the rate, but a root displacement δ is per frame, so at 20 fps it is ~1.5× the 30 fps one and its
normalised values have a std of ~1.5 rather than 1 (harmless for training; stated so nobody is
surprised).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from marionette.corpus import Corpus, as_corpus, paths
from marionette.corpus.vocab import ActionTokens, entity_type_key  # noqa: F401 — the models' token tables
from marionette.dynamics.state import body_index, root_index
from marionette.schema import Layout, SchemaError

DEFAULT_STD_FLOOR = 1e-3


NORMALISER_VERSION = 1


def _affine(x: Any, mean: np.ndarray, std: np.ndarray, inverse: bool) -> Any:
    """(x − mean)/std, or x·std + mean when ``inverse``, over the last axis; float64 inside, x's dtype out."""
    if isinstance(x, torch.Tensor):
        m = torch.as_tensor(mean, dtype=torch.float64, device=x.device)
        s = torch.as_tensor(std, dtype=torch.float64, device=x.device)
        y = x.to(torch.float64)
        out = y * s + m if inverse else (y - m) / s
        return out.to(x.dtype if x.is_floating_point() else torch.float32)
    a = np.asarray(x)
    out = a.astype(np.float64) * std + mean if inverse else (a.astype(np.float64) - mean) / std
    return out.astype(a.dtype if np.issubdtype(a.dtype, np.floating) else np.float32)


@dataclass(frozen=True, eq=False)
class Normaliser:
    """Per-dimension z-score of the root stream and the body state (module doc: the definition)."""

    root_mean: np.ndarray  # (root_dim,) float64
    root_std: np.ndarray  # (root_dim,) float64, already floored
    body_mean: np.ndarray  # (body_dim,)
    body_std: np.ndarray  # (body_dim,), already floored
    std_floor: float
    layout_hash: str
    stats_split: str  # "train", or "all" when the corpus had no train split

    @classmethod
    def from_corpus(
        cls, corpus: Corpus | Path | str, layout: Layout | None = None, std_floor: float = DEFAULT_STD_FLOOR
    ) -> Normaliser:
        """The normaliser of a corpus's ``stats.json`` state statistics (train split), std floored at ``std_floor``."""
        c = as_corpus(corpus)
        layout = layout or c.layout
        if layout.hash != c.layout.hash:
            raise SchemaError(
                f"{c.path}: corpus layout {c.layout.scene!r} ({c.layout.hash}) is not {layout.scene!r} ({layout.hash})"
            )
        if std_floor <= 0:
            raise ValueError(f"std_floor {std_floor} must be > 0")
        st = c.stats.get("state")
        where = paths.meta(c.path, paths.STATS)
        if st is None:
            raise KeyError(f"{where}: no 'state' entry")
        mean, std = np.asarray(st["mean"], np.float64), np.asarray(st["std"], np.float64)
        if mean.shape != (layout.dim,) or std.shape != (layout.dim,):
            raise SchemaError(
                f"{where}: state stats have {mean.shape[0]} means and {std.shape[0]} stds; the layout has dim {layout.dim}"
            )
        std = np.maximum(std, std_floor)
        ri, bi = root_index(layout), body_index(layout)
        return cls(mean[ri], std[ri], mean[bi], std[bi], float(std_floor), layout.hash, str(c.stats.get("split", "train")))

    def normalise_root(self, root: Any) -> Any:
        """Root stream (..., root_dim) → z-scores; numpy or torch, dtype kept."""
        return _affine(root, self.root_mean, self.root_std, inverse=False)

    def normalise_body(self, body: Any) -> Any:
        """Body state (..., body_dim) → z-scores; numpy or torch, dtype kept."""
        return _affine(body, self.body_mean, self.body_std, inverse=False)

    def denormalise_root(self, root: Any) -> Any:
        """Z-scored root stream (..., root_dim) → metres and 6D entries."""
        return _affine(root, self.root_mean, self.root_std, inverse=True)

    def denormalise_body(self, body: Any) -> Any:
        """Z-scored body state (..., body_dim) → metres."""
        return _affine(body, self.body_mean, self.body_std, inverse=True)

    def normalise(self, root: Any, body: Any) -> tuple[Any, Any]:
        """(root, body) → their z-scores."""
        return self.normalise_root(root), self.normalise_body(body)

    def denormalise(self, root: Any, body: Any) -> tuple[Any, Any]:
        """Z-scored (root, body) → state units."""
        return self.denormalise_root(root), self.denormalise_body(body)

    def to_json(self) -> dict:
        """A JSON-ready dict (saved beside checkpoints); the stds are the floored ones in use."""
        return {
            "version": NORMALISER_VERSION,
            "layout_hash": self.layout_hash,
            "stats_split": self.stats_split,
            "std_floor": self.std_floor,
            "root_mean": self.root_mean.tolist(),
            "root_std": self.root_std.tolist(),
            "body_mean": self.body_mean.tolist(),
            "body_std": self.body_std.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict) -> Normaliser:
        """Rebuild from ``to_json()``."""
        if d.get("version") != NORMALISER_VERSION:
            raise ValueError(f"normaliser JSON version {d.get('version')!r}; this code reads {NORMALISER_VERSION}")
        arr = {k: np.asarray(d[k], np.float64) for k in ("root_mean", "root_std", "body_mean", "body_std")}
        return cls(**arr, std_floor=float(d["std_floor"]), layout_hash=d["layout_hash"], stats_split=d["stats_split"])
