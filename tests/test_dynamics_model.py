"""The dynamics model's two transformers: sizes from the layout, causality, the sliding-window KV
cache, the terrain and relative-position switches, bf16 autocast and seeded determinism."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from marionette.dynamics.config import DynamicsConfig
from marionette.dynamics.model import (
    ActionGPT,
    DynamicsModel,
    Frames,
    PoseGPT,
    action_training_pair,
    apply_rope,
    parameter_counts,
    pose_training_pair,
    rope_angles,
)
from marionette.dynamics.state import join_state, root_stream_slices, split_state
from marionette.schema import SchemaError, load_scene

VOCAB = (7, 7)  # the synthetic game's: six clips per species + "no valid action"
WINDOW = 16


@pytest.fixture(scope="module")
def duel():
    return load_scene("duel")


@pytest.fixture(scope="module")
def tiny(duel):
    return DynamicsConfig.preset("tiny", duel, VOCAB, window=WINDOW)


def random_frames(cfg: DynamicsConfig, batch: int, length: int, seed: int = 0) -> Frames:
    g = torch.Generator().manual_seed(seed)
    n = cfg.n_entities
    return Frames(
        root=torch.randn(batch, length, cfg.root_dim, generator=g),
        body=torch.randn(batch, length, cfg.body_dim, generator=g),
        tokens=torch.stack([torch.randint(0, v, (batch, length), generator=g) for v in cfg.vocab_sizes], dim=-1),
        progress=torch.rand(batch, length, n, generator=g),
        terrain=torch.randn(batch, length, n, cfg.terrain_features, generator=g),
        relative=torch.randn(batch, length, n, 3, generator=g),
    )


def with_heads(model: DynamicsModel, seed: int = 5) -> DynamicsModel:
    """``model`` with its output heads drawn N(0, 0.02) instead of zero (an untrained model's heads are zero, so its
    outputs are its anchors and the copy gain: these tests look at what the transformer passes to the heads)."""
    g = torch.Generator().manual_seed(seed)
    heads = [model.action.root_head, *model.action.action_heads.values(), model.pose.body_head]
    with torch.no_grad():
        for head in heads:
            head.weight.normal_(0.0, 0.02, generator=g)
    return model


def flat(out) -> torch.Tensor:
    """All of a model's outputs as (B, T, ·), float32."""
    if isinstance(out, torch.Tensor):
        return out.float()
    return torch.cat([out.root.float(), *(lg.float() for lg in out.logits)], dim=-1)


def perturbed(frames: Frames, k: int, field: str) -> Frames:
    v = getattr(frames, field).clone()
    if field == "tokens":
        v[:, k] = (v[:, k] + 1) % 7
    else:
        v[:, k] = v[:, k] + 1.0
    return replace(frames, **{field: v})


# -- sizes ---------------------------------------------------------------------------------------------


def test_sizes_derive_from_the_layout(duel):
    cfg = DynamicsConfig.preset("tiny", duel, (11, 5))
    assert (cfg.root_dim, cfg.body_dim, cfg.n_entities) == (18, 258, 2)
    assert cfg.entities == ("monster", "hunter") and cfg.terrain == (True, False)
    assert cfg.weapon == (252, 258)  # the weapon's 2 points are the body's tail
    assert [n for n, _ in root_stream_slices(duel)] == ["monster.root", "monster.rot6d", "hunter.root", "hunter.rot6d"]

    solo = load_scene("hunter_solo")
    cs = DynamicsConfig.preset("tiny", solo, (9,))
    assert (cs.root_dim, cs.body_dim, cs.n_entities, cs.terrain) == (9, solo.dim - 9, 1, (False,))
    assert cs.weapon == (cs.body_dim - 6, cs.body_dim)
    two = load_scene("two_hunters")
    ct = DynamicsConfig.preset("tiny", two, (7, 7, 7))
    assert (ct.root_dim, ct.body_dim, ct.weapon_dim) == (27, two.dim - 27, 12)

    m = DynamicsModel(cfg)
    assert m.action.action_heads["monster"].out_features == 11 and m.action.action_heads["hunter"].out_features == 5
    assert m.action.root_head.out_features == 18 and m.pose.body_head.out_features == 258
    with pytest.raises(ValueError, match="vocab sizes"):
        DynamicsConfig.preset("tiny", duel, (7,))
    with pytest.raises(SchemaError, match="hunter_solo"):
        cfg.check_layout(solo)
    cfg.check_layout(duel)


