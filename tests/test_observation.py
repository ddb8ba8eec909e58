"""The observation model's first increment: clips from the video shards, a tiny video DiT trained by
rectified flow (it beats its initialisation on held-out chunks), seeded generation relayed over
chunks, input checks before compute, and the train/generate commands."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
import torch

from marionette.corpus import Corpus
from marionette.corpus.video_shards import read_joined
from marionette.observation.config import ObservationConfig, ObservationTrainConfig
from marionette.observation.data import ChunkStore, ClipSource, _clip_bytes, reduce_codes
from marionette.observation.generate import write_image
from marionette.observation.model import VideoDiT, check_inputs
from marionette.observation.relay import generate
from marionette.observation.train import load_model, train

# 18×32 clips of the session corpus (its 72×128 chunks reduced by 4), two a step: the relay test reads seams against
# steps inside a chunk and against other held-out chunks, which the shared pose model of tests/fixtures/models.py (the
# close-range game, held-out chunks alike) cannot tell apart. After 200 steps its seam is 15 % under half the distance
# to other chunks (after 150 it is over it).
CONFIG = ObservationTrainConfig(preset="tiny", steps=200, batch_size=2, frames=5, reduce=4, patch=2, lr=1e-3, warmup=20)


@pytest.fixture(scope="module")
def obs_corpus(scanned_corpus, tmp_path_factory):
    """A copy of the scanned session corpus with pose targets rendered and one recording held out."""
    from marionette.bridge.targets import render_pose_targets

    out = tmp_path_factory.mktemp("observation") / "corpus"
    shutil.copytree(scanned_corpus, out)
    render_pose_targets(out)
    path = out / "meta" / "segments.parquet"
    seg = pq.read_table(path)
    split = pc.if_else(pc.equal(seg["sample"], "data_part1/rec0001"), pa.scalar("test"), seg["split"])
    pq.write_table(seg.set_column(seg.schema.get_field_index("split"), "split", split), path)
    return out


@pytest.fixture(scope="module")
def trained(obs_corpus, tmp_path_factory):
    out = tmp_path_factory.mktemp("obs-run")
    return out, train(obs_corpus, out, CONFIG, log=lambda *_: None)


def test_clips_are_the_chunks_reduced(obs_corpus):
    src = ClipSource(obs_corpus, "train", 5, (18, 32))
    clips = list(src.clips(seed=0))
    assert clips and not src.skipped
    c = clips[0]
    assert c.rgb.shape == (5, 3, 18, 32) and c.pose.shape == (5, 3, 18, 32)
    assert float(c.rgb.min()) >= -1.0 and float(c.rgb.max()) <= 1.0 and float(c.pose.min()) >= 0.0 and float(c.pose.max()) <= 1.0
    # identity codes are sampled, never blended: whole ids to the G-buffer's quantisation (the rounding to a code)
    ids = np.rint(c.pose[:, 1].numpy() * 1023) / 1023 * 255
    assert np.allclose(ids, np.rint(ids), atol=1.0 * 255 / 1023 + 1e-6) and (ids > 100).any()
    assert [x.start for x in ClipSource(obs_corpus, "train", 5, (18, 32)).clips(seed=0)] == [x.start for x in clips]
    with pytest.raises(ValueError, match="4k"):
        ClipSource(obs_corpus, "train", 6, (18, 32))
    bad = ClipSource(obs_corpus, "train", 5, (20, 32))  # 72×128 does not reduce to 20×32
    assert not list(bad.clips()) and all("reduce" in r for r in bad.skipped.values())


def test_chunks_are_indexed_then_decoded_on_demand_in_bounded_memory(obs_corpus, tmp_path):
    """Issue 16: training reads chunks through an index of the shards (offsets, no decoding) and a cache with a byte
    budget; what it reads equals the chunks decoded whole, at any budget, and memory held stays within the budget."""
    src = ClipSource(obs_corpus, "train", 5, (18, 32), actions=True)
    whole = list(src.chunks())
    refs = src.index()
    assert [r.key for r in refs] == [c.key for c in whole] and len(refs) >= 4
    one = _clip_bytes(whole[0])
    for budget in (0, 2 * one, 1 << 30):
        store = ChunkStore(src, refs, budget_bytes=budget)
        order = [0, 1, 0, 1, 2, 0, len(refs) - 1, len(refs) - 1]
        for i in order:
            got, want = store[i], whole[i]
            assert torch.equal(got.rgb, want.rgb) and torch.equal(got.pose, want.pose) and torch.equal(got.actions, want.actions)
            assert store.held_bytes <= budget
        # two chunks fit: 0 1 miss, 0 1 hit, 2 evicts 0, 0 evicts 1, the last evicts 2, then hits
        assert store.decoded == {0: len(order), 2 * one: 5, 1 << 30: 4}[budget]
    # a shard rewritten after it was indexed is named, not misread
    copy = tmp_path / "corpus"
    shutil.copytree(obs_corpus, copy)
    moved = ClipSource(copy, "train", 5, (18, 32))
    ref = moved.index()[0]
    Path(ref.pose).write_bytes(Path(ref.pose).read_bytes() + bytes(512))
    with pytest.raises(ValueError, match="changed since it was indexed"):
        moved.chunk(ref)


def test_training_reads_the_same_batches_at_any_cache_size(obs_corpus, tmp_path):
    """A cache too small to hold one chunk decodes every clip again and trains to the same losses, bit for bit."""
    config = replace(CONFIG, steps=3, warmup=1)
    a = train(obs_corpus, tmp_path / "a", config, log=lambda *_: None)
    b = train(obs_corpus, tmp_path / "b", replace(config, cache_mb=0), log=lambda *_: None)
    assert [r["loss"] for r in a["losses"]] == [r["loss"] for r in b["losses"]] and len(a["losses"]) == 3


def test_pose_reduction_keeps_one_pixel_bones():
    """A 4 × 4 block keeps all three channels of its bone pixel (the highest id), else of its top-left pixel."""
    codes = np.zeros((2, 8, 8, 3), np.uint16)
    codes[..., 0], codes[..., 2] = np.arange(64).reshape(8, 8), 7  # terrain: heights differ per pixel
    codes[0, 1, 6] = [11, 800, 22]  # a hunter bone, one pixel, in block (0, 1)
    codes[0, 5, 2], codes[0, 6, 3] = [12, 480, 23], [13, 790, 24]  # a monster and a hunter pixel in block (1, 0)
    r = reduce_codes(codes, 4)
    assert r.shape == (2, 2, 2, 3)
    assert r[0, 0, 1].tolist() == [11, 800, 22] and r[0, 1, 0].tolist() == [13, 790, 24]
    assert r[0, 0, 0].tolist() == [0, 0, 7] and r[0, 1, 1].tolist() == [36, 0, 7] and r[1, 1, 1].tolist() == [36, 0, 7]


def test_training_beats_its_initialisation_on_held_out_chunks(trained):
    _, s = trained
    first, last = s["evals"][0]["held_out_loss"], s["evals"][-1]["held_out_loss"]
    print(
        f"\n{s['chunks']} train / {s['held_out']} held-out chunks ({s['held_out_split']}), {s['parameters']:,} parameters: "
        f"held-out flow loss {first:.4f} at initialisation → {last:.4f} after {s['steps']} steps"
    )
    assert s["held_out_split"] == "test"
    assert last < 0.7 * first


def test_the_pixel_ar_baseline_trains_on_action_schedules(follow_corpus, baseline_run):
    """The baseline reads the first frame and the recorded action schedule (no pose video): it learns
    (held-out flow loss), generates from a schedule, and rejects tokens outside the vocabularies. The model is
    the session's (tests/fixtures/models.py), which test_observation_follow scores against the pose model."""
    out, s = baseline_run
    first, last = s["evals"][0]["held_out_loss"], s["evals"][-1]["held_out_loss"]
    print(f"\nbaseline: held-out flow loss {first:.4f} → {last:.4f} after {s['steps']} steps")
    assert last < 0.7 * first
    model = load_model(out)
    assert model.config.control == "actions" and model.actions is not None
    T = model.config.frames
    ch = next(iter(ClipSource(follow_corpus, "test", T, model.config.size, actions=True).chunks()))
    assert ch.actions.shape == (len(ch.rgb), len(model.config.vocab_sizes)) and (ch.actions > 0).any()
    video = generate(model, ch.actions[: 1 + 2 * (T - 1)], ch.rgb[0], chunks=2, steps=4, seed=0)
    assert video.shape == (1 + 2 * (T - 1), 3, *model.config.size) and torch.isfinite(video).all()
    bad = ch.actions.clone()
    bad[0, 0] = model.config.vocab_sizes[0]
    with pytest.raises(ValueError, match="vocabulary"):
        generate(model, bad, ch.rgb[0])
    with pytest.raises(ValueError, match="action schedule"):
        generate(model, ch.pose, ch.rgb[0])  # a pose video given to the baseline


