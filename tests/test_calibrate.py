"""Depth calibration: the synthetic game hides its depth mapping (drawn from a family, written only to the truth);
``marionette calibrate-depth`` recovers it from the recorded skeletons and cameras, and scanning with it gives the
terrain that scanning with the true mapping gives."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from marionette.cli import main as cli
from marionette.ingest.wildworld import discover
from marionette.schema import load_scene
from marionette.synth import generate, load_truth
from marionette.synth import terrain as synth_terrain
from terrain_scan import calibrate
from terrain_scan.accumulate import scan_recording
from terrain_scan.depth import DepthDecoder
from terrain_scan.scan import ScanOptions

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
    # the table, made monotone from each code's median, agrees with the truth where the characters were seen
    cal = calibrate.fit(calibrate.Pairs.concat(list(calibrate.iter_pairs(discover(root), load_scene("duel"), 3))), "table")
    assert cal.chosen.kind == "table" and _max_error(cal.chosen, truth, 6.0, 30.0) < 0.05


def test_terrain_scanned_with_the_calibrated_mapping_is_as_good_as_with_the_truth(hidden):
    root, truth = hidden
    refs, layout = discover(root), load_scene("duel")
    got = calibrate.fit(calibrate.Pairs.concat(list(calibrate.iter_pairs(refs, layout, 1)))).chosen
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
    pairs = calibrate.Pairs.concat(list(calibrate.iter_pairs(discover(root)[:1], load_scene("duel"), 3)))
    few = calibrate.Pairs(pairs.code[:20], pairs.zj[:20], pairs.dist[:20], pairs.joint[:20], pairs.names, pairs.offset)
    with pytest.raises(ValueError, match="20 \\(code, joint\\) pairs: too few"):
        calibrate.fit(few)
    with pytest.raises(ValueError, match="family 'linear': its planes are not a depth range"):
        calibrate.fit(pairs, "linear")
