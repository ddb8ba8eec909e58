"""What a video-feature extractor is (``VideoFeatureExtractor``: the proxy in ``fvd``, Inception-I3D in ``i3d``) and
the one check of the videos it takes (``check_videos``: (N, T, 3, H, W) float in [-1, 1])."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

RANGE_LIMIT = 1.5  # videos beyond ±this are in the wrong range (e.g. [0, 255]); within it they are clamped to [-1, 1]


class VideoFeatureExtractor(Protocol):
    """Maps videos (N, T, 3, H, W) in [-1, 1] to (N, D) float64 features; ``is_fvd`` only for the real I3D."""

    name: str
    is_fvd: bool

    def extract(self, videos: torch.Tensor) -> np.ndarray: ...


def check_videos(videos: torch.Tensor, what: str = "videos") -> torch.Tensor:
    """Validate videos (N, T, 3, H, W) in [-1, 1] and return them as float32, clamped to [-1, 1]."""
    if not isinstance(videos, torch.Tensor):
        raise TypeError(f"{what}: expected a torch.Tensor, got {type(videos).__name__}")
    if videos.ndim != 5 or videos.shape[2] != 3:
        raise ValueError(f"{what}: expected shape (N, T, 3, H, W), got {tuple(videos.shape)}")
    if not videos.is_floating_point():
        raise ValueError(f"{what}: expected float values in [-1, 1], got dtype {videos.dtype}")
    v = videos.detach().to(torch.float32)
    if not torch.isfinite(v).all():
        raise ValueError(f"{what}: contains NaN or inf")
    peak = float(v.abs().max()) if v.numel() else 0.0
    if peak > RANGE_LIMIT:
        raise ValueError(f"{what}: values reach {peak:.3g}; expected [-1, 1] (is it in [0, 255]?)")
    return v.clamp(-1.0, 1.0)
