"""Scanning a recording into terrain observations: depth decoding, back-projection, masking, accuracy."""

from __future__ import annotations

import dataclasses

import av
import numpy as np
import open3d as o3d
import pytest

from marionette.geometry import quat_to_matrix
from marionette.recordings.errors import SampleError
from marionette.recordings.wildworld import RecordedSample, SampleRef, discover, read_sample
from marionette.schema import load_scene
from marionette.synth import generate, load_truth, terrain
from marionette.synth.render import decode_depth, encode_depth
from terrain_scan._points_kernel import grid_points
from terrain_scan.accumulate import (
    VoxelMeans,
    character_mask,
    edge_leaks,
    entity_bones,
    frame_points,
    ground_cloud,
    scan_recording,
    scan_sample,
    segment_distance,
    voxel_reduce,
)
from terrain_scan.depth import DepthDecoder, smooth_codes, smooth_codes_reference
from terrain_scan.field import open_stage
from terrain_scan.image_points import backproject, grid_points_reference, subsampled
from terrain_scan.layers import Observations
from terrain_scan.recording_video import depth_frames, display_ranks
from terrain_scan.store import Stage

pytestmark = pytest.mark.corpus  # generates its own recordings

# the target over every observed (not hole-filled) cell of the stage the two recordings make,
# step cells included; measured 0.029 m at default settings (docs/formats.md)
RMSE_TARGET_M = 0.05
RMSE_AWAY_FROM_STEPS_M = 0.04
# Every step edge (the wall's sides, the deck's rim, the terraces' ledges) lies on an integer metre, so
# no 1 m cell straddles one: a cell touching an edge has its centre 0.5 m from it and one level under
# its whole area. A 0.6 m margin around the edges picks exactly these cells (sides and corners).
STEP_MARGIN_M = 0.6


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    root = tmp_path_factory.mktemp("scan")
    # recording 0 crosses the bridge on its deck, recording 1 runs beneath it along the valley floor
    generate(root, recordings=2, seconds=10.0, seed=0, width=320, height=180)
    ref = discover(root)[0]
    layout = load_scene("duel")
    return root, ref, layout, read_sample(ref, layout), load_truth(root, ref.part, ref.sample_id)


@pytest.fixture(scope="module")
def scan(rec):
    _, ref, layout, _, _ = rec
    return scan_recording(ref, layout, DepthDecoder.synthetic(), keep_points=True)


@pytest.fixture(scope="module")
def stage(rec, scan, tmp_path_factory):
    """The stage of both recordings: their contributions merged, edge aliases dropped, holes filled."""
    root, _, layout, _, _ = rec
    st = Stage(tmp_path_factory.mktemp("stage"))
    for ref in discover(root):
        r = scan if ref.sample_id == rec[1].sample_id else scan_recording(ref, layout, DepthDecoder.synthetic())
        st.put(ref.sample_id, r.observations, ref.sample_id, r.recording_ts)
    st.rebuild()
    return st


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


@pytest.mark.parametrize("kind", ["inverse", "linear", "log", "table"])
def test_decoder_round_trips(kind):
    if kind == "table":  # a monotone curve no parametric kind has, decreasing like the inverse one
        dec = DepthDecoder("table", table=tuple(1.0 + 99.0 * (1 - np.linspace(0, 1, 255)) ** 1.7))
        assert (dec.z_near, dec.z_far) == (1.0, 100.0) and DepthDecoder.from_json(dec.to_json()) == dec
    else:
        dec = DepthDecoder(kind, 1.0, 100.0)
    codes = np.arange(1, 256, dtype=np.uint8)
    np.testing.assert_array_equal(dec.encode(dec.decode(codes)), codes)
    z = np.linspace(1.0, 100.0, 1000)
    c = dec.encode(z).astype(np.float64)  # z lies within its code's half-step bin
    lo, hi = np.sort(np.stack([dec.decode(c - 0.5), dec.decode(np.minimum(c + 0.5, 255.5))]), axis=0)
    assert np.all((z >= lo * (1 - 1e-6)) & (z <= hi * (1 + 1e-6)))
    assert dec.encode(np.array([np.nan, np.inf, 150.0])).tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="expected one of"):
        DepthDecoder("cubic", 1.0, 100.0)
    with pytest.raises(ValueError, match="strictly monotone"):
        DepthDecoder("table", table=(5.0,) * 255)


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
    # the deck's rim and the ledges leak points over cell edges; the leak test takes few of the points
    assert 0 < scan.points_leaked < 0.01 * scan.points_kept, (scan.points_leaked, scan.points_kept)
    assert scan.recording_ts == truth["recording_time"]
    assert np.isfinite(o.h).all() and np.isfinite(o.n).all() and (o.hits > 0).all()
    assert (o.ts == truth["recording_time"]).all()
    assert np.all(o.n[:, 1] >= 0.5 - 1e-6)


