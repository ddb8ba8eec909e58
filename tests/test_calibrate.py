"""Depth calibration: the synthetic game hides its depth mapping (drawn from a family, written only to the truth);
``marionette calibrate-depth`` recovers it from the recorded skeletons and cameras, and scanning with it gives the
terrain that scanning with the true mapping gives."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from marionette.cli import main as cli
from marionette.recordings.wildworld import discover
from marionette.schema import load_scene
from marionette.synth import generate, load_truth
from marionette.synth import terrain as synth_terrain
from terrain_scan import calibrate, contact_scale, depth_fit
from terrain_scan.accumulate import scan_recording
from terrain_scan.depth import DepthDecoder
from terrain_scan.options import ScanOptions

pytestmark = pytest.mark.corpus  # generates its own recordings

STEP_MARGIN_M = 0.6  # as test_terrain_accumulate: cells touching a step edge


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    """Two 10 s recordings whose depth the game encoded with a log mapping it keeps to itself (seed 0)."""
    root = tmp_path_factory.mktemp("hidden")
    generate(root, recordings=2, seconds=10.0, seed=0, width=160, height=90, hidden_depth=True, workers=2)
    ref = discover(root)[0]
    truth = DepthDecoder.from_json(load_truth(root, ref.part, ref.sample_id)["depth_encoding"])
    assert truth != DepthDecoder.synthetic() and truth.kind == "log"
    return root, truth


def _max_error(dec: DepthDecoder, truth: DepthDecoder, lo: float, hi: float) -> float:
    """Largest relative depth error of ``dec`` against ``truth`` over the truth's codes for depths in [lo, hi]."""
    z = np.geomspace(max(lo, truth.z_near), min(hi, truth.z_far), 400)
    return float(np.max(np.abs(dec.depth_of(truth.code_of(z)) - z) / z))


