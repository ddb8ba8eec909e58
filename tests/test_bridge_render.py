"""The bridge's rasterizer and G-buffer codec: exact geometry, occlusion, culling, the lossless round
trip, far-from-origin scenes, degenerate rotations and empty scenes."""

import numpy as np
import pytest

from marionette.bridge.camera import Cameras, intrinsics_for, look_at
from marionette.bridge.gbuffer import BACKGROUND_ID, GBufferMeta, decode_codes, decode_gbuffer, to_codes, write_gbuffer
from marionette.bridge.kinematics import bone_segments, world_skeletons
from marionette.bridge.render import Rasterizer
from marionette.geometry import world_to_state, yaw_quat
from marionette.schema import load_scene

W, H = 256, 144
RANGE = dict(h_min=-10.0, h_max=30.0, z_near=0.3, z_far=120.0)


def camera(eye, target, origin=(0.0, 0.0, 0.0)) -> Cameras:
    o = np.asarray(origin, np.float64)
    eye, target = np.asarray(eye, np.float64) + o, np.asarray(target, np.float64) + o
    return Cameras(intrinsics_for(W, H)[None], eye[None], look_at(eye, target)[None], np.array([True]), W, H)


def grid(x0, x1, z0, z1, y, step=2.0, origin=(0.0, 0.0, 0.0)):
    """A flat horizontal mesh at height y over [x0, x1] × [z0, z1]."""
    xs, zs = np.arange(x0, x1 + 1e-9, step), np.arange(z0, z1 + 1e-9, step)
    X, Z = np.meshgrid(xs, zs)
    V = np.stack([X.ravel(), np.full(X.size, y), Z.ravel()], -1) + np.asarray(origin)
    i = np.arange(X.size).reshape(X.shape)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return V, F


def wall(x0, x1, y0, y1, z, origin=(0.0, 0.0, 0.0)):
    """A vertical rectangle in the plane z = const."""
    V = np.array([[x0, y0, z], [x1, y0, z], [x0, y1, z], [x1, y1, z]], np.float64) + np.asarray(origin)
    return V, np.array([[0, 1, 2], [1, 3, 2]])


def ball(p, r=0.25, ident=200.0):
    p = np.asarray(p, np.float64)[None]
    return p, p + [0.0, 1e-4, 0.0], np.array([r]), np.array([ident])


@pytest.fixture(scope="module")
def rast():
    with Rasterizer(W, H) as r:
        yield r


def ids_of(img):
    return np.rint(img[..., 1] * 255).astype(int)


def centroid(mask):
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean() + 0.5, ys.mean() + 0.5])


def test_a_bone_lands_on_its_projected_pixel(rast):
    cam = camera([0.0, 4.0, 12.0], [0.0, 0.0, 0.0])
    rast.set_terrain(*grid(-40, 40, -40, 40, 0.0))
    for p in ([0.0, 1.0, 0.0], [3.0, 2.0, -5.0], [-6.0, 0.5, 4.0]):
        img = rast.render(cam, 0, ball(p), **RANGE)
        mask = ids_of(img) == 200
        assert mask.sum() >= 10
        uv, _ = cam.project(np.array([p]), 0)
        assert np.abs(centroid(mask) - uv[0]).max() < 1.0, (centroid(mask), uv)


def test_a_plane_at_known_depth_decodes_to_it(rast, tmp_path):
    cam = camera([0.0, 0.0, 0.0], [0.0, 0.0, -1.0])
    rng = dict(h_min=-60.0, h_max=60.0, z_near=0.3, z_far=120.0)  # the plane's rows span ±52 m of height at 90 m
    meta = GBufferMeta(width=W, height=H, fps=30.0, **rng)
    for d in (5.0, 37.3, 90.0):
        rast.set_terrain(*wall(-200, 200, -200, 200, -d))
        img = rast.render(cam, 0, ball([0, 0, 1e3]), **rng)  # the bone is behind the camera: not drawn
        write_gbuffer(tmp_path / "plane.mkv", [img], meta)
        frames, meta2 = decode_gbuffer(tmp_path / "plane.mkv")
        f = frames[0]
        assert meta2 == meta and (f.id == 0).all()  # terrain everywhere
        assert np.abs(f.depth - d).max() <= meta.depth_bound(), (d, np.abs(f.depth - d).max(), meta.depth_bound())
        # heights of the plane's points: y = depth-scaled pixel ray height
        v = np.arange(H) + 0.5
        y = -(v - H / 2) / cam.K[0, 1] * d
        assert np.abs(f.height - y[:, None]).max() <= meta.height_bound() + 1e-9


