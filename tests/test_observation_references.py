"""Persistent entity references: the crops, what a clip may see, the model's reference slots and their checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from marionette.bridge.gbuffer import CODE_MAX
from marionette.observation.config import ObservationConfig
from marionette.observation.model import VideoDiT, flow_loss
from marionette.observation.references import (
    EntityReferences,
    band_masks,
    chunk_references,
    crop,
    merge_bands,
    paint,
)
from marionette.observation.relay import generate

BANDS = ((60, 64), (105, 150), (195, 230))


def pose_with(ids: torch.Tensor) -> torch.Tensor:
    """(T, H, W) render ids → pose frames (T, 3, H, W) as the clip reader gives them (10-bit codes / 1023)."""
    code = torch.round(ids.double() / 255 * CODE_MAX) / CODE_MAX
    return torch.stack([torch.zeros_like(code), code, torch.zeros_like(code)], 1).float()


def test_bands_merge_and_every_render_id_decodes_to_its_band():
    assert merge_bands([(105, 150), (60, 62), (105, 170), (60, 64), (195, 230)]) == ((60, 64), (105, 170), (195, 230))
    ids = torch.arange(256).view(1, 16, 16)
    masks = band_masks(pose_with(ids), BANDS)[0]  # (E, 16, 16)
    for e, (a, b) in enumerate(BANDS):
        assert torch.equal(masks[e].flatten(), (torch.arange(256) >= a) & (torch.arange(256) <= b))


def test_a_crop_is_centred_on_the_entity_and_carries_its_mask():
    rgb = torch.full((3, 36, 64), -1.0)
    mask = torch.zeros(36, 64, dtype=torch.bool)
    mask[10:16, 40:44] = True  # a 6 × 4 body
    rgb[:, mask] = torch.tensor([0.8, -0.2, 0.4])[:, None]
    ref = crop(rgb, mask, 8)
    assert ref.shape == (4, 8, 8)
    centre = ref[:, 3:5, 3:5]
    assert torch.allclose(centre[:3], torch.tensor([0.8, -0.2, 0.4])[:, None, None], atol=1e-5)
    assert torch.all(centre[3] == 1.0)
    assert float(ref[3, 0, 0]) == 0.0  # the corner is background, and marked so
    at_edge = torch.zeros(36, 64, dtype=torch.bool)  # a body cut by the frame's corner: the outside reads as zeros
    at_edge[0:3, 0:2] = True
    assert torch.isfinite(crop(rgb, at_edge, 8)).all()


def test_a_clip_sees_only_entities_shown_at_or_before_its_start():
    T, H, W = 12, 18, 32
    ids = torch.zeros(T, H, W, dtype=torch.long)
    ids[:, 2:6, 3:7] = 120  # the monster from frame 0
    ids[7:, 10:12, 20:22] = 200  # the player from frame 7
    rgb = torch.rand(T, 3, H, W) * 2 - 1
    refs = chunk_references(rgb, pose_with(ids), BANDS, 8)
    assert refs.frame == [None, 0, 7]
    early, late = refs.tensor(upto=3), refs.tensor(upto=7)
    assert early[2].abs().sum() == 0 and late[2, 3].max() == 1.0  # the player's crop only once it has been shown
    assert torch.equal(early[1], late[1]) and early[0].abs().sum() == 0  # the weapon is never shown: no reference
    later = EntityReferences(BANDS, 8)  # a relay: frames arrive a chunk at a time, each entity's first sighting kept
    later.see(rgb[:5], pose_with(ids[:5]))
    later.see(rgb[5:], pose_with(ids[5:]), offset=5)
    assert later.frame == [None, 0, 7] and torch.equal(later.tensor(), refs.tensor())


def test_a_reference_is_retaken_up_a_ladder_as_its_entity_comes_into_view_larger():
    """A monster coming into view a pixel at a time (1, 3, 8, 9, 4, 20 pixels at frames 0, 2, 5, 6, 7, 9): its crop is
    taken at frame 0 and retaken where it first shows twice the pixels of the view last taken (frames 2, 5 and 9),
    never for a smaller or a barely larger view; each clip start gets the latest crop taken by then, whether the frames
    come at once or a chunk at a time; a relay's painted frames never replace a crop of a recorded frame."""
    from marionette.observation.references import RETAKE

    assert RETAKE == 2.0
    T, H, W = 12, 18, 32
    ids = torch.zeros(T, H, W, dtype=torch.long)
    rgb = torch.zeros(T, 3, H, W)
    sizes = {0: (1, 1), 1: (1, 1), 2: (1, 3), 3: (1, 3), 4: (1, 3), 5: (2, 4), 6: (3, 3), 7: (2, 2), 8: (2, 2), 9: (4, 5)}
    for t in range(T):
        h, w = sizes.get(t, (4, 5))
        ids[t, 6 : 6 + h, 10 : 10 + w] = 120
        rgb[t] = -0.3 + 0.05 * t  # each frame in a shade of its own, so a crop says which frame it came from
    pose = pose_with(ids)
    refs = chunk_references(rgb, pose, BANDS, 8)
    assert [f for f, _ in refs.taken[1]] == [0, 2, 5, 9] and refs.frame[1] == 9 and refs.pixels[1] == 20

    def shade(upto=None, of=refs):
        return float(of.tensor(upto=upto)[1, 0, 4, 4])

    for upto, frame in ((0, 0), (1, 0), (4, 2), (5, 5), (8, 5), (11, 9), (None, 9)):
        assert shade(upto) == pytest.approx(-0.3 + 0.05 * frame, abs=1e-6)
    relay = EntityReferences(BANDS, 8)
    for a in (0, 1, 5, 9):  # the first frame, then chunks of generated frames
        b = {0: 1, 1: 5, 5: 9, 9: T}[a]
        relay.see(rgb[a:b], pose[a:b], offset=a)
        assert shade(of=relay) == shade(upto=b - 1)
    assert [f for f, _ in relay.taken[1]] == [0, 2, 5, 9] and torch.equal(relay.tensor(), refs.tensor())
    assert not relay.tensor()[0].any() and not relay.tensor()[2].any()  # never shown: no reference
    # a relay's painted frames: a look the given first frame showed is kept; one it did not is taken and retaken
    kept = EntityReferences(BANDS, 8)
    kept.see(rgb[:1], pose[:1])
    kept.see(rgb[1:], pose[1:], offset=1, painted=True)
    assert [f for f, _ in kept.taken[1]] == [0] and kept.recorded[1]
    late = ids.clone()
    late[0] = 0  # the monster not in the given frame: first painted at frame 1
    unseen = EntityReferences(BANDS, 8)
    unseen.see(rgb[:1], pose_with(late[:1]))
    unseen.see(rgb[1:], pose_with(late[1:]), offset=1, painted=True)
    assert [f for f, _ in unseen.taken[1]] == [1, 2, 5, 9] and not unseen.recorded[1]


