"""The evaluation protocol end to end on the session's dynamics corpus with its tiny checkpoint: windows,
the state layer beside the recorded rows, the controllability probe, the driving states, the report directory
(quick protocol: its first lines say what it reduces), Tables 1 and 3 with a tiny observation model and a tiny
pixel-AR baseline trained here for a few steps (both columns in the same table, the contact sheet), the
whole-clip proxy-FVD rows, rollout clips rendered through the bridge from the recorded view, and clear errors on
bad input."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch

from marionette.corpus import Corpus, world_of_rows
from marionette.eval import clips as C
from marionette.eval import metrics as M
from marionette.eval import report as R
from marionette.eval.ablation import rule_ablation
from marionette.eval.clips import observation_fvd, rollout_clip, rollout_clips, rollout_fvd
from marionette.eval.config import parse_protocol
from marionette.eval.probe import PROBE_CONDITIONS, controllability_probe
from marionette.eval.protocol import foot_joints, recorded_rows, run_windows, select_windows, state_layer, window_metrics
from marionette.eval.report import evaluate
from marionette.schema import load_scene, state_schema

SEED, HORIZON, N = 16, 32, 3
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def corpus(dynamics_corpus):
    return Corpus(dynamics_corpus)


@pytest.fixture(scope="module")
def ckpt(tiny_dynamics):
    return tiny_dynamics[0]


@pytest.fixture(scope="module")
def windows(corpus):
    return select_windows(corpus, N, SEED, HORIZON, seed=3)


@pytest.fixture(scope="module")
def free(ckpt, corpus, windows):
    return run_windows(ckpt, corpus, windows)


@pytest.fixture(scope="module")
def obs_model():
    """An untrained observation model (fixed seed), small enough to paint every window's clip in seconds."""
    from marionette.observation.config import ObservationConfig
    from marionette.observation.model import VideoDiT

    return VideoDiT(ObservationConfig(frames=5, height=36, width_px=64, patch=4, width=32, layers=1, heads=2), seed=0).eval()


def test_windows_are_held_out_deterministic_and_fit(corpus, windows):
    assert windows == select_windows(corpus, N, SEED, HORIZON, seed=3)
    assert windows != select_windows(corpus, N, SEED, HORIZON, seed=4)
    held_out = set(corpus.segment_ids("test"))
    for w in windows:
        assert w.segment in held_out
        M.check_window(corpus.dynamics_segment(w.segment), w.start, w.length)


def test_windows_longer_than_a_segment_are_a_clear_error(corpus):
    with pytest.raises(ValueError, match="longer than every segment"):
        select_windows(corpus, 2, 64, 100_000)
    seg = corpus.segment_ids("test")[0]
    with pytest.raises(ValueError, match=f"do not fit in segment '{seg}'"):
        select_windows(corpus, 2, 64, 100_000, segments=[seg])


def test_state_rollouts_longer_than_every_segment_are_cut_to_the_painted_length(corpus):
    frames = max(corpus.dynamics_segment(s).num_rows for s in corpus.segment_ids("test"))
    proto = parse_protocol("quick", seed_frames=SEED, state_seconds=frames / 20.0)  # seed + this outgrow every segment
    long, why = R.long_windows(corpus, proto, 60, seed=1, split="test", fps=20.0)
    assert len(long) == proto.state_count == 8 and {w.horizon for w in long} == {60}
    assert why.startswith("state rollouts cut to the painted 3 s:") and "longer than every segment" in why
    long, why = R.long_windows(corpus, replace(proto, state_seconds=4.0), 60, seed=1, split="test", fps=20.0)
    assert {w.horizon for w in long} == {80} and why == ""
    long, why = R.long_windows(corpus, proto, frames, seed=1, split="test", fps=20.0)  # not even the painted ones fit
    assert long == [] and "longer than every segment" in why


def test_batched_windows_equal_single_rollouts(ckpt, corpus, windows, free):
    from marionette.dynamics.rollout import rollout

    tables, ran = free
    assert set(ran.values()) == {("cap",)}  # no terrain scan: the collider cannot run, the cap can
    w = windows[1]
    single = rollout(ckpt, corpus, w.segment, SEED, HORIZON, start=w.start)
    a, b = (np.stack(t["state"].to_numpy(zero_copy_only=False)) for t in (tables[1], single))
    assert np.abs(a - b).max() < 1e-5