def _errors(layers):
    x, z = layers.gx + 0.5, layers.gz + 0.5
    d = layers.h - terrain.surface_height(x, z, layers.h)
    return d, terrain.near_step(x, z, STEP_MARGIN_M)


def test_edge_leaks_drop_a_neighbours_surface_leaked_over_a_cell_edge():
    """Known answer: a ledge at x = 10 (lower ground west, plateau 1.5 m up east) leaks ground points
    3 cm into the plateau's cell; only those are dropped, not a surface of its own on an edge."""
    rng = np.random.default_rng(0)

    def patch(x0, x1, z0, z1, y, n):
        return np.c_[rng.uniform(x0, x1, n), np.full(n, y) + rng.normal(0, 0.01, n), rng.uniform(z0, z1, n)]

    ground = patch(9.0, 10.0, 5.0, 6.0, 30.2, 16)  # cell (9, 5)
    plateau = patch(10.0, 11.0, 5.0, 6.0, 31.7, 16)  # cell (10, 5)
    leaked = patch(10.0, 10.03, 5.0, 6.0, 30.2, 4)  # cell (10, 5), 3 cm in: the ground's points
    rim = patch(12.97, 13.0, 5.0, 6.0, 20.0, 3)  # cell (12, 5) on its east edge, no surface at 20 m east of it
    thin = np.r_[patch(7.97, 8.0, 5.0, 6.0, 25.0, 3), patch(8.0, 8.03, 5.0, 6.0, 25.0, 3)]  # on the edge x = 8
    P = np.r_[ground, plateau, leaked, rim, thin]
    leak = edge_leaks(P)
    want = np.r_[np.zeros(len(ground) + len(plateau), bool), np.ones(len(leaked), bool), np.zeros(len(rim) + len(thin), bool)]
    np.testing.assert_array_equal(leak, want)
    # the same strip 20 cm in is the plateau cell's own evidence, not a leak
    assert not edge_leaks(np.r_[ground, plateau, leaked + [0.2, 0.0, 0.0]]).any()
    assert edge_leaks(np.zeros((0, 3))).shape == (0,)


def test_height_rmse_over_observed_cells(stage):
    layers, filled = stage.layers()
    observed = layers.take(np.flatnonzero(~filled))
    d, step = _errors(observed)
    x, z = observed.gx + 0.5, observed.gz + 0.5
    ledge = step & terrain.in_terrace(x, z, STEP_MARGIN_M)
    assert len(d) > 2000 and step.sum() > 100 and ledge.sum() > 20, (len(d), step.sum(), ledge.sum())
    rmse_all = float(np.sqrt(np.mean(d**2)))
    assert rmse_all < RMSE_TARGET_M, rmse_all
    rmse = float(np.sqrt(np.mean(d[~step] ** 2)))
    assert rmse < RMSE_AWAY_FROM_STEPS_M, rmse
    # the cells touching a step hold their own level only: no layer of one sits at the level across the
    # edge (a 1–4.8 m step leaking across a cell edge), the worst cell named
    i = int(np.argmax(np.abs(d)))
    assert abs(d[i]) < 0.5, f"cell ({observed.gx[i]}, {observed.gz[i]}): layer at {observed.h[i]:.2f} m, off by {d[i]:+.2f} m"
    rmse_step = float(np.sqrt(np.mean(d[step] ** 2)))
    assert rmse_step < RMSE_TARGET_M, rmse_step


def test_one_recording_sees_the_deck_without_collapsing_it(scan):
    o = scan.observations
    d, step = _errors(o)
    assert float(np.sqrt(np.mean(d[~step] ** 2))) < RMSE_AWAY_FROM_STEPS_M
    ground, deck = terrain.layers(o.gx + 0.5, o.gz + 0.5)
    high = np.isfinite(deck) & (deck - ground > 3.0)
    # seen at the deck's level, not the valley's: 8 cells. Two more, 1–3 points each, lie within 2 cm of the
    # line x = −976 where this recording's view of the deck begins; per recording such a sliver is a leak
    # to ``edge_leaks`` (it continues the neighbour's surface), so they are dropped.
    assert np.sum(np.abs(o.h[high] - deck[high]) < 0.3) >= 8