def test_a_reference_is_laid_over_its_body_in_every_frame_fitted_to_where_the_body_is_now():
    """The crop of a two-coloured body (top red, bottom blue), laid over the same body moved and grown: the top of
    its new box reads red, the bottom blue; pixels of no entity, and an entity without a reference, read zeros."""
    H, W = 36, 64
    rgb = torch.full((3, H, W), -1.0)
    ids = torch.zeros(1, H, W, dtype=torch.long)
    ids[0, 4:12, 6:10] = 120  # an 8 × 4 monster
    rgb[:, 4:8, 6:10] = torch.tensor([0.9, -0.9, -0.9])[:, None, None]
    rgb[:, 8:12, 6:10] = torch.tensor([-0.9, -0.9, 0.9])[:, None, None]
    mask = band_masks(pose_with(ids), BANDS)[0, 1]
    refs = torch.zeros(1, 3, 4, 16, 16)
    refs[0, 1] = crop(rgb, mask, 16)
    now = torch.zeros(3, H, W, dtype=torch.long)
    now[0, 4:12, 6:10] = 120  # where it was
    now[1, 20:36, 40:48] = 120  # moved and twice the size, cut by the frame's bottom edge at row 36
    now[1, 0:3, 0:3] = 200  # the player, never seen: no reference
    laid = paint(refs, pose_with(now)[None], BANDS)[0]  # (3, 4, H, W)
    assert laid.shape == (3, 4, H, W)
    red, blue = torch.tensor([0.9, -0.9, -0.9])[:, None, None], torch.tensor([-0.9, -0.9, 0.9])[:, None, None]
    # away from the body's outline and the seam (a resampled crop blends there)
    assert torch.allclose(laid[0, :3, 5:7, 7:9], red, atol=1e-4) and torch.allclose(laid[0, :3, 9:11, 7:9], blue, atol=1e-4)
    assert torch.allclose(laid[1, :3, 22:26, 42:46], red, atol=1e-4)
    assert torch.allclose(laid[1, :3, 30:34, 42:46], blue, atol=1e-4)
    assert bool((laid[1, 0, 20:36, 40:48] > -0.9 - 1e-4).all())  # the outline blends red and blue, nothing else
    on = now[:, None] == 120
    assert torch.equal(laid[:, 3:] > 0, on) and torch.all(laid[:, 3][on[:, 0]] == 1.0)
    assert torch.equal(laid.abs().sum(1) > 0, on[:, 0])  # nothing off the monster's pixels, nothing for the player
    assert laid[2].abs().sum() == 0  # a frame without the body


