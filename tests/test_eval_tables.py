"""The paper's tables on hand-built inputs with known answers (FVD16's clips, the final chunk, Table 3 at the final
frame), the protocols, the two shuffles of the probe (run-level keeps progress within a run, per-frame does not),
and the probe's GT < Shuf count and per-class ratios on the session's corpus and tiny checkpoint."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
import torch

from marionette.chunks import relay_spans
from marionette.corpus import Corpus
from marionette.eval import video as V
from marionette.eval.ablation import _ablation_row, recorded_window
from marionette.eval.config import PROTOCOLS, EvalProtocol, parse_protocol
from marionette.eval.probe import controllability_probe, shuffle_frames, shuffle_runs, token_runs
from marionette.eval.protocol import pair_separation, select_windows

PAPER = PROTOCOLS["paper"]
GT_BEATS_SHUF_TARGET = 0.7  # the share of probe windows where Force-GT must beat Force-Shuf


class FrameMeans:
    """A known extractor: a clip's features are its per-frame, per-channel means (T · 3,); records the clips it saw."""

    name, is_fvd = "frame-means", False

    def __init__(self) -> None:
        self.seen: list[tuple[int, ...]] = []

    def extract(self, videos: torch.Tensor) -> np.ndarray:
        self.seen.append(tuple(videos.shape))
        return videos.mean(dim=(3, 4)).flatten(1).double().numpy()


def _videos(n: int, T: int, seed: int) -> torch.Tensor:
    """Videos (n, T, 3, 4, 4) in [−1, 1] whose frame t of video i is a known random level."""
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, T, 3, 1, 1, generator=g) * 2 - 1).expand(n, T, 3, 4, 4).contiguous()


def test_fvd16_takes_exactly_eight_16_frame_clips_per_16_s_rollout():
    T = PAPER.video_frames(30.0)
    assert T == 480 and PAPER.clip_starts(30.0) == [0, 60, 120, 180, 240, 300, 360, 420]
    v = torch.arange(3 * T, dtype=torch.float32).reshape(3, T, 1, 1, 1).expand(3, T, 3, 2, 2)
    clips = V.fvd16_clips(v, PAPER.clip_starts(30.0), PAPER.clip_frames)
    assert clips.shape == (3 * 8, 16, 3, 2, 2)
    # rollout i's clip k is its frames [60k, 60k + 16)
    np.testing.assert_array_equal(
        clips[:, :, 0, 0, 0].numpy(), [[i * T + 60 * k + f for f in range(16)] for i in range(3) for k in range(8)]
    )
    real, ex = _videos(3, T, 0), FrameMeans()
    r = V.score_videos(real, _videos(3, T, 1), PAPER, 30.0, ex)
    assert r["fvd16"]["clips"] == 24 and ex.seen[0] == (24, 16, 3, 4, 4) and ex.seen[1] == (24, 16, 3, 4, 4)
    assert r["frames"] == 480 and r["rollouts"] == 3


def test_the_final_chunk_is_the_last_81_frames():
    T = PAPER.video_frames(30.0)
    v = torch.arange(T + 1, dtype=torch.float32).reshape(1, T + 1, 1, 1, 1).expand(2, T + 1, 3, 1, 1)
    last = V.final_chunk(v, T, PAPER.final_frames)  # the relay may paint past T: the chunk ends at T
    assert last.shape[1] == 81 and last[0, 0, 0, 0, 0] == T - 81 and last[0, -1, 0, 0, 0] == T - 1
    real = _videos(4, T, 0)
    before = real.clone()
    before[:, : T - 81] = _videos(4, T - 81, 5)  # differs only before the final chunk
    r = V.score_videos(real, before, PAPER, 30.0, FrameMeans())
    assert r["final_chunk"]["frames"] == [399, 480] and r["final_chunk"]["value"] == pytest.approx(0.0, abs=1e-9)
    assert r["fvd16"]["value"] > 0.1 and r["per_chunk"][0]["value"] > 0.1
    inside = real.clone()
    inside[:, T - 81 :] = _videos(4, 81, 6)  # differs only inside it
    r = V.score_videos(real, inside, PAPER, 30.0, FrameMeans())
    assert r["final_chunk"]["value"] > 0.1 and r["per_chunk"][0]["value"] == pytest.approx(0.0, abs=1e-9)
    for k in ("fvd16", "final_chunk"):  # the paper's raw percentile interval beside the bias-corrected one
        assert r[k]["raw_low"] <= r[k]["raw_high"] and r[k]["low"] <= r[k]["high"]
    assert relay_spans(T, 81) == [(0, 81), (80, 161), (160, 241), (240, 321), (320, 401)]