def test_state_split_round_trips(duel):
    state = np.arange(duel.dim, dtype=np.float32)[None].repeat(3, 0)
    root, body = split_state(state, duel)
    assert root.shape == (3, 18) and body.shape == (3, 258)
    assert list(root[0, :9]) == list(range(0, 3)) + list(range(264, 270))  # monster root, monster rot6d
    np.testing.assert_array_equal(join_state(root, body, duel), state)
    t = torch.as_tensor(state)
    assert torch.equal(join_state(*split_state(t, duel), duel), t)


def test_parameter_counts(duel, tiny):
    paper = parameter_counts(DynamicsModel(DynamicsConfig.preset("paper", duel, VOCAB)))
    small = parameter_counts(DynamicsModel(tiny))
    print(f"\nparameters, paper preset (vocab {VOCAB}): {paper}\nparameters, tiny preset: {small}")
    assert abs(paper["ActionGPT"] / 2.5e6 - 1) <= 0.30
    assert abs(paper["PoseGPT"] / 25e6 - 1) <= 0.30
    assert paper["total"] == paper["ActionGPT"] + paper["PoseGPT"]
    assert small["total"] < 1e6


def test_config_json_round_trip(duel):
    cfg = DynamicsConfig.preset("tiny", duel, VOCAB, relative_position=True, terrain=(True, True))
    d = json.loads(json.dumps(cfg.to_json()))
    assert DynamicsConfig.from_json(d) == cfg
    with pytest.raises(ValueError, match="unknown fields"):
        DynamicsConfig.from_json({**d, "widht": 3})
    anchored = DynamicsConfig.preset("tiny", duel, VOCAB, body_anchor=True, rotation_anchor=True)
    assert DynamicsConfig.from_json(json.loads(json.dumps(anchored.to_json()))) == anchored
    before = {k: v for k, v in anchored.to_json().items() if k not in ("body_anchor", "rotation_anchor")}
    assert not DynamicsConfig.from_json(before).body_anchor  # a config from before the anchors: absolute heads, as trained
    with pytest.raises(ValueError, match="excludes"):
        DynamicsConfig.preset("tiny", duel, VOCAB, residual=True, body_anchor=True)


def test_an_untrained_model_predicts_its_anchors(tiny):
    """Zero heads: the body and the rotations come back as given, the displacements as 0 (the mean), and the
    current token is the argmax; a trained body gain g and head Δ give g ⊙ body + Δ."""
    cfg = replace(tiny, body_anchor=True, rotation_anchor=True)
    model = DynamicsModel(cfg).eval()
    frames = random_frames(cfg, 2, 8, seed=3)
    with torch.no_grad():
        out, body = model.action(frames), model.pose(frames)
        rot = model.action.rotation_mask.bool()
        assert torch.equal(out.root[..., rot], frames.root[..., rot]) and torch.all(out.root[..., ~rot] == 0)
        assert torch.equal(body, frames.body)
        for i, lg in enumerate(out.logits):
            assert torch.equal(lg.argmax(-1), frames.tokens[..., i])
        model.pose.body_gain.fill_(0.5)
        model.pose.body_head.bias.fill_(0.25)
        assert torch.allclose(model.pose(frames), 0.5 * frames.body + 0.25)