def test_painting_holds_at_the_extremes_one_pixel_bodies_a_body_filling_the_frame_half_precision():
    H, W = 8, 16
    ids = torch.zeros(2, 1, H, W, dtype=torch.long)
    ids[0, 0, 3, 5] = 120  # a one-pixel body
    ids[1, 0] = 120  # a body filling the frame
    rgb = torch.full((2, 3, H, W), -1.0)
    rgb[0, :, 3, 5] = torch.tensor([0.5, 0.2, -0.4])
    rgb[1] = torch.tensor([0.3, -0.6, 0.8])[:, None, None]
    pose = torch.stack([pose_with(ids[0]), pose_with(ids[1])])  # (2, 1, 3, H, W)
    masks = band_masks(pose[:, 0], BANDS)  # (2, E, H, W)
    refs = torch.zeros(2, 3, 4, 8, 8)
    refs[0, 1], refs[1, 1] = crop(rgb[0], masks[0, 1], 8), crop(rgb[1], masks[1, 1], 8)
    for dtype in (torch.float32, torch.float16):
        laid = paint(refs.to(dtype), pose.to(dtype), BANDS).float()
        assert laid.shape == (2, 1, 4, H, W) and torch.isfinite(laid).all() and laid.abs().max() <= 1.0 + 1e-3
        assert float(laid[0, 0, 3, 3, 5]) == 1.0 and float(laid[0, 0, 3].sum()) == 1.0  # one pixel laid
        # the one-pixel body's look is its own colour blended with its surroundings' by the crop's resampling
        assert torch.allclose(laid[0, 0, :3, 3, 5], torch.tensor([0.5, 0.2, -0.4]), atol=0.02)
        assert torch.allclose(laid[1, 0, :3], rgb[1], atol=2e-3)  # a full frame reads its own colour everywhere


def config(**kw) -> ObservationConfig:
    return ObservationConfig(frames=5, height=8, width_px=16, patch=2, width=32, layers=2, heads=2, **kw)