def test_occlusion_and_near_terrain_culling(rast):
    cam = camera([0.0, 1.0, 10.0], [0.0, 1.0, 0.0])
    target = ball([0.0, 1.0, 0.0], r=0.4)
    rast.set_terrain(*wall(-5, 5, -5, 5, 5.0))  # 5 m in front of the camera, between it and the bone
    assert not (ids_of(rast.render(cam, 0, target, **RANGE)) == 200).any()  # hidden
    rast.set_terrain(*wall(-5, 5, -5, 5, 8.0))  # 2 m from the camera: culled, the bone shows
    img = rast.render(cam, 0, target, **RANGE)
    assert (ids_of(img) == 200).sum() > 50
    assert (img.sum(-1) == 0).sum() == (ids_of(img) != 200).sum()  # the wall drew nothing
    # a bone within 3 m is never culled
    near = rast.render(cam, 0, ball([0.0, 1.0, 8.5], r=0.2), **RANGE)
    assert (ids_of(near) == 200).sum() > 50


def traced_capsules(cam: Cameras, bones) -> tuple[np.ndarray, np.ndarray]:
    """The id (−1: none) and view depth (m) each pixel's ray meets first among capsules wholly in front of the camera,
    in float64: the entry into the nearer ball or the cylinder's side between them."""
    K, R, o = cam.K[0], cam.rot[0], cam.pos[0]
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(u - K[2]) / K[0], -(v - K[3]) / K[1], -np.ones_like(u)], -1) @ R.T  # world rays, camera at o
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    best, ids = np.full((H, W), np.inf), np.full((H, W), -1)
    for a, b, r, ident in zip(*bones):
        a, b = np.asarray(a) - o, np.asarray(b) - o
        hits = []
        for c in (a, b):
            h = d @ c
            disc = h * h - (c @ c - r * r)
            hits.append(np.where(disc >= 0, h - np.sqrt(np.maximum(disc, 0)), np.inf))
        n = (b - a) / np.linalg.norm(b - a)
        dn, an = d @ n, -(a @ n)
        dp, ap = d - dn[..., None] * n, -a - an * n
        qa, qb, qc = np.sum(dp * dp, -1), dp @ ap, ap @ ap - r * r
        disc = qb * qb - qa * qc
        t = (-qb - np.sqrt(np.maximum(disc, 0))) / qa
        s = an + t * dn
        hits.append(np.where((disc >= 0) & (s >= 0) & (s <= np.linalg.norm(b - a)), t, np.inf))
        t = np.minimum.reduce(hits)
        nearer = t < best
        best[nearer], ids[nearer] = t[nearer], int(ident)
    depth = best * -(d @ R[:, 2])  # along the optical axis, the camera looking down its −Z
    return ids, depth