# -- causality and the cache ---------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["action", "pose"])
def test_causal(tiny, which):
    model = getattr(with_heads(DynamicsModel(tiny)), which).eval()
    frames = random_frames(tiny, 2, 12)
    k = 5
    fields = ["root", "body", "tokens", "terrain"] + (["progress"] if which == "action" else [])
    with torch.no_grad():
        base = flat(model(frames))
        for field in fields:
            out = flat(model(perturbed(frames, k, field)))
            assert torch.equal(out[:, :k], base[:, :k]), field
            assert (out[:, k] - base[:, k]).abs().max() > 1e-4, field
            assert (out[:, -1] - base[:, -1]).abs().max() > 1e-4, field


def stream(model, frames: Frames, cache=None) -> torch.Tensor:
    cache = model.cache_empty(frames.root.shape[0]) if cache is None else cache
    outs = []
    for t in range(frames.length):
        out, cache = model.step(frames.time_slice(t, t + 1), cache)
        assert cache.length == min(t + 1, model.config.window)
        outs.append(flat(out))
    return torch.cat(outs, dim=1)


@pytest.mark.parametrize("which", ["action", "pose"])
def test_cache_matches_window_recompute_one_layer(tiny, which):
    """One layer: streaming past the window gives, at every frame, the last output of a fresh forward
    over the last min(t + 1, window) frames (positions from 0): RoPE sees only position differences."""
    cfg = replace(tiny, action_gpt=replace(tiny.action_gpt, layers=1), pose_gpt=replace(tiny.pose_gpt, layers=1))
    model = getattr(with_heads(DynamicsModel(cfg)), which).eval()
    T = 2 * WINDOW + 5
    frames = random_frames(cfg, 2, T, seed=1)
    with torch.no_grad():
        streamed = stream(model, frames)
        fresh = torch.cat([flat(model(frames.time_slice(max(0, t + 1 - WINDOW), t + 1)))[:, -1:] for t in range(T)], dim=1)
    err = (streamed - fresh).abs().max().item()
    print(f"\n{which}: 1 layer, stream vs fresh window recompute over {T} frames: max |Δ| = {err:.2e}")
    assert err < 1e-5


@pytest.mark.parametrize("which", ["action", "pose"])
def test_cache_matches_forward(tiny, which):
    """Any depth: streaming equals ``forward`` over the whole stream (a band mask past the window),
    which for t < window is plain causal attention over frames 0..t."""
    model = getattr(with_heads(DynamicsModel(tiny)), which).eval()
    T = 2 * WINDOW + 5
    frames = random_frames(tiny, 2, T, seed=2)
    with torch.no_grad():
        streamed = stream(model, frames)
        banded = flat(model(frames))
        causal = flat(model(frames.time_slice(0, WINDOW)))
        fresh = torch.cat([flat(model(frames.time_slice(t + 1 - WINDOW, t + 1)))[:, -1:] for t in range(WINDOW, T)], dim=1)
    err, err_causal = (streamed - banded).abs().max().item(), (streamed[:, :WINDOW] - causal).abs().max().item()
    deep = (streamed[:, WINDOW:] - fresh).abs().max().item()
    print(
        f"\n{which}: {tiny.action_gpt.layers if which == 'action' else tiny.pose_gpt.layers} layers, {T} frames: "
        f"stream vs banded forward {err:.2e}, vs causal forward (t < window) {err_causal:.2e}; "
        f"vs fresh window recompute past the window {deep:.2e} (a deep stream sees past its window)"
    )
    assert err < 1e-5 and err_causal < 1e-5
    # A deep stream's cached keys of layer 2 saw frames before the window, so the recomputed window
    # differs by more than rounding (small at initialisation, where attention is nearly uniform).
    assert deep > 1e-5


def test_rope_scores_depend_on_position_differences_only():
    g = torch.Generator().manual_seed(9)
    q, k = torch.randn(2, 1, 1, 1, 64, generator=g)
    base = None
    for offset in (0, 10_000, 1_000_000, 50_000_000):
        cos, sin = rope_angles(torch.tensor([offset + 3, offset + 17]), 64)
        score = (apply_rope(q, cos[:1], sin[:1]) * apply_rope(k, cos[1:], sin[1:])).sum().item()
        base = score if base is None else base
        assert abs(score - base) < 1e-5 * max(1.0, abs(base)), offset