def test_table3_reads_sep_and_the_contact_rows_at_the_final_frame(dynamics_corpus):
    c = Corpus(dynamics_corpus)
    w = select_windows(c, 1, 4, 20, seed=0)[0]
    rows = recorded_window(c, w).slice(w.seed_frames, w.horizon)
    mon = np.stack(rows["monster.root_world"].to_numpy(zero_copy_only=False))
    gap = np.linspace(1.0, 5.0, rows.num_rows)  # the hunter 1 m → 5 m from the monster along x: mean 3, final 5
    hunter = mon + np.stack([gap, np.full_like(gap, 0.5), np.zeros_like(gap)], axis=1)
    i = rows.schema.get_field_index("hunter.root_world")
    rows = rows.set_column(i, rows.schema.field(i), pa.array(list(hunter), type=rows.schema.field(i).type))
    row = _ablation_row(c.layout, [(rows, None)], 20.0)
    assert row["sep_m"] == pytest.approx(5.0, abs=1e-9) and row["sep_3d_m"] == pytest.approx(np.hypot(5.0, 0.5), abs=1e-9)
    # beyond the cap: the final 5 m is within max(6 m, the seed's separation) for any seed separation; 7 m is not
    # when the seed ended within 6 m, and is when it ended 7.5 m apart
    assert _ablation_row(c.layout, [(rows, None)], 20.0, [2.0])["beyond_cap"] == 0.0
    far = rows.set_column(i, rows.schema.field(i), pa.array(list(mon + [7.0, 0.0, 0.0]), type=rows.schema.field(i).type))
    assert _ablation_row(c.layout, [(far, None), (rows, None)], 20.0, [2.0, 2.0])["beyond_cap"] == 0.5
    assert _ablation_row(c.layout, [(far, None)], 20.0, [7.5])["beyond_cap"] == 0.0
    assert np.isnan(row["beyond_cap"])  # no seed separations given: not measured

    class Flat:  # ground at y = 0 everywhere
        def query(self, x, z, ref_y):
            return np.zeros(np.broadcast(x, z, ref_y).shape)

    low = mon.copy()
    low[:, 1] = 10.0  # the monster 10 m above the ground on every frame but the last, 10 m below it on the last
    low[-1, 1] = -10.0
    j = rows.schema.get_field_index("monster.root_world")
    sunk = rows.set_column(j, rows.schema.field(j), pa.array(list(low), type=rows.schema.field(j).type))
    r = _ablation_row(c.layout, [(sunk, Flat())], 20.0)["per_entity"]["monster"]
    assert r["cfr"] == 1.0 and r["mmp_m"] > 5.0  # only the final frame sinks: a mean over frames would be 1/20 and ~0.5 m
    assert r["on_ground"] == 1.0


def test_engaged_windows_start_with_the_pair_within_the_distance(dynamics_corpus):
    """``select_windows(engaged=d)``: every window whose segment allows it ends its seed with the pair within d."""
    c = Corpus(dynamics_corpus)
    plain = select_windows(c, 12, 16, 40, seed=5)
    near = select_windows(c, 12, 16, 40, seed=5, engaged=6.0)
    assert [w.segment for w in near] == [w.segment for w in plain]  # the same segments, other starts
    seps = [float(pair_separation(c.layout, recorded_window(c, w).slice(w.seed_frames - 1, 1))[0]) for w in near]
    allowed = []
    for w in near:
        s = pair_separation(c.layout, c.dynamics_segment(w.segment))
        allowed.append(bool((s[w.seed_frames - 1 : len(s) - w.horizon] <= 6.0).any()))
    print(
        f"\nseed-end separations (m): plain {[round(float(pair_separation(c.layout, recorded_window(c, w).slice(w.seed_frames - 1, 1))[0]), 1) for w in plain]}, engaged {[round(x, 1) for x in seps]}"
    )
    assert all(s <= 6.0 for s, ok in zip(seps, allowed) if ok) and any(allowed)


