"""Training windows from the dynamics view: normalisation, action tokens and progress, cached terrain
features, and the train / held-out window samplers."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
import torch

from marionette import geometry as geo
from marionette.corpus import Corpus, fixed_rows, world_of_rows
from marionette.corpus.paths import stage_dir
from marionette.dynamics.config import TERRAIN_FEATURES, DynamicsConfig
from marionette.dynamics.data import ActionTokens, HeldOutWindows, WindowData, WindowSampler, vocab_sizes
from marionette.dynamics.features import terrain_feature_path, terrain_feature_shard
from marionette.dynamics.model import DynamicsModel, action_training_pair, pose_training_pair
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.state import split_state
from marionette.dynamics.windows import shard_windows_dir
from terrain_scan.field import egocentric_patch, joint_clearances, open_stage

HELD_OUT = "data_part1/rec0001"  # the recording the split tests move to "test"


@pytest.fixture(scope="module")
def scanned(scanned_copy):
    return scanned_copy


@pytest.fixture(scope="module")
def split_corpus(corpus) -> Corpus:
    """The session corpus with one recording's segments moved to the test split (in memory only)."""
    c = Corpus(corpus)
    seg = c.segments
    assert set(seg["split"].to_pylist()) == {"train"}  # the 3-recording corpus: all train
    split = pc.if_else(pc.equal(seg["sample"], HELD_OUT), pa.scalar("test"), seg["split"])
    c.segments = seg.set_column(seg.schema.get_field_index("split"), "split", split)
    return c


def source_state(c: Corpus, split: str = "train") -> np.ndarray:
    return np.concatenate([fixed_rows(c.read_segment(s)["state"], c.layout.dim) for s in c.segment_ids(split)])


# -- normalisation -----------------------------------------------------------------------------------


def test_normalise_round_trip_and_json(corpus):
    c = Corpus(corpus)
    norm = Normaliser.from_corpus(c, c.layout)
    root, body = split_state(fixed_rows(c.dynamics_shard(0)["state"], c.layout.dim), c.layout)
    for r, b in [
        (root, body),
        (root.astype(np.float64), body.astype(np.float64)),
        (torch.from_numpy(root), torch.from_numpy(body)),
    ]:
        rn, bn = norm.normalise(r, b)
        assert type(rn) is type(r) and rn.dtype == r.dtype and bn.dtype == b.dtype
        r2, b2 = norm.denormalise(rn, bn)
        assert np.abs(np.asarray(r2, np.float64) - np.asarray(r, np.float64)).max() < 1e-6
        assert np.abs(np.asarray(b2, np.float64) - np.asarray(b, np.float64)).max() < 1e-6
    again = Normaliser.from_json(json.loads(json.dumps(norm.to_json())))
    assert np.array_equal(again.normalise_body(body), norm.normalise_body(body))
    assert np.array_equal(again.denormalise_root(root), norm.denormalise_root(root))
    assert again.std_floor == norm.std_floor and again.layout_hash == c.layout.hash


def test_normaliser_is_the_train_split_stats_with_a_std_floor(corpus):
    c = Corpus(corpus)
    assert c.stats["split"] == "train"
    state = source_state(c, "train").astype(np.float64)  # the source-rate train rows stats.json summarises
    root, body = split_state(state, c.layout)
    norm = Normaliser.from_corpus(c)
    assert norm.stats_split == "train"
    assert np.allclose(norm.root_mean, root.mean(0), atol=1e-9) and np.allclose(norm.body_mean, body.mean(0), atol=1e-9)
    assert np.allclose(norm.root_std, np.maximum(root.std(0), 1e-3), atol=1e-9)
    assert np.allclose(norm.body_std, np.maximum(body.std(0), 1e-3), atol=1e-9)
    raw_root, raw_body = split_state(np.asarray(c.stats["state"]["std"]), c.layout)
    tiny = raw_body < 1e-3
    assert tiny.sum() > 10 and (raw_root == 0).any()  # rigid joints and yaw-only 6D entries
    assert np.all(norm.body_std[tiny] == 1e-3) and np.all(norm.body_std[~tiny] == raw_body[~tiny])
    coarse = Normaliser.from_corpus(c, std_floor=0.05)
    assert np.all(coarse.root_std == np.maximum(raw_root, 0.05)) and coarse.root_std.min() == 0.05
    with pytest.raises(ValueError, match="std_floor"):
        Normaliser.from_corpus(c, std_floor=0.0)


