"""Pose-control targets in the corpus: rendered per video chunk into pose shards keyed like the video
shards, cached, re-rendered only where the terrain they see changed, never rewriting an RGB byte."""

import io
import json
import tarfile

import av
import numpy as np
import pytest

from marionette.bridge.gbuffer import GBZ_MAGIC, decode_gbuffer, iter_planes
from marionette.bridge.targets import render_pose_targets
from marionette.corpus import Corpus, paths
from marionette.corpus.paths import stage_dir
from marionette.corpus.video_shards import pose_matches
from terrain_scan.layers import Observations
from terrain_scan.store import Stage


@pytest.fixture(scope="module")
def scanned(scanned_copy):
    return scanned_copy


def members(tar_path):
    with tarfile.open(tar_path) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar if m.isfile()}


def frame_count(data: bytes) -> int:
    """The frames of an RGB video or a G-buffer file."""
    if data.startswith(GBZ_MAGIC):
        return sum(1 for _ in iter_planes(data))
    with av.open(io.BytesIO(data)) as c:
        return sum(1 for _ in c.decode(video=0))


def pose_records(corpus):
    """Chunk key → pose.json record, over every pose shard."""
    return {
        name[: -len(".pose.json")]: json.loads(data)
        for t in sorted((corpus / "pose").glob("*.tar"))
        for name, data in members(t).items()
        if name.endswith(".pose.json")
    }


def snapshot(corpus, kind):
    """Name → (bytes, mtime_ns, inode) of a corpus's video or pose shards."""
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns, p.stat().st_ino) for p in (corpus / kind).glob("*.tar")}


def test_every_chunk_gets_a_pose_target_of_equal_length(scanned, tmp_path):
    videos = snapshot(scanned, "video")
    report = render_pose_targets(scanned)
    assert report.chunks >= 8 and len(report.rendered) == report.chunks
    assert snapshot(scanned, "video") == videos  # the pass only reads the video shards
    c = Corpus(scanned)
    seen_bones = 0
    for shard in c.shard_ids():
        video, pose = members(c.video_path(shard)), members(c.pose_path(shard))
        assert all(n.endswith((".rgb.mp4", ".json")) for n in video)
        chunks = [n[: -len(".json")] for n in video if n.endswith(".json")]
        assert chunks
        # keyed like the video chunks, in their order, each target's record first (webdataset joins by key)
        assert list(pose) == [f"{k}.{kind}" for k in chunks for kind in ("pose.json", "pose.gbz")]
        for k in chunks:
            rec, pose_rec = json.loads(video[f"{k}.json"]), json.loads(pose[f"{k}.pose.json"])
            assert pose_matches(pose_rec, video[f"{k}.json"], c.shard_hash(shard))
            n = rec["frames"][1] - rec["frames"][0]
            assert frame_count(video[f"{k}.rgb.mp4"]) == frame_count(pose[f"{k}.pose.gbz"]) == n == pose_rec["frames"]
            assert pose_rec["terrain_chunks"]  # the scanned stage is in view
        p = tmp_path / "pose.gbz"
        p.write_bytes(pose[f"{chunks[0]}.pose.gbz"])
        frames, meta = decode_gbuffer(p)  # decoding needs only the file
        h, w = json.loads(video[f"{chunks[0]}.json"])["resize"]
        n = json.loads(pose[f"{chunks[0]}.pose.json"])["frames"]
        assert (meta.height, meta.width) == (h, w) and len(frames) == n
        ids = np.stack([f.id for f in frames])
        assert (ids == 0).mean() > 0.2  # terrain
        seen_bones += int((ids >= 195).any(axis=(1, 2)).sum())  # frames showing the hunter
        heights = np.stack([f.height for f in frames])
        assert np.all(np.isfinite(heights[ids >= 0])) and np.all(np.isnan(heights[ids < 0]))
    assert seen_bones > 100


