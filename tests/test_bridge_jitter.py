"""Jittered state for training targets (issue 18, item 3; ``marionette.bridge.jitter``): every bone keeps its length,
the roots move by exactly the configured distance and the bones turn by no more than the configured angle, time is
warped within its bound and never runs backwards, and a target rendered from the jittered state shows the bodies
that far from where the recorded state puts them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from marionette.bridge.camera import Cameras, intrinsics_for, look_at
from marionette.bridge.gbuffer import decode_codes, iter_codes, unpack_codes
from marionette.bridge.jitter import Jitter, rotation
from marionette.bridge.kinematics import world_skeletons
from marionette.bridge.render import Rasterizer
from marionette.bridge.targets import RenderSettings, chunk_inputs, render_frames
from marionette.cli import main as cli
from marionette.corpus import Corpus


@pytest.fixture(scope="module")
def recorded(corpus):
    c = Corpus(corpus)
    segment = c.segment_ids("train")[0]
    rows = c.read_segment(segment).slice(0, 60)
    state, anchors, valid, t = chunk_inputs(c.layout, rows)
    return c.layout, world_skeletons(c.layout, state, anchors, valid, t), segment


def _bone_lengths(layout, skel, name):
    rig = next(e.rig for e in layout.entities if e.name == name)
    J = skel.joints[name]
    return np.stack([np.linalg.norm(J[:, c] - J[:, p], axis=-1) for c, p in rig.bones], -1)


def test_bones_keep_their_lengths_and_move_by_the_configured_amounts(recorded):
    layout, skel, segment = recorded
    jit = Jitter(root_m=0.5, joint_deg=10.0, seed=3)
    moved = jit.apply(layout, skel, segment)
    for e in layout.articulated:
        assert np.abs(_bone_lengths(layout, moved, e.name) - _bone_lengths(layout, skel, e.name)).max() < 1e-9
        shift = moved.joints[e.name][:, 0] - skel.joints[e.name][:, 0]
        assert np.allclose(shift, shift[0], atol=1e-12) and shift[0, 1] == 0.0  # constant over the clip, horizontal
        assert np.linalg.norm(shift[0]) == pytest.approx(0.5, abs=1e-12)
        turned = []
        for c, p in e.rig.bones:
            a, b = skel.joints[e.name][:, c] - skel.joints[e.name][:, p], moved.joints[e.name][:, c] - moved.joints[e.name][:, p]
            cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
            turned.append(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())
        assert max(turned) <= 10.0 + 1e-6 and np.median(turned) > 3.0  # within the bound, and most bones turned
        for a in layout.attachments:
            if a.owner == e.name:  # a weapon moves with its bearer's root
                assert np.allclose(moved.joints[a.name] - skel.joints[a.name], shift[0], atol=1e-12)
    again = jit.apply(layout, skel, segment)
    other = jit.apply(layout, skel, segment + "x")
    name = layout.articulated[0].name
    assert np.array_equal(again.joints[name], moved.joints[name]) and not np.allclose(other.joints[name], moved.joints[name])
    assert Jitter().apply(layout, skel, segment) is skel


def test_time_is_warped_within_its_bound_and_never_backwards():
    t = np.arange(200) / 20.0
    for amount in (0.05, 0.3, 1.0):
        w = Jitter(time_s=amount).times(t, "clip")
        assert np.abs(w - t).max() <= amount + 1e-12 and np.abs(w - t).max() > 0.3 * amount
        assert np.all(np.diff(w) >= 0) and w[0] >= t[0] and w[-1] <= t[-1]
    assert np.array_equal(Jitter().times(t, "clip"), t)
    R = rotation(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]) and np.allclose(R @ R.T, np.eye(3))
    for bad in ({"root_m": -1.0}, {"joint_deg": 50.0}, {"time_s": float("nan")}, {"seed": -1}):
        with pytest.raises(ValueError, match="jitter"):
            Jitter(**bad)


def test_a_target_rendered_from_jittered_state_shows_the_bodies_that_far_away(recorded):
    """A camera 25 m above each frame's recorded monster root, looking down, renders the recorded and the jittered
    state (roots shifted 1 m): the monster's silhouette moves by 1 m on the ground (its pixel shift × depth / f)."""
    layout, skel, segment = recorded
    monster = next(e for e in layout.articulated if e.rig.edges_key != "npc")
    W, H, n = 128, 128, len(skel)
    root = skel.joints[monster.name][:, 0]
    eye = root + np.array([0.0, 25.0, 0.0])
    rot = look_at(eye, root, up=np.array([0.0, 0.0, 1.0]))
    cams = Cameras(np.tile(intrinsics_for(W, H, 40.0), (n, 1)), eye, rot, np.ones(n, bool), W, H)
    settings = RenderSettings()
    h = (float(np.floor(root[:, 1].min() - 2)), float(np.ceil(root[:, 1].max() + 10)))
    moved = Jitter(root_m=1.0, seed=1).apply(layout, skel, segment)
    lo, hi = monster.rig.id_band
    centroids, depths = [], []
    with Rasterizer(W, H) as rast:
        for s in (skel, moved):
            cs, ds = [], []
            for words in render_frames(rast, layout, s, cams, h, settings):
                frame = decode_codes(unpack_codes(words), _meta(h, settings, W, H))
                body = (frame.id >= lo) & (frame.id <= hi)
                v, u = np.nonzero(body)
                cs.append([u.mean() + 0.5, v.mean() + 0.5])
                ds.append(np.nanmean(frame.depth[body]))
            centroids.append(np.array(cs))
            depths.append(np.array(ds))
    f = intrinsics_for(W, H, 40.0)[0]
    metres = np.linalg.norm(centroids[1] - centroids[0], axis=1) * depths[0] / f
    print(f"\nsilhouette shift on the ground: median {np.median(metres):.3f} m (configured 1.0 m)")
    assert np.median(metres) == pytest.approx(1.0, abs=0.1)