def test_cache_is_exact_at_far_positions(tiny):
    """A stream that starts a million frames in gives what one starting at 0 gives (angles in float64)."""
    model = with_heads(DynamicsModel(tiny)).pose.eval()
    frames = random_frames(tiny, 1, WINDOW + 3, seed=3)
    with torch.no_grad():
        for block in model.transformer.blocks:  # peaked attention, as after training, so scores matter
            block.attn.qkv.weight.mul_(10.0)
        near = stream(model, frames)
        far = stream(model, frames, replace(model.cache_empty(1), position=1_000_000))
    err = (near - far).abs().max().item()
    print(f"\nstream at position 0 vs 1e6: max |Δ| = {err:.2e}")
    assert err < 1e-5


# -- switches ------------------------------------------------------------------------------------------


def test_terrain_switch(duel):
    off = with_heads(DynamicsModel(DynamicsConfig.preset("tiny", duel, VOCAB, terrain=(False, False))))
    on = with_heads(DynamicsModel(DynamicsConfig.preset("tiny", duel, VOCAB)))  # monster only
    both = with_heads(DynamicsModel(DynamicsConfig.preset("tiny", duel, VOCAB, terrain=(True, True))))
    assert not any("terrain" in n for n, _ in off.named_parameters())
    assert list(on.action.terrain_mlp) == ["monster"] and list(both.pose.terrain_mlp) == ["monster", "hunter"]
    assert on.action.terrain_mlp["monster"][-1].out_features == 32 and on.pose.terrain_mlp["monster"][-1].out_features == 64

    frames = random_frames(on.config, 2, 8, seed=4)
    no_terrain = replace(frames, terrain=None)
    hunter_changed = frames.terrain.clone()
    hunter_changed[:, :, 1] += 1.0
    monster_changed = frames.terrain.clone()
    monster_changed[:, :, 0] += 1.0
    with torch.no_grad():
        for model in (off.action, off.pose):
            assert torch.equal(flat(model(frames)), flat(model(no_terrain)))  # ignored when off
        for model in (on.action, on.pose):
            base = flat(model(frames))
            assert torch.equal(flat(model(replace(frames, terrain=hunter_changed))), base)  # hunter's terrain is off
            assert (flat(model(replace(frames, terrain=monster_changed))) - base).abs().max() > 1e-4
            with pytest.raises(ValueError, match="terrain"):
                model(no_terrain)
        base = flat(both.pose(frames))
        assert (flat(both.pose(replace(frames, terrain=hunter_changed))) - base).abs().max() > 1e-4


def test_relative_position_switch(duel, tiny):
    off = with_heads(DynamicsModel(tiny))
    on = with_heads(DynamicsModel(replace(tiny, relative_position=True)))
    for a, b in ((off.action, on.action), (off.pose, on.pose)):
        assert b.input.in_features == a.input.in_features + 3 * tiny.n_entities
    frames = random_frames(tiny, 2, 8, seed=5)
    moved = replace(frames, relative=frames.relative + 1.0)
    with torch.no_grad():
        for model in (off.action, off.pose):
            assert torch.equal(flat(model(frames)), flat(model(replace(frames, relative=None))))
            assert torch.equal(flat(model(frames)), flat(model(moved)))
        for model in (on.action, on.pose):
            assert (flat(model(moved)) - flat(model(frames))).abs().max() > 1e-4
            with pytest.raises(ValueError, match="relative"):
                model(replace(frames, relative=None))


