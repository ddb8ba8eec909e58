"""State-layer metrics on hand-built trajectories with known answers, the layer choice under a bridge deck
(hand-built candidate layers and a real ``LayeredField``), far-from-origin stability, and bad inputs."""

import numpy as np
import pyarrow as pa
import pytest

from marionette.corpus import world_of_rows
from marionette.eval.metrics import (
    body_shares,
    bone_length_cv,
    check_rollout_table,
    check_skeletons,
    check_window,
    clearances,
    contact_failure_rate,
    foot_contacts,
    foot_skate,
    key_joint_clearances,
    mean_max_penetration,
    ra_mpjpe,
    ra_mpjpe_frames,
    root_drift,
    separation,
)
from marionette.schema import load_rig, load_scene, state_schema
from terrain_scan.field import LayeredField
from terrain_scan.trn2 import FLAG_VALID, Chunk

FPS = 20.0
FAR = np.array([-4321.25, 1000.0, 8765.5])  # a scene thousands of metres out, at negative x


def rng(seed=0):
    return np.random.default_rng(seed)


def random_rotations(n, seed=0):
    q = rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def hunter_sequence(n=40, seed=0):
    """World joints (n, 32, 3) of the hunter rig: one random pose moved rigidly (random rotation and
    translation per frame), so every bone keeps its length."""
    rig = load_rig("hunter")
    pose = rng(seed).normal(scale=0.4, size=(rig.n_keep, 3))
    R = random_rotations(n, seed)
    t = rng(seed + 1).normal(scale=5.0, size=(n, 1, 3))
    return np.einsum("nij,kj->nki", R, pose) + t, rig


# -- RA-MPJPE and root drift --------------------------------------------------------------------------------


def test_ra_mpjpe_invariant_to_global_translation_and_known_offsets():
    rec, _ = hunter_sequence()
    moved = rec + rng(3).normal(scale=50.0, size=(len(rec), 1, 3))  # a different translation every frame
    assert ra_mpjpe(moved, rec) == pytest.approx(0.0, abs=1e-12)
    one = rec.copy()
    one[:, 7] += (0.3, 0.4, 0.0)  # one non-root joint 0.5 m off: 0.5 / 31 over the 31 non-root joints
    assert ra_mpjpe(one, rec) == pytest.approx(0.5 / 31, abs=1e-12)
    root = rec.copy()
    root[:, 0] += (0.0, 0.0, 0.2)  # the root 0.2 m off: every root-relative joint is 0.2 m off
    assert ra_mpjpe(root, rec) == pytest.approx(0.2, abs=1e-12)
    half = rec.copy()
    half[::2, 7] += (0.0, 3.1, 0.0)
    assert ra_mpjpe_frames(half, rec)[::2] == pytest.approx(3.1 / 31)
    assert ra_mpjpe_frames(half, rec)[1::2] == pytest.approx(0.0, abs=1e-12)


def test_ra_mpjpe_with_given_roots_and_absent_frames():
    rec, _ = hunter_sequence(10)
    pts = rec[:, 20:22]  # two points measured against the root (an attachment's owner)
    assert ra_mpjpe(pts + (1, 2, 3), pts, rec[:, 0] + (1, 2, 3), rec[:, 0]) == pytest.approx(0.0, abs=1e-12)
    assert ra_mpjpe(pts + (0, 0.25, 0), pts, rec[:, 0], rec[:, 0]) == pytest.approx(0.25)
    gen = rec.copy()
    gen[:3] = np.nan  # absent frames are left out, not counted as 0 or as errors
    gen[3:, 5] += (0.0, 0.0, 0.62)
    assert ra_mpjpe(gen, rec) == pytest.approx(0.62 / 31)
    assert np.isnan(ra_mpjpe(np.full_like(rec, np.nan), rec))


def test_root_drift_per_horizon_frame():
    rec = rng(1).normal(size=(50, 3)) * 10
    gen = rec + np.arange(50)[:, None] * np.array([0.0, 0.06, 0.08])  # 0.1 m further every frame
    assert root_drift(gen, rec) == pytest.approx(0.1 * np.arange(50))
    batch = root_drift(np.stack([gen, rec]), np.stack([rec, rec]))  # (rollouts, H)
    assert batch.shape == (2, 50) and batch[1] == pytest.approx(0.0)


# -- bone lengths ----------------------------------------------------------------------------------------------


