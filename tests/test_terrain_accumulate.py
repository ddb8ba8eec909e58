"""Scanning a recording into terrain observations: depth decoding, back-projection, masking, accuracy."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from marionette.ingest.wildworld import RecordedSample, SampleRef, discover, read_sample
from marionette.schema import load_scene
from marionette.synth import generate, load_truth, terrain
from marionette.synth.render import decode_depth, encode_depth
from terrain_scan.accumulate import (
    backproject,
    depth_frames,
    entity_bones,
    frame_points,
    scan_recording,
    scan_sample,
    segment_distance,
)
from terrain_scan.depth import DepthDecoder
from terrain_scan.layers import Observations

# measured on this recording at default settings: 0.028 m away from vertical steps (see docs/formats.md)
RMSE_AWAY_FROM_STEPS_M = 0.04


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    generate(root, recordings=1, seconds=10.0, seed=0, width=320, height=180)
    ref = discover(root)[0]
    layout = load_scene("duel")
    return root, ref, layout, read_sample(ref, layout), load_truth(root, ref.part, ref.sample_id)


@pytest.fixture(scope="module")
def scan(rec):
    _, ref, layout, _, _ = rec
    return scan_recording(ref, layout, DepthDecoder.synthetic(), keep_points=True)


def test_decoder_matches_synth_exactly():
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    dec = DepthDecoder.synthetic()
    got = dec.decode(codes)
    want = decode_depth(codes).astype(np.float32)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_array_equal(got[codes > 0], want[codes > 0])
    assert np.isnan(got[0, 0])
    z = np.geomspace(2.0, 299.0, 500)
    np.testing.assert_array_equal(dec.encode(z), encode_depth(z))
    assert DepthDecoder.from_json(dec.to_json()) == dec


@pytest.mark.parametrize("kind", ["inverse", "linear"])
def test_decoder_round_trips(kind):
    dec = DepthDecoder(kind, 1.0, 100.0)
    codes = np.arange(1, 256, dtype=np.uint8)
    np.testing.assert_array_equal(dec.encode(dec.decode(codes)), codes)
    z = np.linspace(1.0, 100.0, 1000)
    c = dec.encode(z).astype(np.float64)  # z lies within its code's half-step bin
    lo, hi = np.sort(np.stack([dec.decode(c - 0.5), dec.decode(np.minimum(c + 0.5, 255.5))]), axis=0)
    assert np.all((z >= lo * (1 - 1e-6)) & (z <= hi * (1 + 1e-6)))
    assert dec.encode(np.array([np.nan, np.inf, 150.0])).tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        DepthDecoder("log", 1.0, 100.0)


def test_backprojection_lands_on_ground(rec):
    """Raw (unsmoothed) ground pixels of a frame back-project onto the analytic surface."""
    _, ref, layout, sample, _ = rec
    dec = DepthDecoder.synthetic()
    i = 20
    codes = next(c for k, c in enumerate(depth_frames(ref.path / "depth.mkv")) if k == i)
    P = backproject(dec.decode(codes), sample.camera_K[i], sample.camera_pos[i], sample.camera_rot[i]).reshape(-1, 3)
    P = P[np.isfinite(P).all(1)]
    near = np.linalg.norm(P - sample.camera_pos[i], axis=1) < 15.0
    P = P[near]
    dy = P[:, 1] - terrain.surface_height(P[:, 0], P[:, 2], P[:, 1])
    assert len(P) > 1000
    # raw codes within 15 m: one code spans up to 0.44 m of depth, ~0.12 m of height at these angles
    assert np.median(np.abs(dy)) < 0.05, np.median(np.abs(dy))
    assert abs(np.median(dy)) < 0.02, np.median(dy)
    # a wrong convention (no pixel-centre offset, or y not flipped) is visibly off
    bad = backproject(dec.decode(codes)[::-1], sample.camera_K[i], sample.camera_pos[i], sample.camera_rot[i]).reshape(-1, 3)
    bad = bad[np.isfinite(bad).all(1)]
    bad = bad[np.linalg.norm(bad - sample.camera_pos[i], axis=1) < 15.0]
    assert np.median(np.abs(bad[:, 1] - terrain.surface_height(bad[:, 0], bad[:, 2], bad[:, 1]))) > 0.3


def test_characters_are_masked(rec):
    _, ref, layout, sample, _ = rec
    dec = DepthDecoder.synthetic()
    total_masked = 0
    for i, codes in enumerate(depth_frames(ref.path / "depth.mkv")):
        if i % 25 or not sample.camera_valid[i]:
            continue
        P, masked = frame_points(codes, sample, layout, i, dec)
        total_masked += masked
        for a, b, r in entity_bones(sample, layout, i, radius_scale=1.0, margin_m=0.0):
            assert not (segment_distance(P, a, b) <= r).any(), f"frame {i}: a kept point inside a recorded capsule"
    assert total_masked > 1000


def test_scan_counters_ts_and_no_nan(scan, rec):
    _, _, _, sample, truth = rec
    o = scan.observations
    n_invalid = int((~truth["camera_valid"]).sum())
    assert scan.frames_total == sample.n_frames == 300
    assert scan.frames_skipped_camera == n_invalid == 4
    assert scan.frames_used == 300 - n_invalid
    assert scan.points_masked > 0 and scan.contacts_added > 0 and scan.points_kept > 1000
    assert scan.recording_ts == truth["recording_time"]
    assert np.isfinite(o.h).all() and np.isfinite(o.n).all() and (o.hits > 0).all()
    assert (o.ts == truth["recording_time"]).all()
    assert np.all(o.n[:, 1] >= 0.5 - 1e-6)


def test_height_rmse_and_both_bridge_levels(scan):
    o = scan.observations
    x, z = o.gx + 0.5, o.gz + 0.5
    d = o.h - terrain.surface_height(x, z, o.h)
    # cells touching a vertical step (the wall's sides, the deck's long edges) hold both heights within 1 m
    step = (terrain.in_wall(x, z, 0.6) & ~terrain.in_wall(x, z, -0.6)) | (terrain.in_deck(x, z, 0.6) & ~terrain.in_deck(x, z, -0.6))
    assert (~step).sum() > 1000
    rmse = float(np.sqrt(np.mean(d[~step] ** 2)))
    assert rmse < RMSE_AWAY_FROM_STEPS_M, rmse
    # the bridge: deck cells are seen at the deck's level, not collapsed onto the valley floor. The
    # default recording never sees the floor under the 4 m wide deck (it is occluded from the
    # follow camera), so two-layer cells there are not asserted.
    ground, deck = terrain.layers(x, z)
    high = np.isfinite(deck) & (deck - ground > 3.0)
    assert high.sum() >= 10
    assert np.all(np.abs(o.h[high] - deck[high]) < 0.3) or np.all(
        np.minimum(np.abs(o.h[high] - deck[high]), np.abs(o.h[high] - ground[high])) < 0.3
    )
    assert np.sum(np.abs(o.h[high] - deck[high]) < 0.3) >= 10

def test_invalid_cameras_and_empty_recordings_are_harmless(rec):
    _, ref, layout, sample, _ = rec
    dec = DepthDecoder.synthetic()
    blind = dataclasses.replace(sample, camera_valid=np.zeros(sample.n_frames, bool))
    frames = (np.full((180, 320), 120, np.uint8) for _ in range(10))
    r = scan_sample(blind, layout, frames, dec, recording_ts=5, frame_stride=2)
    assert r.frames_total == 5 and r.frames_skipped_camera == 5 and r.frames_used == 0 and r.points_kept == 0
    assert np.isfinite(r.observations.h).all()  # contacts only
    empty = RecordedSample(ref=SampleRef(ref.root, ref.part, "none"), n_frames=0, fps=30.0)
    r = scan_sample(empty, layout, iter(()), dec)
    assert len(r.observations) == 0 and r.counters() == dict.fromkeys(r.counters(), 0)
    assert isinstance(r.observations, Observations)