@pytest.fixture(scope="module")
def relayed(obs_corpus, trained):
    """(model, held-out chunks, a 3-chunk relay of the first one painted at seed 1)."""
    model = load_model(trained[0])
    T = model.config.frames
    held = list(ClipSource(obs_corpus, "test", T, model.config.size).chunks())
    chunk = held[0]
    return model, held, generate(model, chunk.pose[: 1 + 3 * (T - 1)], chunk.rgb[0], chunks=3, steps=8, seed=1)


def test_generation_is_seeded(relayed):
    model, held, a = relayed
    T = model.config.frames
    pose, first = held[0].pose[: 1 + 3 * (T - 1)], held[0].rgb[0]
    b = generate(model, pose, first, chunks=3, steps=8, seed=1)
    c = generate(model, pose, first, chunks=3, steps=8, seed=2)
    assert a.shape == (1 + 3 * (T - 1), 3, *model.config.size)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch.equal(a[0], first)  # the given frame


def test_generation_relays_chunks(relayed):
    """The first *generated* frame of chunks 2 and 3 against the frame that seeded them, beside the step between
    consecutive generated frames inside a chunk and the distance to other held-out chunks."""
    model, held, a = relayed
    T = model.config.frames
    seams = [float((a[1 + k * (T - 1)] - a[k * (T - 1)]).abs().mean()) for k in (1, 2)]
    within = [float((a[j + 1] - a[j]).abs().mean()) for j in range(1, len(a) - 1) if j % (T - 1)]
    other = [float((a[k * (T - 1)] - h.rgb[0]).abs().mean()) for k in (1, 2) for h in held[1:]]
    print(
        f"\nrelay seams (mean |Δ|, [-1, 1] units): {[round(x, 4) for x in seams]}; consecutive generated frames inside a "
        f"chunk {np.mean(within):.4f}; seed frames against other held-out chunks {np.mean(other):.4f}"
    )
    assert max(seams) <= 1.5 * np.mean(within)  # a seam is no rougher than a step inside a chunk (± half)
    assert max(seams) < 0.5 * np.mean(other)