def test_bone_length_cv_constant_is_zero_varying_has_known_value():
    joints, rig = hunter_sequence()
    assert bone_length_cv(joints, rig.parents) == pytest.approx(0.0, abs=1e-12)
    scaled = joints - joints[:, :1]
    scaled = scaled * np.where(np.arange(len(joints)) % 2 == 0, 1.0, 3.0)[:, None, None]  # L, 3L, L, ...: std/mean = 1/2
    assert bone_length_cv(scaled, rig.parents) == pytest.approx(0.5)
    # one bone of three varies (lengths 1 and 3: CV 0.5), the others are rigid: the mean over bones is 1/6
    chain = np.zeros((4, 4, 3))
    chain[:, 1, 0] = 1.0
    chain[:, 2, 0] = 2.0
    chain[:, 3, 0] = 2.0 + np.array([1.0, 3.0, 1.0, 3.0])
    assert bone_length_cv(chain, (-1, 0, 1, 2)) == pytest.approx(0.5 / 3)


# -- foot skate --------------------------------------------------------------------------------------------------


def foot(n, speed_mps, y=0.05):
    """A foot at height y moving along +x at ``speed_mps``: (n, 3)."""
    t = np.arange(n) / FPS
    return np.stack([speed_mps * t, np.full(n, y), np.zeros(n)], axis=1)


def test_foot_skate_sliding_stationary_and_airborne():
    assert foot_skate(foot(60, 1.0), FPS) == pytest.approx(1.0)  # sliding in contact at 1 m/s
    assert foot_skate(foot(60, 0.0), FPS) == pytest.approx(0.0)
    assert foot_contacts(foot(60, 1.0), FPS)[1:].all()
    # planted (sliding at 1 m/s) for 1 s, a 0.5 s hop at 5 m/s and 0.5 m up, planted again: the hop is not counted
    x, y, xs = [], [], 0.0
    for k in range(60):
        air = 20 <= k < 30
        xs += (5.0 if air else 1.0) / FPS
        x.append(xs)
        y.append(0.5 if air else 0.0)
    f = np.stack([x, y, np.zeros(60)], axis=1)
    contact = foot_contacts(f, FPS)
    assert not contact[20:31].any()  # in the air, and the landing frame (vertical speed 0.5 m/frame)
    assert contact[1:20].all() and contact[31:].all()
    assert foot_skate(f, FPS) == pytest.approx(1.0)
    # two feet (N, F, 3): one stationary, one sliding at 2 m/s → the mean over contact frames is 1 m/s
    assert foot_skate(np.stack([foot(40, 0.0), foot(40, 2.0)], axis=1), FPS) == pytest.approx(1.0)


def test_foot_contact_needs_low_height_and_slow_vertical_motion():
    # walking up a slope faster than 3 cm/frame vertically: never in contact, whatever the height
    climb = foot(40, 0.5)
    climb[:, 1] = 0.04 * np.arange(40)
    assert not foot_contacts(climb, FPS).any()
    assert np.isnan(foot_skate(climb, FPS))
    # 2 cm/frame vertically but within 8 cm of the rolling floor only near the window's low point
    slow = foot(40, 0.5)
    slow[:, 1] = 0.02 * np.arange(40)
    c = foot_contacts(slow, FPS)
    # floor at t = min over [t − 10, t + 10] = 0.02 (t − 10) for t ≥ 10: height − floor = 0.2 m > 8 cm
    assert c[1:5].all() and not c[5:].any()


def test_local_floor_is_a_centred_one_second_window():
    # 1.5 s still on a 0.5 m ledge, then a drop to the ground: the floor of frames within 0.5 s (10 frames at
    # 20 fps) of the drop is the ground, so the last 10 ledge frames are not in contact; earlier ones are
    ledge = foot(60, 0.0)
    ledge[:, 1] = np.where(np.arange(60) < 30, 0.5, 0.0)
    c = foot_contacts(ledge, FPS)
    assert c[1:20].all() and not c[20:31].any() and c[31:].all()
    assert foot_contacts(ledge, FPS, window_s=2.0)[1:10].all() and not foot_contacts(ledge, FPS, window_s=2.0)[10:31].any()


# -- penetration -------------------------------------------------------------------------------------------------


def standing_hunter(n=10, root_y=1.0, offset=(0.0, 0.0, 0.0)):
    """Hunter joints (n, 32, 3): every joint at the root's (x, z), 1 m below the root (0 m for root_y = 1)."""
    rig = load_rig("hunter")
    j = np.zeros((n, rig.n_keep, 3))
    j[:, :, 1] = root_y - 1.0
    j[:, 0, 1] = root_y
    j[:, :, 0] += np.linspace(0.0, 3.0, n)[:, None] + 40.3
    j[:, :, 2] += 50.7
    return j + np.asarray(offset), rig