def test_state_layer_reports_generated_beside_recorded(ckpt, corpus, windows, free):
    res = state_layer(ckpt, corpus, windows, free[0])
    L = corpus.layout
    names = [e.name for e in L.articulated]
    for metric in ("ra_mpjpe_m", "root_drift_final_m", "bone_length_cv", "foot_skate_mps", "body_share"):
        for n in names:
            row = res["metrics"][f"{metric}/{n}"]
            assert row["generated"]["n"] == N and np.isfinite(row["generated"]["mean"]), (metric, n)
    assert res["metrics"]["separation_m/scene"]["generated"]["n"] == N
    assert np.isnan(res["metrics"]["cfr/hunter"]["generated"]["mean"]) and res["notes"]  # no terrain scan: said so
    # the recorded column is the same measurement on the recorded rows of the same windows
    for n in names:
        e = L.entity(n)
        cv, skate = [], []
        for w in windows:
            j = world_of_rows(L, recorded_rows(corpus, w))[n]
            cv.append(M.bone_length_cv(j, e.rig.parents))
            skate.append(M.foot_skate(j[:, foot_joints(e.rig)], res["fps"]))
        assert res["metrics"][f"bone_length_cv/{n}"]["recorded"]["mean"] == pytest.approx(np.mean(cv), rel=1e-12)
        assert res["metrics"][f"foot_skate_mps/{n}"]["recorded"]["mean"] == pytest.approx(np.nanmean(skate), rel=1e-12)
        assert res["metrics"][f"ra_mpjpe_m/{n}"]["recorded"]["mean"] == 0.0
        assert res["drift"][n].shape == (N, HORIZON) and (res["drift"][n] >= 0).all()
    shares = res["metrics"]["body_share/hunter"]
    assert 0 < shares["recorded"]["mean"] < 1 and 0 < shares["generated"]["mean"] < 1


def test_probe_conditions_differ_and_classes_are_broken_down(ckpt, corpus, windows, free):
    p = controllability_probe(ckpt, corpus, windows, free=free[0])
    means = [p["conditions"][c]["mean"] for c in PROBE_CONDITIONS]
    print(
        f"\nprobe over {N} windows: "
        + ", ".join(f"{c} {p['conditions'][c]['mean']:.4f} ± {p['conditions'][c]['std']:.4f} m" for c in PROBE_CONDITIONS)
        + f"; GT < Shuf on {p['force_gt_beats_shuf']}"
    )
    assert all(np.isfinite(means)) and len(set(means)) == len(PROBE_CONDITIONS)
    assert 0 <= p["force_gt_beats_shuf"] <= p["compared"] == N
    assert p["compliance"] and set(p["compliance"]) <= {"stationary", "locomotion", "attack", "other"}
    for v in p["compliance"].values():
        assert v["runs"] >= 1 and all(0.0 <= v[k] <= 1.0 for k in ("free", "force_gt", "recorded"))


def test_ablation_numbers_for_every_condition(ckpt, corpus, windows):
    a = rule_ablation(ckpt, corpus, windows)
    rows = {r["condition"]: r for r in a["conditions"]}
    assert list(rows) == ["recorded", "no rule", "+ collider", "+ collider + cap"]
    assert a["at"] == "final frame"
    for r in rows.values():
        assert np.isfinite(r["sep_m"]) and (np.isnan(r["skate_mps"]) or r["skate_mps"] >= 0)
    # without a terrain scan the collider cannot run: "+ collider" is "no rule", and the table says why
    assert "collider inactive (no terrain scan)" in rows["+ collider"]["note"]
    np.testing.assert_equal(rows["+ collider"]["per_entity"], rows["no rule"]["per_entity"])
    assert np.isnan(rows["no rule"]["on_ground"])  # no scan: not measured
    assert np.isnan(rows["no rule"]["cfr"]) and np.isnan(rows["no rule"]["mmp_m"])
    assert rows["+ collider + cap"]["ran"] and all(v == ["cap"] for v in rows["+ collider + cap"]["ran"].values())
    # the cap holds every window within max(6 m, its separation at the seed's last frame); the bound is what it holds
    assert rows["+ collider + cap"]["beyond_cap"] == 0.0 and rows["recorded"]["beyond_cap"] >= 0.0