def _meta(h, settings, W, H):
    from marionette.bridge.gbuffer import GBufferMeta

    return GBufferMeta(h[0], h[1], settings.z_near, settings.z_far, W, H, 20.0)


def test_render_jitters_on_request(corpus, tmp_path):
    c = Corpus(corpus)
    segment = c.segment_ids("train")[0]
    base = ["render", str(corpus), "--segment", segment, "--size", "72x128", "--fps", "10"]
    assert cli([*base, "--out", str(tmp_path / "a.mkv")]) == 0
    assert (
        cli([*base, "--out", str(tmp_path / "b.mkv"), "--jitter-root", "0.5", "--jitter-joint-deg", "5", "--jitter-time", "0.1"])
        == 0
    )
    a, b = list(iter_codes(tmp_path / "a.mkv")), list(iter_codes(tmp_path / "b.mkv"))
    assert len(a) == len(b) and any(not np.array_equal(x, y) for x, y in zip(a, b))
    with pytest.raises(SystemExit):
        cli([*base, "--out", str(tmp_path / "c.mkv"), "--jitter-root", "-1"])


def test_jittered_training_targets_are_a_product_of_their_own(corpus, tmp_path):
    """The pose pass renders the targets of jittered state beside the corpus's own (never touching them), a second pass
    renders nothing, the clip reader takes them by key (RGB the same, pose moved), and a training run that asks for
    jitter trains on them."""
    import shutil

    from marionette.bridge.targets import render_pose_targets
    from marionette.corpus import paths
    from marionette.observation.config import ObservationTrainConfig
    from marionette.observation.data import ClipSource
    from marionette.observation.train import train

    work = tmp_path / "corpus"
    shutil.copytree(corpus, work)
    render_pose_targets(work)
    own = {p.name: p.read_bytes() for p in (work / "pose").glob("*.tar")}
    jit = Jitter(root_m=0.5, joint_deg=5.0, time_s=0.05, seed=0)
    first = render_pose_targets(work, jitter=jit)
    assert first.rendered and not first.failed
    assert {p.name: p.read_bytes() for p in (work / "pose").glob("*.tar")} == own  # the corpus's own, untouched
    assert sorted(p.name for p in paths.jitter_dir(work, jit.key()).joinpath("pose").glob("*.tar")) == sorted(own)
    assert not render_pose_targets(work, jitter=jit).rendered
    plain = list(ClipSource(work, "train", 5, (18, 32)).chunks())
    moved = list(ClipSource(work, "train", 5, (18, 32), jitter=jit.key()).chunks())
    assert [c.key for c in plain] == [c.key for c in moved]
    assert all(torch.equal(a.rgb, b.rgb) for a, b in zip(plain, moved))
    assert any(not torch.equal(a.pose, b.pose) for a, b in zip(plain, moved))
    said = []
    config = ObservationTrainConfig(
        preset="tiny", steps=2, batch_size=2, frames=5, reduce=4, patch=2, jitter_root_m=0.5, jitter_joint_deg=5.0
    )
    summary = train(work, tmp_path / "run", config, log=said.append)
    assert summary["steps"] == 2 and any("pose targets of jittered state" in line for line in said)
    assert paths.jitter_dir(work, Jitter(0.5, 5.0, 0.0, config.seed).key()).is_dir()
    with pytest.raises(ValueError, match="jitter_joint_deg"):
        ObservationTrainConfig(jitter_joint_deg=60.0)
    # the Wan trainer reads the same product: its train windows (the first chunk's) are those of the jittered targets
    from test_wan import tiny_modules, write_backbone

    from marionette.observation.config import WanTrainConfig
    from marionette.observation.wan_train import train as train_wan

    backbone = tmp_path / "wan"
    write_backbone(backbone, *tiny_modules())
    wan = dict(backbone=str(backbone), steps=1, frames=9, reduce=2, max_chunks=1, jitter_root_m=0.5, jitter_joint_deg=5.0)
    said.clear()
    run = train_wan(work, tmp_path / "wan-jit", WanTrainConfig(**wan), log=said.append)
    assert any("pose targets of jittered state" in line for line in said)
    # the first train chunk is also the first held-out one (the recorded state's) here: its windows were encoded twice,
    # once with each pose video
    assert run["held_out_split"] == "train" and run["encoded"] == run["windows"] + run["held_out"] == 20