def test_capsules_are_traced_exactly(rast):
    """Every pixel of a bone is the capsule the pixel's ray meets first (ids and depths against a float64 trace of the
    same rays), silhouettes included; a camera inside a capsule sees its inside."""
    rng = np.random.default_rng(3)
    cam = camera([0.0, 2.0, 9.0], [0.0, 1.0, 0.0])
    rast.set_terrain(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    meta = GBufferMeta(width=W, height=H, fps=30.0, **RANGE)
    drawn = wrong = 0
    for _ in range(12):
        a = rng.normal(size=(30, 3)) * [1.5, 0.6, 1.5] + [0.0, 1.2, 0.0]
        bones = (a, a + rng.normal(size=(30, 3)) * 0.4, rng.uniform(0.03, 0.3, 30), rng.integers(100, 250, 30).astype(float))
        f = decode_codes(to_codes(rast.render(cam, 0, bones, **RANGE)), meta)
        want, depth = traced_capsules(cam, bones)
        covered = (want >= 0) | (f.id >= 0)
        drawn, wrong = drawn + int(covered.sum()), wrong + int((f.id != want).sum())
        for y, x in np.argwhere(f.id != want):  # only where the ray grazes a silhouette: a neighbour holds another id
            patch = want[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2]
            assert (patch != want[y, x]).any(), (y, x)
        same = (f.id == want) & (want >= 0)
        assert np.abs(f.depth[same] - depth[same]).max() <= meta.depth_bound() + 1e-4
    assert drawn > 10_000 and wrong <= drawn * 2e-3, (drawn, wrong)
    through = (np.array([[0.0, 2.0, 8.9]]), np.array([[0.0, 2.0, 7.0]]), np.array([0.5]), np.array([200.0]))
    inside = ids_of(rast.render(cam, 0, through, **RANGE))
    assert (inside == 200).all()  # the camera is inside the capsule: its inside fills the view


def test_a_point_bone_is_its_ball_and_a_bone_seen_end_on_is_its_near_ball(rast):
    """Degenerate capsules: a bone of zero length (no cylinder) is its ball, pixel for pixel against a float64 trace;
    a bone whose axis is the central ray (the cylinder's quadratic vanishes there) shows its near ball's front."""
    cam = camera([0.0, 2.0, 9.0], [0.0, 2.0, 0.0])
    rast.set_terrain(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    meta = GBufferMeta(width=W, height=H, fps=30.0, **RANGE)
    K, R, o = cam.K[0], cam.rot[0], cam.pos[0]
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(u - K[2]) / K[0], -(v - K[3]) / K[1], -np.ones_like(u)], -1) @ R.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)

    c, r = np.array([0.4, 2.3, 4.0]), 0.5
    f = decode_codes(to_codes(rast.render(cam, 0, (c[None], c[None].copy(), np.array([r]), np.array([200.0])), **RANGE)), meta)
    h = d @ (c - o)
    disc = h * h - ((c - o) @ (c - o) - r * r)
    want = disc >= 0
    depth = (h - np.sqrt(np.maximum(disc, 0))) * -(d @ R[:, 2])
    got = f.id == 200
    assert want.sum() > 300 and (got == want).mean() > 0.995
    for y, x in np.argwhere(got != want):  # only at the silhouette
        assert (
            want[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].any()
            and not want[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].all()
        )
    assert np.abs(f.depth[got & want] - depth[got & want]).max() <= meta.depth_bound() + 1e-4

    a, b = np.array([[0.0, 2.0, 5.0]]), np.array([[0.0, 2.0, 3.0]])  # end-on: a 4 m from the camera, b behind it
    f = decode_codes(to_codes(rast.render(cam, 0, (a, b, np.array([0.3]), np.array([150.0])), **RANGE)), meta)
    centre = (slice(H // 2 - 2, H // 2 + 2), slice(W // 2 - 2, W // 2 + 2))
    assert (f.id[centre] == 150).all()
    assert np.abs(f.depth[centre] - 3.7).max() <= meta.depth_bound() + 0.01  # a's front, 4 m − r, near the centre


@pytest.mark.parametrize("suffix", [".gbz", ".mkv"])
def test_codec_round_trip(rast, tmp_path, suffix):
    layout = load_scene("duel")
    skel = standing_pair(layout, origin=(-950.0, 30.0, 850.0))
    cam = camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0], origin=(-950.0, 30.0, 850.0))
    rast.set_terrain(*grid(-30, 30, -30, 30, 0.0, origin=(-950.0, 30.0, 850.0)))
    rng = dict(h_min=20.0, h_max=45.0, z_near=0.3, z_far=120.0)
    frames = [rast.render(cam, 0, bone_segments(layout, skel, i), **rng) for i in range(len(skel))]
    meta = GBufferMeta(width=W, height=H, fps=30.0, **rng)
    assert write_gbuffer(tmp_path / f"pose{suffix}", frames, meta) == len(frames)
    decoded, back = decode_gbuffer(tmp_path / f"pose{suffix}")
    assert back == meta
    assert len(decoded) == len(frames)
    for img, f in zip(frames, decoded):
        want_ids = np.where(img.sum(-1) > 0, ids_of(img), BACKGROUND_ID)
        covered = want_ids != BACKGROUND_ID
        assert covered.mean() > 0.3 and (want_ids >= 195).sum() > 50 and (want_ids >= 105).sum() > 200
        assert (f.id[covered] == want_ids[covered]).mean() >= 0.999
        assert (f.id[~covered] == BACKGROUND_ID).all()
        exact = decode_codes(to_codes(img), meta)  # the file is lossless: same as decoding the codes directly
        np.testing.assert_array_equal(f.id, exact.id)
        np.testing.assert_array_equal(np.nan_to_num(f.depth, nan=-1), np.nan_to_num(exact.depth, nan=-1))
        terrain = f.id == 0
        assert np.abs(f.height[terrain] - 30.0).max() <= meta.height_bound()  # the ground is flat at y = 30
        bones = f.id > 0
        assert np.all((f.height[bones] > 30.0 - meta.height_bound(False)) & (f.height[bones] < 34.0))