def test_protocols_are_typed_and_checked():
    quick = PROTOCOLS["quick"]
    assert PAPER.reduced() == [] and "probe_windows 8 (paper 48)" in quick.reduced()
    assert (PAPER.probe_windows, PAPER.seed_frames, PAPER.horizon, PAPER.temperature) == (48, 64, 120, 0.0)
    assert parse_protocol("quick", rollouts=3).rollouts == 3
    # Table 3's state rollouts: the paper's are the painted ones; the quick protocol measures the rules on more and longer
    assert (PAPER.state_count, PAPER.state_length_s) == (PAPER.rollouts, PAPER.rollout_seconds) == (32, 16.0)
    assert (quick.state_count, quick.state_length_s) == (8, 9.0) and "state_seconds 9 (paper 16)" in quick.reduced()
    more = parse_protocol("quick", rollouts=12, rollout_seconds=10.0)  # the state rollouts grow with the painted ones
    assert (more.state_count, more.state_length_s) == (12, 10.0)
    assert parse_protocol("quick", rollouts=3, state_rollouts=5).state_count == 5
    with pytest.raises(ValueError, match="state_rollouts is an integer ≥ rollouts"):
        parse_protocol("quick", rollouts=4, state_rollouts=3)
    with pytest.raises(ValueError, match="state_seconds ≥ rollout_seconds"):
        parse_protocol("quick", state_seconds=2.0)
    with pytest.raises(ValueError, match="unknown protocol 'papr'"):
        parse_protocol("papr")
    with pytest.raises(ValueError, match=r"\['segments'\] are not fields"):
        parse_protocol("paper", segments=3)
    with pytest.raises(ValueError, match="rollouts ≥ 2"):
        EvalProtocol("x", rollouts=1)
    with pytest.raises(ValueError, match="cannot hold 8 clips of 16 frames"):
        EvalProtocol("x", rollout_seconds=2.0).video_frames(30.0)


def test_run_level_shuffle_permutes_whole_runs_the_per_frame_one_does_not():
    tokens = np.array([3] * 10 + [5] * 4 + [0] * 3 + [7] * 8 + [3] * 5)
    runs = token_runs(tokens)
    assert runs == [(0, 10), (10, 14), (14, 17), (17, 25), (25, 30)]
    force = shuffle_runs("hunter", tokens, np.random.default_rng(0))
    assert sorted((e - s, tok) for _, s, e, tok in force) == sorted((b - a, int(tokens[a])) for a, b in runs if tokens[a])
    assert [(s, e, t) for _, s, e, t in force] != [(a, b, int(tokens[a])) for a, b in runs if tokens[a]]  # permuted
    per_frame = shuffle_frames("hunter", tokens, np.random.default_rng(0))
    assert len(per_frame) > 2 * len(force)


def test_run_level_shuffle_keeps_progress_within_each_run(tiny_dynamics, dynamics_corpus):
    from marionette.corpus.vocab import ActionTokens
    from marionette.dynamics.controls import forced_at
    from marionette.dynamics.engine import Rollout

    ckpt, c = tiny_dynamics[0], Corpus(dynamics_corpus)
    w = select_windows(c, 1, 16, 60, seed=2)[0]
    tokens = ActionTokens.from_corpus(c)
    i = tokens.entities.index("hunter")
    view = c.dynamics_segment(w.segment)
    stream = tokens.encode(c.layout, view.slice(w.start + w.seed_frames, w.horizon))[0][:, i]
    names = [e.name for e in c.layout.articulated]
    progress = {}
    for name, force in (
        ("runs", shuffle_runs("hunter", stream, np.random.default_rng(1))),
        ("frames", shuffle_frames("hunter", stream, np.random.default_rng(1))),
    ):
        ro = Rollout(ckpt, c)
        ro.start(view.slice(w.start, w.seed_frames))
        p = []
        for t in range(w.horizon):
            forced, restart = forced_at(force, t, names)
            ro.step(forced, None, restart)
            p.append(float(ro.progress[i]))
        progress[name] = (np.array(p), force)
    p, force = progress["runs"]
    inside = [t for _, s, e, _ in force for t in range(s + 1, e)]
    assert inside and all(p[t] > 0 or p[t - 1] > 0.9 for t in inside)  # progress runs on (or wraps) inside every run
    q, per_frame = progress["frames"]
    starts = [s for _, s, _, _ in per_frame]
    restarts = int((q[starts] == 0).sum())
    print(f"\n{len(force)} runs kept whole; the per-frame shuffle restarted progress on {restarts} of {w.horizon} frames")
    assert np.mean(q[starts] == 0) > 0.8 and restarts > 2 * len(force)  # it restarts progress far more often than there are runs


