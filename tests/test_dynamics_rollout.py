"""Rollouts of a tiny trained dynamics model: determinism, forcing, counterfactuals, the table, the rules, rendering."""

from __future__ import annotations

import time

import numpy as np
import pytest

from marionette.bridge.targets import TerrainScene, render_rows
from marionette.corpus import Corpus, fixed_rows, world_of_rows
from marionette.corpus.paths import stage_dir
from marionette.dynamics.config import TrainConfig
from marionette.dynamics.controls import force_windows, forced_at
from marionette.dynamics.data import ActionTokens
from marionette.dynamics.engine import Rollout, open_terrain_field
from marionette.dynamics.rollout import main, rollout
from marionette.dynamics.train import train
from marionette.io import read_ipc
from marionette.schema import check_layout

SEED_FRAMES, HORIZON = 16, 24


@pytest.fixture(scope="module")
def scanned(scanned_corpus):
    return scanned_corpus


@pytest.fixture(scope="module")
def ckpt(scanned, tmp_path_factory):
    out = tmp_path_factory.mktemp("rollout-ckpt")
    train(scanned, out, TrainConfig(steps=40, batch_size=4, window=32, warmup=5, lr=1e-3), log=lambda *_: None)
    return out


@pytest.fixture(scope="module")
def segment(scanned):
    c = Corpus(scanned)
    return max(c.segment_ids(), key=lambda s: c.dynamics_segment(s).num_rows)


def run(ckpt, scanned, segment, **kw):
    kw = {"seed_frames": SEED_FRAMES, "horizon": HORIZON, "rules": "none", **kw}
    return rollout(ckpt, scanned, segment, **kw)


def same(a, b) -> bool:
    """Bit-identical in every column, NaN equal to NaN (the predicted rows' camera is NaN)."""
    return a.schema == b.schema and all(
        np.array_equal(np.asarray(a[n].to_pylist(), dtype=object), np.asarray(b[n].to_pylist(), dtype=object))
        or np.array_equal(_flat(a[n]), _flat(b[n]), equal_nan=True)
        for n in a.column_names
    )


def _flat(col):
    arr = col.combine_chunks()
    while hasattr(arr, "values") and not hasattr(arr, "dictionary"):
        arr = arr.values
    return arr.to_numpy(zero_copy_only=False)


def predicted(table, column):
    return table[column].to_numpy()[SEED_FRAMES:]


def test_temperature_zero_is_bit_identical_and_seeds_differ_when_sampling(ckpt, scanned, segment):
    a, b = run(ckpt, scanned, segment), run(ckpt, scanned, segment)
    assert same(a, b)
    s0 = run(ckpt, scanned, segment, temperature=3.0, seed=0)
    s1 = run(ckpt, scanned, segment, temperature=3.0, seed=1)
    streams = [np.stack([predicted(t, f"{e.name}.action") for e in Corpus(scanned).layout.articulated]) for t in (s0, s1)]
    assert not np.array_equal(*streams)


def test_counterfactual_force_differs_only_from_its_start(ckpt, scanned, segment):
    c = Corpus(scanned)
    hunter = c.layout.articulated[0].name
    F = 10
    base = run(ckpt, scanned, segment, force=[(hunter, 0, F, 1)])
    other = run(ckpt, scanned, segment, force=[(hunter, 0, F, 1), (hunter, F, HORIZON, 2)])
    sa, sb = (fixed_rows(t["state"], c.layout.dim)[SEED_FRAMES:] for t in (base, other))
    assert np.array_equal(sa[:F], sb[:F])
    assert np.array_equal(predicted(base, f"{hunter}.action")[:F], predicted(other, f"{hunter}.action")[:F])
    assert not np.array_equal(sa[F], sb[F])  # the forced token changes PoseGPT's very first animated frame
    assert not np.array_equal(sa[F:], sb[F:])