def test_both_bridge_levels_and_queries_under_the_deck(stage):
    layers, filled = stage.layers()
    x, z = layers.gx + 0.5, layers.gz + 0.5
    ground, deck = terrain.layers(x, z)
    high = np.isfinite(deck) & (deck - ground > 3.0) & ~filled
    on_deck = high & (np.abs(layers.h - deck) < 0.3)
    on_floor = high & (np.abs(layers.h - ground) < 0.3)
    assert on_deck.sum() >= 10 and on_floor.sum() >= 10
    cells = lambda m: set(zip(layers.gx[m].tolist(), layers.gz[m].tolist()))  # noqa: E731
    both = cells(on_deck) & cells(on_floor)
    assert len(both) >= 8, both  # cells holding the floor and the deck above it
    field = open_stage(stage.dir)
    rng = np.random.default_rng(0)
    gx, gz = np.array(sorted(both)).T
    # points inside those cells, away from their edges so that all four bilinear neighbours are two-level too
    px, pz = gx + rng.uniform(0.45, 0.55, len(gx)), gz + rng.uniform(0.45, 0.55, len(gz))
    g, dk = terrain.layers(px, pz)
    low = field.query(px, pz, g + 0.9)  # a hunter's pelvis height above the floor, 4 m under the deck
    high_q = field.query(px, pz, dk + 0.9)
    assert np.all(np.abs(low - g) < 0.15), np.c_[low, g]
    assert np.all(np.abs(high_q - dk) < 0.15), np.c_[high_q, dk]


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


@pytest.mark.parametrize("f", [2, 3, 4])
def test_subsampled_depth_keeps_pixels_and_maps_the_intrinsics(f):
    """Issue 16: ``depth_subsample`` keeps one source pixel per f × f block (never a blend of codes) and maps K so
    each kept pixel back-projects to the very world point it does at full size, far from the origin too."""
    from terrain_scan.options import ScanOptions

    rng = np.random.default_rng(f)
    H, W = 72, 128
    codes = rng.integers(1, 255, (H, W), dtype=np.uint8)
    K = np.array([110.0, 112.0, 63.7, 36.2])
    pos, rot = np.array([-2500.0, 40.0, 3100.0]), np.array([0.1, 0.7, -0.1, 0.7]) / np.linalg.norm([0.1, 0.7, -0.1, 0.7])
    small, K2 = subsampled(codes, K, f)
    o = f // 2
    assert small.shape == (len(range(o, H, f)), len(range(o, W, f)))
    np.testing.assert_array_equal(small, codes[o::f, o::f])
    z = codes.astype(np.float64) / 10.0
    full = backproject(z, K, pos, rot)[o::f, o::f]
    np.testing.assert_allclose(backproject(small.astype(np.float64) / 10.0, K2, pos, rot), full, rtol=0, atol=1e-9)
    assert subsampled(codes, K, 1)[0] is codes
    with pytest.raises(ValueError, match="at least 1"):
        subsampled(codes, K, 0)
    # the scan's key: unchanged at 1 (scans made before the knob stay current), new at f
    assert ScanOptions().key() == ScanOptions(depth_subsample=1).key() != ScanOptions(depth_subsample=f).key()
    with pytest.raises(ValueError, match="depth_subsample"):
        ScanOptions(depth_subsample=0)


def test_fast_paths_equal_their_definitions():
    """The scan's compiled and packed paths give their plain definitions' values bit for bit: the smoothing of
    8-bit codes, the per-frame voxel means (one hashed pass over the points, against ``np.unique(axis=0)``) and the character
    mask (bones tested where their grown boxes hold a point, against every point × every bone) — on random data,
    at negative and far-out coordinates."""
    rng = np.random.default_rng(5)
    codes = rng.integers(0, 256, (37, 53)).astype(np.uint8)
    codes[rng.random(codes.shape) < 0.2] = 0
    smooth = np.cumsum(rng.integers(-1, 2, (40, 61)), axis=1) % 200 + 30  # plane-like runs of near codes
    for c in (codes, smooth.astype(np.uint8)):
        for radius, tol in ((3, 1.0), (1, 0.5), (2, 4.0), (3, 0.0), (1, -1.0), (2, 300.0), (40, 1.0)):
            np.testing.assert_array_equal(smooth_codes(c, radius, tol), smooth_codes_reference(c.astype(float), radius, tol))
    for origin in (np.zeros(3), np.array([-4321.7, -12.3, 98765.4])):
        pts = origin + rng.normal(0, 3, (5000, 3))
        key = np.floor(pts / 0.125).astype(np.int64)
        _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        want = np.stack([np.bincount(inv.reshape(-1), weights=pts[:, k]) / cnt for k in range(3)], axis=1)
        np.testing.assert_array_equal(voxel_reduce(pts, 0.125), want)
        a, b = origin + rng.normal(0, 2, (40, 3)), origin + rng.normal(0, 2, (40, 3))
        bones = [(a[:25], b[:25], 0.8), (a[25:], a[25:], 0.4)]  # a rig, and single points
        brute = np.zeros(len(pts), bool)
        for sa, sb, r in bones:
            brute |= (segment_distance(pts, sa, sb) <= r).any(1)
        assert 0 < brute.sum() < len(pts)
        np.testing.assert_array_equal(character_mask(pts, bones), brute)