def test_probe_gt_beats_shuf_on_most_windows(tiny_dynamics, dynamics_corpus):
    c = Corpus(dynamics_corpus)
    windows = select_windows(c, PAPER.probe_windows, PAPER.seed_frames, PAPER.horizon, seed=0)
    p = controllability_probe(tiny_dynamics[0], c, windows, temperature=PAPER.temperature)
    n, won = p["compared"], p["force_gt_beats_shuf"]
    print(
        f"\nprobe over {n} windows of {PAPER.seed_frames} + {PAPER.horizon}: GT < Shuf on {won}, GT < run-shuffle on "
        f"{p['force_gt_beats_shuf_runs']}; "
        + ", ".join(f"{k} {v['mean']:.4f} m" for k, v in p["conditions"].items())
        + "\nper-class Shuf/GT: "
        + ", ".join(
            f"{k} {v['force_shuf/force_gt']:.2f} (run-shuffle {v['force_shuf_runs/force_gt']:.2f}, {v['frames']} frames)"
            for k, v in p["class_ratios"].items()
        )
    )
    assert n == 48 and set(p["class_ratios"]) <= {"stationary", "locomotion", "attack", "other"}
    assert all(np.isfinite(v["force_shuf/force_gt"]) for v in p["class_ratios"].values())
    assert won >= GT_BEATS_SHUF_TARGET * n, f"Force-GT < Force-Shuf on {won} of {n} windows, below {GT_BEATS_SHUF_TARGET:.0%}"


def test_class_ratios_pool_frames_by_the_recorded_class():
    from marionette.eval.probe import class_ratios

    classes = [np.array(["attack", "attack", "none", "stationary"]), np.array(["stationary", "attack", "attack", "attack"])]
    gt = [np.array([0.1, 0.1, 9.0, 0.2]), np.array([0.2, 0.1, 0.1, 0.1])]
    shuf = [np.array([0.3, 0.3, 9.0, 0.2]), np.array([0.4, 0.3, 0.3, 0.3])]
    r = class_ratios({"force_gt": gt, "force_shuf": shuf}, classes)
    assert list(r) == ["stationary", "attack"]  # the order of CLASSES; token 0's frames have no class
    assert r["attack"]["frames"] == 5 and r["attack"]["force_shuf/force_gt"] == pytest.approx(3.0)
    assert r["stationary"]["force_shuf/force_gt"] == pytest.approx(0.6 / 0.4)


def test_the_report_opens_with_the_model_against_its_trivial_baselines(tmp_path):
    """A training summary whose model loses on root MSE: the report's first lines say so and show every comparison;
    a summary with a non-number is refused naming the file; a directory without one adds nothing."""
    import json

    from marionette.eval.markdown import _baseline_lines, training_against_baselines

    ev = {"action_accuracy": 0.98, "body_mse": 0.01, "root_mse": 0.05, "windows": 6, "step": 300}
    base = {
        "copy_last_action_accuracy": 0.97,
        "most_frequent_action_accuracy": 0.2,
        "copy_last_body_mse": 0.07,
        "constant_velocity_root_mse": 0.02,
    }
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 300, "eval": ev, "baselines": base}))
    tb = training_against_baselines(tmp_path)
    assert [r["wins"] for r in tb["rows"]] == [True, True, True, False]
    text = "\n".join(_baseline_lines({"training": tb}))
    assert "does not beat every trivial baseline" in text and "1 of 4" in text and "**no**" in text
    ev["root_mse"] = 0.01
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 300, "eval": ev, "baselines": base}))
    assert "beats every trivial baseline" in _baseline_lines({"training": training_against_baselines(tmp_path)})[0]
    ev["root_mse"] = "0.01"
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 300, "eval": ev, "baselines": base}))
    with pytest.raises(ValueError, match="summary.json"):
        training_against_baselines(tmp_path)
    assert training_against_baselines(tmp_path / "missing") is None
    assert _baseline_lines({"training": None}) == []