def test_token_classes_share_an_embedding_per_class(duel, tiny):
    """With ``token_classes``, two tokens of one class differ only by their own embeddings: giving both the same own
    embedding gives the same outputs, and moving a class's embedding moves every token of that class; the mapping
    round-trips through JSON and a wrong one is refused."""
    classes = tuple(tuple([0] + [1 + k % 4 for k in range(v - 1)]) for v in tiny.vocab_sizes)
    cfg = replace(tiny, token_classes=classes)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    with pytest.raises(ValueError, match="token_classes"):
        replace(tiny, token_classes=((0, 9),) * tiny.n_entities)
    model = with_heads(DynamicsModel(cfg))
    e = cfg.entities[0]
    frames = random_frames(cfg, 1, 6, seed=3)
    a, b = 1, 5  # both of class 1
    assert classes[0][a] == classes[0][b]
    with torch.no_grad():
        model.pose.embed[e].weight[b] = model.pose.embed[e].weight[a]
        tok_a, tok_b = frames.tokens.clone(), frames.tokens.clone()
        tok_a[..., 0], tok_b[..., 0] = a, b
        out_a, out_b = model.pose(replace(frames, tokens=tok_a)), model.pose(replace(frames, tokens=tok_b))
        assert torch.equal(flat(out_a), flat(out_b))
        model.pose.class_embed[e].weight[classes[0][a]] += 1.0
        assert (flat(model.pose(replace(frames, tokens=tok_b))) - flat(out_b)).abs().max() > 1e-4
    assert not hasattr(DynamicsModel(tiny).pose, "class_embed")  # off by default in the config: old checkpoints load


def test_time_left_counts_down_to_an_events_end(duel, tiny):
    """With ``clip_frames``, ActionGPT reads each entity's time left in its event: seconds (capped at 4) and the
    inverse of the source frames left (1 on the last frame); a token of length 0 (a loop, no action) reads 4 s and 0.
    Known answers; the config round-trips, a wrong table is refused, and the feature reaches the outputs."""
    assert tiny.vocab_sizes == (7, 7)
    lengths = ((0.0, 30.0, 10.0, 30.0, 0.0, 50.0, 150.0),) * 2  # tokens 0 and 4 do not end on their own
    cfg = replace(tiny, clip_frames=lengths, source_fps=30.0)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    with pytest.raises(ValueError, match="clip_frames"):
        replace(tiny, clip_frames=((0.0, 0.5),) * tiny.n_entities)
    model = DynamicsModel(cfg)
    n = cfg.n_entities
    tokens = torch.tensor([[[3] * n, [3] * n, [2] * n, [6] * n, [4] * n, [0] * n]])
    progress = torch.tensor([[[0.0] * n, [29 / 30] * n, [0.5] * n, [0.0] * n, [0.9] * n, [0.0] * n]])
    left = model.action.time_left(tokens, progress)  # (1, 6, 2N): seconds per entity, then inverses
    expected_s = torch.tensor([1.0, 1 / 30, 5 / 30, 4.0, 4.0, 4.0])  # 150 frames = 5 s, capped at 4
    expected_inv = torch.tensor([1 / 30, 1.0, 1 / 5, 1 / 150, 0.0, 0.0])
    for i in range(n):
        assert torch.allclose(left[0, :, i], expected_s)
        assert torch.allclose(left[0, :, n + i], expected_inv)
    model = with_heads(model)
    frames = random_frames(cfg, 1, 6, seed=4)
    later = replace(frames, progress=(frames.progress + 0.3).clamp(max=1.0))
    assert (flat(model.action(later)) - flat(model.action(frames))).abs().max() > 1e-4
    assert model.action.input.in_features == DynamicsModel(tiny).action.input.in_features + 2 * n


