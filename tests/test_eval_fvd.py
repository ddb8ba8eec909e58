"""Fréchet distance, bootstrap intervals and the proxy video extractor (FVD) on synthetic moving blobs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from marionette.eval.fvd import (
    PROXY_LABEL,
    ProxyExtractor,
    extractor_for,
    frechet_distance,
    fvd_per_chunk,
    fvd_report,
    fvd_with_interval,
    gaussian_stats,
    split_chunks,
)

N, T, H, W = 24, 12, 36, 64


def moving_blobs(n: int, t: int = T, h: int = H, w: int = W, seed: int = 0) -> torch.Tensor:
    """(n, t, 3, h, w) in [-1, 1]: a Gaussian blob of random colour moving at constant speed over a colour gradient."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.arange(h) / h, np.arange(w) / w, indexing="ij")
    out = np.empty((n, t, 3, h, w), np.float32)
    for i in range(n):
        left, right = rng.uniform(-1, 0.2, 3)[:, None, None], rng.uniform(-0.2, 1, 3)[:, None, None]
        background = left * (1 - xx) + right * xx
        colour = rng.uniform(-1, 1, 3)[:, None, None]
        start, velocity, radius = rng.uniform(0.2, 0.8, 2), rng.uniform(-0.04, 0.04, 2), rng.uniform(0.1, 0.2)
        for k in range(t):
            cy, cx = start + velocity * k
            mask = np.exp(-((yy - cy) ** 2 + ((xx - cx) * w / h) ** 2) / (2 * radius**2))
            out[i, k] = background * (1 - mask) + colour * mask
    return torch.from_numpy(out)


def noisy(videos: torch.Tensor, sigma: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (videos + sigma * torch.randn(videos.shape, generator=g)).clamp(-1, 1)


@pytest.fixture(scope="module")
def extractor() -> ProxyExtractor:
    return ProxyExtractor()


@pytest.fixture(scope="module")
def real() -> torch.Tensor:
    return moving_blobs(N, seed=1)


@pytest.fixture(scope="module")
def other() -> torch.Tensor:
    """A second, independent sample of the same process."""
    return moving_blobs(N, seed=2)


@pytest.fixture(scope="module")
def real_feats(extractor, real) -> np.ndarray:
    return extractor.extract(real)


def distance(fa: np.ndarray, fb: np.ndarray) -> float:
    return frechet_distance(*gaussian_stats(fa), *gaussian_stats(fb))


# -- Fréchet distance --------------------------------------------------------------------------------------


def test_frechet_identical_gaussians_is_zero():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 5))
    cov = a @ a.T + 1e-3 * np.eye(5)
    mu = rng.normal(size=5)
    assert frechet_distance(mu, cov, mu, cov) == pytest.approx(0.0, abs=1e-9)
    singular = a[:, :2] @ a[:, :2].T  # rank 2: eigenvalues that round to tiny negatives must not go complex
    value = frechet_distance(mu, singular, mu, singular)
    assert isinstance(value, float) and value == pytest.approx(0.0, abs=1e-9)


def test_frechet_closed_forms():
    # 1-D: (m1 − m2)² + (s1 − s2)²
    assert frechet_distance(np.array([1.0]), np.array([[4.0]]), np.array([-2.0]), np.array([[9.0]])) == pytest.approx(9.0 + 1.0)
    # diagonal: the sum over dimensions of the 1-D form
    m1, m2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 1.0, -1.0])
    s1, s2 = np.array([1.0, 2.0, 0.5]), np.array([3.0, 2.0, 1.5])
    expected = ((m1 - m2) ** 2).sum() + ((s1 - s2) ** 2).sum()
    assert frechet_distance(m1, np.diag(s1**2), m2, np.diag(s2**2)) == pytest.approx(expected)
    # invariant to a common rotation of both Gaussians (exercises the non-diagonal path)
    q, _ = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))
    rotated = frechet_distance(q @ m1, q @ np.diag(s1**2) @ q.T, q @ m2, q @ np.diag(s2**2) @ q.T)
    assert rotated == pytest.approx(expected)


@pytest.mark.parametrize("n_a, n_b, d", [(10, 14, 40), (50, 60, 6)])
def test_feature_path_matches_covariance_path(n_a, n_b, d):
    """Fewer clips than dimensions takes the N×M Gram route; it must equal the D×D covariance route."""
    rng = np.random.default_rng(d)
    a, b = rng.normal(size=(n_a, d)), 0.5 + 2.0 * rng.normal(size=(n_b, d)) @ rng.normal(size=(d, d)) / d
    expected = frechet_distance(*gaussian_stats(a), *gaussian_stats(b))
    # clipping eigh's tiny eigenvalues of a rank-deficient C is the looser of the two routes
    assert fvd_with_interval(a, b, resamples=1)["value"] == pytest.approx(expected, rel=1e-6)


def test_gaussian_stats_matches_numpy():
    f = np.random.default_rng(0).normal(size=(10, 3))
    mu, cov = gaussian_stats(f)
    np.testing.assert_allclose(mu, f.mean(0))
    np.testing.assert_allclose(cov, np.cov(f, rowvar=False))