def flat_layers(joints, *heights):
    """Candidate layers (N, K, L) at every joint: the given heights everywhere."""
    return np.broadcast_to(np.asarray(heights, np.float64), joints.shape[:2] + (len(heights),)).copy()


def test_mmp_and_cfr_on_flat_ground():
    j, rig = standing_hunter()
    first_key = rig.contact_index[0]
    j[:, first_key, 1] -= 0.3  # one key joint 0.3 m below flat ground at 0
    c = key_joint_clearances(j, rig, flat_layers(j, 0.0))
    assert mean_max_penetration(c) == pytest.approx(0.3)
    j2, _ = standing_hunter()
    j2[::2, first_key, 1] -= 0.3  # half of the frames: MMP is the mean over all frames
    assert mean_max_penetration(key_joint_clearances(j2, rig, flat_layers(j2, 0.0))) == pytest.approx(0.15)
    j3, _ = standing_hunter()
    j3[:, rig.contact_index[4], 1] -= 0.1  # 0.1 m below
    c3 = key_joint_clearances(j3, rig, flat_layers(j3, 0.0))
    assert contact_failure_rate(c3, margin_m=0.0) == 1.0
    assert contact_failure_rate(c3) == 0.0  # the default 0.15 m margin
    assert contact_failure_rate(c3, margin_m=0.05) == 1.0
    assert mean_max_penetration(c3) == pytest.approx(0.1)
    ok, _ = standing_hunter()
    assert mean_max_penetration(key_joint_clearances(ok, rig, flat_layers(ok, 0.0))) == 0.0
    # a non-key joint below the ground does not count
    hand, _ = standing_hunter()
    non_key = next(k for k in range(1, rig.n_keep) if k not in rig.contact_index)
    hand[:, non_key, 1] -= 1.0
    assert contact_failure_rate(key_joint_clearances(hand, rig, flat_layers(hand, 0.0)), 0.0) == 0.0


def deck_layers(j, ground, deck):
    return flat_layers(j, deck, ground)  # slot order carries no meaning


def _bridge_cases(ground, deck, offset):
    """The hunter rig and two bodies: one standing under the deck, one on it (ground and deck heights in m,
    ``offset`` already added; the bodies are built at ground 0 and moved by ``offset``)."""
    _, rig = standing_hunter()
    k0, k1 = rig.contact_index[0], rig.contact_index[8]
    under, _ = standing_hunter(root_y=1.0, offset=offset)  # the root 1 m above the ground
    under[:, k0, 1] = ground - 0.2  # a foot 0.2 m into the ground
    under[:, k1, 1] = ground + 4.0  # a raised hand 1 m below the deck: nearer the deck, but the body stands below
    on, _ = standing_hunter(root_y=6.0, offset=offset)  # the root 1 m above the deck
    on[:, k0, 1] = deck - 0.1  # a foot 0.1 m into the deck
    on[:, k1, 1] = deck - 3.0  # a joint poking 3 m through the deck: nearer the ground, measured against the deck
    return rig, under, on


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), tuple(FAR)])
def test_joint_under_a_bridge_deck_uses_the_layer_the_body_stands_on(offset):
    ground, deck = 0.0 + offset[1], 5.0 + offset[1]
    rig, under, on = _bridge_cases(ground, deck, offset)
    assert mean_max_penetration(key_joint_clearances(under, rig, deck_layers(under, ground, deck))) == pytest.approx(0.2)
    assert mean_max_penetration(key_joint_clearances(on, rig, deck_layers(on, ground, deck))) == pytest.approx(3.0)
    assert contact_failure_rate(key_joint_clearances(on, rig, deck_layers(on, ground, deck))) == 1.0
    assert contact_failure_rate(key_joint_clearances(under, rig, deck_layers(under, ground, deck))) == 1.0
    assert contact_failure_rate(key_joint_clearances(under, rig, deck_layers(under, ground, deck)), 0.25) == 0.0