def test_a_played_out_event_gives_way(duel, tiny):
    """With ``events_end``, where an entity's event has at most source_fps / model_fps source frames left, its current
    token's logit is −inf (the next token is another); earlier, and for loops, the logits are a plain model's. The loss
    stays finite with label smoothing, spread over the tokens the frame allows; the config round-trips."""
    from marionette.dynamics.train import action_loss

    lengths = ((0.0, 30.0, 10.0, 30.0, 0.0, 50.0, 150.0),) * 2  # tokens 0 and 4 do not end on their own
    cfg = replace(tiny, events_end=lengths, source_fps=30.0, model_fps=20.0)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    assert DynamicsConfig.from_json({k: v for k, v in cfg.to_json().items() if k != "events_end"}).events_end == ()
    with pytest.raises(ValueError, match="events_end"):
        replace(tiny, events_end=((0.0, 0.5),) * tiny.n_entities)
    model, plain = with_heads(DynamicsModel(cfg)).eval(), with_heads(DynamicsModel(tiny)).eval()
    n = cfg.n_entities
    # frames left (1 − p) · L: 1.0 (last frame), 1.5 (½ frame late, 2 left: ends by the next model frame), 2.0, 5.0,
    # a loop at its end, token 0
    tokens = torch.tensor([[[3] * n, [3] * n, [3] * n, [2] * n, [4] * n, [0] * n]])
    progress = torch.tensor([[[29 / 30] * n, [28.5 / 30] * n, [28 / 30] * n, [0.5] * n, [1.0] * n, [0.0] * n]])
    frames = replace(random_frames(cfg, 1, 6, seed=4), tokens=tokens, progress=progress)
    assert torch.equal(model.action.ending(frames)[0, :, 0], torch.tensor([True, True, False, False, False, False]))
    with torch.no_grad():
        out, ref = model.action(frames), plain.action(frames)
    for i, (lg, rg) in enumerate(zip(out.logits, ref.logits)):
        cur = tokens[0, :, i]
        assert torch.isneginf(lg[0, [0, 1], cur[:2]]).all()
        assert torch.equal(lg[0, 2:], rg[0, 2:]) and torch.equal(lg[0, :2].isfinite().sum(-1), torch.tensor([6, 6]))
        assert (lg[0, :2].argmax(-1) != cur[:2]).all()
    target = torch.tensor([[[1] * n] * 6])  # another token everywhere
    for smoothing in (0.0, 0.1):
        loss = action_loss(out.logits, target, smoothing)
        assert torch.isfinite(loss)
    # with nothing dropped, the smoothed loss is torch's
    ref_loss = sum(
        torch.nn.functional.cross_entropy(
            lg.reshape(-1, lg.shape[-1]), target[..., i].reshape(-1), label_smoothing=0.1, reduction="sum"
        )
        for i, lg in enumerate(ref.logits)
    ) / (6 * n)
    assert torch.allclose(action_loss(ref.logits, target, 0.1), ref_loss, atol=1e-6)


def test_events_that_run_on_in_the_train_split_keep_their_odds():
    """``ended_events`` zeroes a token whose rows run on past its played-out frame (replayed back to back)."""
    from types import SimpleNamespace

    from marionette.dynamics.data import ended_events

    lengths = ((0.0, 4.0, 6.0),)
    ok = np.array([[1], [1], [1], [1], [2], [2]]), np.array([[0.0], [0.25], [0.5], [0.75], [0.0], [0.5]], np.float32)
    run_on = np.array([[2], [2], [2], [2]]), np.array([[0.5], [0.75], [5 / 6], [0.0]], np.float32)  # 2 played out, then 2
    data = SimpleNamespace(action=[ok[0]], progress=[ok[1]])
    assert ended_events(data, lengths, 1.5) == lengths
    data = SimpleNamespace(action=[ok[0], run_on[0]], progress=[ok[1], run_on[1]])
    assert ended_events(data, lengths, 1.5) == ((0.0, 4.0, 0.0),)