def test_report_directory_end_to_end(ckpt, dynamics_corpus, tmp_path):
    out = tmp_path / "report"
    lines = []
    run = dict(protocol="quick", probe_windows=N, seed_frames=SEED, horizon=HORIZON, state_rollouts=3, state_seconds=5.0)
    s = evaluate(ckpt, dynamics_corpus, out, **run, log=lines.append)
    assert s["out_dir"] == str(out) and s["windows"] == N and lines
    md = (out / "report.md").read_text()
    assert md.splitlines()[2].startswith(
        "**Protocol `quick (changed: horizon, probe_windows, seed_frames, state_rollouts, state_seconds)` is smaller than"
    )
    for heading in ("Table 1", "Table 2 — Controllability probe", "Table 3", "Long horizon", "State layer", "Not run"):
        assert heading in md
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["probe"]["conditions"]) == set(PROBE_CONDITIONS)
    assert [r["condition"] for r in rep["ablation"]["conditions"]] == ["recorded", "no rule", "+ collider", "+ collider + cap"]
    # Table 3's state columns run on the 3 state rollouts of 5 s (the first 2 would be painted, cut to 3 s)
    assert len(rep["ablation"]["windows"]) == rep["protocol"]["state_rollouts"] == 3 and rep["protocol"]["rollouts"] == 2
    assert {w["horizon"] for w in rep["ablation"]["windows"]} == {100} and rep["ablation"]["seconds"] == 5.0
    assert "3 long rollouts of 5 s from" in md and not rep["ablation"]["cut"]
    assert len(rep["long_horizon"]["drift_m"]["hunter"]) == 100  # the curves run as long as the state rollouts
    assert set(s["plots"]) == {"ablation", "class_ratios", "compliance", "drift"}
    for path in s["plots"].values():
        assert Path(path).read_bytes()[:8] == PNG
    assert s["headline"]["hunter_ra_mpjpe_force_gt_m"] > 0 and s["headline"]["windows"] == N
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp directory left behind
    (out / "report.md").write_text("stale")
    evaluate(ckpt, dynamics_corpus, out, **run, log=lambda *_: None)
    assert (out / "report.md").read_text() == md  # a rerun replaces the previous report, same bytes
    with pytest.raises(FileExistsError, match="not a previous report"):
        (tmp_path / "other").mkdir()
        (tmp_path / "other" / "keep.txt").write_text("mine")
        evaluate(ckpt, dynamics_corpus, tmp_path / "other", **run, log=lambda *_: None)
    with pytest.raises(ValueError, match="not fields of EvalProtocol"):
        evaluate(ckpt, dynamics_corpus, tmp_path / "bad", segments=3, log=lambda *_: None)


def test_rollout_table_of_another_layout_is_a_clear_error(corpus, windows, free):
    solo = load_scene("hunter_solo")
    w = windows[0]
    rec = recorded_rows(corpus, w)
    other = pa.Table.from_pylist([], schema=state_schema(solo))
    with pytest.raises(ValueError, match="generated rows"):
        window_metrics(corpus.layout, other, rec, 20.0, render_size=None)
    short = free[0][0].slice(SEED, HORIZON - 1)
    with pytest.raises(ValueError, match="differ in length"):
        window_metrics(corpus.layout, short, rec, 20.0, render_size=None)


def test_observation_fvd_on_a_small_model():
    from marionette.observation.config import OBS_PRESETS
    from marionette.observation.model import VideoDiT

    model = VideoDiT(OBS_PRESETS["tiny"]).eval()
    g = torch.Generator().manual_seed(0)
    clips = [(torch.rand(17, 3, 36, 64, generator=g) * 2 - 1, torch.rand(17, 3, 36, 64, generator=g)) for _ in range(3)]
    r = observation_fvd(model, clips, steps=2, seed=0, resamples=20)
    assert r["frames"] == 17 and r["whole"]["metric"] == "proxy-FVD (not FVD)" and r["whole"]["value"] > 0
    assert [c["chunk"] for c in r["per_chunk"]] == [0]
    with pytest.raises(ValueError, match="at least 2 clips"):
        observation_fvd(model, clips[:1])


