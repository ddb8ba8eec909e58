"""The evaluation protocol end to end on the session's dynamics corpus with its tiny checkpoint: windows,
the state layer beside the recorded rows, the controllability probe, the rule ablation, the report
directory, the observation layer's proxy-FVD on a small model, and clear errors on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch

from marionette.corpus import Corpus, world_of_rows
from marionette.eval import metrics as M
from marionette.eval.protocol import (
    PROBE_CONDITIONS,
    controllability_probe,
    foot_joints,
    recorded_rows,
    rule_ablation,
    run_windows,
    select_windows,
    state_layer,
    window_metrics,
)
from marionette.eval.report import evaluate, observation_fvd
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
    print(f"\nprobe over {N} windows: " + ", ".join(f"{c} {p['conditions'][c]['mean']:.4f} ± {p['conditions'][c]['std']:.4f} m"
                                                    for c in PROBE_CONDITIONS) + f"; GT < Shuf on {p['force_gt_beats_shuf']}")  # fmt: skip
    assert all(np.isfinite(means)) and len(set(means)) == 3
    assert 0 <= p["force_gt_beats_shuf"] <= p["compared"] == N
    assert p["compliance"] and set(p["compliance"]) <= {"stationary", "locomotion", "attack", "other"}
    for v in p["compliance"].values():
        assert v["runs"] >= 1 and all(0.0 <= v[k] <= 1.0 for k in ("free", "force_gt", "recorded"))


def test_ablation_numbers_for_every_condition(ckpt, corpus, windows):
    a = rule_ablation(ckpt, corpus, windows)
    rows = {r["condition"]: r for r in a["conditions"]}
    assert list(rows) == ["recorded", "no rule", "+ collider", "+ collider + cap"]
    for r in rows.values():
        assert np.isfinite(r["skate_mps"]) and np.isfinite(r["sep_m"])
    # without a terrain scan the collider cannot run: "+ collider" is "no rule", and the table says why
    assert "collider inactive (no terrain scan)" in rows["+ collider"]["note"]
    assert rows["+ collider"]["skate_mps"] == rows["no rule"]["skate_mps"]
    assert np.isnan(rows["no rule"]["cfr"]) and np.isnan(rows["no rule"]["mmp_m"])
    assert rows["+ collider + cap"]["ran"] and all(v == ["cap"] for v in rows["+ collider + cap"]["ran"].values())


def test_report_directory_end_to_end(ckpt, dynamics_corpus, tmp_path):
    out = tmp_path / "report"
    lines = []
    s = evaluate(ckpt, dynamics_corpus, out, segments=N, seed_frames=SEED, horizon=HORIZON, log=lines.append)
    assert s["out_dir"] == str(out) and s["windows"] == N and lines
    md = (out / "report.md").read_text()
    for heading in ("State layer", "Controllability probe", "Rule ablation", "Observation layer", "Not run"):
        assert heading in md
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["probe"]["conditions"]) == set(PROBE_CONDITIONS)
    assert [r["condition"] for r in rep["ablation"]["conditions"]] == ["recorded", "no rule", "+ collider", "+ collider + cap"]
    assert set(s["plots"]) == {"ablation", "compliance", "drift"}
    for path in s["plots"].values():
        assert Path(path).read_bytes()[:8] == PNG
    assert s["headline"]["hunter_ra_mpjpe_force_gt_m"] > 0 and s["headline"]["windows"] == N
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp directory left behind
    (out / "report.md").write_text("stale")
    evaluate(ckpt, dynamics_corpus, out, segments=N, seed_frames=SEED, horizon=HORIZON, log=lambda *_: None)
    assert (out / "report.md").read_text() == md  # a rerun replaces the previous report, same bytes
    with pytest.raises(FileExistsError, match="not a previous report"):
        (tmp_path / "other").mkdir()
        (tmp_path / "other" / "keep.txt").write_text("mine")
        evaluate(ckpt, dynamics_corpus, tmp_path / "other", segments=N, seed_frames=SEED, horizon=HORIZON, log=lambda *_: None)


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
    from marionette.observation.model import OBS_PRESETS, VideoDiT

    model = VideoDiT(OBS_PRESETS["tiny"]).eval()
    g = torch.Generator().manual_seed(0)
    clips = [(torch.rand(17, 3, 36, 64, generator=g) * 2 - 1, torch.rand(17, 3, 36, 64, generator=g)) for _ in range(3)]
    r = observation_fvd(model, clips, steps=2, seed=0, resamples=20)
    assert r["frames"] == 17 and r["whole"]["metric"] == "proxy-FVD (not FVD)" and r["whole"]["value"] > 0
    assert [c["chunk"] for c in r["per_chunk"]] == [0]
    with pytest.raises(ValueError, match="at least 2 clips"):
        observation_fvd(model, clips[:1])
