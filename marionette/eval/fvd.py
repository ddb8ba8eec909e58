"""Fréchet distance of video features, with clip-level bootstrap intervals (the observation layer).

Videos are float tensors (N, T, 3, H, W) in [-1, 1]: N clips of T RGB frames. An extractor maps them to
(N, D) float64 features; the Fréchet distance between the Gaussians fitted to two feature sets is the score.

- ``frechet_distance`` / ``gaussian_stats``: the closed form ||mu1 − mu2||² + tr(C1 + C2 − 2 (C1^½ C2 C1^½)^½),
  in float64, with matrix square roots by symmetric eigen-decomposition (tiny negative eigenvalues from
  rounding are clipped to 0), so the result is always real.
- ``fvd_with_interval``: the point estimate on all clips and a percentile interval over bootstrap
  resamples, each set resampled with replacement independently (numpy Generator seeded by ``seed``),
  by default shifted by the resamples' mean bias (resampling inflates a Fréchet distance).
- ``ProxyExtractor``: no trained weights — a fixed, seeded bank of 3-D convolution kernels at two scales
  plus per-frame colour and frame-difference statistics. Its numbers are labelled "proxy-FVD (not FVD)"
  and are comparable only with numbers from the same extractor (same seed and working size).
- The standard I3D extractor lives in ``i3d`` (Inception-I3D from a local safetensors file, loaded strictly);
  ``extractor_for(path)`` returns it for a path and the proxy otherwise.
- ``fvd_report`` / ``fvd_per_chunk``: one labelled report for two sets of clips, or one per chunk of
  T consecutive frames of long videos (chunk k of the generated set against chunk k of the real set).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from marionette.eval.features import VideoFeatureExtractor, check_videos
from marionette.eval.i3d import I3DExtractor

FVD_LABEL = "FVD"
PROXY_LABEL = "proxy-FVD (not FVD)"
_ENERGY_FLOOR = 1e-3  # added before the log of motion energies: a still clip reads log(1e-3), not −inf


# -- Gaussians and the Fréchet distance ------------------------------------------------------------------


def _check_features(features: np.ndarray, what: str) -> np.ndarray:
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"{what}: expected features of shape (N, D), got shape {f.shape}")
    if f.shape[0] < 2:
        raise ValueError(f"{what}: need at least 2 clips to fit a covariance, got N={f.shape[0]}")
    if not np.isfinite(f).all():
        raise ValueError(f"{what}: features contain NaN or inf")
    return f


def gaussian_stats(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and unbiased covariance (D, D) of features (N, D), float64; N ≥ 2."""
    f = _check_features(features, "gaussian_stats")
    mu = f.mean(axis=0)
    centred = f - mu
    cov = centred.T @ centred / (f.shape[0] - 1)  # (D, D)
    return mu, cov


def _psd_sqrt(c: np.ndarray) -> np.ndarray:
    """Symmetric square root of a symmetric positive semi-definite matrix, negative eigenvalues clipped to 0."""
    w, v = np.linalg.eigh((c + c.T) / 2)
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def frechet_distance(mu1: np.ndarray, cov1: np.ndarray, mu2: np.ndarray, cov2: np.ndarray) -> float:
    """Fréchet (2-Wasserstein²) distance between N(mu1, cov1) and N(mu2, cov2), float64, ≥ 0."""
    mu1, mu2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    cov1, cov2 = np.atleast_2d(np.asarray(cov1, np.float64)), np.atleast_2d(np.asarray(cov2, np.float64))
    d = mu1.shape[0]
    for name, shape, want in (
        ("mu1", mu1.shape, (d,)),
        ("mu2", mu2.shape, (d,)),
        ("cov1", cov1.shape, (d, d)),
        ("cov2", cov2.shape, (d, d)),
    ):
        if shape != want:
            raise ValueError(f"frechet_distance: {name} has shape {shape}, expected {want} (D={d} from mu1)")
    s1 = _psd_sqrt(cov1)
    inner = s1 @ cov2 @ s1  # symmetric PSD; its square root has the same trace as (C1 C2)^½
    w = np.linalg.eigvalsh((inner + inner.T) / 2)
    tr_cross = np.sqrt(np.clip(w, 0.0, None)).sum()
    diff = mu1 - mu2
    value = float(diff @ diff + np.trace(cov1) + np.trace(cov2) - 2.0 * tr_cross)
    return max(value, 0.0)  # rounding can leave −1e-12 where the Gaussians are equal