def test_rollout_clips_start_from_the_recorded_view(corpus, windows, free):
    from marionette.corpus import fixed_rows
    from marionette.geometry import quat_to_matrix
    from marionette.video import decode_frames

    clips, skipped, T = rollout_clips(corpus, windows, free[0], 5, (36, 64))
    assert not skipped and [k for k, _ in clips] == list(range(N))
    assert (T - 1) % 4 == 0 and HORIZON / 20 * 30 - 4 < T <= HORIZON / 20 * 30 + 1  # the horizon's 30 fps video frames
    for k, clip in clips:
        w, table = windows[k], free[0][k]
        assert clip.rgb.shape == clip.pose.shape == (T, 3, 36, 64)
        assert clip.rgb.min() >= -1 and clip.rgb.max() <= 1 and clip.pose.min() >= 0 and clip.pose.max() <= 1
        a, b = clip.source_frames
        assert b - a == T
        rows = corpus.read_segment(w.segment)
        i = int(np.flatnonzero(rows["frame"].to_numpy() == a)[0])
        t_seed, t_first = float(table["t"][w.seed_frames - 1].as_py()), float(rows["t"][i].as_py())
        assert t_seed - 1e-6 <= t_first < t_seed + 1 / 30  # the first video frame at or after the last (recorded) seed row
        # the bridge camera's first frame is the recorded camera of that frame (the chunk's intrinsics) ...
        chunk = next(r for r in C.segment_chunks(corpus, w.segment) if r["frames"][0] <= a < r["frames"][1])
        np.testing.assert_allclose(clip.cameras.pos[0], fixed_rows(rows["camera.pos"], 3)[i], atol=1e-9)
        np.testing.assert_allclose(clip.cameras.rot[0], quat_to_matrix(fixed_rows(rows["camera.rot"], 4)[i]), atol=1e-9)
        np.testing.assert_allclose(clip.cameras.K[0], chunk["K"][a - chunk["frames"][0]], atol=1e-9)
        assert clip.cameras.valid.all() and (clip.cameras.width, clip.cameras.height) == (64, 36)
        # ... and it frames the generated bodies; the RGB is the recorded frame of the chunk
        assert (clip.pose[0, 1] > 0).any() and (clip.pose[-1, 1] > 0).any()
        first = decode_frames(chunk["rgb"], {a - chunk["frames"][0]})[a - chunk["frames"][0]]
        np.testing.assert_allclose(clip.rgb[0].numpy(), first.transpose(2, 0, 1) / 127.5 - 1.0, atol=1e-6)


def test_rollout_windows_without_video_are_skipped_with_reasons(corpus, windows, free, monkeypatch):
    gone = windows[0].segment
    real = C.segment_chunks
    monkeypatch.setattr(C, "segment_chunks", lambda c, s: [] if s == gone else real(c, s))
    clips, skipped, T = rollout_clips(corpus, windows, free[0], 5, (36, 64))
    lost = [k for k, w in enumerate(windows) if w.segment == gone]
    assert [r["window"] for r in skipped] == lost and [k for k, _ in clips] == [k for k in range(N) if k not in lost]
    assert all("are not all in the segment's video chunks" in r["reason"] and r["segment"] == gone for r in skipped)
    w = windows[1]
    rows, chunks = corpus.read_segment(w.segment), real(corpus, w.segment)
    with pytest.raises(C.WindowSkipped, match="has no rgb.mp4"):
        rollout_clip(corpus, w, free[0][1], T, (36, 64), rows, [{**r, "rgb": None} for r in chunks])
    with pytest.raises(C.WindowSkipped, match="fewer than the clip's"):
        rollout_clip(corpus, w, free[0][1], 10 * T, (36, 64), rows, chunks)
    with pytest.raises(C.WindowSkipped, match="does not reduce"):
        rollout_clip(corpus, w, free[0][1], T, (20, 64), rows, chunks)