def test_forcing_sets_the_token_and_restarts_progress(ckpt, scanned, segment):
    c = Corpus(scanned)
    e = c.layout.articulated[0]
    ro = Rollout(ckpt, c, rules="none", terrain_field=open_terrain_field(c, segment))  # the monster reads terrain
    token, start, end = 2, 5, 15
    table = run(ckpt, scanned, segment, force=[(e.name, start, end, token)])
    actions = predicted(table, f"{e.name}.action")
    assert np.all(actions[start:end] == ro.tokens.composites[0][token])
    mf = predicted(table, f"{e.name}.motion_frame")
    if predicted(table, f"{e.name}.action")[start - 1] != ro.tokens.composites[0][token]:  # a new token restarts
        assert mf[start] == 0
    assert np.all(np.diff(mf[start : start + 4]) > 0)  # an unchanged (state) token advances ~1.5 clip frames a step
    # the streaming class gives the same stream as the function
    ro.start(c.dynamics_segment(segment).slice(0, SEED_FRAMES))
    force, names, first = [(e.name, start, end, token)], [x.name for x in c.layout.articulated], []
    for t in range(end):
        forced, restart = forced_at(force, t, names)
        first.append(ro.step(forced, None, restart))
    assert np.array_equal(np.stack(first), fixed_rows(table["state"], c.layout.dim)[SEED_FRAMES : SEED_FRAMES + end])


def _playing_start(c: Corpus, segment: str, entity: int, run: int) -> int:
    """A seed start whose last seed frame and the next ``run`` recorded frames hold one token of ``entity``,
    well into its clip (motion_frame ≥ 6 at the first predicted frame)."""
    view = c.dynamics_segment(segment)
    tok = ActionTokens.from_corpus(c).encode(c.layout, view)[0][:, entity]
    mf = view[f"{c.layout.articulated[entity].name}.motion_frame"].to_numpy()
    for k in range(len(tok) - SEED_FRAMES - run):
        at = k + SEED_FRAMES  # the first predicted frame
        if tok[at - 1] != 0 and np.all(tok[at - 1 : at + run] == tok[at - 1]) and mf[at] >= 6:
            return k
    raise AssertionError(f"{segment}: no stretch of {run} frames of one playing token: the test needs one")


def test_forcing_the_playing_token_continues_it_and_another_token_restarts(ckpt, scanned):
    """Force-GT over a recorded stretch where the hunter's action keeps playing continues its progress (the
    rollout's motion_frame follows the recording's within 2 clip frames, never back to 0); forcing another
    token restarts at 0; back-to-back windows of one token replay it from 0."""
    c = Corpus(scanned)
    names = [e.name for e in c.layout.articulated]
    hi, run_ = names.index("hunter"), 12
    segment = max(c.segment_ids(), key=lambda s: c.dynamics_segment(s).num_rows)
    start = _playing_start(c, segment, hi, run_)
    recorded = c.dynamics_segment(segment).slice(start + SEED_FRAMES, run_)
    stream = ActionTokens.from_corpus(c).encode(c.layout, recorded)[0][:, hi]
    gt = run(ckpt, scanned, segment, start=start, horizon=run_, force=force_windows("hunter", stream))
    mf_gt, mf_rec = predicted(gt, "hunter.motion_frame"), recorded["hunter.motion_frame"].to_numpy()
    print(f"\nForce-GT of a playing action: motion_frame rollout {mf_gt.tolist()}, recorded {mf_rec.tolist()}")
    assert np.array_equal(predicted(gt, "hunter.action"), recorded["hunter.action"].to_numpy())
    assert np.all(np.abs(mf_gt.astype(int) - mf_rec) <= 2)
    assert mf_gt[0] >= 4  # continued, not restarted

    other = next(t for t in range(1, ActionTokens.from_corpus(c).sizes[hi]) if t != stream[0])
    shifted = run(ckpt, scanned, segment, start=start, horizon=run_, force=[("hunter", 0, run_, other)])
    mf_other = predicted(shifted, "hunter.motion_frame")
    print(f"forcing token {other} instead of {stream[0]}: motion_frame {mf_other.tolist()}")
    assert mf_other[0] == 0 and mf_other[1] > 0

    replay = [("hunter", 0, 4, int(stream[0])), ("hunter", 4, run_, int(stream[0]))]
    again = predicted(run(ckpt, scanned, segment, start=start, horizon=run_, force=replay), "hunter.motion_frame")
    print(f"back-to-back windows of token {stream[0]}: motion_frame {again.tolist()}")
    assert np.array_equal(again[:4], mf_gt[:4]) and again[4] == 0


