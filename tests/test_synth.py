"""The synthetic game: public-layout conformance, truth, motion statistics, determinism, depth."""

from __future__ import annotations

import ast
import csv
import json
from pathlib import Path

import av
import numpy as np
import pytest

from marionette.corpus import Corpus
from marionette.corpus.play_stats import play_stats
from marionette.geometry import quat_to_matrix
from marionette.schema import load_rig
from marionette.synth import generate, load_truth, terrain, world_skeletons_at
from marionette.synth.behaviour import MIN_SEP
from marionette.synth.clips import CLIPS
from marionette.synth.controls import hunter_controls, monster_controls
from marionette.synth.game import COLUMNS
from marionette.synth.render import decode_depth
from marionette.synth.sim import BLEND_FRAMES
from marionette.synth.skeletons import hunter_skeleton, monster_skeleton

pytestmark = pytest.mark.corpus  # generates its own recordings

PART = "data_part1"
GEN = {"recordings": 3, "seconds": 12.0, "seed": 2, "width": 160, "height": 90}
FPS = 30


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth_game")
    generate(root, **GEN, workers=2)  # a recording per process, its rays cast on one thread
    return root


@pytest.fixture(scope="module")
def play(dynamics_corpus) -> tuple[Path, Path]:
    """(recordings, corpus) of minutes of play, for the game's statistics: the session's dynamics corpus (16 × 45 s,
    tests/fixtures/corpora.py), which the trained models read too."""
    return dynamics_corpus.parent / "recordings", dynamics_corpus


def _rows(path: Path) -> tuple[list[str], list[dict]]:
    with open(path, newline="") as fh:
        r = csv.DictReader(fh)
        return list(r.fieldnames), list(r)