# -- tokens and progress -----------------------------------------------------------------------------


def test_tokens_map_back_to_their_composite_ids_through_vocab_json(corpus):
    c = Corpus(corpus)
    vocab = json.loads((corpus / "meta" / "vocab.json").read_text())["entity_types"]
    tok = ActionTokens.from_corpus(c)
    sizes = vocab_sizes(c)
    first = c.read_segment(c.segment_ids()[0])
    assert sizes == tuple(vocab[f"{e.rig.name}:{first[f'{e.name}.type_id'][0].as_py()}"]["size"] for e in c.layout.articulated)
    steps = 0
    for s in c.segment_ids():
        rows = c.read_segment(s)
        tokens, progress = tok.encode(c.layout, rows)
        assert tokens.dtype == np.int64 and progress.dtype == np.float32
        assert np.all((progress >= 0) & (progress <= 1))
        for i, e in enumerate(c.layout.articulated):
            action = rows[f"{e.name}.action"].to_numpy()
            types = rows[f"{e.name}.type_id"].to_numpy()
            mf = rows[f"{e.name}.motion_frame"].to_numpy()
            assert np.all((tokens[:, i] >= 0) & (tokens[:, i] < sizes[i]))
            for r in range(rows.num_rows):
                key, v = tok.type_token(i, int(tokens[r, i]))
                assert key == f"{e.rig.name}:{types[r]}"
                entry = next(a for a in vocab[key]["actions"] if a["token"] == v)
                assert entry["composite"] == action[r]
                assert progress[r, i] == pytest.approx(min(mf[r] / entry["clip_length"], 1.0), abs=1e-7)
            # inside a clip (same token, motion_frame counting up) progress grows 1/clip_length per source frame
            inside = (tokens[1:, i] == tokens[:-1, i]) & (np.diff(mf) == 1)
            clip = tok.clip_lengths[i][tokens[1:, i]]
            assert np.allclose(np.diff(progress[:, i])[inside], 1.0 / clip[inside], atol=1e-6)
            steps += int(inside.sum())
    assert steps > 1000


def test_token_zero_has_progress_zero(corpus):
    c = Corpus(corpus)
    rows = c.read_segment(c.segment_ids()[0]).slice(0, 40)
    action = rows["monster.action"].to_numpy().copy()
    action[10:20] = 0
    rows = rows.set_column(rows.schema.get_field_index("monster.action"), "monster.action", pa.array(action, pa.int32()))
    assert (rows["monster.motion_frame"].to_numpy()[10:20] > 0).any()
    tokens, progress = ActionTokens.from_corpus(c).encode(c.layout, rows)
    assert np.all(tokens[10:20, 0] == 0) and np.all(progress[10:20, 0] == 0)
    assert np.all(tokens[:10, 0] > 0) and progress[1:10, 0].max() > 0