def layered_field(x0, z0, heights):
    """A real LayeredField over the chunk holding (x0, z0) and its 8 neighbours, every cell holding ``heights``."""
    cx0, cz0 = int(np.floor(x0 / 100)), int(np.floor(z0 / 100))
    chunks = {}
    for cx in (cx0 - 1, cx0, cx0 + 1):
        for cz in (cz0 - 1, cz0, cz0 + 1):
            c = Chunk.empty(cx, cz, 4)
            for s, h in enumerate(heights):
                c.cells["h"][:, 3 - s] = h
                c.cells["n"][:, 3 - s] = (0.0, 1.0, 0.0)
                c.cells["flags"][:, 3 - s] = FLAG_VALID
            chunks[(cx, cz)] = c
    return LayeredField.from_chunks(chunks)


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), tuple(FAR)])
def test_bridge_deck_through_the_terrain_field(offset):
    ground, deck = 0.0 + offset[1], 5.0 + offset[1]
    rig, under, on = _bridge_cases(ground, deck, offset)
    field = layered_field(under[0, 0, 0], under[0, 0, 2], (ground, deck))
    c_under = key_joint_clearances(under, rig, field)
    c_on = key_joint_clearances(on, rig, field)
    assert mean_max_penetration(c_under) == pytest.approx(0.2, abs=1e-9)
    assert mean_max_penetration(c_on) == pytest.approx(3.0, abs=1e-9)
    # the field and the candidate-layer array agree joint by joint
    assert c_under == pytest.approx(key_joint_clearances(under, rig, deck_layers(under, ground, deck)), abs=1e-9)
    assert c_on == pytest.approx(key_joint_clearances(on, rig, deck_layers(on, ground, deck)), abs=1e-9)


def test_unknown_surface_frames_are_left_out():
    j, rig = standing_hunter(4)
    j[:, rig.contact_index[0], 1] -= 0.4
    layers = flat_layers(j, 0.0)
    layers[:2] = np.nan  # no terrain known under the first two frames
    c = key_joint_clearances(j, rig, layers)
    assert np.isnan(c[:2]).all()
    assert mean_max_penetration(c) == pytest.approx(0.4)
    assert contact_failure_rate(c) == 1.0
    assert np.isnan(mean_max_penetration(c[:2])) and np.isnan(contact_failure_rate(c[:2]))


# -- separation and the pose-control frame -----------------------------------------------------------------


def test_separation_known():
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    b = np.array([[3.0, 2.0, 4.0], [1.0, 5.0, 1.0]])
    d3, dh = separation(a, b)
    assert d3 == pytest.approx([np.sqrt(29.0), 4.0])
    assert dh == pytest.approx([5.0, 0.0])


def test_body_shares_from_a_hand_built_id_mask():
    layout = load_scene("duel")
    ids = np.full((4, 5), -1, np.int16)  # 20 pixels of background
    ids[3] = 0  # terrain
    ids[0, :3] = (195, 196, 195 + 30)  # hunter bones (31 of them: 195..225)
    ids[1, :2] = (105, 105 + 52)  # monster bones (53: 105..157)
    ids[2, 0] = 60  # the weapon's one bone
    ids[2, 1] = 254  # inside the hunter's id band but no bone of its rig
    ids[2, 2] = 180  # inside the monster's band, past its last bone
    s = body_shares(ids, layout)
    assert set(s) == {"monster", "hunter", "weapon"}
    assert s["hunter"] == pytest.approx(3 / 20) and s["monster"] == pytest.approx(2 / 20) and s["weapon"] == pytest.approx(1 / 20)
    with_weapon = body_shares(ids, layout, include_attachments=True)
    assert set(with_weapon) == {"monster", "hunter"} and with_weapon["hunter"] == pytest.approx(4 / 20)
    frames = np.stack([ids, np.zeros_like(ids)])  # (N, H, W) → (N,)
    assert body_shares(frames, layout)["hunter"] == pytest.approx([3 / 20, 0.0])


# -- stability far from the origin ------------------------------------------------------------------------------


def test_metrics_far_from_the_origin_and_at_negative_coordinates():
    joints, rig = hunter_sequence(60)
    gen = joints.copy()
    gen[:, 3] += (0.1, -0.2, 0.05)
    gen[:, 0] += np.arange(60)[:, None] * 0.01
    feet = np.stack([foot(60, 1.3), foot(60, 0.0, y=0.02)], axis=1)
    feet[30:40, 0, 1] += np.linspace(0.0, 0.6, 10)

    def measure(shift):
        shift = np.asarray(shift)
        d3, dh = separation(joints[:, 0] + shift, gen[:, 0] + shift)
        return np.concatenate(
            [
                [ra_mpjpe(gen + shift, joints + shift)],
                root_drift(gen[:, 0] + shift, joints[:, 0] + shift),
                [bone_length_cv(gen + shift, rig.parents)],
                [foot_skate(feet + shift, FPS)],
                d3,
                dh,
            ]
        )

    near = measure((0.0, 0.0, 0.0))
    assert np.isfinite(near).all()
    np.testing.assert_allclose(measure(FAR), near, rtol=0, atol=1e-9)
    np.testing.assert_allclose(measure(-FAR * 2.3), near, rtol=0, atol=1e-9)