def test_bad_inputs_give_clear_errors(extractor):
    with pytest.raises(ValueError, match="at least 2 clips"):
        gaussian_stats(np.zeros((1, 4)))
    with pytest.raises(ValueError, match=r"\(N, D\)"):
        gaussian_stats(np.zeros(4))
    with pytest.raises(ValueError, match="feature dimensions differ"):
        fvd_with_interval(np.zeros((4, 3)), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="cov2 has shape"):
        frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match=r"\(N, T, 3, H, W\)"):
        extractor.extract(torch.zeros(4, 3, H, W))
    with pytest.raises(ValueError, match=r"\(N, T, 3, H, W\)"):
        extractor.extract(torch.zeros(2, T, 4, H, W))
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        extractor.extract(torch.full((2, T, 3, H, W), 255.0))
    with pytest.raises(ValueError, match="at least 3 frames"):
        extractor.extract(torch.zeros(2, 2, 3, H, W))
    with pytest.raises(ValueError, match="equal L"):
        fvd_per_chunk(torch.zeros(2, 16, 3, H, W), torch.zeros(2, 12, 3, H, W), extractor, frames=8)
    with pytest.raises(ValueError, match="does not fit"):
        split_chunks(torch.zeros(2, 6, 3, H, W), 8)


# -- the proxy extractor -----------------------------------------------------------------------------------


def test_proxy_is_deterministic_and_resolution_agnostic(extractor, real, real_feats):
    assert real_feats.shape == (N, extractor.dim) and real_feats.dtype == np.float64
    np.testing.assert_array_equal(ProxyExtractor().extract(real), real_feats)
    small = F.interpolate(real[:4].flatten(0, 1), size=(18, 32), mode="area").view(4, T, 3, 18, 32)
    large = F.interpolate(real[:4].flatten(0, 1), size=(360, 640), mode="bilinear").view(4, T, 3, 360, 640)
    for resized in (small, large):
        f = extractor.extract(resized)
        assert f.shape == (4, extractor.dim)
        np.testing.assert_allclose(f, real_feats[:4], atol=0.1)  # same content at another resolution, same features


def test_proxy_of_a_set_against_itself_is_zero_and_another_sample_is_small(extractor, real_feats, other):
    assert distance(real_feats, real_feats) == pytest.approx(0.0, abs=1e-9)
    sampling = distance(real_feats, extractor.extract(other))
    degraded = distance(real_feats, extractor.extract(noisy(other, 0.02)))
    assert 0.0 < sampling < degraded / 5


def test_proxy_grows_with_noise(extractor, real_feats, other):
    values = [distance(real_feats, extractor.extract(noisy(other, s))) for s in (0.0, 0.02, 0.05, 0.2)]
    assert all(a < b for a, b in zip(values, values[1:])), values


def test_proxy_grows_when_frames_are_shuffled(extractor, real_feats, other):
    perm = torch.randperm(T, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(perm, torch.arange(T))
    shuffled = extractor.extract(other[:, perm])
    ordered = extractor.extract(other)
    assert not np.allclose(shuffled, ordered)  # the same frames in another order are other features
    assert distance(real_feats, shuffled) > 5 * distance(real_feats, ordered)


# -- bootstrap and reports ---------------------------------------------------------------------------------


def test_bootstrap_interval_is_reproducible_and_contains_the_estimate(extractor, real_feats, other):
    other_feats = extractor.extract(noisy(other, 0.02))
    a = fvd_with_interval(real_feats, other_feats, resamples=100, seed=7)
    assert a == fvd_with_interval(real_feats, other_feats, resamples=100, seed=7)
    b = fvd_with_interval(real_feats, other_feats, resamples=100, seed=8)
    assert (a["low"], a["high"]) != (b["low"], b["high"])
    assert a["value"] == b["value"] == pytest.approx(distance(real_feats, other_feats))
    for r in (a, b):
        assert r["low"] < r["value"] < r["high"]
        assert (r["resamples"], r["n_a"], r["n_b"]) == (100, N, N)
    raw = fvd_with_interval(real_feats, other_feats, resamples=100, seed=7, bias_correct=False)
    assert raw["bias"] == 0.0 and raw["low"] > a["low"]  # resampling inflates the distance


def test_report_labels_say_proxy(extractor, real, other):
    report = fvd_report(real, noisy(other, 0.05), extractor, resamples=20, seed=0)
    assert report["metric"] == PROXY_LABEL == "proxy-FVD (not FVD)"
    assert "fvd" not in report["extractor"].lower() and "proxy" in report["extractor"]
    assert report["low"] <= report["value"] <= report["high"]

    class FakeI3D:
        name, is_fvd = "i3d", True

        def extract(self, videos: torch.Tensor) -> np.ndarray:
            return extractor.extract(videos)

    assert fvd_report(real, other, FakeI3D(), resamples=5)["metric"] == "FVD"


def test_extractor_for_without_weights_is_the_proxy_and_a_bad_file_is_named(tmp_path):
    assert isinstance(extractor_for(None), ProxyExtractor) and not extractor_for(None).is_fvd
    with pytest.raises(FileNotFoundError, match="missing.safetensors"):
        extractor_for(tmp_path / "missing.safetensors")
    weights = tmp_path / "i3d.safetensors"
    weights.write_bytes(b"")
    with pytest.raises(ValueError, match="i3d.safetensors: not a safetensors file"):
        extractor_for(weights)


def test_per_chunk_reports_find_the_degraded_chunk(extractor):
    long_real = moving_blobs(16, t=24, seed=4)
    long_gen = moving_blobs(16, t=24, seed=5)
    long_gen[:, 16:] = noisy(long_gen[:, 16:], 0.1)  # only the last chunk degrades
    reports = fvd_per_chunk(long_real, long_gen, extractor, frames=8, resamples=10, seed=0)
    assert [(r["chunk"], r["start_frame"], r["end_frame"]) for r in reports] == [(0, 0, 8), (1, 8, 16), (2, 16, 24)]
    assert all(r["metric"] == PROXY_LABEL and r["frames"] == 8 for r in reports)
    assert reports[2]["value"] > 5 * max(reports[0]["value"], reports[1]["value"])
    assert len(split_chunks(long_real[:, :20], 8)) == 2  # a trailing partial chunk is dropped