def _frames(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as c:
        return [f.to_ndarray() for f in c.decode(video=0)]


def _tuple(cell: str, n: int) -> np.ndarray:
    if cell == "nan":
        return np.full(n, np.nan)
    v = ast.literal_eval(cell)
    assert isinstance(v, tuple) and len(v) == n
    return np.array(v, dtype=np.float64)


def _samples(root: Path) -> list[Path]:
    return sorted(p for p in (root / PART).iterdir() if p.is_dir())


def test_public_layout_conformance(synth):
    edges = json.loads((synth / PART / "skeleton_edges.json").read_text())
    assert set(edges) == {"em_25", "npc", "wp_3"}
    assert [len(edges[k]) + 1 for k in ("em_25", "npc", "wp_3")] == [64, 36, 5]
    samples = _samples(synth)
    assert [p.name for p in samples] == ["rec0000", "rec0001", "rec0002"]
    for d in samples:
        header, rows = _rows(d / "state.csv")
        assert header == list(COLUMNS)
        n = len(rows)
        assert n == int(GEN["seconds"] * FPS)
        for row in rows:
            for col, width in (
                ("camera.K", 4),
                ("camera.pos", 3),
                ("camera.rot", 4),
                ("npc.list.0.pos", 3),
                ("npc.list.0.rot", 4),
                ("monster.list.0.pos", 3),
                ("monster.list.0.rot", 4),
            ):
                _tuple(row[col], width)
        assert {r["npc.list.0.type_id"] for r in rows} == {"0"} and {r["npc.list.0.weapon_id"] for r in rows} == {"3"}
        assert {r["monster.list.0.type_id"] for r in rows} == {"25", "nan"}
        with np.load(d / "skeleton.npz", allow_pickle=False) as z:
            assert sorted(z.files) == ["m1_25", "n1_0", "w1_3"]
            for key, joints in (("m1_25", 64), ("n1_0", 36), ("w1_3", 5)):
                assert z[key].shape == (n, joints, 3) and z[key].dtype == np.float32
        with av.open(str(d / "rgb.mp4")) as c:
            s = c.streams.video[0]
            assert (s.codec_context.name, s.width, s.height) == ("h264", GEN["width"], GEN["height"])
            assert sum(1 for _ in c.decode(video=0)) == n
        assert len(_frames(d / "depth.mkv")) == n


def test_nan_conventions(synth):
    d = _samples(synth)[0]
    _, rows = _rows(d / "state.csv")
    truth = load_truth(synth, PART, d.name)
    mcols = [c for c in COLUMNS if c.startswith("monster.list.0.")]
    absent = [r["monster.list.0.type_id"] == "nan" for r in rows]
    assert np.array_equal(~np.array(absent), truth["monster_present"])
    assert 10 <= sum(absent) <= 40
    for r, a in zip(rows, absent):
        assert all(r[c] == "nan" for c in mcols) if a else all(r[c] != "nan" for c in mcols)
    bad_cam = [r["camera.K"] == "nan" for r in rows]
    assert np.array_equal(~np.array(bad_cam), truth["camera_valid"]) and 1 <= sum(bad_cam) <= 10
    for r, b in zip(rows, bad_cam):
        assert all((r[c] == "nan") == b for c in ("camera.K", "camera.pos", "camera.rot"))
    with np.load(d / "skeleton.npz", allow_pickle=False) as z:
        m = z["m1_25"]
    assert np.isnan(m[np.array(absent)]).all() and np.isfinite(m[~np.array(absent)]).all()


def _entity(synth, d: Path, entity: str):
    """Recorded roots (N, 3), rotations (N, 3, 3), clip names, motion_frame and world joints (N, J, 3)."""
    _, rows = _rows(d / "state.csv")
    p = "npc.list.0." if entity == "hunter" else "monster.list.0."
    truth = load_truth(synth, PART, d.name)
    table = truth["clips"][entity]
    pos = np.array([_tuple(r[p + "pos"], 3) for r in rows])
    R = quat_to_matrix(np.array([_tuple(r[p + "rot"], 4) for r in rows]))
    names, mf = [], []
    for r in rows:
        ok = r[p + "motion_id"] != "nan"
        comp = int(float(r[p + "motion_bank_id"])) * 1000 + int(float(r[p + "motion_id"])) + 1 if ok else 0
        names.append(table[comp]["name"] if ok else None)
        mf.append(int(r[p + "motion_frame"]) if ok else -1)
    with np.load(d / "skeleton.npz", allow_pickle=False) as z:
        X = z["n1_0"].astype(np.float64) if entity == "hunter" else z["m1_25"].astype(np.float64)
        if entity == "hunter":
            X = np.concatenate([X, z["w1_3"].astype(np.float64)], axis=1)
    return pos, R, names, np.array(mf), X, truth


def test_root_rotation_matches_heading_and_stage(synth):
    for d in _samples(synth):
        for entity, rig in (("hunter", "hunter"), ("monster", "drake")):
            pos, R, names, _, X, truth = _entity(synth, d, entity)
            ok = np.isfinite(pos[:, 0])
            fwd = R[ok] @ np.array(load_rig(rig).forward_axis, dtype=np.float64)
            heading = truth["heading"][entity][ok]
            assert np.allclose(fwd[:, 0], np.sin(heading), atol=1e-6) and np.allclose(fwd[:, 2], np.cos(heading), atol=1e-6)
            assert np.allclose(pos[ok], X[ok, 0], atol=1e-4)  # pos is the root (pelvis) joint
            assert np.allclose(pos[ok], truth["root_world"][entity][ok], atol=1e-5)
            assert np.all(np.abs(pos[ok, 0] + 950) < 60) and np.all(np.abs(pos[ok, 2] - 850) < 60)


def _root_frame(X: np.ndarray, pos: np.ndarray, R: np.ndarray) -> np.ndarray:
    return np.einsum("nji,nkj->nki", R, X - pos[:, None])  # p = Rᵀ (X − x_root)


def test_motion_frames_and_speed_signatures(synth):
    seen: dict[tuple[str, str], list] = {}
    for d in _samples(synth):
        for entity in ("hunter", "monster"):
            pos, R, names, mf, X, truth = _entity(synth, d, entity)
            table = {v["name"]: v for v in truth["clips"][entity].values()}
            local = _root_frame(X, pos, R)
            speed = np.linalg.norm(np.diff(local, axis=0), axis=-1) * FPS  # (N-1, J)
            root_speed = np.linalg.norm(np.diff(pos[:, [0, 2]], axis=0), axis=-1) * FPS
            # Segments: runs of one clip; motion_frame +1 per frame, wrapping only in state clips.
            start = 0
            for i in range(1, len(names) + 1):
                if i < len(names) and names[i] == names[start]:
                    continue
                name = names[start]
                if name is not None:
                    c = table[name]
                    seg = mf[start:i]
                    steps = np.diff(seg)
                    wrap = steps != 1
                    assert np.all(seg[wrap.nonzero()[0] + 1] == 0) if wrap.any() else True
                    if c["kind"] == "event":
                        assert not wrap.any() and (start == 0 or names[start - 1] is None or seg[0] == 0)
                    if i < len(names) and names[i] is not None and c["kind"] == "event":
                        assert names[i] != name  # an event never repeats back to back
                    seen.setdefault((entity, name), []).append((start, i, speed, root_speed, wrap.any(), i < len(names)))
                start = i
    attacks_checked = set()
    for (entity, name), segs in seen.items():
        c = {v["name"]: v for v in load_truth(synth, PART, "rec0000")["clips"][entity].values()}[name]
        clip = CLIPS[entity][name]
        # Frames of the segment past the blend from the previous clip (speeds are differences: index i−1 → i).
        body = np.concatenate([sp[a + 1 : b - 1] for a, b, sp, *_ in segs])
        roots = np.concatenate([rs[a + int(BLEND_FRAMES) : b - 1] for a, b, _, rs, *_ in segs])
        if c["class"] == "attack":
            # an attack the recording's end cuts short may stop before its strike
            done = [sp[a : b - 1] for a, b, sp, _, _, complete in segs if complete]
            if done:
                assert np.concatenate(done).max() >= 10.0, (entity, name)
                attacks_checked.add(entity)
        else:
            # a run up the valley's 23° side swings the trailing shin at up to ~6 m/s
            assert body.max() <= 7.0, (entity, name, body.max())
        if c["class"] == "stationary" and len(roots):
            assert roots.max() < 0.2, (entity, name)
        if c["class"] == "locomotion" and len(roots) > 10:
            assert roots.mean() >= 0.6, (entity, name, roots.mean())
        if name.startswith(("sidestep_", "roll_")) and name != "roll_forward":
            assert np.concatenate([rs[a + 2 : b - 4] for a, b, _, rs, *_ in segs]).mean() >= 2.5, name
        if c["class"] == "other" and clip.speed == 0 and len(roots):
            assert roots.max() < 0.2, (entity, name)  # roars, taunts: no root motion
        if c["kind"] == "state" and sum(b - a for a, b, *_ in segs) > 2 * c["length"]:
            assert any(w for *_, w, _ in segs), (entity, name)  # loops visibly wrap
    for entity in ("hunter", "monster"):  # (every class, with its tokens, is checked on a longer play below)
        played = {CLIPS[entity][n].cls for e, n in seen if e == entity}
        assert {"stationary", "locomotion", "attack"} <= played, (entity, played)
    assert attacks_checked == {"hunter", "monster"}  # each entity finished at least one attack


def test_feet_on_ground_and_bridge(synth):
    on_bridge = 0
    for d in _samples(synth):
        for entity, rig, feet, pelvis in (
            ("hunter", "hunter", ("toe_tip_l", "toe_tip_r"), 0.95),
            ("monster", "drake", ("claw_fl", "claw_fr", "claw_hl", "claw_hr"), 1.5),
        ):
            pos, R, names, mf, X, truth = _entity(synth, d, entity)
            src = load_rig(rig).source_joints
            F = X[:, [src.index(f) for f in feet]]
            ok = np.isfinite(pos[:, 0])
            surf = terrain.surface_height(F[..., 0], F[..., 2], (pos[:, 1] - pelvis)[:, None])
            h = F[..., 1] - surf
            assert np.all(h[ok] > -0.05)
            # A foot that stands still in the world, past clip blends, is planted: within 5 cm.
            still = np.linalg.norm(np.diff(F[..., [0, 2]], axis=0), axis=-1) * FPS < 0.1
            clip_change = np.array([names[i] != names[i - 1] for i in range(1, len(names))])
            recent = np.convolve(clip_change, np.ones(int(BLEND_FRAMES) + 1), "full")[: len(clip_change)] > 0
            planted = still & ~recent[:, None] & ok[1:, None]
            assert planted.sum() > 20
            assert np.abs(h[1:][planted]).max() < 0.05
            if entity == "hunter":
                ground, deck = terrain.layers(pos[:, 0], pos[:, 2])
                high = np.isfinite(deck) & (deck - ground > 2.0)
                on_bridge += int(np.sum(high & (np.abs(pos[:, 1] - pelvis - deck) < 0.01)))
    assert on_bridge > 10


def test_terrain_shape():
    x, z = np.meshgrid(np.linspace(-1005, -895, 111), np.linspace(795, 905, 111))
    g = terrain.ground_height(x, z)
    assert g.max() - g.min() > 15.0
    assert terrain.ground_height(-935.0, 864.0) - terrain.ground_height(-935.0, 861.9) > 2.5  # the wall step
    rises = []
    for t in terrain.TERRACES:
        xm = (t.x0 + t.x1) / 2
        # a ledge of a metre or more on the plateau's south side, a ramp that meets the ground at its north edge
        ledge = terrain.ground_height(xm, t.z0 + 0.01) - terrain.ground_height(xm, t.z0 - 0.01)
        assert 1.0 <= ledge <= 2.0, (t, ledge)
        foot = terrain.ground_height(xm, t.z1 - 0.01) - terrain.ground_height(xm, t.z1 + 0.01)
        assert abs(foot) < 0.05, (t, foot)
        zs = np.linspace(t.z_ramp, t.z1 - 0.01, 50)
        slope = np.diff(terrain.terrace_height(np.full(50, xm), zs)) / np.diff(zs)
        assert np.all(slope < 0) and np.all(np.abs(slope) < np.tan(np.radians(25))), t
        assert t.x1 < 0 and t.z0 > 500  # far from the origin
        rises.append(t.rise)
    assert max(rises) >= 1.5 and terrain.near_step(terrain.TERRACES[0].x0, terrain.TERRACES[0].z0 + 3.0)
    ground, deck = terrain.layers(np.array([-980.0]), np.array([848.0]))
    assert 5.0 < deck[0] - ground[0] < 6.0
    assert terrain.surface_height(-980.0, 848.0, deck[0] + 1) == deck[0]
    assert terrain.surface_height(-980.0, 848.0, ground[0] + 1) == ground[0]


def test_determinism(synth, tmp_path):
    """A recording is the same bytes generated alone (in this process, rays cast on every core) and in a pool."""
    generate(tmp_path, **{**GEN, "recordings": 1})
    for name in ("state.csv", "skeleton.npz", "depth.mkv", "rgb.mp4"):
        assert (tmp_path / PART / "rec0000" / name).read_bytes() == (synth / PART / "rec0000" / name).read_bytes()


def test_analytic_motion_matches_recording(synth):
    d = _samples(synth)[0]
    n = int(GEN["seconds"] * FPS)
    sk = world_skeletons_at(synth, PART, d.name, np.arange(n) / FPS)
    with np.load(d / "skeleton.npz", allow_pickle=False) as z:
        assert np.allclose(sk["hunter"], z["n1_0"], atol=1e-3) and np.allclose(sk["weapon"], z["w1_3"], atol=1e-3)
        present = load_truth(synth, PART, d.name)["monster_present"]
        assert np.allclose(sk["monster"][present], z["m1_25"][present], atol=1e-3)
    # A 20 fps view of the 30 fps recording (linear interpolation) stays near the analytic motion.
    t20 = np.arange(int(GEN["seconds"] * 20) - 1) / 20
    a = world_skeletons_at(synth, PART, d.name, t20)["hunter"][:, 0]
    rec = np.stack([np.interp(t20, np.arange(n) / FPS, z) for z in sk["hunter"][:, 0].T], -1)
    assert np.abs(a - rec).max() < 0.05


def test_depth_is_lossless_and_metric(synth):
    d = _samples(synth)[0]
    truth = load_truth(synth, PART, d.name)
    assert truth["depth_encoding"]["kind"] == "inverse_depth_u8"
    codes = _frames(d / "depth.mkv")
    f = 20
    from marionette.synth.cast import rig_edges
    from marionette.synth.game import RIGS
    from marionette.synth.render import Renderer, encode_depth

    rigs = {e: load_rig(r) for e, r in RIGS.items()}
    edges = {e: rig_edges(r) for e, r in rigs.items()}
    radii = {e: np.full(len(edges[e]), r.capsule_radius_m) for e, r in rigs.items()}
    ren = Renderer(GEN["width"], GEN["height"], edges, radii)
    pos, R = truth["camera_pos_world"][f], truth["camera_rot_cw"][f]
    _, z = ren.render(pos, R, {})  # terrain only
    code = encode_depth(z)
    assert codes[f].dtype == np.uint8
    # Where no character is in front, the decoded frame is exactly the terrain-only rendering.
    same = codes[f] == code
    assert same.mean() > 0.8
    # Ground pixels: the analytic terrain along the ray lies within the code's quantisation bin.
    rays = ren.rays(pos, R)
    vs, us = np.nonzero(same & (code > 0))
    rng = np.random.default_rng(0)
    pick = rng.choice(len(vs), size=min(200, len(vs)), replace=False)
    for v, u in zip(vs[pick], us[pick]):
        ray = rays[v, u]
        far_t = decode_depth(code[v, u] - 0.5) * 1.05
        end = pos + z[v, u] * ray
        if terrain.near_step(end[0], end[2], 1.0) or terrain.in_deck(end[0], end[2], 1.0):
            continue
        ts = np.arange(0.1, far_t, 0.02)  # march to the first crossing, then bisect
        q = pos + ts[:, None] * ray
        below = np.nonzero(q[:, 1] <= terrain.ground_height(q[:, 0], q[:, 2]))[0]
        lo, hi = ts[below[0] - 1], ts[below[0]]
        for _ in range(30):
            mid = (lo + hi) / 2
            q = pos + mid * ray
            if q[1] > terrain.ground_height(q[0], q[2]):
                lo = mid
            else:
                hi = mid
        near, far = decode_depth(code[v, u] + 0.5), decode_depth(code[v, u] - 0.5)
        assert near - 0.05 <= lo <= far + 0.05, (v, u, lo, near, far)


# ---------------------------------------------------------------------------------------- the game's play


def test_clip_table_vocabulary():
    for entity, minimum in (("hunter", 80), ("monster", 40)):
        clips = list(CLIPS[entity].values())
        assert len(clips) >= minimum
        assert len({c.composite for c in clips}) == len(clips) and all(c.composite == c.bank * 1000 + c.motion + 1 for c in clips)
        assert all(0.3 * FPS <= c.length <= 3.0 * FPS for c in clips), entity
        assert {c.kind for c in clips} == {"state", "event"}
        for cls in ("stationary", "locomotion", "attack", "other"):
            assert sum(c.cls == cls for c in clips) >= 3, (entity, cls)
        assert all((c.kind == "state") == (c.cls in ("stationary", "locomotion")) for c in clips)


def _pose_sequence(entity: str, clip) -> np.ndarray:
    """Root-frame joints (16, J, 3) of a clip at 16 phases over its length, on flat ground."""
    rig = load_rig("hunter" if entity == "hunter" else "drake")
    phase = np.linspace(0, clip.length, 16, endpoint=False)
    if entity == "hunter":
        J, W = hunter_skeleton(rig, hunter_controls(clip, phase), lambda x, z: np.zeros_like(x) - 0.95)
        return np.concatenate([J, W], 1)
    return monster_skeleton(rig, monster_controls(clip, phase), lambda x, z: np.zeros_like(x) - 1.5)


def test_clips_differ_in_pose():
    for entity in ("hunter", "monster"):
        clips = list(CLIPS[entity].values())
        poses = [_pose_sequence(entity, c) for c in clips]
        for i in range(len(clips)):
            for j in range(i):
                diff = np.abs(poses[i] - poses[j]).max()
                assert diff > 0.05, (entity, clips[i].name, clips[j].name, diff)


def test_play_engages_at_close_range(play):
    stats = play_stats(Corpus(play[1]))
    (sep,) = stats.separation
    assert sep.pair == ("monster", "hunter")
    assert 3.0 <= sep.median_after_approach_m <= 7.0, sep
    assert 3.0 <= sep.median_m <= 7.5, sep
    assert sep.after_approach_frames >= 0.8 * sep.frames  # the approach is short
    for rec in sorted((play[0] / "truth" / PART).glob("*.npz")):
        with np.load(rec, allow_pickle=False) as z:
            d = np.linalg.norm((z["root_world_monster"] - z["root_world_hunter"])[:, [0, 2]], axis=1)
        assert d.min() >= MIN_SEP - 0.05, (rec.name, d.min())


def test_play_vocabulary_and_classes(play):
    """The corpus's vocab (ingest's class rule over the recorded motion) finds the clip table's classes and kinds,
    a few minutes of play use most of the clip table, and every class has at least three tokens."""
    c = Corpus(play[1])
    stats = play_stats(c)
    for key, v in c.vocab["entity_types"].items():
        entity = "hunter" if key.startswith("hunter") else "monster"
        by_id = {clip.composite: clip for clip in CLIPS[entity].values()}
        actions = v["actions"][1:]
        # most of the clip table (the dynamics corpus's 12 minutes of play use 82 of the hunter's 89 clips and 48 of
        # the drake's 49)
        assert len(actions) >= (0.5 if entity == "hunter" else 0.6) * len(by_id), (key, len(actions), len(by_id))
        # a played instance the segment's end cuts short can hide a strike or a wrap; a few such tokens are allowed
        wrong = [
            (by_id[a["composite"]].name, a["class"], a["kind"])
            for a in actions
            if (a["class"], a["kind"]) != (by_id[a["composite"]].cls, by_id[a["composite"]].kind)
        ]
        assert len(wrong) <= 0.1 * len(actions), (key, wrong)
        for cls in ("stationary", "locomotion", "attack", "other"):
            assert sum(a["class"] == cls for a in actions) >= 3, (key, cls)
        assert {a["kind"] for a in actions} == {"state", "event"}
        tokens = stats.tokens[entity]
        assert tokens.vocab == len(actions) and tokens.used == len(actions)
        share = stats.class_share[entity]
        assert all(share.get(cls, 0.0) > 0.05 for cls in ("stationary", "locomotion", "attack", "other")), (entity, share)


def test_bodies_follow_the_terraces(play):
    """The fight goes up the terraces' ramps; there the feet stand on the surface (never below it) and the
    roots rise with it, so a model that kept the ground's height would sink into the ramps."""
    rec_dir, _ = play
    on_terrace = 0
    for d in sorted(p for p in (rec_dir / PART).iterdir() if p.is_dir()):
        for entity, rig, feet, pelvis in (
            ("hunter", "hunter", ("toe_tip_l", "toe_tip_r"), 0.95),
            ("monster", "drake", ("claw_fl", "claw_fr", "claw_hl", "claw_hr"), 1.5),
        ):
            pos, R, names, mf, X, truth = _entity(rec_dir, d, entity)
            ok = np.isfinite(pos[:, 0])
            up = ok & (terrain.terrace_height(pos[:, 0], pos[:, 2]) > 0.3)
            on_terrace += int(up.sum())
            assert np.allclose(pos[up, 1] - pelvis, terrain.ground_height(pos[up, 0], pos[up, 2]), atol=1e-3)
            src = load_rig(rig).source_joints
            F = X[:, [src.index(f) for f in feet]]
            surf = terrain.surface_height(F[..., 0], F[..., 2], (pos[:, 1] - pelvis)[:, None])
            assert np.all((F[..., 1] - surf)[ok] > -0.05), (d.name, entity)
            # bones keep their lengths (slopes tilt the toes, never stretch them)
            parents = load_rig(rig).source_parents
            bones = np.stack([np.linalg.norm(X[ok, c] - X[ok, p], axis=-1) for c, p in enumerate(parents) if p >= 0], 1)
            assert (bones.std(0) / bones.mean(0)).max() < 0.01, (d.name, entity)
    assert on_terrace > 200


def test_skins_and_camera_pans_change_only_what_they_say(tmp_path):
    """``skins``: each recording's monster and player in colours of their own (drawn by seed and index); ``camera_pans``:
    the player looks around, so the bodies leave the view and come back. The play itself is the game's."""
    from marionette.synth.cast import draw_skin
    from marionette.synth.render import camera_pans

    short = {**GEN, "recordings": 2, "seconds": 4.0}
    generate(tmp_path / "plain", **short)
    generate(tmp_path / "skins", **short, skins=True)
    generate(tmp_path / "pans", **{**short, "recordings": 1}, camera_pans=True)  # the first recording is compared
    assert draw_skin(2, 0) != draw_skin(2, 1) and draw_skin(2, 0) == draw_skin(2, 0)
    for k in range(2):
        assert load_truth(tmp_path / "skins", PART, f"rec{k:04d}")["role"]["skin"] == draw_skin(GEN["seed"], k).to_json()
        assert "skin" not in load_truth(tmp_path / "plain", PART, f"rec{k:04d}")["role"]
    plain, skins, pans = (_samples(tmp_path / d)[0] for d in ("plain", "skins", "pans"))
    assert (plain / "state.csv").read_bytes() == (skins / "state.csv").read_bytes()  # the same play and cameras
    # a skin changes the characters' pixels only: most of the frame is the same
    a, b = _rgb(plain / "rgb.mp4")[0], _rgb(skins / "rgb.mp4")[0]
    changed = np.abs(a.astype(int) - b.astype(int)).max(-1) > 24
    assert 0 < changed.mean() < 0.2
    # panning turns the whole view away and back: frames differ most where the pan is largest, not before it starts
    pan = camera_pans(GEN["seed"], 0, len(_rgb(plain / "rgb.mp4")), FPS)
    assert np.radians(119) < np.abs(pan).max() <= np.pi and pan[0] == 0.0
    p = _rgb(pans / "rgb.mp4")
    plain_frames = _rgb(plain / "rgb.mp4")
    diff = [float(np.abs(x.astype(int) - y.astype(int)).mean()) for x, y in zip(p, plain_frames)]
    assert diff[0] < 1.0 and diff[int(np.argmax(np.abs(pan)))] > 10 * max(diff[0], 0.1)


def _rgb(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