def test_displacement_gate_blends_the_carried_displacement_and_the_head(tiny):
    """With ``displacement_gate``, each displacement is g · carried + (1 − g) · head, g = sigmoid(gate head), carried =
    ``frames.skip`` (a rollout's own proposal) or else ``frames.root``, nothing where an action starts (``frames.changed``,
    else a token unlike the frame before); rotations are untouched. Untrained: g = sigmoid(2) and a zero head."""
    from marionette.dynamics.model import GATE_INIT

    cfg = replace(tiny, displacement_gate=True, rotation_anchor=True)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    with pytest.raises(ValueError, match="residual"):
        replace(tiny, displacement_gate=True, residual=True)
    model = DynamicsModel(cfg).eval()
    frames = random_frames(cfg, 2, 5, seed=6)
    n = cfg.n_entities
    frames = replace(frames, changed=torch.zeros(2, 5, n, dtype=torch.bool))  # every action continues
    skip = torch.randn(frames.root.shape, generator=torch.Generator().manual_seed(7))
    rot = model.action.rotation_mask.bool()
    g0 = torch.sigmoid(torch.tensor(GATE_INIT))
    with torch.no_grad():
        out = model.action(frames).root
        assert torch.allclose(out[..., ~rot], g0 * frames.root[..., ~rot])
        assert torch.equal(out[..., rot], frames.root[..., rot])
        carried = model.action(replace(frames, skip=skip)).root
        assert torch.allclose(carried[..., ~rot], g0 * skip[..., ~rot])
        assert torch.equal(carried[..., rot], frames.root[..., rot])
        starts = torch.zeros(2, 5, n, dtype=torch.bool)
        starts[:, 2, 0] = True  # entity 0's action starts at frame 2: nothing carried there
        fresh = model.action(replace(frames, changed=starts)).root
        first = torch.arange(cfg.root_dim) < 9  # entity 0's root stream
        assert torch.all(fresh[:, 2, ~rot & first] == 0)
        assert torch.equal(fresh[:, 2, ~rot & ~first], out[:, 2, ~rot & ~first])
        derived = model.action(replace(frames, changed=None, tokens=frames.tokens[:, :1].expand(-1, 5, -1))).root
        assert torch.allclose(derived[..., ~rot], g0 * frames.root[..., ~rot])  # constant tokens: no start
        model.action.gate_head.bias.fill_(0.0)  # g = 0.5
        model.action.root_head.bias.fill_(0.25)
        half = model.action(frames)
        assert torch.allclose(half.root[..., ~rot], 0.5 * frames.root[..., ~rot] + 0.5 * 0.25)
        assert torch.allclose(half.proposal[..., ~rot], torch.full_like(half.proposal[..., ~rot], 0.25))  # the head's
    # the blend holds the head fixed: its loss trains the gate (and the trunk through it), the proposal's the head
    out = model.action(frames)
    out.root.square().sum().backward()
    assert model.action.root_head.weight.grad is None or not model.action.root_head.weight.grad.any()
    assert model.action.gate_head.weight.grad.abs().sum() > 0
    model.zero_grad()
    model.action(frames).proposal.square().sum().backward()
    assert model.action.root_head.weight.grad.abs().sum() > 0
    assert model.action.gate_head.weight.grad is None or not model.action.gate_head.weight.grad.any()
    assert DynamicsModel(tiny).action(frames).proposal is None
    assert not hasattr(DynamicsModel(tiny).action, "gate_head")  # off in the preset: old checkpoints load


def test_pose_progress_is_read_by_posegpt_only_when_on(tiny):
    """With ``pose_progress``, PoseGPT reads each entity's progress at the frame it animates (n more inputs): its body
    moves with the progress; without it, progress changes nothing PoseGPT predicts and a window needs none."""
    cfg = replace(tiny, pose_progress=True)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    model, plain = with_heads(DynamicsModel(cfg)).eval(), with_heads(DynamicsModel(tiny)).eval()
    assert model.pose.input.in_features == plain.pose.input.in_features + cfg.n_entities
    assert model.action.input.in_features == plain.action.input.in_features
    frames = random_frames(cfg, 2, 6, seed=8)
    later = replace(frames, progress=(frames.progress + 0.3) % 1.0)
    with torch.no_grad():
        assert (model.pose(later) - model.pose(frames)).abs().max() > 1e-4
        assert torch.equal(plain.pose(later), plain.pose(frames))
        assert torch.equal(plain.pose(replace(frames, progress=None)), plain.pose(frames))
    with pytest.raises(ValueError, match="pose_progress"):
        model.pose(replace(frames, progress=None))
    assert not DynamicsModel(tiny).config.pose_progress  # off in the preset: old checkpoints load