def test_progress_in_the_20fps_view_counts_the_time_past_its_source_frame(corpus):
    """A 20 fps row carries the source frame at or before its time, and its progress adds the time past that frame:
    along a run, progress grows by exactly 1.5 source frames per model frame, as a rollout advances it."""
    c = Corpus(corpus)
    tok = ActionTokens.from_corpus(c)
    assert tok.source_fps == 30.0
    for s in c.segment_ids():
        src, view = c.read_segment(s), c.dynamics_segment(s)
        t_src, p_src = tok.encode(c.layout, src)
        t_view, p_view = tok.encode(c.layout, view)
        # the view's row k carries source frame ⌊1.5 k⌋ of the segment, ½ a source frame late on odd rows
        frame0 = src["frame"][0].as_py()
        k = np.arange(view.num_rows)
        assert np.array_equal(view["frame"].to_numpy() - frame0, np.floor(1.5 * k + 1e-9).astype(int))
        at = view["frame"].to_numpy() - frame0
        assert np.array_equal(t_view, t_src[at])
        for i in range(len(c.layout.articulated)):
            L = tok.clip_lengths[i][t_view[:, i]]
            late = 1.5 * k - np.floor(1.5 * k + 1e-9)
            live = (t_view[:, i] > 0) & (p_src[at, i] * L + late < L)  # not clipped at the clip's end
            assert live.any() and np.allclose(((p_view[:, i] - p_src[at, i]) * L)[live], late[live], atol=1e-4)
            mf = view[f"{c.layout.articulated[i].name}.motion_frame"].to_numpy()
            inside = (t_view[1:, i] == t_view[:-1, i]) & (np.diff(mf) > 0) & live[1:] & live[:-1]
            steps = np.diff(p_view[:, i])[inside] * tok.clip_lengths[i][t_view[1:, i]][inside]
            assert len(steps) and np.allclose(steps, 1.5, atol=1e-4)
    # without the source rate, the source frame's progress
    plain = ActionTokens.from_vocab(c.vocab, c.layout)
    view = c.dynamics_segment(c.segment_ids()[0])
    frame0 = c.read_segment(c.segment_ids()[0])["frame"][0].as_py()
    t_src, p_src = plain.encode(c.layout, c.read_segment(c.segment_ids()[0]))
    assert np.array_equal(plain.encode(c.layout, view)[1], p_src[view["frame"].to_numpy() - frame0])


def test_an_unknown_action_id_names_the_segment_and_row(corpus):
    c = Corpus(corpus)
    seg = c.segment_ids()[1]
    view = c.dynamics_segment(seg)
    action = view["hunter.action"].to_numpy().copy()
    action[7] = 987654
    bad = view.set_column(view.schema.get_field_index("hunter.action"), "hunter.action", pa.array(action, pa.int32()))
    frame = view["frame"][7].as_py()
    with pytest.raises(ValueError, match=rf"segment {seg}, row 7 \(source frame {frame}\): hunter .*987654"):
        ActionTokens.from_corpus(c).encode(c.layout, bad)
    types = view["monster.type_id"].to_numpy().copy()
    types[3:] = 99  # a species the vocab never saw
    alien = view.set_column(view.schema.get_field_index("monster.type_id"), "monster.type_id", pa.array(types, pa.int32()))
    acts = view["monster.action"].to_numpy()
    rows = np.arange(3, len(acts))[acts[3:] != 0]  # "no valid action" rows name no type
    first = int(rows[acts[rows] == acts[rows].min()][0])  # the message names the smallest unknown pair's first row
    with pytest.raises(ValueError, match=rf"segment {seg}, row {first} .*no entity type drake:99"):
        ActionTokens.from_corpus(c).encode(c.layout, alien)


# -- windows -----------------------------------------------------------------------------------------