# -- bad input --------------------------------------------------------------------------------------------------


def fake_rollout(layout, rows=3):
    """A table of ``rows`` rows in ``layout``'s state schema (zeros; NaN camera), as a rollout writes one."""
    schema = state_schema(layout)
    cols = {}
    for f in schema:
        t = f.type
        if pa.types.is_fixed_size_list(t):
            cols[f.name] = pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(rows * t.list_size), t.value_type), t.list_size)
        elif pa.types.is_string(t):
            cols[f.name] = pa.array(["seg-0"] * rows)
        elif pa.types.is_boolean(t):
            cols[f.name] = pa.array([True] * rows)
        else:
            cols[f.name] = pa.array(np.arange(rows), t)
    return pa.Table.from_pydict(cols, schema=schema)


def test_rollout_table_of_another_layout_is_rejected():
    duel, solo = load_scene("duel"), load_scene("hunter_solo")
    check_rollout_table(fake_rollout(duel), duel)
    with pytest.raises(ValueError, match=r"rollout table: shard layout 'hunter_solo' \(dim 108.*expected layout 'duel'"):
        check_rollout_table(fake_rollout(solo), duel)
    table = fake_rollout(duel)
    no_meta = table.replace_schema_metadata(None)
    with pytest.raises(ValueError, match="no layout in the schema metadata"):
        check_rollout_table(no_meta, duel)
    dropped = table.drop_columns(["monster.root_world"])
    with pytest.raises(ValueError, match=r"lacks columns \['monster.root_world'\]"):
        check_rollout_table(dropped, duel)
    i = table.schema.get_field_index("state")
    narrow = pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(3 * 200, np.float32)), 200)
    wrong = table.set_column(i, pa.field("state", narrow.type), narrow)
    with pytest.raises(ValueError, match=r"column 'state' is fixed_size_list<item: float>\[200\].*dim 276"):
        check_rollout_table(wrong, duel)
    with pytest.raises(ValueError, match="holds no rows"):
        check_rollout_table(table.slice(0, 0), duel)


def test_skeletons_of_another_layout_are_rejected():
    duel = load_scene("duel")
    good = {"monster": np.zeros((5, 54, 3)), "hunter": np.zeros((5, 32, 3)), "weapon": np.zeros((5, 2, 3))}
    assert check_skeletons(good, duel) == 5
    assert check_skeletons(world_of_rows(duel, fake_rollout(duel)), duel) == 3  # a rollout table's world skeletons
    with pytest.raises(ValueError, match=r"skeletons\['monster'\]: shape \(5, 50, 3\), rig 'drake' needs \(N, 54, 3\)"):
        check_skeletons({**good, "monster": np.zeros((5, 50, 3))}, duel)
    with pytest.raises(ValueError, match=r"lacks entities \['weapon'\]"):
        check_skeletons({k: v for k, v in good.items() if k != "weapon"}, duel)
    with pytest.raises(ValueError, match="different frame counts"):
        check_skeletons({**good, "hunter": np.zeros((6, 32, 3))}, duel)
    rig = load_rig("hunter")
    with pytest.raises(ValueError, match="joints_world: 31 joints, rig 'hunter' keeps 32"):
        key_joint_clearances(np.zeros((4, 31, 3)), rig, np.zeros((4, 31, 1)))
    with pytest.raises(ValueError, match=r"surface: layer heights of shape \(4, 30, 1\)"):
        clearances(np.zeros((4, 32, 3)), np.zeros(4), np.zeros((4, 30, 1)))
    with pytest.raises(ValueError, match="joints_gen has shape"):
        ra_mpjpe(np.zeros((4, 32, 3)), np.zeros((4, 31, 3)))
    with pytest.raises(ValueError, match=r"parents: 31 entries for 32 joints"):
        bone_length_cv(np.zeros((4, 32, 3)), rig.parents[:-1])


def test_window_longer_than_a_segment_is_rejected():
    rows = pa.table({"segment": ["rec-a:0"] * 50, "frame": np.arange(50)})
    check_window(rows, 0, 50)
    check_window(rows, 10, 40)
    with pytest.raises(ValueError, match=r"frames \[10, 55\).*segment 'rec-a:0', which has 50 frames"):
        check_window(rows, 10, 45)
    with pytest.raises(ValueError, match="do not fit"):
        check_window(rows, 0, 184)
    two = pa.table({"segment": ["a"] * 5 + ["b"] * 5})
    with pytest.raises(ValueError, match="one segment, got 2"):
        check_window(two, 0, 3)