@pytest.mark.parametrize("suffix", [".gbz", ".mkv"])
def test_overlapped_encoding_writes_the_serial_bytes_and_raises_either_sides_error(tmp_path, suffix):
    """The encoder thread (``write_gbuffer(overlap=True)``, the default from 72 × 128 pixels up) writes the bytes of
    the serial loop; a bad frame fails naming it, and an error while producing frames reaches the caller; neither
    leaves a file."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 1024, (3, H, W), dtype=np.uint16) for _ in range(12)]
    meta = GBufferMeta(width=W, height=H, fps=30.0, h_min=0.0, h_max=10.0, z_near=0.3, z_far=100.0)
    assert write_gbuffer(tmp_path / f"a{suffix}", iter(frames), meta, overlap=True) == 12
    assert write_gbuffer(tmp_path / f"b{suffix}", iter(frames), meta, overlap=False) == 12
    assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()
    bad = frames[:5] + [np.zeros((3, H + 1, W), np.uint16)] + frames[5:]
    with pytest.raises(ValueError, match="frame 5"):
        write_gbuffer(tmp_path / f"bad{suffix}", iter(bad), meta, overlap=True)

    def broken():
        yield from frames[:3]
        raise RuntimeError("the renderer stopped")

    with pytest.raises(RuntimeError, match="renderer stopped"):
        write_gbuffer(tmp_path / f"broken{suffix}", broken(), meta, overlap=True)
    assert not (tmp_path / f"bad{suffix}").exists() and not (tmp_path / f"broken{suffix}").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"a{suffix}", f"b{suffix}"]  # no temp file left


def test_decoding_rejects_other_files(tmp_path):
    import av

    p = tmp_path / "plain.mkv"
    with av.open(str(p), "w", format="matroska") as c:
        s = c.add_stream("ffv1", rate=30)
        s.width, s.height, s.pix_fmt = 16, 16, "gbrp10le"
        for pk in s.encode(av.VideoFrame.from_ndarray(np.zeros((16, 16, 3), np.uint16), format="gbrp10le")):
            c.mux(pk)
        for pk in s.encode():
            c.mux(pk)
    with pytest.raises(ValueError, match="plain.mkv: no MARIONETTE_GBUFFER"):
        decode_gbuffer(p)
    (tmp_path / "junk.mkv").write_bytes(b"not a video")
    with pytest.raises(ValueError, match="junk.mkv"):
        decode_gbuffer(tmp_path / "junk.mkv")


def standing_pair(layout, origin, n=3, rot6d=None):
    """Skeletons of a drake and a hunter standing 4 m apart on flat ground at ``origin`` (n frames)."""
    o = np.asarray(origin, np.float64)
    joints, rots = {}, {}
    for e, x0 in zip(layout.articulated, (-2.5, 2.0)):
        K = e.rig.n_keep
        rng = np.random.default_rng(len(e.name))
        local = np.zeros((K, 3))
        local[0] = [0, 1.0 if e.name == "hunter" else 1.5, 0]
        for c, p in e.rig.bones:  # each child 0.25 m from its parent, spreading out and down
            d = rng.normal(size=3)
            d[1] = -abs(d[1]) * 0.5
            local[c] = local[p] + 0.25 * d / np.linalg.norm(d)
        local[:, 1] = np.maximum(local[:, 1], 0.05)
        J = np.repeat((local + o + [x0, 0.0, 0.0])[None], n, 0)
        J[:, :, 0] += np.arange(n)[:, None] * 0.05
        joints[e.name] = J
        rots[e.name] = np.repeat(yaw_quat(np.array([0.3]))[None, 0], n, 0)
    hunter = joints["hunter"]
    joints["weapon"] = hunter[:, [1, 2]] + [0.0, 0.3, 0.0]
    state = world_to_state(layout, joints, rots)
    if rot6d is not None:
        state[:, layout.slice("hunter.rot6d")] = rot6d
    anchors = {e.name: joints[e.name][0, 0] for e in layout.articulated}
    valid = {e.name: np.ones(n, bool) for e in layout.articulated}
    return world_skeletons(layout, state, anchors, valid, np.arange(n) / 30.0)


def test_far_from_the_origin_renders_like_the_origin(rast):
    layout = load_scene("duel")
    masks = []
    for origin in ((0.0, 0.0, 0.0), (1e5, 0.0, -1e5), (-1e5, 12.0, 1e5)):
        skel = standing_pair(layout, origin)
        cam = camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0], origin=origin)
        rast.set_terrain(*grid(-30, 30, -30, 30, 0.0, origin=origin))
        oy = origin[1]
        img = rast.render(cam, 0, bone_segments(layout, skel, 0), h_min=oy - 10, h_max=oy + 30, z_near=0.3, z_far=120.0)
        masks.append(ids_of(img))
    for m in masks[1:]:
        for ident in (195, 105):
            a, b = masks[0] >= ident, m >= ident
            assert np.abs(centroid(a) - centroid(b)).max() < 1.0
            assert (a & b).sum() / (a | b).sum() > 0.97
        assert (masks[0] == m).mean() > 0.995


def test_a_frame_draws_the_terrain_it_may_see_and_the_whole_meshs_pixels(rast, monkeypatch):
    """A stage far larger than the view (1.2 km square of rolling ground, 4 km from the origin at negative x): each
    frame draws a small part of its triangles, and its codes are those of the whole mesh drawn as one piece."""
    import marionette.bridge.render as render

    origin = np.array([-4000.0, 0.0, 2500.0])
    V, F = grid(-600, 600, -600, 600, 0.0, step=4.0, origin=origin)
    V[:, 1] = 5.0 * np.sin(V[:, 0] / 37.0) + 3.0 * np.cos(V[:, 2] / 23.0)
    monkeypatch.setattr(render, "TERRAIN_TILE_M", 1e7)  # one tile: the whole stage, drawn whenever any of it is seen
    with Rasterizer(W, H) as whole:
        whole.set_terrain(V, F)
        monkeypatch.undo()
        rast.set_terrain(V, F)
        views = [  # eye, target (relative to the origin)
            ([0.0, 8.0, 0.0], [40.0, 0.0, -30.0]),  # across the ground, the horizon beyond z_far
            ([100.0, 60.0, 100.0], [100.0, 0.0, 90.0]),  # looking down
            ([-700.0, 20.0, 0.0], [-800.0, 20.0, 0.0]),  # off the stage, looking away from it: nothing to draw
            ([590.0, 4.0, 590.0], [0.0, 0.0, 0.0]),  # from a corner across the stage
        ]
        for eye, target in views:
            cam = camera(eye, target, origin=origin)
            bones = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
            got, want = rast.render_packed(cam, 0, bones, **RANGE), whole.render_packed(cam, 0, bones, **RANGE)
            np.testing.assert_array_equal(got, want)
            drawn = sum(n for _, n in rast.terrain_ranges(cam, 0, RANGE["z_near"], RANGE["z_far"], render.TERRAIN_CULL_M))
            assert drawn <= 0.1 * F.size, (eye, drawn, F.size)
            if eye[0] == -700.0:
                assert drawn == 0 and not got.any()
            else:
                assert (got != 0).mean() > 0.3  # the ground fills much of the view


@pytest.mark.parametrize(
    "d6", [np.zeros(6), np.array([1.0, 0, 0, 2.0, 0, 0]), np.array([1e8, 0, 0, 0, 1e8, 0]), np.array([np.nan, 0, 0, 0, 1, 0])]
)
def test_degenerate_rotations_never_give_nan_pixels(rast, d6):
    layout = load_scene("duel")
    if not np.isfinite(d6).all():
        with pytest.raises(ValueError, match="not finite"):
            standing_pair(layout, (0.0, 0.0, 0.0), rot6d=d6)
        return
    skel = standing_pair(layout, (0.0, 0.0, 0.0), rot6d=d6)
    R = skel.rot["hunter"]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    cam = camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0])
    rast.set_terrain(*grid(-30, 30, -30, 30, 0.0))
    img = rast.render(cam, 0, bone_segments(layout, skel, 0), **RANGE)
    assert np.isfinite(img).all() and (ids_of(img) >= 195).sum() > 20


def test_an_empty_scene_renders_terrain_only(rast):
    layout = load_scene("duel")
    skel = standing_pair(layout, (0.0, 0.0, 0.0))
    for e in layout.entities:
        skel.valid[e.name][:] = False
    a, b, r, ids = bone_segments(layout, skel, 0)
    assert len(a) == 0
    rast.set_terrain(*grid(-30, 30, -30, 30, 0.0))
    img = rast.render(camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0]), 0, (a, b, r, ids), **RANGE)
    assert (img[..., 1] == 0).all() and (img[..., 0] >= 0.5).mean() > 0.3
    rast.set_terrain(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert (rast.render(camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0]), 0, (a, b, r, ids), **RANGE) == 0).all()


def test_resampling_keeps_bone_lengths_and_source_frames():
    layout = load_scene("duel")
    n = 21
    base = standing_pair(layout, (5.0, 0.0, -3.0), n=n)
    yaw = np.linspace(0.0, 2.5, n)  # the drake turns 143° over a second
    from marionette.geometry import quat_to_matrix, to_local, to_world

    joints, rots = {}, {}
    for e in layout.articulated:
        J = base.joints[e.name]
        local = to_local(J, J[:, 0], base.rot[e.name])
        R = quat_to_matrix(yaw_quat(yaw if e.name == "monster" else np.zeros(n)))
        joints[e.name] = to_world(local, J[:, 0], R)
        rots[e.name] = yaw_quat(yaw if e.name == "monster" else np.zeros(n))
    joints["weapon"] = base.joints["weapon"]
    state = world_to_state(layout, joints, rots)
    anchors = {e.name: joints[e.name][0, 0] for e in layout.articulated}
    valid = {e.name: np.ones(n, bool) for e in layout.articulated}
    valid["hunter"][10] = False
    t20 = np.arange(n) / 20.0
    t30 = np.arange(31) / 30.0
    src = world_skeletons(layout, state, anchors, valid, t20)
    out = world_skeletons(layout, state, anchors, valid, t20, t30)
    m = layout.entity("monster")
    bones = np.array(m.rig.bones)
    length = lambda J: np.linalg.norm(J[:, bones[:, 0]] - J[:, bones[:, 1]], axis=-1)  # noqa: E731
    np.testing.assert_allclose(
        length(out.joints["monster"]), np.broadcast_to(length(src.joints["monster"])[:1], (31, len(bones))), atol=1e-5
    )
    # output times that fall on source frames give the source skeleton
    np.testing.assert_allclose(out.joints["monster"][::3], src.joints["monster"][::2], atol=1e-9)
    # the hunter is invalid at 0.5 s (source row 10): the output frames around it are too
    assert not out.valid["hunter"][15] and not out.valid["hunter"][14] and not out.valid["hunter"][16] and out.valid["hunter"][13]
    assert out.valid["weapon"].tolist() == out.valid["hunter"].tolist()


def test_follow_camera_is_causal_and_frames_the_pair():
    from marionette.bridge.camera import follow_cameras

    n = 90
    t = np.arange(n) / 30.0
    a = np.stack([np.cos(t), np.zeros(n), np.sin(t)], -1) * 10 + [1e5, 20.0, -1e5]
    b = a + np.stack([8 * np.ones(n), np.zeros(n), 4 * np.sin(3 * t)], -1)
    fwd = np.tile([0.0, 0.0, 1.0], (n, 1))
    ok = np.ones(n, bool)
    full = follow_cameras([a, b], fwd, [ok, ok], 30.0, W, H)
    for k in (1, 30, 60):
        part = follow_cameras([a[:k], b[:k]], fwd[:k], [ok[:k], ok[:k]], 30.0, W, H)
        np.testing.assert_array_equal(part.pos, full.pos[:k])  # no future frame changes the past
        np.testing.assert_array_equal(part.rot, full.rot[:k])
    R = full.rot
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    for i in range(n):
        uv, depth = full.project(np.stack([a[i], b[i]]), i)
        assert np.all(depth > 0) and np.all((uv >= 0) & (uv <= [W, H])), (i, uv)  # both roots in view


def test_follow_camera_keeps_a_player_running_toward_it_in_frame():
    from marionette.bridge.camera import follow_cameras

    # the player backs away from the other at 4.5 m/s (the synthetic hunter's top speed), straight at the camera:
    # plain smoothing, lagging v·τ = 1.8 m behind the wanted eye, came within 2.8 m and cut it off in 94 of 120 frames
    n = 120
    t = np.arange(n) / 30.0
    a = np.stack([-4.5 * t, np.zeros(n), np.zeros(n)], -1) + [1e5, 20.0, -1e5]
    b = a + [5.0, 0.0, 0.0]
    ok = np.ones(n, bool)
    cams = follow_cameras([a, b], np.tile([1.0, 0.0, 0.0], (n, 1)), [ok, ok], 30.0, W, H)
    for i in range(n):
        feet_head = np.stack([a[i] - [0.0, 0.95, 0.0], a[i] + [0.0, 0.85, 0.0], b[i]])
        uv, depth = cams.project(feet_head, i)
        assert np.all(depth > 0) and np.all((uv >= 0) & (uv <= [W, H])), (i, uv)
        np.testing.assert_allclose(np.linalg.norm((cams.pos[i] - a[i])[[0, 2]]), 4.5, atol=1e-9)  # 9.5 m − 5 m


def test_the_follow_camera_rides_behind_the_player():
    from dataclasses import replace

    from marionette.bridge.targets import followed_entities

    assert [e.name for e in followed_entities(load_scene("duel"))] == ["hunter", "monster"]
    assert [e.name for e in followed_entities(load_scene("two_hunters"))] == ["hunter1", "monster", "hunter2"]
    assert [e.name for e in followed_entities(load_scene("hunter_solo"))] == ["hunter"]
    duel = load_scene("duel")
    no_player = replace(duel, entities=tuple(replace(e, rig=replace(e.rig, edges_key="em_25")) for e in duel.entities))
    assert [e.name for e in followed_entities(no_player)] == ["monster", "hunter"]  # none: the first articulated


def test_follow_camera_seeded_from_a_start_camera():
    from marionette.bridge.camera import FOLLOW_TAU_S, follow_cameras

    n, fps = 240, 30.0
    t = np.arange(n) / fps
    a = np.stack([np.cos(t), np.zeros(n), np.sin(t)], -1) * 10 + [1e5, 20.0, -1e5]
    b = a + np.stack([8 * np.ones(n), np.zeros(n), 4 * np.sin(3 * t)], -1)
    fwd = np.tile([0.0, 0.0, 1.0], (n, 1))
    ok = np.ones(n, bool)
    plain = follow_cameras([a, b], fwd, [ok, ok], fps, W, H)
    # unseeded: the docstring's closed form, frame by frame
    d = (b - a) * [1.0, 0.0, 1.0]
    s = np.linalg.norm(d, axis=-1)
    f = d / s[:, None]
    D = np.maximum(3.5, 9.5 - s)
    eye_w = a - D[:, None] * f + np.outer(0.2 * D + 0.8, [0.0, 1.0, 0.0])
    tgt_w = a + np.minimum(s / 2, 3.0)[:, None] * f + [0.0, 0.25, 0.0]
    alpha = 1 - np.exp(-1 / (fps * FOLLOW_TAU_S))
    e, g = eye_w[0], tgt_w[0]
    for i in range(n):
        if i:
            m = (a[i] - a[i - 1]) * [1.0, 0.0, 1.0]  # the camera rides with A's horizontal motion
            e, g = e + m, g + m
            e, g = e + alpha * (eye_w[i] - e), g + alpha * (tgt_w[i] - g)
        np.testing.assert_allclose(plain.pos[i], e, rtol=0, atol=1e-9)
        np.testing.assert_allclose(plain.rot[i], look_at(e, g), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(plain.K, np.tile(intrinsics_for(W, H), (n, 1)))
    # seeded from a rolled, zoomed camera elsewhere: frame 0 is that camera, then it eases to the plain one
    roll = np.array([[np.cos(0.2), -np.sin(0.2), 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.0, 0.0, 1.0]])
    R0 = look_at(a[0] + [-3.0, 4.0, -9.0], a[0]) @ roll
    K0 = np.array([180.0, 180.0, 120.0, 70.0])
    start = Cameras(K0[None], (a[0] + [-3.0, 4.0, -9.0])[None], R0[None], np.ones(1, bool), W, H)
    seeded = follow_cameras([a, b], fwd, [ok, ok], fps, W, H, start=start)
    np.testing.assert_allclose(seeded.pos[0], start.pos[0], atol=1e-12)
    np.testing.assert_allclose(seeded.rot[0], R0, atol=1e-12)
    np.testing.assert_allclose(seeded.K[0], K0, atol=1e-12)
    R = seeded.rot
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    gap = np.linalg.norm(seeded.pos - plain.pos, axis=-1)
    assert gap[0] > 1.0 and np.all(np.diff(gap[:60]) < 0) and gap[-1] < 1e-4 * gap[0]
    np.testing.assert_allclose(seeded.rot[-1], plain.rot[-1], atol=1e-4)
    np.testing.assert_allclose(seeded.K[-1], plain.K[-1], atol=1e-4)
    for k in (1, 30):  # still causal
        part = follow_cameras([a[:k], b[:k]], fwd[:k], [ok[:k], ok[:k]], fps, W, H, start=start)
        np.testing.assert_array_equal(part.pos, seeded.pos[:k])
        np.testing.assert_array_equal(part.rot, seeded.rot[:k])
    with pytest.raises(ValueError, match="start camera"):
        follow_cameras([a, b], fwd, [ok, ok], fps, W + 2, H, start=start)


def test_the_code_planes_are_the_float_path_and_either_file_gives_them_back(rast, tmp_path):
    from marionette.bridge.gbuffer import iter_codes, iter_planes

    layout = load_scene("duel")
    skel = standing_pair(layout, (0.0, 0.0, 0.0))
    cam = camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0])
    rast.set_terrain(*grid(-30, 30, -30, 30, 0.0))
    bones = bone_segments(layout, skel, 0)
    codes = to_codes(rast.render(cam, 0, bones, **RANGE))
    planes = rast.render_planes(cam, 0, bones, **RANGE)
    np.testing.assert_array_equal(planes, codes.transpose(2, 0, 1)[[1, 2, 0]])
    meta = GBufferMeta(width=W, height=H, fps=30.0, **RANGE)
    for suffix in (".gbz", ".mkv"):
        write_gbuffer(tmp_path / f"a{suffix}", [planes], meta)
        write_gbuffer(tmp_path / f"b{suffix}", [codes], meta)
        assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()
        np.testing.assert_array_equal(next(iter_codes(tmp_path / f"a{suffix}")), codes)
        np.testing.assert_array_equal(next(iter_planes((tmp_path / f"a{suffix}").read_bytes())), planes)
    with pytest.raises(ValueError, match="out.mp4: a G-buffer file is .gbz"):
        write_gbuffer(tmp_path / "out.mp4", [planes], meta)


def test_bone_capsules_are_every_frames_bone_segments():
    from marionette.bridge.kinematics import bone_capsules

    layout = load_scene("duel")
    skel = standing_pair(layout, (-950.0, 30.0, 850.0), n=5)
    skel.valid["hunter"][1] = False
    skel.joints["monster"][3, 2] = np.nan  # a frame whose skeleton cannot be drawn
    got = list(bone_capsules(layout, skel))
    assert len(got) == 5
    for i, frame in enumerate(got):
        for x, y in zip(frame, bone_segments(layout, skel, i)):
            np.testing.assert_array_equal(x, y)
    assert len(got[1][0]) < len(got[0][0]) and len(got[3][0]) < len(got[0][0])


def test_two_rasterizers_in_one_thread_draw_into_their_own_targets(rast):
    """A pose pass keeps one rasterizer per chunk size in its thread: a second context made and drawn with between two
    frames of the first leaves the first's frames as they were."""
    rast.set_terrain(*grid(-30, 30, -30, 30, 0.0))
    cam, bones = camera([0.0, 3.0, 9.0], [0.0, 1.0, 0.0]), ball([0.0, 1.0, 0.0], 0.5)
    first = rast.render_packed(cam, 0, bones, **RANGE)
    eye, target = np.array([0.0, 3.0, 9.0]), np.array([0.0, 1.0, 0.0])
    big = Cameras(intrinsics_for(2 * W, 2 * H)[None], eye[None], look_at(eye, target)[None], np.array([True]), 2 * W, 2 * H)
    with Rasterizer(2 * W, 2 * H) as other:
        other.set_terrain(*grid(-30, 30, -30, 30, 5.0))
        theirs = other.render_packed(big, 0, bones, **RANGE)
        assert np.array_equal(rast.render_packed(cam, 0, bones, **RANGE), first)
    assert theirs.shape == (2 * H, 2 * W) and np.count_nonzero(first) and not np.array_equal(theirs[::2, ::2], first)
    assert np.array_equal(rast.render_packed(cam, 0, bones, **RANGE), first)  # and after the other is released
