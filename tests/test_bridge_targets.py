"""Pose-control targets in the corpus: rendered per video chunk beside rgb.mp4, cached, re-rendered only
where the terrain they see changed."""

import io
import json
import tarfile

import av
import numpy as np
import pytest

from marionette.bridge.gbuffer import decode_gbuffer
from marionette.bridge.targets import render_pose_targets
from marionette.corpus.paths import stage_dir
from terrain_scan.layers import Observations
from terrain_scan.store import Stage


@pytest.fixture(scope="module")
def scanned(scanned_copy):
    return scanned_copy


def members(tar_path):
    with tarfile.open(tar_path) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar if m.isfile()}


def frame_count(data: bytes) -> int:
    with av.open(io.BytesIO(data)) as c:
        return sum(1 for _ in c.decode(video=0))


def test_every_chunk_gets_a_pose_target_of_equal_length(scanned, tmp_path):
    report = render_pose_targets(scanned)
    assert report.chunks >= 8 and len(report.rendered) == report.chunks
    tars = sorted((scanned / "video").glob("*.tar"))
    seen_bones = 0
    for t in tars:
        m = members(t)
        names = list(m)
        chunks = [n[: -len(".json")] for n in names if n.endswith(".json")]
        assert chunks
        for c in chunks:
            rec = json.loads(m[f"{c}.json"])
            # webdataset groups a sample's members by adjacency: rgb, json, pose of one chunk together
            i = names.index(f"{c}.rgb.mp4")
            assert names[i : i + 3] == [f"{c}.rgb.mp4", f"{c}.json", f"{c}.pose.mkv"]
            n = rec["frames"][1] - rec["frames"][0]
            assert frame_count(m[f"{c}.rgb.mp4"]) == frame_count(m[f"{c}.pose.mkv"]) == n == rec["pose"]["frames"]
            assert rec["pose"]["terrain_chunks"]  # the scanned stage is in view
        p = tmp_path / "pose.mkv"
        p.write_bytes(m[f"{chunks[0]}.pose.mkv"])
        frames, meta = decode_gbuffer(p)  # decoding needs only the file
        h, w = json.loads(m[f"{chunks[0]}.json"])["resize"]
        assert (meta.height, meta.width) == (h, w) and len(frames) == n
        ids = np.stack([f.id for f in frames])
        assert (ids == 0).mean() > 0.2  # terrain
        seen_bones += int((ids >= 195).any(axis=(1, 2)).sum())  # frames showing the hunter
        heights = np.stack([f.height for f in frames])
        assert np.all(np.isfinite(heights[ids >= 0])) and np.all(np.isnan(heights[ids < 0]))
    assert seen_bones > 100


def test_a_second_pass_does_nothing(scanned):
    render_pose_targets(scanned)
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (scanned / "video").glob("*.tar")}
    report = render_pose_targets(scanned)
    assert report.rendered == [] and report.shards_rewritten == [] and report.frames_rendered == 0
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in (scanned / "video").glob("*.tar")} == before


def test_a_rescan_rerenders_only_the_chunks_that_see_the_change(scanned):
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
    before = {p.name: p.read_bytes() for p in (scanned / "video").glob("*.tar")}
    # fanned out: a shard a job on two fresh processes, merged in shard order
    report = render_pose_targets(scanned, workers=2)
    seeing, all_chunks = set(), set()
    for t in sorted((scanned / "video").glob("*.tar")):
        for name, data in members(t).items():
            if name.endswith(".json"):
                chunk = name[: -len(".json")]
                all_chunks.add(chunk)
                if "-11_8" in json.loads(data)["pose"]["terrain_chunks"]:
                    seeing.add(chunk)
    assert 0 < len(seeing) < len(all_chunks)  # the test needs both kinds
    assert set(report.rendered) == seeing
    rewritten = {f"shard-{s:06d}.tar" for s in report.shards_rewritten}
    for name, data in before.items():  # shards without a re-rendered chunk keep their bytes
        assert (name in rewritten) == ((scanned / "video" / name).read_bytes() != data)
    assert len(rewritten) < len(before)
    # and removing the contribution brings back the first renders (the cache key is the content): the two
    # workers write the bytes the one-process pass wrote, and drop the derived files no chunk uses any more
    stage.remove("extra/west")
    stage.rebuild()
    again = render_pose_targets(scanned, workers=2)
    assert set(again.rendered) == seeing and again.failed == {}
    assert {p.name: p.read_bytes() for p in (scanned / "video").glob("*.tar")} == before
    used = {
        f"{name[: -len('.json')]}-{json.loads(data)['pose']['key']}.mkv"
        for t in sorted((scanned / "video").glob("*.tar"))
        for name, data in members(t).items()
        if name.endswith(".json")
    }
    assert {p.name for p in (scanned / "derived" / "pose").glob("*.mkv")} == used


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