def _frechet_of_features(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance of the Gaussians fitted to checked features a (N, D), b (M, D).

    With fewer clips than dimensions the cross term comes from the clips' Gram matrix: for centred A, B and
    C1 = AᵀA/(N−1), C2 = BᵀB/(M−1), tr (C1^½ C2 C1^½)^½ is the sum of the singular values of A Bᵀ (N, M)
    over √((N−1)(M−1)) — exact, real, and an N×M SVD instead of two D×D eigen-decompositions.
    """
    if min(len(a), len(b)) >= a.shape[1]:
        return frechet_distance(*gaussian_stats(a), *gaussian_stats(b))
    ca, cb = a - a.mean(axis=0), b - b.mean(axis=0)
    ka, kb = len(a) - 1, len(b) - 1
    tr_cross = np.linalg.svd(ca @ cb.T, compute_uv=False).sum() / np.sqrt(ka * kb)
    diff = a.mean(axis=0) - b.mean(axis=0)
    value = float(diff @ diff + (ca * ca).sum() / ka + (cb * cb).sum() / kb - 2.0 * tr_cross)
    return max(value, 0.0)


def fvd_with_interval(
    feats_a: np.ndarray,
    feats_b: np.ndarray,
    resamples: int = 200,
    confidence: float = 0.95,
    seed: int = 0,
    bias_correct: bool = True,
) -> dict[str, Any]:
    """Fréchet distance of two feature sets (N, D), (M, D) and a clip-level bootstrap percentile interval.

    Resampling clips with replacement repeats some of them, which shrinks the fitted covariances' rank and
    inflates every resample's distance (much more so when D is near N): the raw percentiles can lie wholly
    above the point estimate. With ``bias_correct`` the resamples are first shifted by their mean excess over
    the point estimate (returned as ``bias``); ``bias_correct=False`` gives the raw percentiles (bias 0).
    Bounds are clipped at 0.
    """
    a, b = _check_features(feats_a, "feats_a"), _check_features(feats_b, "feats_b")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"feature dimensions differ: feats_a has D={a.shape[1]}, feats_b has D={b.shape[1]}")
    if resamples < 1:
        raise ValueError(f"resamples must be ≥ 1, got {resamples}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    value = _frechet_of_features(a, b)
    rng = np.random.default_rng(seed)
    boot = np.empty(resamples)
    for i in range(resamples):
        ia = rng.integers(0, len(a), len(a))
        ib = rng.integers(0, len(b), len(b))
        boot[i] = _frechet_of_features(a[ia], b[ib])
    bias = float(boot.mean() - value) if bias_correct else 0.0
    alpha = (1.0 - confidence) / 2
    low, high = np.quantile(boot - bias, [alpha, 1.0 - alpha])
    return {
        "value": value,
        "low": max(float(low), 0.0),
        "high": max(float(high), 0.0),
        "bias": bias,
        "confidence": confidence,
        "resamples": resamples,
        "n_a": len(a),
        "n_b": len(b),
    }


# -- feature extractors ----------------------------------------------------------------------------------


class ProxyExtractor:
    """Proxy video features without trained weights: a seeded 3-D conv bank at two scales + colour/motion stats.

    Frames are resized (bilinear, antialiased when shrinking) to ``working_size`` (H, W), so any resolution works. Two
    kernel banks of shape (3 frames, 5, 5): one random, one with zero mean over time (responds to change
    only); each kernel zero-mean and unit-norm. Valid convolution at full and half working size; per random
    kernel the global means of relu(r) and relu(−r), per temporal kernel log(mean |r| + 1e-3). Then
    per-channel colour mean/std per frame (mean and std over frames) and per-channel log mean |Δ| and
    |Δ²| of first and second frame differences; logs make relative changes of small motion energies count.
    Temporal order matters: shuffling frames changes the temporal kernels' and the frame differences'
    responses. Needs T ≥ 3.
    """

    is_fvd = False

    def __init__(self, seed: int = 0, kernels: int = 16, working_size: tuple[int, int] = (36, 64), batch: int = 8):
        g = torch.Generator().manual_seed(seed)
        banks = []
        for temporal_only in (False, True):
            w = torch.randn(kernels, 3, 3, 5, 5, generator=g)  # (C_out, C_in, kt, kh, kw)
            if temporal_only:
                w = w - w.mean(dim=2, keepdim=True)
            w = w - w.mean(dim=(1, 2, 3, 4), keepdim=True)
            banks.append(w / w.flatten(1).norm(dim=1).view(-1, 1, 1, 1, 1))
        self.weights = torch.cat(banks)  # (2·kernels, 3, 3, 5, 5)
        self.working_size = working_size
        self.batch = batch
        self.name = f"proxy-conv3d(seed={seed}, kernels={2 * kernels}, size={working_size[0]}x{working_size[1]})"

    @property
    def dim(self) -> int:
        """Feature dimension D."""
        k = self.weights.shape[0] // 2
        return 2 * (2 * k + k) + 12 + 6

    def extract(self, videos: torch.Tensor) -> np.ndarray:
        """Features (N, D) float64 of videos (N, T, 3, H, W) in [-1, 1]."""
        v = check_videos(videos)
        n, t = v.shape[:2]
        if t < 3:
            raise ValueError(f"videos: the proxy needs at least 3 frames per clip, got T={t}")
        if n == 0:
            return np.zeros((0, self.dim))
        with torch.inference_mode():
            out = [self._extract_batch(v[i : i + self.batch]) for i in range(0, n, self.batch)]
        return torch.cat(out).to(torch.float64).numpy()

    def _extract_batch(self, v: torch.Tensor) -> torch.Tensor:
        b, t, c, h, w = v.shape
        frames = v.reshape(b * t, c, h, w)
        if (h, w) != self.working_size:
            down = h > self.working_size[0] or w > self.working_size[1]
            frames = F.interpolate(frames, size=self.working_size, mode="bilinear", align_corners=False, antialias=down)
        x = frames.reshape(b, t, c, *self.working_size)  # (B, T, 3, h, w)
        k = self.weights.shape[0] // 2
        feats = []
        vol = x.transpose(1, 2)  # (B, 3, T, h, w)
        for scale in (vol, F.avg_pool3d(vol, kernel_size=(1, 2, 2))):
            r = F.conv3d(scale, self.weights)  # (B, 2K, T-2, h', w')
            appearance, motion = r[:, :k], r[:, k:]
            feats += [F.relu(appearance).mean(dim=(2, 3, 4)), F.relu(-appearance).mean(dim=(2, 3, 4))]
            feats.append(_log_energy(motion.abs().mean(dim=(2, 3, 4))))
        frame_mean, frame_std = x.mean(dim=(3, 4)), x.std(dim=(3, 4))  # (B, T, 3)
        feats += [frame_mean.mean(1), frame_mean.std(1), frame_std.mean(1), frame_std.std(1)]
        d1 = x[:, 1:] - x[:, :-1]  # (B, T-1, 3, h, w)
        d2 = d1[:, 1:] - d1[:, :-1]  # (B, T-2, 3, h, w)
        feats += [_log_energy(d1.abs().mean(dim=(1, 3, 4))), _log_energy(d2.abs().mean(dim=(1, 3, 4)))]
        return torch.cat(feats, dim=1)  # (B, D)


def _log_energy(e: torch.Tensor) -> torch.Tensor:
    """Log of a non-negative energy: relative changes of small motion energies count as much as large ones."""
    return torch.log(e + _ENERGY_FLOOR)


def extractor_for(path: Path | None) -> VideoFeatureExtractor:
    """The feature extractor for an optional I3D safetensors path (``i3d.I3DExtractor``, FVD proper): the proxy
    when no path is given."""
    if path is None:
        return ProxyExtractor()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"I3D weights not found: {path}")
    return I3DExtractor.from_safetensors(path)


# -- reports ---------------------------------------------------------------------------------------------


def fvd_report(
    real: torch.Tensor, generated: torch.Tensor, extractor: VideoFeatureExtractor, resamples: int = 200, seed: int = 0
) -> dict[str, Any]:
    """Fréchet distance of generated clips against real ones with a 95 % bootstrap interval, labelled by extractor."""
    real_v, gen_v = check_videos(real, "real"), check_videos(generated, "generated")
    if real_v.shape[1:] != gen_v.shape[1:]:
        raise ValueError(
            f"real clips have shape {tuple(real_v.shape[1:])}, generated {tuple(gen_v.shape[1:])}; expected equal (T, 3, H, W)"
        )
    stats = fvd_with_interval(extractor.extract(real_v), extractor.extract(gen_v), resamples=resamples, seed=seed)
    metric = FVD_LABEL if extractor.is_fvd else PROXY_LABEL
    return {"metric": metric, "extractor": extractor.name, "frames": int(real_v.shape[1]), "seed": seed, **stats}


def split_chunks(videos: torch.Tensor, frames: int) -> list[torch.Tensor]:
    """Consecutive chunks (N, frames, 3, H, W) of long videos (N, L, 3, H, W); a trailing partial chunk is dropped."""
    if videos.ndim != 5:
        raise ValueError(f"expected long videos of shape (N, L, 3, H, W), got {tuple(videos.shape)}")
    if frames < 1 or videos.shape[1] < frames:
        raise ValueError(f"chunk length {frames} does not fit videos of {videos.shape[1]} frames")
    return [videos[:, k : k + frames] for k in range(0, videos.shape[1] - frames + 1, frames)]


def fvd_per_chunk(
    real: torch.Tensor,
    generated: torch.Tensor,
    extractor: VideoFeatureExtractor,
    frames: int,
    resamples: int = 200,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """One ``fvd_report`` per chunk of ``frames`` consecutive frames of long videos (N, L, 3, H, W), equal L."""
    if real.ndim != 5 or generated.ndim != 5 or real.shape[1] != generated.shape[1]:
        raise ValueError(f"real {tuple(real.shape)} and generated {tuple(generated.shape)} must be (N, L, 3, H, W) with equal L")
    reports = []
    for k, (r, g) in enumerate(zip(split_chunks(real, frames), split_chunks(generated, frames))):
        rep = fvd_report(r, g, extractor, resamples=resamples, seed=seed)
        reports.append({"chunk": k, "start_frame": k * frames, "end_frame": (k + 1) * frames, **rep})
    return reports