def test_reference_slots_are_checked_and_round_trip_through_json():
    c = config(reference_bands=BANDS, reference_size=8)
    assert c.references == 3 and ObservationConfig.from_json(c.to_json()) == c
    assert ObservationConfig.from_json({k: v for k, v in config().to_json().items() if not k.startswith("reference")}) == config()
    with pytest.raises(ValueError, match="whole number"):
        config(reference_bands=BANDS, reference_size=7)
    with pytest.raises(ValueError, match="render ids"):
        config(reference_bands=((0, 10),), reference_size=8)
    with pytest.raises(ValueError, match="without reference_bands"):
        config(reference_size=8)
    with pytest.raises(ValueError, match="reference_paint without reference_bands"):
        config(reference_paint=True)
    painted = config(reference_bands=BANDS, reference_size=8, reference_paint=True)
    assert ObservationConfig.from_json(painted.to_json()) == painted and painted.in_channels == c.in_channels + 4
    with pytest.raises(ValueError, match="reference_bands"):
        ObservationConfig.from_json({**c.to_json(), "reference_bands": [["a", 1]]})


@pytest.mark.parametrize("painted", [False, True])
def test_the_model_reads_its_references_and_refuses_the_wrong_shape(painted):
    torch.manual_seed(0)
    model = VideoDiT(config(reference_bands=BANDS, reference_size=8, reference_paint=painted), seed=1)
    for p in (model.head.weight, model.final_mod.weight, *(b.modulation.weight for b in model.blocks)):
        torch.nn.init.normal_(p, 0.0, 0.1)  # past adaLN-Zero's identity start, so inputs reach the output
    x, pose, first, s = torch.randn(2, 5, 3, 8, 16), torch.rand(2, 5, 3, 8, 16), torch.randn(2, 3, 8, 16), torch.rand(2)
    refs = torch.randn(2, 3, 4, 8, 8)
    out = model(x, pose, first, s, refs)
    assert out.shape == x.shape
    assert not torch.allclose(out, model(x, pose, first, s, refs.flip(0)))  # the references change the velocity
    assert torch.equal(model(x, pose, first, s), model(x, pose, first, s, torch.zeros_like(refs)))  # none = zeros
    with pytest.raises(ValueError, match="references"):
        model(x, pose, first, s, refs[:, :2])
    loss = flow_loss(model, x.clamp(-1, 1), pose, torch.Generator().manual_seed(0), refs=refs)
    loss.backward()
    assert model.ref_embed.weight.grad.abs().sum() > 0 and model.ref_slot.weight.grad.abs().sum() > 0
    if painted:  # the laid references reach the velocity without the tokens: through the pixels' own input channels
        laid = model.embed.weight.grad.view(32, -1, 2, 2)[:, 10:14]
        assert model.config.in_channels == 14 and laid.abs().sum() > 0
        with torch.no_grad():
            model.ref_embed.weight.zero_(), model.ref_embed.bias.zero_(), model.ref_slot.weight.zero_()
            assert not torch.allclose(model(x, pose, first, s, refs), model(x, pose, first, s, refs.flip(0)))
    with torch.no_grad():  # a relay takes its references from what it shows and paints
        ids = torch.zeros(9, 8, 16, dtype=torch.long)
        ids[:, 2:5, 3:6] = 120
        video = generate(model, pose_with(ids), first[0], steps=2)
    assert video.shape == (9, 3, 8, 16)


@pytest.mark.parametrize("painted", [False, True])
def test_a_forced_relay_is_the_relay_when_the_recording_is_what_the_relay_painted(painted):
    """``forced_chunks`` starts every chunk from the recorded frame (and takes references from recorded frames): given
    the relay's own video as the recording, it is that video bit for bit; given the real recording it is not."""
    from marionette.observation.quality import forced_chunks

    torch.manual_seed(0)
    model = VideoDiT(config(reference_bands=BANDS, reference_size=8, reference_paint=painted), seed=1)
    for p in (model.head.weight, model.final_mod.weight, *(b.modulation.weight for b in model.blocks)):
        torch.nn.init.normal_(p, 0.0, 0.1)
    ids = torch.zeros(13, 8, 16, dtype=torch.long)
    ids[:, 2:5, 3:6] = 120
    ids[6:, 5:7, 9:12] = 200  # the player first shown in the second chunk
    pose, recorded = pose_with(ids), torch.rand(13, 3, 8, 16) * 2 - 1
    with torch.no_grad():
        relayed = generate(model, pose, recorded[0], steps=2, seed=3)
        assert torch.equal(forced_chunks(model, pose, relayed, 3, steps=2, seed=3), relayed)
        forced = forced_chunks(model, pose, recorded, 3, steps=2, seed=3)
    assert torch.equal(forced[:5], relayed[:5]) and not torch.allclose(forced[5:], relayed[5:])