def test_windows_come_from_the_train_split_only(split_corpus):
    c = split_corpus
    train, test = set(c.segment_ids("train")), set(c.segment_ids("test"))
    assert train and test and not train & test
    data = WindowData(c, "train")
    assert set(data.segments) == train
    sampler = WindowSampler(data, length=12, batch_size=3, seed=5)
    seen = {data.segments[i] for e in range(4) for i, _ in sampler.windows(e)}
    assert seen and seen <= train
    assert {s for e in range(2) for b in sampler.epoch(e) for s in b.segments} <= train
    held = WindowData(c, "test")
    with pytest.raises(ValueError, match="train split only"):
        WindowSampler(held, length=12, batch_size=3)
    # held-out: fixed tiles from each segment's start, the same on every pass
    ev = HeldOutWindows(held, length=12, batch_size=4)
    wins = ev.windows()
    assert {held.segments[i] for i, _ in wins} <= test and len(wins) == sum(n // 13 for n in held.lengths)
    assert all(s % 13 == 0 for _, s in wins)
    first, second = list(ev), list(ev)
    assert len(first) == len(ev) and [b.starts for b in first] == [b.starts for b in second]
    assert all(torch.equal(a.frames.body, b.frames.body) for a, b in zip(first, second))
    halves = [HeldOutWindows(held, length=12, batch_size=4, rank=r, world_size=2).windows() for r in (0, 1)]
    assert sorted(halves[0] + halves[1]) == sorted(wins) and not set(halves[0]) & set(halves[1])


def test_windows_are_deterministic_and_disjoint_across_ranks(corpus):
    data = WindowData(corpus)
    a = WindowSampler(data, length=10, batch_size=2, seed=3)
    b = WindowSampler(WindowData(corpus), length=10, batch_size=2, seed=3)
    assert a.windows(1) == b.windows(1) and a.windows(0) != a.windows(1)
    assert WindowSampler(data, length=10, batch_size=2, seed=4).windows(1) != a.windows(1)
    for x, y in zip(a.epoch(1), b.epoch(1), strict=True):
        assert x.segments == y.segments and x.starts == y.starts
        assert all(torch.equal(getattr(x.frames, k), getattr(y.frames, k)) for k in ("root", "body", "tokens", "progress"))

    def frames_of(wins):
        return {(i, s + k) for i, s in wins for k in range(11)}

    for epoch in range(3):
        ranks = [WindowSampler(data, length=10, batch_size=2, seed=3, rank=r, world_size=2) for r in (0, 1)]
        w0, w1 = (r.windows(epoch) for r in ranks)
        assert len(w0) == len(w1) > 0 and ranks[0].batches(epoch) == ranks[1].batches(epoch) == len(w0) // 2
        f0, f1 = frames_of(w0), frames_of(w1)
        assert not f0 & f1  # no frame read by both ranks
        assert len(f0) == 11 * len(w0)  # nor twice by one rank
        assert all(s + 11 <= data.lengths[i] for i, s in w0 + w1)


def test_batches_have_the_config_shapes(corpus):
    c = Corpus(corpus)
    cfg = DynamicsConfig.preset("tiny", c.layout, vocab_sizes(c))
    data = WindowData(c)
    batch = next(WindowSampler(data, length=16, batch_size=4, seed=0).epoch(0))
    f = batch.frames
    assert f.root.shape == (4, 17, cfg.root_dim) and f.body.shape == (4, 17, cfg.body_dim)
    assert f.tokens.shape == f.progress.shape == (4, 17, cfg.n_entities)
    assert f.root.dtype == f.body.dtype == f.progress.dtype == torch.float32 and f.tokens.dtype == torch.int64
    assert f.terrain is None and batch.terrain_known is None
    for i, v in enumerate(cfg.vocab_sizes):
        assert int(f.tokens[..., i].min()) >= 0 and int(f.tokens[..., i].max()) < v
    # the batch is the normalised view
    i, s = data.segments.index(batch.segments[0]), batch.starts[0]
    view = c.dynamics_segment(batch.segments[0])
    root, body = split_state(fixed_rows(view["state"], c.layout.dim)[s : s + 17], c.layout)
    assert np.allclose(data.normaliser.denormalise_root(f.root[0].numpy()), root, atol=1e-5)
    assert np.allclose(data.normaliser.denormalise_body(f.body[0].numpy()), body, atol=1e-5)


def test_a_window_longer_than_every_segment_is_an_error(corpus):
    data = WindowData(corpus)
    longest = int(data.lengths.max())
    name = data.segments[int(np.argmax(data.lengths))]
    with pytest.raises(ValueError, match=rf"longer than every 'train' segment; the longest, {name}, has {longest} frames"):
        WindowSampler(data, length=longest, batch_size=1)
    fits = WindowSampler(data, length=longest - 1, batch_size=1)  # each longest segment holds exactly one window
    longest_ones = [i for i, n in enumerate(data.lengths) if n == longest]
    assert fits.usable == longest_ones and len(fits.skipped) == len(data.segments) - len(longest_ones)
    assert sorted(fits.windows(0)) == [(i, 0) for i in longest_ones]
    with pytest.raises(ValueError, match=f"batch_size {len(longest_ones) + 1}"):
        WindowSampler(data, length=longest - 1, batch_size=len(longest_ones) + 1)


# -- terrain features --------------------------------------------------------------------------------


def test_terrain_features_equal_direct_field_queries(scanned):
    c = Corpus(scanned)
    view = c.dynamics_shard(0)
    feats, known = terrain_feature_shard(c, 0)
    n = view.num_rows
    assert feats.shape == known.shape == (n, len(c.layout.articulated), TERRAIN_FEATURES)
    assert np.all(np.isfinite(feats)) and known.mean() > 0.95 and np.all(feats[~known] == 0)
    field = open_stage(stage_dir(scanned, c.segment_row(view["segment"][0].as_py())["stage"]))
    world = world_of_rows(c.layout, view)
    for r in (0, n // 2, n - 1):
        for i, e in enumerate(c.layout.articulated):
            root = fixed_rows(view[f"{e.name}.root_world"], 3)[r : r + 1]
            R = geo.quat_to_matrix(fixed_rows(view[f"{e.name}.rot_world"], 4)[r : r + 1])
            patch, ok = egocentric_patch(field, root, R, np.asarray(e.rig.forward_axis))
            assert np.array_equal(known[r, i, :121], ok.reshape(-1))
            assert np.allclose(feats[r, i, :121], np.nan_to_num(patch.reshape(-1)), atol=1e-5)
            clear = joint_clearances(field, world[e.name][r : r + 1, list(e.rig.contact_index)], root[:, 1])
            assert np.allclose(feats[r, i, 121:], np.nan_to_num(clear.reshape(-1)), atol=1e-5)
    assert np.abs(feats[:, :, :121]).max() > 0.05  # the stage is not a flat plane at root height


def test_terrain_features_are_cached_and_follow_the_stage_chunks(scanned):
    c = Corpus(scanned)
    first, _ = terrain_feature_shard(c, 1)
    path = terrain_feature_path(c, 1)
    assert path.exists() and path.parent == scanned / "derived" / "terrain-features"
    mtime = path.stat().st_mtime_ns
    again, _ = terrain_feature_shard(Corpus(scanned), 1)
    assert path.stat().st_mtime_ns == mtime and np.array_equal(again, first)
    manifest = stage_dir(scanned, "default") / "manifest.json"
    original = manifest.read_text()
    try:
        m = json.loads(original)
        name = next(iter(m["chunks"]))
        m["chunks"][name]["sha256"] = "0" * 64  # as if a re-scan changed that chunk
        manifest.write_text(json.dumps(m))
        moved = terrain_feature_path(c, 1)
        assert moved != path
        redone, _ = terrain_feature_shard(c, 1)
        assert moved.exists() and not path.exists()  # recomputed under the new key, the old file gone
        assert np.array_equal(redone, first)
    finally:
        manifest.write_text(original)


def test_batches_with_terrain_feed_both_models(scanned):
    c = Corpus(scanned)
    cfg = DynamicsConfig.preset("tiny", c.layout, vocab_sizes(c), window=16, terrain=(True, True))
    batch = next(WindowSampler(WindowData(c, terrain=True), length=12, batch_size=3, seed=1).epoch(0))
    f = batch.frames
    assert f.terrain.shape == batch.terrain_known.shape == (3, 13, cfg.n_entities, cfg.terrain_features)
    assert f.terrain.dtype == torch.float32 and batch.terrain_known.dtype == torch.bool
    model = DynamicsModel(cfg, seed=0)
    x, (root_next, tokens_next) = action_training_pair(f)
    out = model.action(x)
    assert out.root.shape == root_next.shape == (3, 12, cfg.root_dim)
    assert [lg.shape for lg in out.logits] == [(3, 12, v) for v in cfg.vocab_sizes] and tokens_next.shape == (3, 12, 2)
    x, body_next = pose_training_pair(f)
    assert model.pose(x).shape == body_next.shape == (3, 12, cfg.body_dim)
    assert torch.isfinite(out.root).all()


def test_an_unscanned_stage_gives_zero_features_marked_unknown(corpus, tmp_path):
    plain = tmp_path / "corpus"
    shutil.copytree(corpus, plain, ignore=shutil.ignore_patterns("video", "terrain-features"))
    feats, known = terrain_feature_shard(plain, 2)
    assert feats.shape[0] == Corpus(plain).dynamics_shard(2).num_rows
    assert not known.any() and np.all(feats == 0)


def test_window_arrays_are_memory_mapped_from_a_checked_cache(scanned):
    """WindowData holds read-only maps of per-shard .npy files under derived/windows/, equal to the shard's own
    computation; a damaged file (wrong dtype and shape, or a broken header) is recomputed, never trusted."""
    c = Corpus(scanned)
    a = WindowData(c, "train", terrain=True, relative=True)
    assert all(isinstance(x, np.memmap) and not x.flags.writeable for x in a.root + a.body + a.action + a.features + a.rel)
    shard = int(c.segment_row(a.segments[0])["shard"])
    view = c.dynamics_shard(shard)
    rows = np.flatnonzero(view["segment"].to_numpy(zero_copy_only=False) == a.segments[0])
    state = fixed_rows(view["state"], c.layout.dim)[rows]
    root, body = a.normaliser.normalise(*split_state(state, c.layout))
    assert np.array_equal(a.root[0], root.astype(np.float32)) and np.array_equal(a.body[0], body.astype(np.float32))
    feats, known = terrain_feature_shard(c, shard)
    assert np.array_equal(a.features[0], feats[rows]) and np.array_equal(a.known[0], known[rows])
    d = shard_windows_dir(c, shard, a.normaliser, a.tokens, terrain=True, relative=True, fps=20.0, method="linear")
    names = ["action", "body", "features", "known", "progress", "rel", "root"]
    assert sorted(p.name for p in d.iterdir()) == sorted([f"{k}.npy" for k in names] + ["segments.json"])
    expect = {k: [np.array(x) for x in getattr(a, k)] for k in ("root", "body", "action", "progress", "features", "known", "rel")}
    batch = a.batch([(0, 3), (1, 0)], 17).frames
    del a  # its maps read the files damaged below
    (d / "root.npy").unlink()
    np.save(d / "root.npy", np.zeros((3, 2)))  # float64, 3 rows: disagrees with the layout and the other arrays
    b = WindowData(c, "train", terrain=True, relative=True)
    assert all(np.array_equal(x, y) for k, v in expect.items() for x, y in zip(getattr(b, k), v))
    del b
    (d / "body.npy").unlink()
    (d / "body.npy").write_bytes(b"\x93NUMPY\x01\x00garbage")
    again = WindowData(c, "train", terrain=True, relative=True)
    assert all(np.array_equal(x, y) for k, v in expect.items() for x, y in zip(getattr(again, k), v))
    assert torch.equal(again.batch([(0, 3), (1, 0)], 17).frames.root, batch.root)
    # the arrays without terrain or the relative feature live beside, under their own key
    plain = WindowData(c, "train")
    assert plain.features[0] is None and plain.rel[0] is None and np.array_equal(plain.root[0], expect["root"][0])
    held = {p.name.split("-")[4] for p in d.parent.glob(f"shard-{shard:06d}-*")}
    assert d.is_dir() and {"t1r1", "t0r0"} <= held
