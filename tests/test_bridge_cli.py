"""`marionette render`: one corpus segment or a rollout table, any size, rate and camera."""

import json

import numpy as np
import pytest

from marionette.bridge.gbuffer import decode_gbuffer
from marionette.bridge.targets import render_pose_targets
from marionette.cli import main
from marionette.corpus import Corpus
from marionette.corpus.video_shards import read_joined
from marionette.io import write_ipc


@pytest.fixture(scope="module")
def scanned(scanned_copy):
    render_pose_targets(scanned_copy)
    return scanned_copy


def first_chunk(corpus):
    """(video json record, pose.gbz bytes) of the first chunk of the first shard."""
    c = Corpus(corpus)
    n = c.shard_ids()[0]
    joined = read_joined(c.video_path(n), c.pose_path(n), c.shard_hash(n))
    m = joined[sorted(joined)[0]]
    return json.loads(m["json"]), m["pose.gbz"]


def test_recorded_camera_render_matches_the_pose_target(scanned, tmp_path):
    rec, pose = first_chunk(scanned)
    (tmp_path / "target.gbz").write_bytes(pose)
    target, _ = decode_gbuffer(tmp_path / "target.gbz")
    h, w = rec["resize"]
    out = tmp_path / "seg.mkv"
    assert main(["render", str(scanned), "--segment", rec["segment"], "--size", f"{h}x{w}", "--out", str(out)]) == 0
    frames, meta = decode_gbuffer(out)
    seg = Corpus(scanned).read_segment(rec["segment"])
    assert len(frames) == seg.num_rows and meta.fps == pytest.approx(30.0)
    first = int(seg["frame"][0].as_py())
    a, b = rec["frames"]
    for k in range(a, b, 10):  # the same frames, the same camera: the same G-buffer up to the rounding of K in the record
        got, want = frames[k - first], target[k - a]
        assert (got.id == want.id).mean() > 0.995


def test_follow_camera_at_another_rate_and_a_rollout_table(scanned, tmp_path):
    c = Corpus(scanned)
    seg = c.segment_ids()[0]
    rows = c.read_segment(seg)
    out = tmp_path / "follow.mkv"
    assert (
        main(
            ["render", str(scanned), "--segment", seg, "--camera", "follow", "--size", "90x160", "--fps", "20", "--out", str(out)]
        )
        == 0
    )
    frames, meta = decode_gbuffer(out)
    t = rows["t"].to_numpy()
    assert (meta.width, meta.height, meta.fps) == (160, 90, 20.0)
    assert len(frames) == int(np.floor((t[-1] - t[0]) * 20 + 1e-6)) + 1
    ids = np.stack([f.id for f in frames])
    assert ((ids >= 105) & (ids < 195)).any(axis=(1, 2)).mean() > 0.9  # the drake is framed
    assert (ids == 0).mean() > 0.2
    # the same rows as a rollout table render identically (terrain given explicitly)
    write_ipc(tmp_path / "states.arrow", rows)
    out2 = tmp_path / "rollout.mkv"
    stage = next((scanned / "terrain").iterdir())
    argv = [
        "render",
        str(tmp_path / "states.arrow"),
        "--terrain",
        str(stage),
        "--size",
        "90x160",
        "--fps",
        "20",
        "--out",
        str(out2),
    ]
    assert main(argv) == 0
    assert out2.read_bytes() == out.read_bytes()
    # a rollout has no recorded camera
    assert main(["render", str(tmp_path / "states.arrow"), "--camera", "recorded", "--out", str(tmp_path / "x.mkv")]) != 0