def test_calibration_recovers_the_hidden_mapping_and_the_corpus_scans_with_it(hidden, corpus, tmp_path, capsys):
    root, truth = hidden
    work = tmp_path / "c"
    shutil.copytree(corpus, work)
    out, png = tmp_path / "mapping.json", tmp_path / "fit.png"
    args = ["calibrate-depth", str(root), "--frame-stride", "3", "--out", str(out), "--plot", str(png), "--corpus", str(work)]
    assert cli([*args, "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "<- best" in said and "chosen: log" in said
    got = DepthDecoder.from_json(json.loads(out.read_text())["decoder"])
    err = _max_error(got, truth, 2.0, 100.0)
    print(f"calibrated {got} against {truth}: max relative error over 2-100 m {err:.4f}")
    assert got.kind == "log" and err < 0.02
    report = json.loads(out.read_text())["report"]
    assert report["pairs"] > 5000 and report["fits"]["log"]["rms_inliers_codes"] < 1.5
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert ScanOptions.stored(work).decoder == got.to_json()  # the corpus's next scan decodes with it
    assert "contact scale: every depth ×" in said and report["contact_scale"]["points"] > 1000
    assert cli(["calibrate-depth", str(root), "--frame-stride", "10", "--no-contact-scale", "--out", str(out), "--quiet"]) == 0
    assert "contact scale" not in capsys.readouterr().out and "contact_scale" not in json.loads(out.read_text())["report"]
    # the table, made monotone from each code's median, agrees with the truth where the characters were seen
    cal = depth_fit.fit(depth_fit.Pairs.concat(list(calibrate.iter_pairs(discover(root), load_scene("duel"), 3))), "table")
    assert cal.chosen.kind == "table" and _max_error(cal.chosen, truth, 6.0, 30.0) < 0.05


def test_terrain_scanned_with_the_calibrated_mapping_is_as_good_as_with_the_truth(hidden):
    root, truth = hidden
    refs, layout = discover(root), load_scene("duel")
    cal, failed = calibrate.calibrate_recordings(refs, layout, 1, knobs=ScanOptions().scan_kwargs())
    got = cal.chosen
    assert not failed and cal.contact.applied and abs(cal.contact.after_m) < abs(cal.contact.before_m) + 0.005
    assert 0.99 < cal.contact.scale < 1.01  # the drake's thin limbs leave the joints' fit little to correct
    rmse = {}
    for name, dec in (("truth", truth), ("calibrated", got), ("the synthetic default", DepthDecoder.synthetic())):
        obs = scan_recording(refs[0], layout, dec, frame_stride=2).observations
        x, z = obs.gx + 0.5, obs.gz + 0.5
        d = obs.h - synth_terrain.surface_height(x, z, obs.h)
        away = ~synth_terrain.near_step(x, z, STEP_MARGIN_M)
        rmse[name] = float(np.sqrt(np.mean(d[away] ** 2)))
    print("terrain RMSE away from steps (m):", rmse)
    assert rmse["calibrated"] <= 1.10 * rmse["truth"]
    assert rmse["the synthetic default"] > 2 * rmse["truth"]  # the calibration is what made the difference


def test_too_few_pairs_and_a_family_that_does_not_fit_are_clear_errors(hidden):
    root, _ = hidden
    pairs = depth_fit.Pairs.concat(list(calibrate.iter_pairs(discover(root)[:1], load_scene("duel"), 3)))
    few = depth_fit.Pairs(pairs.code[:20], pairs.zj[:20], pairs.dist[:20], pairs.joint[:20], pairs.names, pairs.offset)
    with pytest.raises(ValueError, match="20 \\(code, joint\\) pairs: too few"):
        depth_fit.fit(few)
    with pytest.raises(ValueError, match="family 'linear': its planes are not a depth range"):
        depth_fit.fit(pairs, "linear")


def test_a_scaled_decoder_scales_every_depth():
    z = np.geomspace(3.0, 90.0, 50)
    table = DepthDecoder("table", table=tuple(np.geomspace(2.0, 200.0, 255)))
    for dec in (DepthDecoder("inverse", 1.2, 150.0), DepthDecoder("log", 2.5, 400.0), DepthDecoder("linear", 0.5, 120.0), table):
        codes = np.linspace(1.0, 255.0, 77)
        assert np.allclose(dec.scaled(1.03).depth_of(codes), 1.03 * dec.depth_of(codes), rtol=1e-12)
        assert np.allclose(dec.scaled(0.97).code_of(0.97 * z), dec.code_of(z), atol=1e-9)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="depth scale"):
            DepthDecoder("log", 2.5, 400.0).scaled(bad)


def _flat_ground(
    read_scale: float, height: float = 0.0, cells: int = 60, seed: int = 0, aside_m: float = 8.0
) -> contact_scale.ContactPoints:
    """Depth points of flat ground at ``height`` seen from cameras 3–6 m above it and up to ``aside_m`` to the side,
    read with every depth multiplied by ``read_scale`` (a mapping that far off), around contacts at ``height``:
    one cell each, far from the origin and on both sides of it."""
    rng = np.random.default_rng(seed)
    feet = np.stack([rng.uniform(-4000, 4000, cells), np.full(cells, height), rng.uniform(-4000, 4000, cells)], 1)
    cams, offs = [], []
    for f in feet:
        ground = f + np.stack([rng.uniform(-0.1, 0.1, 40), np.zeros(40), rng.uniform(-0.1, 0.1, 40)], 1)
        cam = f + np.array([rng.uniform(-aside_m, aside_m), rng.uniform(3, 6), rng.uniform(-aside_m, aside_m)])
        cams.append(np.broadcast_to(cam, (40, 3)))
        offs.append(read_scale * (ground - cam))
    from terrain_scan.contact_scale import _cell_key

    keys = _cell_key(feet[:, 0], feet[:, 2])
    order = np.argsort(keys)
    cam, off = np.concatenate(cams), np.concatenate(offs)
    return contact_scale.ContactPoints(cam, off, np.zeros(len(cam), np.int64), [(keys[order], feet[order, 1])], frames=cells)


def test_the_contact_scale_puts_the_ground_where_the_feet_stood():
    """Ground read 2 % too far (the depth below the camera too long) comes back × 1/1.02, on cells thousands of
    metres from the origin on either side; too few points or a scale out of range are not applied, and say why."""
    cs = contact_scale.fit_contact_scale([_flat_ground(1.02), _flat_ground(1.02, height=-250.0, seed=1)])
    assert cs.applied and cs.scale == pytest.approx(1 / 1.02, rel=1e-6) and cs.recordings == 2
    assert cs.before_m < -0.05 and abs(cs.after_m) < 1e-6 and "× 0.98039" in cs.line()
    assert contact_scale.fit_contact_scale([_flat_ground(1.0)]).scale == pytest.approx(1.0, abs=1e-9)
    few = contact_scale.fit_contact_scale([_flat_ground(1.02, cells=4)])
    assert not few.applied and few.scale == 1.0 and re.search(r"\d+ depth points on contact cells, fewer than 200", few.line())
    far = contact_scale.fit_contact_scale([_flat_ground(1.5, aside_m=0.0)])  # straight down: the points stay on their cells
    assert not far.applied and "outside 0.8–1.25" in far.note
    assert not contact_scale.fit_contact_scale([]).applied
    # applied to a calibration: the chosen decoder and the table, not the joints' fits; the report says so
    cal = depth_fit.Calibration(
        {}, DepthDecoder("log", 2.5, 400.0), DepthDecoder("table", table=tuple(np.geomspace(2, 300, 255))), None, "log"
    )
    scaled = cal.with_contact_scale(cs)
    assert scaled.chosen == DepthDecoder("log", 2.5, 400.0).scaled(cs.scale) and scaled.table.z_far == pytest.approx(
        300 * cs.scale
    )
    assert cal.with_contact_scale(few).chosen == cal.chosen and cal.with_contact_scale(few).contact.note
    assert contact_scale.weighted_median(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 5.0])) == 3.0