def test_adaptive_copy_starts_at_the_copy_gain_and_can_let_go(tiny):
    """With ``adaptive_copy``, the current token's logit gets copy_gain + stay_head(h): untrained (stay head zero) the
    logits equal a plain model's; a stay head that cancels the copy gain leaves the action heads alone."""
    cfg = replace(tiny, adaptive_copy=True)
    assert DynamicsConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    model, plain = DynamicsModel(cfg).eval(), DynamicsModel(tiny).eval()
    frames = random_frames(cfg, 2, 5, seed=8)
    with torch.no_grad():
        for a, b in zip(model.action(frames).logits, plain.action(frames).logits):
            assert torch.equal(a, b)
        for i in range(cfg.n_entities):
            model.action.stay_head.bias[i] = -model.action.copy_gain[i]
        assert all(torch.all(lg == 0) for lg in model.action(frames).logits)  # zero heads, no copy: uniform


# -- alignment, precision, determinism -----------------------------------------------------------------


def test_training_pairs_align(tiny):
    frames = random_frames(tiny, 2, 9, seed=6)
    a_in, (root_next, tokens_next) = action_training_pair(frames)
    assert a_in.length == 8 and torch.equal(a_in.root, frames.root[:, :-1]) and torch.equal(root_next, frames.root[:, 1:])
    assert torch.equal(tokens_next, frames.tokens[:, 1:])
    p_in, body_next = pose_training_pair(frames)
    assert torch.equal(p_in.body, frames.body[:, :-1]) and torch.equal(body_next, frames.body[:, 1:])
    for f in ("root", "tokens", "terrain", "relative"):
        assert torch.equal(getattr(p_in, f), getattr(frames, f)[:, 1:]), f
    with torch.no_grad():
        assert DynamicsModel(tiny).pose(p_in).shape == body_next.shape


def test_bf16_autocast(tiny):
    model = with_heads(DynamicsModel(tiny)).eval()
    frames = random_frames(tiny, 2, 12, seed=7)
    with torch.no_grad():
        ref = {w: flat(getattr(model, w)(frames)) for w in ("action", "pose")}
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = {w: flat(getattr(model, w)(frames)) for w in ("action", "pose")}
            out, cache = model.pose.step(frames.time_slice(0, 1), model.pose.cache_empty(2))
            out, cache = model.pose.step(frames.time_slice(1, 2), cache)
    assert torch.isfinite(out).all()
    for w in ref:
        assert torch.isfinite(low[w]).all()
        err = (low[w] - ref[w]).abs().max().item()
        print(f"\n{w}: bf16 autocast vs fp32 max |Δ| = {err:.3f} (outputs' max |x| {ref[w].abs().max().item():.2f})")
        assert err < 0.25


def test_deterministic_given_the_seed(tiny):
    rng = torch.get_rng_state()
    a, b, c = DynamicsModel(tiny, seed=3), DynamicsModel(tiny, seed=3), DynamicsModel(tiny, seed=4)
    assert torch.equal(torch.get_rng_state(), rng)  # the global generator is untouched
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    assert all(p.dtype == torch.float32 for p in a.parameters())
    frames = random_frames(tiny, 2, 10, seed=8)
    with torch.no_grad():
        assert torch.equal(flat(a.action(frames)), flat(b.action(frames)))
        assert torch.equal(flat(a.pose(frames)), flat(b.pose(frames)))
    assert isinstance(a.action, ActionGPT) and isinstance(a.pose, PoseGPT)