def test_training_batches_carry_each_clips_references_and_drift_only_the_bodies_of_its_first_frame():
    from marionette.observation.data import Clip
    from marionette.observation.train import ChunkReferences, _batch

    T, H, W = 20, 8, 16
    chunks = []
    for k in range(3):
        ids = torch.zeros(T, H, W, dtype=torch.long)
        ids[:, 1:4, 2:5] = 120  # the monster throughout
        ids[10:, 5:7, 9:12] = 200  # the player from frame 10
        chunks.append(Clip(rgb=torch.rand(T, 3, H, W) - 0.5, pose=pose_with(ids), key=f"c{k}", start=0))
    c = config(reference_bands=BANDS, reference_size=8)
    refs_of = ChunkReferences(chunks, c)
    plain = _batch(chunks, 5, 32, seed=1, step=2, control="pose")
    rgb, pose, first, refs, _ = _batch(chunks, 5, 32, seed=1, step=2, control="pose", refs_of=refs_of, drift=0.5, bands=BANDS)
    assert plain[3] is None and torch.equal(plain[0], rgb)  # references and drift never change the clips drawn
    assert refs.shape == (32, 3, 4, 8, 8)
    rng = __import__("numpy").random.default_rng([1, 2])  # the starts _batch drew
    picks = rng.integers(0, 3, 32)
    starts = [int(rng.integers(0, T - 5 + 1)) for _ in picks]
    for b, s in enumerate(starts):
        assert bool(refs[b, 1, 3].any())  # the monster is shown from frame 0
        assert bool(refs[b, 2, 3].any()) == (s >= 10)  # the player only to clips that start once it has been shown
        assert not refs[b, 0].any()  # no weapon
    body = band_masks(pose[:, 0], BANDS).any(1)  # (B, H, W)
    moved = (first - rgb[:, 0]).abs().amax(1) > 0  # (B, H, W)
    assert torch.equal(moved & ~body, torch.zeros_like(moved))  # only the bodies' pixels drift
    assert moved.any()