def test_bad_inputs_fail_before_compute():
    c = ObservationConfig(frames=5, height=18, width_px=32, patch=2, width=32, layers=1, heads=2)
    model = VideoDiT(c)
    pose, first = torch.zeros(9, 3, 18, 32), torch.zeros(3, 18, 32)
    check_inputs(c, pose, first)
    for bad_pose, bad_first, match in (
        (torch.zeros(9, 4, 18, 32), first, "pose video"),  # another channel layout
        (torch.zeros(9, 3, 20, 32), first, "pose video"),  # another size
        (torch.zeros(3, 3, 18, 32), first, "frames"),  # shorter than a chunk
        (pose, torch.zeros(3, 36, 64), "first frame"),  # a first frame of another size
    ):
        with pytest.raises(ValueError, match=match):
            generate(model, bad_pose, bad_first)


def test_train_and_generate_commands(obs_corpus, tmp_path):
    from marionette.cli import main as cli
    from marionette.video import decode_frames

    runs = tmp_path / "obs"
    assert (
        cli(
            [
                "train",
                "observation",
                str(obs_corpus),
                "--out",
                str(runs),
                "--steps",
                "3",
                "--frames",
                "5",
                "--reduce",
                "4",
                "--patch",
                "2",
                "--batch-size",
                "2",
            ]
        )
        == 0
    )
    c = Corpus(obs_corpus)
    n = c.shard_ids()[0]
    m = next(m for m in read_joined(c.video_path(n), c.pose_path(n), c.shard_hash(n)).values() if "pose.gbz" in m)
    (tmp_path / "pose.gbz").write_bytes(m["pose.gbz"])
    rgb = decode_frames(m["rgb.mp4"])
    write_image(tmp_path / "first.png", rgb[0])
    out = tmp_path / "gen.mp4"
    args = [
        "generate",
        str(runs),
        "--pose",
        str(tmp_path / "pose.gbz"),
        "--first-frame",
        str(tmp_path / "first.png"),
        "--out",
        str(out),
        "--chunks",
        "2",
        "--steps",
        "2",
    ]
    assert cli(args) == 0
    frames = decode_frames(out.read_bytes())
    assert len(frames) == 9 and frames[0].shape == (18, 32, 3)
    write_image(tmp_path / "small.png", rgb[0][::2, ::2])
    assert cli([*args[:5], str(tmp_path / "small.png"), *args[6:]]) == 2  # a first frame of another size
    assert cli([*args[:3], str(tmp_path / "first.png"), *args[4:]]) == 2  # an image is not a G-buffer video