def test_rollout_fvd_rows_are_finite_and_seeded(corpus, windows, free, obs_model):
    r = rollout_fvd(obs_model, corpus, windows, free[0], steps=1, seed=0, resamples=20)
    assert r["run"] and r["clips"] == N and not r["skipped"]
    w = r["whole"]
    assert w["metric"] == "proxy-FVD (not FVD)" and np.isfinite(w["value"]) and w["value"] > 0 and 0 <= w["low"] <= w["high"]
    assert [c["chunk"] for c in r["per_chunk"]] == list(range(r["frames"] // 5))
    assert all(np.isfinite(c["value"]) and c["metric"] == "proxy-FVD (not FVD)" for c in r["per_chunk"])
    print(f"\nrollout proxy-FVD over {N} windows of {r['frames']} frames: {w['value']:.2f} [{w['low']:.2f}, {w['high']:.2f}]")
    again = rollout_fvd(obs_model, corpus, windows, free[0], steps=1, seed=0, resamples=20)
    assert again["whole"] == w and again["per_chunk"] == r["per_chunk"]  # same seed, same numbers


@pytest.fixture(scope="module")
def posed(dynamics_corpus, tmp_path_factory):
    """A copy of the dynamics corpus whose held-out video shards and one train shard carry pose targets (the other
    shards' video dropped: the tiny observation models here train on one shard)."""
    from marionette.bridge.targets import render_pose_targets

    copy = tmp_path_factory.mktemp("posed") / "corpus"
    shutil.copytree(dynamics_corpus, copy)
    c = Corpus(copy)
    keep = {c.segment_row(s)["shard"] for s in c.segment_ids("test")} | {c.segment_row(c.segment_ids("train")[0])["shard"]}
    for shard in c.shard_ids():
        if shard not in keep:
            c.video_path(shard).unlink(missing_ok=True)
    render_pose_targets(copy)
    return copy


def test_rollout_clips_match_the_recorded_pose_targets(posed, windows, free):
    import tarfile

    from marionette.bridge.gbuffer import CODE_MAX, iter_codes

    c = Corpus(posed)
    # a rollout clip's first pose frame (recorded state, recorded camera) is the recorded pose target of that frame
    clips, _, _ = rollout_clips(c, windows, free[0], 5, (36, 64))
    for k, clip in clips:
        a = clip.source_frames[0]
        chunk = next(r for r in C.segment_chunks(c, windows[k].segment) if r["frames"][0] <= a < r["frames"][1])
        with tarfile.open(c.pose_path(c.segment_row(windows[k].segment)["shard"])) as tar:
            target = list(iter_codes(tar.extractfile(f"{chunk['key']}.pose.gbz").read()))[a - chunk["frames"][0]]
        ours, theirs = clip.pose[0, 1].numpy() > 0, target[..., 1] > 0
        assert (ours & theirs).sum() >= 0.6 * (ours | theirs).sum() > 0, k  # bone pixels' IoU (the time may differ by < 1/30 s)
        assert clip.pose[0].numpy().max() <= 1 and np.abs(clip.pose[0, 1].numpy() * CODE_MAX - target[..., 1]).mean() < 5


def test_report_scores_the_baseline_in_the_same_table(ckpt, posed, pose_run, baseline_run, tmp_path):
    """The session's pose model and pixel-AR baseline (tests/fixtures/models.py) paint the state rollouts."""
    obs, base = pose_run[0], baseline_run[0]
    out = tmp_path / "report"
    run = dict(protocol="quick", probe_windows=2, state_rollouts=3, state_seconds=4.0, rollout_seconds=2.0)
    s = evaluate(ckpt, posed, out, **run, observation=obs, baseline=base, log=lambda *_: None)
    rep = json.loads((out / "report.json").read_text())
    v, proto = rep["video"], rep["protocol"]
    assert v["run"] and v["skipped"] == [] and v["windows"] == list(range(proto["rollouts"]))  # the state rollouts' first
    assert len(rep["ablation"]["windows"]) == 3 and "FVD16: the first 2 of them" in (out / "report.md").read_text()
    T = round(proto["rollout_seconds"] * 30)
    t1 = v["table1"]
    for col in ("marionette", "baseline"):
        r = t1[col]
        assert r["metric"] == "proxy-FVD (not FVD)" and r["frames"] == T
        assert r["fvd16"]["clips"] == proto["rollouts"] * proto["clips_per_rollout"] and r["fvd16"]["value"] > 0
        assert r["final_chunk"]["frames"] == [T - proto["final_frames"], T] and r["final_chunk"]["value"] > 0
        assert [c["chunk"] for c in r["per_chunk"]] == list(range((T - 1) // (proto["final_frames"] - 1)))
    assert t1["baseline"]["fvd16"]["value"] != t1["marionette"]["fvd16"]["value"]  # its own model painted it
    assert t1["marionette"] == v["table3"]["+ collider"]  # Table 1's Marionette column is Table 3's collider state
    assert set(v["table3"]) == {"recorded", "no rule", "+ collider", "+ collider + cap"}
    md = (out / "report.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| pixel-AR baseline"))
    assert f"{t1['baseline']['fvd16']['value']:.3f}" in row and "n/a" not in row
    assert "![contact sheet](contact_sheet.png)" in md
    assert set(s["plots"]) == {"contact_sheet", "ablation", "class_ratios", "compliance", "drift", "fvd_per_chunk"}
    assert all(Path(p).read_bytes()[:8] == PNG for p in s["plots"].values())
    assert s["headline"]["proxy_fvd16_baseline"] == t1["baseline"]["fvd16"]["value"]
    with pytest.raises(ValueError, match="control 'actions'"):
        evaluate(ckpt, posed, tmp_path / "r2", protocol="quick", baseline=obs, log=lambda *_: None)