def test_appearance_drift_tells_a_look_kept_from_a_look_lost_when_a_body_leaves_the_view():
    from marionette.observation.data import Clip
    from marionette.observation.quality import appearance_drift, drift_growth

    T, H, W = 33, 8, 16
    ids = torch.zeros(T, H, W, dtype=torch.long)
    ids[:, 1:4, 2:5] = 120  # the monster, always in view
    ids[:12, 5:7, 9:12] = 200  # the player, out of view for frames 12–19, then back
    ids[20:, 5:7, 9:12] = 200
    ids[24:, 6:8, 0:2] = 62  # the weapon, from frame 24: a look the first frame never gave
    rgb = torch.full((T, 3, H, W), -0.5)
    rgb[:, :, 1:4, 2:5] = torch.tensor([0.6, -0.4, 0.2])[:, None, None]
    rgb[:, :, 5:7, 9:12] = torch.tensor([-0.3, 0.1, 0.7])[:, None, None]
    rgb[:, :, 6:8, 0:2] = 0.2
    video = Clip(rgb=rgb, pose=pose_with(ids), key="v", start=0)

    def truth(pose, first, chunks):
        return rgb[: 1 + 4 * chunks]

    def forgets(pose, first, chunks):  # paints the player grey once it has been out of view
        out = rgb[: 1 + 4 * chunks].clone()
        out[20:, :, 5:7, 9:12] = 0.0
        return out

    exact = appearance_drift([video], BANDS, 4, truth)
    assert exact["colour"].shape == (8,) and float(abs(exact["colour"]).max()) == 0.0 and exact["after_gap"] == 0.0
    assert exact["pairs"] == {"in_view": 32 + 11 + 9, "after_gap": 13}  # the monster's 32 frames, the player's, the weapon's
    lost = appearance_drift([video], BANDS, 4, forgets)
    assert lost["in_view"] == 0.0 and abs(lost["after_gap"] - (0.3 + 0.1 + 0.7) / 3) < 1e-6
    assert drift_growth(lost["colour"]) > 0.1 and drift_growth(exact["colour"]) == 0.0
    assert lost["pixel"][-1] > 0 and lost["pixel"][0] == 0
    # the looks the first frame gave (monster, player) apart from the one it did not (the weapon, chunks 5–7)
    assert drift_growth(lost["known"]) > 0.15 and np.isnan(lost["unknown"][:5]).all() and (lost["unknown"][5:] == 0).all()

    def invents(pose, first, chunks):  # keeps every look it was given, paints the weapon grey
        out = rgb[: 1 + 4 * chunks].clone()
        out[24:, :, 6:8, 0:2] = 0.0
        return out

    new = appearance_drift([video], BANDS, 4, invents)
    assert (new["known"] == 0).all() and np.allclose(new["unknown"][5:], 0.2) and drift_growth(new["colour"]) > 0


def test_a_model_trained_with_references_takes_them_from_the_corpus_and_a_relay_reads_them(follow_corpus, tmp_path):
    """Trains (briefly) with references and drifted first frames on the session's posed corpus: the model's slots are
    the layout's id bands, long relay videos are the segment's consecutive chunks joined, and the references a relay
    takes reach what it paints (withheld, the relay differs). Whether they keep a look better than no references is
    bench_references.py's measurement (docs/tradeoffs.md, "Persistent entity references")."""
    from dataclasses import replace

    from fixtures.models import OBS_SIZE, obs_config

    from marionette.corpus import Corpus
    from marionette.observation.data import ClipSource
    from marionette.observation.quality import entity_drift, relay_videos
    from marionette.observation.references import layout_bands
    from marionette.observation.train import load_model, train

    corpus = Corpus(follow_corpus)
    bands = layout_bands(corpus.layouts.values())
    assert len(bands) == 3  # the hunter's, the drake's and the greatsword's
    config = replace(obs_config(), steps=12, references=True, first_frame_drift=0.3)
    summary = train(follow_corpus, tmp_path / "run", config, log=lambda *_: None)
    assert np.isfinite(summary["evals"][-1]["held_out_loss"])
    model = load_model(tmp_path / "run")
    assert model.config.reference_bands == bands and model.config.reference_size == 4 * config.patch

    source = ClipSource(corpus, "test", 5, OBS_SIZE)
    refs = source.index()
    videos = relay_videos(source, 1 + 4 * 21, 200)
    assert videos and all(len(v.rgb) == 85 for v in videos)
    segment, at = videos[0].key.split("@")
    run = sorted((r for r in refs if r.key.startswith(segment + "__")), key=lambda r: r.first_frame)
    a, b = next((a, b) for a, b in zip(run, run[1:]) if a.first_frame == int(at))  # a run of chunks, joined
    assert b.first_frame == a.first_frame + a.frames
    assert torch.equal(videos[0].rgb, torch.cat([source.chunk(a).rgb, source.chunk(b).rgb])[:85])
    given = entity_drift(model, videos[:2], bands, steps=2)
    withheld = entity_drift(model, videos[:2], bands, steps=2, references=False)
    assert given["colour"].shape == (21,) and np.isfinite(given["colour"]).all()
    assert not np.allclose(given["colour"], withheld["colour"])