def test_a_second_pass_does_nothing_but_sweep_what_a_killed_pass_left(scanned, monkeypatch):
    from marionette.corpus import video_shards

    render_pose_targets(scanned)
    before = {kind: snapshot(scanned, kind) for kind in ("video", "pose")}
    targets = paths.pose_targets_dir(scanned)
    left = [targets / ".data_part1-rec0000-s000__c00000-0123456789abcdef.mkv.k1ll3d.tmp", targets / ".x.mkv.tmp"]
    for p in left:  # what a pass killed mid-write leaves
        p.write_bytes(b"")

    def no_read(*a):
        raise AssertionError("a pass with nothing new read a target")

    monkeypatch.setattr(video_shards.PoseShard, "read", no_read)
    report = render_pose_targets(scanned)
    assert report.rendered == [] and report.shards_rewritten == [] and report.frames_rendered == 0
    assert {kind: snapshot(scanned, kind) for kind in ("video", "pose")} == before
    assert not any(p.exists() for p in left)


def test_a_pass_killed_before_its_shards_were_written_leaves_renders_the_next_pass_takes_up(scanned, monkeypatch):
    """The pose shards are the targets' one copy; a target is rendered into ``derived/pose`` first, and a pass killed
    before writing its shard leaves it there: the next pass writes the shard from it, renders nothing, and the
    shard's bytes are a clean pass's; once written, ``derived/pose`` holds no target."""
    from marionette.corpus import video_shards

    render_pose_targets(scanned)
    before = snapshot(scanned, "pose")
    shard = Corpus(scanned).shard_ids()[0]
    good = Corpus(scanned).pose_path(shard).read_bytes()
    Corpus(scanned).pose_path(shard).unlink()
    write = video_shards.write_members

    def killed(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(video_shards, "write_members", killed)
    with pytest.raises(KeyboardInterrupt):
        render_pose_targets(scanned)
    staged = {p.name[: -len("-0123456789abcdef.gbz")] for p in paths.pose_targets_dir(scanned).glob("*.gbz")}
    assert staged == set(video_shards.read_chunks(Corpus(scanned).video_path(shard), kinds=("json",)))
    monkeypatch.setattr(video_shards, "write_members", write)
    report = render_pose_targets(scanned)
    assert report.rendered == [] and report.shards_rewritten == [shard] and report.failed == {}
    assert Corpus(scanned).pose_path(shard).read_bytes() == good and snapshot(scanned, "pose").keys() == before.keys()
    assert not list(paths.pose_targets_dir(scanned).glob("*.gbz"))


def test_a_rescan_rerenders_only_the_chunks_that_see_the_change_and_no_rgb_byte(scanned):
    """A pose re-render after a terrain change rewrites no video shard (bytes, mtime and inode kept)."""
    render_pose_targets(scanned)
    stage = Stage(stage_dir(scanned, "default"))
    # new ground west of the arena, in a chunk of its own (x in [-1100, -1000)): some cameras look that way
    gx, gz = (a.ravel() for a in np.meshgrid(np.arange(-1040, -1000), np.arange(820, 880), indexing="ij"))
    obs = Observations(
        gx,
        gz,
        np.full(len(gx), 25.0),
        np.tile([0.0, 1.0, 0.0], (len(gx), 1)),
        np.ones(len(gx), np.int64),
        np.zeros(len(gx), np.int64),
    )
    stage.put("extra/west", obs, "test", 0)
    rebuilt = stage.rebuild()
    assert rebuilt.written == [(-11, 8)]
    videos = snapshot(scanned, "video")
    before = {p.name: p.read_bytes() for p in (scanned / "pose").glob("*.tar")}
    # fanned out: a shard a job on two fresh processes, merged in shard order
    report = render_pose_targets(scanned, workers=2)
    records = pose_records(scanned)
    seeing = {k for k, r in records.items() if "-11_8" in r["terrain_chunks"]}
    assert 0 < len(seeing) < len(records)  # the test needs both kinds
    assert set(report.rendered) == seeing
    assert snapshot(scanned, "video") == videos
    rewritten = {f"shard-{s:06d}.tar" for s in report.shards_rewritten}
    for name, data in before.items():  # pose shards without a re-rendered chunk keep their bytes
        assert (name in rewritten) == ((scanned / "pose" / name).read_bytes() != data)
    assert 0 < len(rewritten) < len(before)
    # and removing the contribution brings back the first renders (the cache key is the content): the two
    # workers write the bytes the one-process pass wrote; the pose shards hold the one copy of every target
    stage.remove("extra/west")
    stage.rebuild()
    again = render_pose_targets(scanned, workers=2)
    assert set(again.rendered) == seeing and again.failed == {}
    assert {p.name: p.read_bytes() for p in (scanned / "pose").glob("*.tar")} == before
    assert snapshot(scanned, "video") == videos
    assert not list((scanned / "derived" / "pose").glob("*.gbz"))


def test_stale_damaged_and_orphan_pose_shards(scanned):
    """A target rendered for another recording is never joined; a damaged pose shard's targets are rendered and
    written again (the pose shards are their one copy), the same bytes; the pose shard of a shard number the corpus
    no longer holds is removed."""
    from marionette.corpus.video_shards import PoseShard, read_chunks, read_joined

    render_pose_targets(scanned)
    c = Corpus(scanned)
    shard = c.shard_ids()[0]
    seg = next(s for s in c.segment_ids() if c.segment_row(s)["shard"] == shard and c.segment_row(s)["chunks"])
    joined = read_joined(c.video_path(shard), c.pose_path(shard), c.shard_hash(shard), seg)
    assert joined and all("pose.gbz" in m for m in joined.values())
    # another state shard hash: the pose shard is stale for it, nothing is joined
    assert all("pose.gbz" not in m for m in read_joined(c.video_path(shard), c.pose_path(shard), "0" * 64, seg).values())
    key, m = next(iter(joined.items()))
    with PoseShard(c.pose_path(shard)) as ps:
        assert ps.get(key, m["json"], c.shard_hash(shard))[1] == m["pose.gbz"]
        assert ps.get(key, m["json"] + b" ", c.shard_hash(shard)) is None  # another chunk record
    good = c.pose_path(shard).read_bytes()
    c.pose_path(shard).write_bytes(good[: len(good) // 3])  # truncated
    orphan = c.pose_path(999_999)
    orphan.write_bytes(good)
    report = render_pose_targets(scanned)
    assert report.shards_rewritten == [shard] and report.failed == {}
    assert report.rendered == list(read_chunks(c.video_path(shard), kinds=("json",)))
    assert c.pose_path(shard).read_bytes() == good and not orphan.exists()


def test_the_follow_camera_frames_both_fighters_on_recorded_state(scanned_corpus):
    """Issue 15: behind the player, each body near the paper's 1.5–1.8 % of the pose frame. Measured here (72 × 128,
    the eval's ``body_share``): hunter ~1.5 %, drake ~2.5 % (4-5 % in the close fight: its frontal area is 10-15× the
    hunter's); the camera behind the drake gave the hunter 0.05 % (zero in a third of the frames), the recorded
    camera 0.53 %. The band: each mean in [1, 3] %, so neither fighter is a speck nor fills the frame."""
    from marionette.bridge.kinematics import world_skeletons
    from marionette.bridge.targets import chunk_inputs, follow_view
    from marionette.corpus import Corpus
    from marionette.eval.protocol import body_share_frames, terrain_scene

    c = Corpus(scanned_corpus)
    L = c.layout
    shares: dict[str, list] = {e.name: [] for e in L.articulated}
    close = []
    for seg in c.segment_ids():
        rows = c.dynamics_segment(seg, 20.0)  # the rows the eval renders
        for name, v in body_share_frames(L, rows, terrain_scene(c, seg)).items():
            shares[name].append(v)
        state, anchors, valid, t = chunk_inputs(L, rows)
        skel = world_skeletons(L, state, anchors, valid, t, t)
        cams = follow_view(L, skel, 20.0, 128, 72)
        for i in range(len(cams)):
            uv, depth = cams.project(np.stack([skel.joints[e.name][i, 0] for e in L.articulated]), i)
            assert np.all(depth > 0) and np.all((uv >= 0) & (uv <= [128, 72])), (seg, i, uv)  # both roots in frame
        gap = skel.joints["monster"][:, 0] - skel.joints["hunter"][:, 0]
        close.append(np.linalg.norm(gap[:, [0, 2]], axis=-1) < 8.0)
    s = {n: np.concatenate(v) for n, v in shares.items()}
    close_fight = np.concatenate(close)
    assert close_fight.mean() > 0.3, "the corpus should hold the close-range fight"
    print("\nfollow-camera body share: " + ", ".join(f"{n} {100 * v.mean():.2f} %" for n, v in s.items()))
    assert (s["hunter"] > 0).all()  # never hidden
    assert (s["monster"][close_fight] > 0).all() and (s["monster"] > 0).mean() > 0.95  # terrain hides the far charge
    for name, v in s.items():
        assert 0.01 <= v.mean() <= 0.03, (name, v.mean())
