"""The session's trained tiny checkpoint (``tiny_dynamics``, tests/fixtures/models.py) on its held-out split: it beats the
baselines, obeys forced tokens, stays stable over 3,000 frames (10,000: ``benchmarks/bench_dynamics.py --part long``),
and its cached, recomputed, bf16 and
float64-integrated rollouts agree."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from marionette import geometry as geo
from marionette.corpus import Corpus, fixed_rows, world_of_rows
from marionette.dynamics.controls import force_windows
from marionette.dynamics.data import ActionTokens
from marionette.dynamics.engine import Rollout
from marionette.dynamics.rollout import rollout
from marionette.eval.control import FAST_TIP_MPS, held_out_seeds, recorded_swingers, swing_rates
from marionette.eval.protocol import Window, run_windows

SEED = 32  # seed frames


@pytest.fixture(scope="module")
def corpus(dynamics_corpus):
    return Corpus(dynamics_corpus)


@pytest.fixture(scope="module")
def ckpt(tiny_dynamics):
    return tiny_dynamics[0]


def bone_cv(joints: np.ndarray, rig) -> np.ndarray:
    """Per bone, the coefficient of variation of its length over frames."""
    lengths = np.stack([np.linalg.norm(joints[:, a] - joints[:, b], axis=-1) for a, b in rig.bones], axis=1)
    return lengths.std(0) / lengths.mean(0)


def ra_mpjpe(table, recorded, layout, entity: str) -> float:
    """Root-aligned MPJPE (m) of the predicted rows against the recorded rows of the same frames."""
    p = world_of_rows(layout, table)[entity][SEED:]
    r = world_of_rows(layout, recorded)[entity]
    return float(np.linalg.norm((p - p[:, :1]) - (r - r[:, :1]), axis=-1).mean())


def test_learning_beats_the_body_and_most_frequent_baselines(tiny_dynamics):
    """The body state one step ahead beats copy-last, the next action beats the most frequent train action."""
    _, s = tiny_dynamics
    ev, base = s["eval"], s["baselines"]
    print(f"\nbody MSE (normalised): model {ev['body_mse']:.5f}, copy-last {base['copy_last_body_mse']:.5f}")
    assert ev["body_mse"] < base["copy_last_body_mse"]
    assert ev["action_accuracy"] > base["most_frequent_action_accuracy"]


def test_learning_beats_every_baseline(tiny_dynamics):
    """Issue 15's bar: on held-out play the tiny checkpoint beats copy-last and the most frequent action on the next
    action, copy-last on the body and constant velocity on the root. Copy-last misses every change; the model calls
    the ones an ending event makes (the game's recovery follows every event) and few that do not happen."""
    _, s = tiny_dynamics
    ev, base = s["eval"], s["baselines"]
    print(f"\nheld-out windows {ev['windows']} after {s['steps']} steps; parameters {s['parameters']}")
    print(
        f"next-action accuracy: model {ev['action_accuracy']:.4f}, copy-last {base['copy_last_action_accuracy']:.4f}, "
        f"most-frequent {base['most_frequent_action_accuracy']:.4f}; of {ev['action_changes']} changes the model called "
        f"{ev['changes_called']}, and called {ev['false_changes']} that did not happen"
    )
    print(f"body MSE (normalised): model {ev['body_mse']:.5f}, copy-last {base['copy_last_body_mse']:.5f}")
    print(f"root MSE (normalised): model {ev['root_mse']:.5f}, constant velocity {base['constant_velocity_root_mse']:.5f}")
    assert ev["action_accuracy"] > base["copy_last_action_accuracy"]
    assert ev["action_accuracy"] > base["most_frequent_action_accuracy"]
    assert ev["body_mse"] < base["copy_last_body_mse"]
    assert ev["root_mse"] < base["constant_velocity_root_mse"]


def test_forcing_an_attack_swings_the_weapon_within_10_frames(corpus, ckpt):
    """Forcing the hunter's attack tokens whose recorded plays swing within 10 frames (on ≥ 80 % of plays) brings a
    fast weapon tip within 10 frames on ≥ 60 % of the held-out seeds, 0.3 more often than the unforced rollouts of
    the same seeds, and every forced token more often than those.
    (The game has ~35 attack tokens, many winding up for longer than 10 frames, and most are played a handful of
    times in 7.5 minutes of training play: the test forces the most played of those that swing at once — a test
    of forcing, not of few-shot learning.)"""
    tokens = ActionTokens.from_corpus(corpus)
    hi = tokens.entities.index("hunter")
    attacks = recorded_swingers(corpus, "hunter", 10, 4)
    assert len(attacks) >= 2, f"only {attacks} of the hunter's attack tokens swing within 10 frames in the train split"
    seeds = held_out_seeds(corpus, SEED, 10)
    assert len(seeds) >= 20
    rates = swing_rates(ckpt, corpus, "hunter", attacks, seeds, SEED, frames=10)
    forced = float(np.mean([rates[t] for t in attacks]))
    print(
        f"\n{len(seeds)} held-out seeds; tip > {FAST_TIP_MPS} m/s within 10 frames: free {rates[None]:.2f}, "
        + ", ".join(f"forced token {t} (composite {int(tokens.composites[hi][t])}) {rates[t]:.2f}" for t in attacks)
        + f"; all attacks {forced:.2f}"
    )
    assert forced >= 0.6 and forced > rates[None] + 0.3
    assert all(rates[t] > rates[None] for t in attacks)


def test_forcing_the_recorded_stream_beats_a_shuffled_one(corpus, ckpt):
    """Force-GT (the recorded hunter tokens of the horizon) gives a lower hunter RA-MPJPE than Force-Shuf
    (the same tokens permuted over frames with a fixed seed)."""
    H = 40
    tokens = ActionTokens.from_corpus(corpus)
    hi = tokens.entities.index("hunter")
    seeds = held_out_seeds(corpus, SEED, H, stride=20)
    windows, force, recorded = [], [], []
    for seg, start in seeds:
        rows = corpus.dynamics_segment(seg).slice(start + SEED, H)
        stream = tokens.encode(corpus.layout, rows)[0][:, hi]
        shuffled = stream[np.random.default_rng(0).permutation(H)]
        for s in (stream, shuffled):  # Force-GT, then Force-Shuf, of each seed: one batch of rollouts
            windows.append(Window.at(corpus, seg, start, SEED, H))
            force.append(force_windows("hunter", s))
            recorded.append(rows)
    tables, _ = run_windows(ckpt, corpus, windows, rules="none", force=force, batch=64)
    err = np.array([ra_mpjpe(t, r, corpus.layout, "hunter") for t, r in zip(tables, recorded)])
    gt, shuf = err[0::2], err[1::2]
    print(
        f"\nhunter RA-MPJPE over {len(seeds)} held-out seeds, horizon {H}: Force-GT {gt.mean():.4f} ± {gt.std():.4f} m, "
        f"Force-Shuf {shuf.mean():.4f} ± {shuf.std():.4f} m; Force-GT lower on {(gt < shuf).sum()} of {len(gt)}"
    )
    assert gt.mean() < shuf.mean()


def test_cached_and_recomputed_rollouts_agree_over_twice_the_window(corpus, ckpt):
    window = Rollout(ckpt, corpus).config.window
    seg = max(corpus.segment_ids("test"), key=lambda s: corpus.dynamics_segment(s).num_rows)
    horizon = 2 * window + 8  # predicted frames, past twice the window
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the bound below was measured at two threads (one thread orders the sums otherwise: 5.1e-5)
    try:
        a = rollout(ckpt, corpus, seg, SEED, horizon, rules="auto")
        b = rollout(ckpt, corpus, seg, SEED, horizon, rules="auto", cached=False)
    finally:
        torch.set_num_threads(threads)
    sa, sb = (fixed_rows(t["state"], corpus.layout.dim)[SEED:] for t in (a, b))
    err = np.abs(sa - sb).max()
    print(f"\ncached vs recomputed over {horizon} predicted frames (window {window}): max |Δ state| = {err:.2e}")
    # Two float32 evaluations of one function in different summation orders, fed back for 136 steps: their
    # difference grows with the steps (1.1-1.4e-5 at two threads); 5e-5 is still a thousandth of the pose error.
    assert err < 5e-5
    assert np.array_equal(a["hunter.action"].to_numpy(), b["hunter.action"].to_numpy())


LONG = 3_000  # predicted frames: 150 s of play, 47 windows of the tiny model


def test_a_long_rollout_stays_finite_with_steady_bones(corpus, ckpt):
    c = corpus
    seg = c.segment_ids("test")[0]
    started = time.perf_counter()
    table = rollout(ckpt, c, seg, SEED, LONG, rules="auto")
    took = time.perf_counter() - started
    state = fixed_rows(table["state"], c.layout.dim)
    assert np.isfinite(state).all()
    world = world_of_rows(c.layout, table)
    print(f"\n{LONG:,} frames in {took:.1f} s ({LONG / took:.0f} frames/s, tiny model, rules on)")
    recorded = {e.name: [] for e in c.layout.articulated}
    for s in c.segment_ids("train"):
        w = world_of_rows(c.layout, c.dynamics_segment(s))
        for e in c.layout.articulated:
            recorded[e.name].append(w[e.name])
    for e in c.layout.articulated:
        pred = bone_cv(world[e.name][SEED:], e.rig)
        rec = bone_cv(np.concatenate(recorded[e.name]), e.rig)
        roots = world[e.name][SEED:, 0]
        print(
            f"{e.name}: bone-length CV median {np.median(pred):.4f} (recorded {np.median(rec):.4f}), mean {pred.mean():.4f} "
            f"(recorded {rec.mean():.4f}), max {pred.max():.3f} (recorded {rec.max():.3f}); roots span "
            f"{np.ptp(roots, axis=0).round(1)} m"
        )
        # A "bone" joins kept joints and may span dropped ones (the drake's toe-hand crosses a wrist):
        # the recording's own CV reaches 0.2 there, so the bar is the median bone.
        assert np.median(pred) < 0.05
        assert np.ptp(roots, axis=0).max() < 1000.0  # a diverging root runs off by kilometres


def test_bf16_drift_and_root_integration_error(corpus, ckpt):
    """bf16 models against fp32 (stated, bounded), and the table's float64 roots against integrating its
    float32 state stream in float32 and in float64 far from the origin (stated, bounded)."""
    c = corpus
    seg = c.segment_ids("test")[0]
    H = 200
    fp32 = rollout(ckpt, c, seg, SEED, H, rules="auto")
    bf16 = rollout(ckpt, c, seg, SEED, H, rules="auto", dtype=torch.bfloat16)
    hunter = c.layout.entity("hunter")
    p32, p16 = (world_of_rows(c.layout, t)[hunter.name][SEED:] for t in (fp32, bf16))
    joint = np.linalg.norm((p16 - p16[:, :1]) - (p32 - p32[:, :1]), axis=-1).mean(1)
    root = np.linalg.norm(p16[:, 0] - p32[:, 0], axis=-1)
    same_tokens = (fp32["hunter.action"].to_numpy() == bf16["hunter.action"].to_numpy())[SEED:].mean()
    print(
        f"\nbf16 vs fp32 over {H} frames: root-aligned joint drift at 10/50/200 frames {joint[9]:.4f}/{joint[49]:.4f}/"
        f"{joint[-1]:.4f} m, root distance {root[9]:.3f}/{root[49]:.3f}/{root[-1]:.3f} m, same hunter token on "
        f"{same_tokens:.0%} of frames"
    )
    assert np.isfinite(p16).all() and joint[:10].max() < 0.1

    table = rollout(ckpt, c, seg, SEED, 2000, rules="none")
    e = c.layout.articulated[0]
    state = fixed_rows(table["state"], c.layout.dim)[SEED:]
    R = geo.rot6d_to_matrix(state[:, c.layout.slice(f"{e.name}.rot6d")].astype(np.float64))
    delta = state[:, c.layout.slice(f"{e.name}.root")]
    far = np.array([-4000.5, 12.25, 7000.75])  # thousands of metres from the origin, negative x
    truth = fixed_rows(table[f"{e.name}.root_world"], 3)[SEED:] - fixed_rows(table[f"{e.name}.root_world"], 3)[SEED - 1] + far
    step = np.einsum("nij,nj->ni", R, delta)
    f64 = far + np.cumsum(step, axis=0)
    f32 = np.empty_like(step, dtype=np.float32)
    acc = far.astype(np.float32)
    for k, d in enumerate(step.astype(np.float32)):
        acc = acc + d
        f32[k] = acc
    e64 = np.linalg.norm(f64 - truth, axis=1).max()
    e32 = np.linalg.norm(f32 - truth, axis=1).max()
    print(
        f"root integration over 2,000 frames 7 km from the origin: float64 of the float32 state {e64:.2e} m, "
        f"float32 accumulator {e32:.2e} m"
    )
    assert e64 < 1e-3
    assert e32 > e64  # why the table's roots are integrated in float64