def test_the_table_is_a_corpus_state_table_continuous_with_its_seed(ckpt, scanned, segment):
    c = Corpus(scanned)
    started = time.perf_counter()
    table = run(ckpt, scanned, segment, horizon=60)
    rate = 60 / (time.perf_counter() - started)
    print(f"rollout: {rate:.0f} frames/s (tiny model, incl. seeding and loading)")
    check_layout(table.schema, c.layout, "rollout")
    assert table.num_rows == SEED_FRAMES + 60
    state = fixed_rows(table["state"], c.layout.dim)
    assert np.all(np.isfinite(state))
    assert np.allclose(np.diff(table["t"].to_numpy()), 1 / 20)
    assert table["valid"].to_numpy(zero_copy_only=False).all()
    for e in c.layout.articulated:
        roots = fixed_rows(table[f"{e.name}.root_world"], 3)
        step = np.linalg.norm(roots[SEED_FRAMES] - roots[SEED_FRAMES - 1])
        assert step < 0.5, f"{e.name}: first predicted root {step:.3f} m from the last seed root"
        assert np.all(np.linalg.norm(np.diff(roots[SEED_FRAMES - 1 :], axis=0), axis=1) < 0.5)  # ≤ 10 m/s


def test_bone_lengths_of_the_table(ckpt, scanned, segment):
    """The table's seed rows are the recorded 20 fps skeletons (the state ↔ world conversion is right);
    the predicted rows' bone-length spread is printed, not asserted: a 40-step tiny model does not hold
    bone lengths (the issue's < 5 % is for a trained model; 800 steps bring it to ~0.3)."""
    c = Corpus(scanned)
    table = run(ckpt, scanned, segment, horizon=60)
    hunter = c.layout.entity("hunter")
    joints = world_of_rows(c.layout, table)[hunter.name]
    lengths = np.stack([np.linalg.norm(joints[:, a] - joints[:, b], axis=-1) for a, b in hunter.rig.bones], axis=1)
    seed_cv = lengths[:SEED_FRAMES].std(0) / lengths[:SEED_FRAMES].mean(0)
    pred_cv = lengths[SEED_FRAMES:].std(0) / lengths[SEED_FRAMES:].mean(0)
    print(f"hunter bone-length CV (max over bones): seed rows {seed_cv.max():.4f}, predicted rows {pred_cv.max():.3f}")
    recorded = world_of_rows(c.layout, c.dynamics_segment(segment).slice(0, SEED_FRAMES))[hunter.name]
    np.testing.assert_allclose(joints[:SEED_FRAMES], recorded, atol=1e-4)
    assert np.isfinite(pred_cv).all()


def test_rules_keep_the_hunter_out_of_the_ground(ckpt, scanned, segment):
    c = Corpus(scanned)
    field = open_terrain_field(c, segment)
    assert field is not None
    hunter = c.layout.articulated[0].name
    below = {}
    for rules in ("none", "auto"):
        table = run(ckpt, scanned, segment, horizon=60, rules=rules)
        joints = world_of_rows(c.layout, table)[hunter][SEED_FRAMES:]
        low = joints[np.arange(len(joints)), joints[:, :, 1].argmin(1)]
        ground = field.query(low[:, 0], low[:, 2], low[:, 1])
        below[rules] = np.nan_to_num(ground - low[:, 1])
    settle = 10  # frames for the collider's lift (0.04 m a frame) to catch up
    assert below["auto"][settle:].max() < 0.1, below["auto"]
    assert below["auto"].max() <= below["none"].max() + 1e-9


def test_the_rollout_renders_with_the_follow_camera(ckpt, scanned, segment, tmp_path):
    c = Corpus(scanned)
    out = tmp_path / "states.arrow"
    main(
        [
            str(ckpt),
            str(scanned),
            "--segment",
            segment,
            "--seed-frames",
            "4",
            "--horizon",
            "4",
            "--out",
            str(out),
            "--force",
            f"{c.layout.articulated[0].name}:0:2:1",
        ]
    )
    table = read_ipc(out)
    assert table.num_rows == 8
    terrain = TerrainScene.of_stage(stage_dir(scanned, c.segment_row(segment)["stage"]))
    meta = render_rows(c.layout, table, tmp_path / "g.mkv", terrain, camera="follow", size=(72, 128))
    assert (meta.height, meta.width) == (72, 128)