def test_compiled_frame_pass_equals_its_numpy_definition(rec):
    """``grid_points`` keeps the pixels ``grid_points_reference`` keeps, at the same points (to rounding: the camera
    rotation's dot products are summed in a fixed order, numpy's matmul leaves it to BLAS), on recorded frames and at
    the settings' extremes."""
    _, ref, _, sample, _ = rec
    dec = DepthDecoder.synthetic()
    frames = depth_frames(ref.path / "depth.mkv", keep=lambda k: k % 60 == 7)
    kept = 0
    for i, codes in enumerate(frames):
        if codes is None or not sample.camera_valid[i]:
            continue
        for f, max_depth, rel, ny in ((1, 20.0, 0.1, 0.8), (2, 20.3, 0.1, 0.8), (3, 300.0, 0.02, 0.0), (1, 8.0, 1.0, -1.0)):
            c, K = subsampled(codes, sample.camera_K[i], f)
            z_raw = dec.decode(c)
            z = dec.decode(smooth_codes(c, 3, 1.0))
            pos, rot = sample.camera_pos[i], sample.camera_rot[i]
            want = grid_points_reference(z, z_raw, K, pos, rot, max_depth, rel, ny)
            R = quat_to_matrix(np.asarray(rot, np.float64))
            got = grid_points(z, z_raw, K, R, np.asarray(pos, np.float64), max_depth, rel, ny)
            assert got.shape == want.shape, (i, f, got.shape, want.shape)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
            kept += len(got)
    assert kept > 10000


def _gray_video(path, frames: int = 40) -> None:
    """A short lossless HEVC gray video with B-frames (some referenced by other frames, some not)."""
    rng = np.random.default_rng(0)
    base = rng.integers(1, 200, (48, 64))
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx265", rate=30, options={"x265-params": "lossless=1:log-level=error:pools=1:frame-threads=1"})
        s.width, s.height, s.pix_fmt = 64, 48, "gray"
        for k in range(frames):
            img = ((base + k) % 255 + 1).astype(np.uint8)
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="gray")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_depth_frames_keep_decodes_only_what_it_must(tmp_path):
    """Frames ``keep`` leaves out are None and the rest are the full decode's bytes, whichever frames the decoder
    skips; a file that is no video still raises SampleError naming it."""
    path = tmp_path / "depth.mkv"
    _gray_video(path)
    full = list(depth_frames(path))
    assert len(full) == 40 and sorted(display_ranks(path).values()) == list(range(40))
    for stride in (1, 3, 4):
        got = list(depth_frames(path, keep=lambda i, s=stride: i % s == 0))
        assert len(got) == len(full)
        for i, (a, b) in enumerate(zip(got, full, strict=True)):
            if i % stride:
                assert a is None
            else:
                np.testing.assert_array_equal(a, b)
    bad = tmp_path / "broken.mkv"
    bad.write_bytes(b"not a video")
    with pytest.raises(SampleError, match="broken.mkv"):
        next(depth_frames(bad, keep=lambda i: True))


def test_voxel_means_in_batches_and_ground_cloud_on_any_thread_count():
    """``VoxelMeans`` fed in batches gives the voxel means of all the points at once (bit for bit), and the open3d
    steps give the same points and normals on one thread and on several."""
    rng = np.random.default_rng(3)
    x, z = rng.uniform(-960, -940, 60000), rng.uniform(300, 320, 60000)
    pts = np.c_[x, 30 + 0.1 * np.sin(x) + rng.normal(0, 0.01, len(x)), z]
    acc = VoxelMeans(0.25, capacity=2)
    for part in np.array_split(pts, 9):
        acc.add(part)
    whole = voxel_reduce(pts, 0.25)
    np.testing.assert_array_equal(acc.means(), whole)
    assert sorted(map(tuple, acc.means(ordered=False))) == sorted(map(tuple, whole))
    out = []
    for threads in (1, 4):
        o3d.utility.set_max_threads(threads)
        out.append(ground_cloud(whole, 0.25, 0.5, 2.0))
    o3d.utility.set_max_threads(0)
    assert len(out[0][0]) > 1000
    for a, b in zip(out[0], out[1], strict=True):
        np.testing.assert_array_equal(a, b)