def test_ddp_two_processes_gloo(obs_corpus, tmp_path):
    """``marionette train observation --nproc 2`` trains under torchrun (2 × gloo); the checkpoint loads in one process."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "ddp"
    marionette = str(Path(sys.executable).with_name("marionette"))
    cmd = [
        marionette,
        "train",
        "observation",
        str(obs_corpus),
        "--out",
        str(out),
        "--steps",
        "3",
        "--frames",
        "5",
        "--reduce",
        "4",
        "--patch",
        "2",
        "--batch-size",
        "2",
        "--nproc",
        "2",
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 3 and summary["checkpoint"].endswith("step-00000003")
    assert r.stdout.count("held-out flow loss") == 1  # rank 0 alone logs
    model = load_model(out)
    assert model.config.frames == 5 and all(torch.isfinite(p).all() for p in model.parameters())


def test_handoff_noise_trains_on_noised_first_frames_and_a_relay_gives_its_hand_offs_noised():
    from marionette.observation.data import Clip
    from marionette.observation.train import _batch

    chunks = [Clip(rgb=torch.rand(9, 3, 8, 8) - 0.5, pose=torch.zeros(9, 3, 8, 8), key=f"c{k}", start=0) for k in range(3)]
    plain = _batch(chunks, 5, 16, seed=3, step=7, control="pose", swap=0.3)
    rgb, _, first, refs, level = _batch(chunks, 5, 16, seed=3, step=7, control="pose", swap=0.3, noise=0.4)
    assert plain[4] is None and refs is None
    assert torch.equal(plain[0], rgb)  # the noise is drawn last: the clips, swaps and drifts of a run without it stay
    assert level.shape == (16,) and float(level.min()) >= 0 and float(level.max()) <= 0.4 and float(level.std()) > 0.05
    spread = (first - plain[2]).flatten(1).std(1)  # 192 values a clip
    assert torch.allclose(spread, level, rtol=0.25, atol=0.01)

    class Seen(VideoDiT):  # the real network, recording what each call is given
        def forward(self, x_s, control, first, s, refs=None, level=None):
            self.given.append((first.clone(), level))
            return super().forward(x_s, control, first, s, refs, level)

    c = ObservationConfig(frames=5, height=16, width_px=16, patch=4, width=32, layers=1, heads=2, handoff_noise=0.4)
    model = Seen(c)
    model.given = []
    start = torch.rand(3, 16, 16) - 0.5
    video = generate(model, torch.zeros(9, 3, 16, 16), start, chunks=2, steps=3, seed=0)
    assert len(model.given) == 6
    for given, lv in model.given[:3]:  # the first chunk starts from the given frame, clean
        assert lv is None and torch.equal(given[0], start)  # (the network reads no level as level 0)
    for given, lv in model.given[3:]:  # the second from the first chunk's last frame, noised at half the trained range
        assert torch.equal(lv, torch.full((1,), 0.2))
        assert abs(float((given[0] - video[4]).std()) - 0.2) < 0.03
    assert "given_level.weight" in model.state_dict()
    assert "given_level.weight" not in VideoDiT(replace(c, handoff_noise=0.0)).state_dict()  # older checkpoints load
    assert ObservationConfig.from_json(c.to_json()) == c
    for bad in (-0.1, 2.5, True):
        with pytest.raises(ValueError, match="handoff_noise"):
            replace(c, handoff_noise=bad)
    with pytest.raises(ValueError, match="handoff_noise"):
        ObservationTrainConfig(handoff_noise=3.0)
    for bad_model, bad in ((model, -0.1), (VideoDiT(replace(c, handoff_noise=0.0)), 0.2)):
        with pytest.raises(ValueError, match="hand-off noise"):
            generate(bad_model, torch.zeros(9, 3, 16, 16), start, chunks=2, steps=3, handoff=bad)