def test_cli_trains_then_rolls_out_with_a_scripted_root_and_renders(scanned, segment, tmp_path):
    from marionette.bridge.gbuffer import decode_gbuffer
    from marionette.cli import main as cli

    c = Corpus(scanned)
    runs = tmp_path / "runs"
    assert (
        cli(
            [
                "train",
                "dynamics",
                str(scanned),
                "--out",
                str(runs),
                "--steps",
                "3",
                "--batch-size",
                "4",
                "--window",
                "16",
                "--warmup",
                "1",
            ]
        )
        == 0
    )
    out, video = tmp_path / "states.arrow", tmp_path / "rollout.mkv"
    hunter = c.layout.entity("hunter").name
    assert (
        cli(
            [
                "rollout",
                str(runs),
                str(scanned),
                "--segment",
                segment,
                "--seed-frames",
                "8",
                "--horizon",
                "10",
                "--script-root",
                f"{hunter}:2:7:0,0,2.5",
                "--force",
                f"{hunter}:0:3:1",
                "--rules",
                "none",
                "--out",
                str(out),
                "--render",
                str(video),
                "--size",
                "72x128",
            ]
        )
        == 0
    )
    table = read_ipc(out)
    delta = fixed_rows(table["state"], c.layout.dim)[8:, c.layout.slice(f"{hunter}.root")]
    np.testing.assert_allclose(delta[2:7], np.tile([0.0, 0.0, 2.5 / 20], (5, 1)), atol=1e-5)  # 2.5 m/s forward at 20 fps
    assert not np.allclose(delta[7:], [0.0, 0.0, 0.125], atol=1e-3)  # the script ends at frame 7
    frames, meta = decode_gbuffer(video)
    assert len(frames) == 18 and (meta.height, meta.width) == (72, 128)
    assert any((f.id >= 60).any() for f in frames)  # bone ids (weapon, drake or hunter) are in the picture
    assert (
        cli(
            [
                "rollout",
                str(runs),
                str(scanned),
                "--segment",
                segment,
                "--horizon",
                "4",
                "--seed-frames",
                "8",
                "--script-root",
                "dragon:0:1:0,0,1",
                "--out",
                str(tmp_path / "x.arrow"),
            ]
        )
        == 2
    )


def test_relative_feature_known_answer_far_from_the_origin():
    from marionette import geometry as geo
    from marionette.dynamics.features import RELATIVE_SCALE_M, relative_roots

    a = np.array([1.0e4, 5.0, -1.0e4])
    roots = np.stack([a, a + [3.0, 0.0, 0.0], a + [-40.0, 0.0, 0.0]])  # the third is farther from both
    R = geo.quat_to_matrix(geo.yaw_quat(np.array([np.pi / 2, 0.0, 0.0])))
    rel = relative_roots(roots, R) * RELATIVE_SCALE_M
    np.testing.assert_allclose(rel[0], R[0].T @ [3.0, 0.0, 0.0], atol=1e-9)  # yaw 90°: world +x is local +z or −z
    assert abs(abs(rel[0][2]) - 3.0) < 1e-9 and abs(rel[0][0]) < 1e-9
    np.testing.assert_allclose(rel[1], [-3.0, 0.0, 0.0], atol=1e-9)  # the nearest other is the first
    np.testing.assert_allclose(rel[2], [40.0, 0.0, 0.0], atol=1e-9)  # nearer the first (40 m) than the second (43 m)
    assert np.all(relative_roots(roots[:1], R[:1]) == 0)  # one entity: nothing to be near


def test_a_relative_position_model_trains_and_rolls_out(scanned, segment, tmp_path):
    runs = tmp_path / "rel"
    s = train(scanned, runs, TrainConfig(steps=3, batch_size=4, window=16, warmup=1, relative=True), log=lambda *_: None)
    assert s["steps"] == 3
    ro = Rollout(runs, Corpus(scanned), rules="none")
    assert ro.config.relative_position
    table = rollout(runs, scanned, segment, seed_frames=8, horizon=6, rules="none")
    assert np.isfinite(fixed_rows(table["state"], Corpus(scanned).layout.dim)).all()


def test_a_batch_of_streams_equals_the_streams_run_alone(ckpt, scanned):
    """``start_batch``/``step_batch`` over three segments give each stream's own rollout (its rules, its
    terrain, seed + b) up to float rounding of the batched matmuls."""
    c = Corpus(scanned)
    segs = sorted(c.segment_ids(), key=lambda s: -c.dynamics_segment(s).num_rows)[:3]
    field = open_terrain_field(c, segs[0])
    seeds = [c.dynamics_segment(s).slice(0, SEED_FRAMES) for s in segs]
    batched = Rollout(ckpt, c, rules="auto", terrain_field=field, temperature=0.0)
    batched.start_batch(seeds)
    force = [{0: 2}, None, {1: 1}]
    together = np.stack([batched.step_batch(force if t < 5 else None) for t in range(12)], axis=1)  # (3, 12, dim)
    for b, rows in enumerate(seeds):
        alone = Rollout(ckpt, c, rules="auto", terrain_field=field, temperature=0.0)
        alone.start(rows)
        states = np.stack([alone.step(force[b] if t < 5 else None) for t in range(12)])
        np.testing.assert_allclose(together[b], states, atol=1e-4)
    with pytest.raises(ValueError, match="equal lengths"):
        batched.start_batch([seeds[0], seeds[1].slice(0, 4)])
    # sampling: stream b draws from its own generator, _stream_seed(seed, b)
    from marionette.dynamics.engine import _stream_seed

    hot = Rollout(ckpt, c, rules="none", terrain_field=field, temperature=2.0, seed=5)
    hot.start_batch(seeds)
    drawn = np.stack([hot.step_batch() for _ in range(8)], axis=1)
    for b, rows in enumerate(seeds):
        alone = Rollout(ckpt, c, rules="none", terrain_field=field, temperature=2.0, seed=_stream_seed(5, b))
        alone.start(rows)
        np.testing.assert_allclose(drawn[b], np.stack([alone.step() for _ in range(8)]), atol=1e-4)
    assert len({_stream_seed(s, b) for s in range(4) for b in range(4)}) == 16  # nearby seeds never coincide


def test_the_optional_action_heads_train_and_roll_out_cached_as_recomputed(scanned, segment, tmp_path):
    """``time_left`` and ``adaptive_copy`` (off by default) beside ``displacement_gate`` and ``pose_progress`` (on): a few
    steps train, the checkpoint records them, and a rollout with the rules on is finite and the same through the KV cache as
    recomputed; the gate reads the rollout's own proposal (``Frames.skip``) and where each action starts
    (``Frames.changed``), PoseGPT the progress of the frame it animates, restarted where a token is forced."""
    runs = tmp_path / "heads"
    heads = dict(time_left=True, adaptive_copy=True, displacement_gate=True, pose_progress=True)
    cfg = TrainConfig(steps=3, batch_size=4, window=16, warmup=1, **heads)
    s = train(scanned, runs, cfg, log=lambda *_: None)
    assert s["first"]["proposal"] > 0  # the gate's head learns from its own loss term
    c = Corpus(scanned)
    ro = Rollout(runs, c, rules="auto")
    assert ro.config.clip_frames and ro.config.adaptive_copy and ro.config.displacement_gate and ro.config.pose_progress
    events = [k for k, n in enumerate(ro.config.clip_frames[0]) if n > 0]
    assert events and len(events) < len(ro.config.clip_frames[0]) - 1  # loops and token 0 read "not ending"
    seen = []
    step = ro.action_stream.model.read_out
    ro.action_stream.model.read_out = lambda frames, h: seen.append(frames) or step(frames, h)
    a = rollout(runs, scanned, segment, seed_frames=8, horizon=12, rules="auto")
    b = rollout(runs, scanned, segment, seed_frames=8, horizon=12, rules="auto", cached=False)
    sa, sb = (fixed_rows(t["state"], c.layout.dim) for t in (a, b))
    assert np.isfinite(sa).all() and np.abs(sa - sb).max() < 1e-4
    posed = []
    animate = ro.pose_stream.model.read_out
    ro.pose_stream.model.read_out = lambda frames, h: posed.append(frames) or animate(frames, h)
    ro.start(c.dynamics_segment(segment).slice(0, 8))
    assert len(posed) == 7 and all(f.progress is not None for f in posed)  # the seed's frames, with their progress
    seen.clear()
    ro.step()
    assert seen[-1].skip is not None and seen[-1].changed is not None and seen[-1].changed.shape == (1, 1, 2)
    other = next(k for k in events if k != int(ro.streams[0].tok[0]))
    ro.step(force_tokens={0: other})
    assert posed[-1].progress[0, 0, 0] == 0 and int(posed[-1].tokens[0, 0, 0]) == other  # a forced token starts at 0
