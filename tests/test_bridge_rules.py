"""The bridge's rules: the terrain collider (ground lift, walls judged per cell, decks) and the separation
cap, on hand-built skeleton sequences; rigid, deterministic, far from the origin, with absent frames."""

import numpy as np
import pytest

from marionette.bridge.rules import RuleParams, Rules, apply_rules, enabled_rules
from marionette.schema import load_scene
from terrain_scan.field import LayeredField
from terrain_scan.trn2 import FLAG_VALID, Chunk

DUEL = load_scene("duel")
SOLO = load_scene("hunter_solo")
ORIGIN = np.zeros(3)
FAR = np.array([-1e5, 0.0, 1e5])  # a scene translated here lies in chunks cx = −1000, cz = 1000


# -- terrain ---------------------------------------------------------------------------------------------


def make_chunk(cx, cz, surfaces, origin, max_layers=2):
    """A chunk whose slot s holds surfaces[s](x, z) (coordinates relative to origin) at every cell centre where it is finite."""
    c = Chunk.empty(cx, cz, max_layers)
    idx = np.arange(10000)
    x, z = cx * 100 + idx % 100 + 0.5 - origin[0], cz * 100 + idx // 100 + 0.5 - origin[2]
    for s, f in enumerate(surfaces):
        h = np.broadcast_to(np.asarray(f(x, z), np.float64), x.shape)
        ok = np.isfinite(h)
        c.cells["h"][ok, max_layers - 1 - s] = h[ok]
        c.cells["n"][ok, max_layers - 1 - s] = (0.0, 1.0, 0.0)
        c.cells["flags"][ok, max_layers - 1 - s] = FLAG_VALID
    return c


def field_of(*surfaces, origin=ORIGIN):
    """A field over the four chunks around origin; heights are relative to origin's y (0 here)."""
    cx, cz = int(origin[0]) // 100, int(origin[2]) // 100
    keys = [(cx + i, cz + j) for i in (-1, 0) for j in (-1, 0)]
    return LayeredField.from_chunks({k: make_chunk(*k, surfaces, origin) for k in keys})


def floor(x, z):
    return np.zeros_like(x)


def block(height, x0=10.0, x1=20.0, z0=-100.0, z1=100.0):
    """Floor with a block of ``height`` m on the cells x ∈ [x0, x1), z ∈ [z0, z1)."""
    return lambda x, z: np.where((x > x0) & (x < x1) & (z > z0) & (z < z1), height, 0.0)


def deck(x, z):
    return np.where((x > 10) & (x < 20), 5.0, np.nan)


# -- bodies ----------------------------------------------------------------------------------------------


def body(k, seed):
    """(K, 3) joint offsets from the root (joint 0); the lowest joint, a foot, 1 m below the root."""
    rng = np.random.default_rng(seed)
    off = np.column_stack([rng.uniform(-0.25, 0.25, k), rng.uniform(-0.9, 0.8, k), rng.uniform(-0.25, 0.25, k)])
    off[0], off[1] = 0.0, (0.05, -1.0, 0.1)
    return off


HUNTER, MONSTER = body(32, 0), body(54, 1)
WEAPON = np.array([[0.4, 0.1, 0.2], [0.4, 1.3, 0.2]])  # in the hunter's frame, relative to its root


def posed(roots, offsets, yaw=None):
    """(N, K, 3) joints of a body with root track roots (N, 3), turned by yaw (N,) (rad) about +Y."""
    if yaw is None:
        return roots[:, None, :] + offsets[None]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x, z = offsets[None, :, 0], offsets[None, :, 2]
    y = np.broadcast_to(offsets[None, :, 1], (len(yaw), len(offsets)))
    return roots[:, None, :] + np.stack([c * x + s * z, y, -s * x + c * z], -1)


def hunter(roots, yaw=None):
    return {"hunter": posed(roots, HUNTER, yaw), "weapon": posed(roots, WEAPON, yaw)}


def walk(n, start, velocity):
    """(N, 3) roots from start moving by velocity per frame."""
    return np.asarray(start, np.float64) + np.arange(n)[:, None] * np.asarray(velocity, np.float64)


def lowest(seq, name="hunter"):
    return seq[name][:, :, 1].min(axis=1)


def duel_course(origin=ORIGIN, n=120):
    """A duel on a floor with a 3 m wall at x ∈ [10, 20), z ∈ [40, 60): the hunter walks into the wall
    (frame 50) while sinking into the floor and turning; the monster walks away along −z (the cap engages
    from frame 46)."""
    t = np.arange(n)
    h = walk(n, (5.03, 1.0, 50.3), (0.1, 0.0, 0.0))
    h[:, 1] -= 0.02 * np.minimum(t, 30)
    m = walk(n, (8.53, 1.0, 48.0), (0.0, 0.0, -0.08))
    seq = {"monster": posed(m + origin, MONSTER, 0.01 * t), **hunter(h + origin, 0.05 * t)}
    return seq, field_of(block(3.0, z0=40, z1=60), origin=origin)


# -- the collider ----------------------------------------------------------------------------------------


def test_collider_lifts_a_sinking_body_by_at_most_4cm_per_frame():
    n = 60
    roots = walk(n, (5.03, 1.0, 50.3), (0.05, 0.0, 0.0))
    roots[:, 1] -= 0.1 * np.minimum(np.arange(n), 10)  # the foot sinks 0.1 m/frame to 1 m below the floor
    seq = hunter(roots)
    out = apply_rules(SOLO, seq, field_of(floor))
    lift = out["hunter"][:, 0, 1] - seq["hunter"][:, 0, 1]
    assert lowest(seq)[-1] == pytest.approx(-1.0) and abs(lowest(out)[-1]) < 1e-9  # resting on the surface
    assert lift[0] == 0.0 and np.diff(lift).max() <= 0.04 + 1e-12 and np.diff(lift).max() > 0.039
    assert (out["hunter"][..., 1] >= seq["hunter"][..., 1]).all()  # never below the input trajectory
    np.testing.assert_array_equal(out["hunter"][..., [0, 2]], seq["hunter"][..., [0, 2]])
    np.testing.assert_allclose(
        out["weapon"] - seq["weapon"], np.broadcast_to(out["hunter"][:, :1] - seq["hunter"][:, :1], (n, 2, 3)), atol=1e-12
    )


def test_collider_lets_a_jump_pass_and_the_lift_decay():
    n = 40
    roots = walk(n, (5.03, 1.0, 50.3), (0.05, 0.0, 0.0))
    roots[:, 1] += np.maximum(0.0, 0.8 - 0.08 * np.abs(np.arange(n) - 20))  # a hop above the floor
    roots[5:8, 1] -= 0.1  # a brief dip below it: lifted, then the lift decays back to zero
    seq = hunter(roots)
    out = apply_rules(SOLO, seq, field_of(floor))
    lift = out["hunter"][:, 0, 1] - seq["hunter"][:, 0, 1]
    assert lift[5:8].max() > 0.0 and (lift[15:] == 0.0).all()
    np.testing.assert_array_equal(out["hunter"][15:], seq["hunter"][15:])


def test_collider_blocks_a_wall_per_cell_and_passes_a_step_and_a_jump():
    n = 140  # walk x from 5.03 to 18.93 at 3 m/s; the block covers the cells x ∈ [10, 20)
    flat = walk(n, (5.03, 1.0, 50.3), (0.1, 0.0, 0.0))
    seq = hunter(flat)
    for height in (3.0, 1.9):  # a 1.9 m wall still blocks: the bilinear surface would make it a ramp
        out = apply_rules(SOLO, seq, field_of(block(height)))
        x = out["hunter"][:, 0, 0]
        assert 9.9 < x.max() < 10.0 and x[-1] == x.max()  # stopped before the wall cell, held there
        np.testing.assert_array_equal(out["hunter"][:50, :, [0, 2]], seq["hunter"][:50, :, [0, 2]])  # moving freely up to it
        np.testing.assert_allclose(
            out["weapon"][:, :, [0, 2]] - seq["weapon"][:, :, [0, 2]],
            np.broadcast_to(out["hunter"][:, :1, [0, 2]] - seq["hunter"][:, :1, [0, 2]], (n, 2, 2)),
            atol=1e-12,
        )

    out = apply_rules(SOLO, seq, field_of(block(1.0)))  # a 1 m step: walked onto, lifted onto its top
    np.testing.assert_array_equal(out["hunter"][..., [0, 2]], seq["hunter"][..., [0, 2]])
    assert lowest(out)[130] == pytest.approx(1.0, abs=1e-9)

    t = np.arange(n)
    for rise, passes in ((0.15, True), (0.05, False)):  # rising 4.5 m/s into the wall is a jump; 1.5 m/s is not
        roots = flat.copy()
        roots[:, 1] += np.clip(rise * (t - 40), 0.0, 3.0)
        out = apply_rules(SOLO, hunter(roots), field_of(block(3.0)))
        x = out["hunter"][:, 0, 0]
        if passes:
            np.testing.assert_array_equal(x, roots[:, 0])
            assert lowest(out)[-1] == pytest.approx(3.0, abs=1e-9)  # landed on the wall's top
        else:
            assert x.max() < 10.0


def test_collider_under_and_on_a_deck():
    crate = block(3.0, x0=15, x1=17, z0=40, z1=45)  # a 3 m crate on the floor, under the deck
    field = field_of(crate, deck)  # a floor everywhere and a deck 5 m above it on the cells x ∈ [10, 20)
    n = 200
    under = hunter(walk(n, (5.03, 1.0, 50.3), (0.1, 0.0, 0.0)))  # on the floor, under the deck and out again
    out = apply_rules(SOLO, under, field)
    for name in under:
        np.testing.assert_array_equal(out[name], under[name])  # neither blocked nor lifted onto the deck
    tall = {"hunter": posed(walk(60, (11.03, 2.8, 42.3), (0.1, 0.0, 0.0)), HUNTER * (1.0, 2.8, 1.0))}  # root nearer the deck
    x = apply_rules(SOLO, tall, field)["hunter"][:, 0, 0]
    assert 14.9 < x.max() < 15.0  # the crate blocks: the standing surface is judged from the lowest joint, not the root
    on = hunter(walk(70, (11.03, 5.9, 50.3), (0.1, 0.0, 0.0)))  # on the deck, the foot 0.1 m into it
    out = apply_rules(SOLO, on, field)
    np.testing.assert_array_equal(out["hunter"][..., [0, 2]], on["hunter"][..., [0, 2]])
    assert np.abs(lowest(out)[3:] - 5.0).max() < 1e-9 and lowest(out).max() <= 5.0 + 1e-9  # deck level, not the floor


def test_rules_are_rigid_per_body_and_move_the_weapon_with_the_hunter():
    seq, field = duel_course()
    out = apply_rules(DUEL, seq, field)
    for body_names in (("monster",), ("hunter", "weapon")):
        a = np.concatenate([seq[k] for k in body_names], axis=1)  # (N, K, 3)
        b = np.concatenate([out[k] for k in body_names], axis=1)
        dist = lambda j: np.linalg.norm(j[:, :, None] - j[:, None, :], axis=-1)  # noqa: E731
        np.testing.assert_allclose(dist(b), dist(a), rtol=0, atol=1e-12)
        shift = b - a  # one translation per frame for every joint of the body
        np.testing.assert_allclose(shift, np.broadcast_to(shift[:, :1], shift.shape), rtol=0, atol=1e-12)
        assert np.abs(shift).max() > 0.1  # the test is not vacuous: both bodies were moved
    assert out["hunter"][:, 0, 0].max() < 10.0  # the wall held


# -- the separation cap ----------------------------------------------------------------------------------


def pair(monster_roots, hunter_roots):
    return {"monster": posed(monster_roots, MONSTER), **hunter(hunter_roots)}


def separation(seq):
    d = seq["hunter"][:, 0] - seq["monster"][:, 0]
    return np.hypot(d[:, 0], d[:, 2])


def test_cap_holds_a_drifting_pair_at_6m_from_the_frame_it_would_cross():
    n = 100
    seq = pair(walk(n, (0.0, 1.0, 0.0), (-0.01, 0.0, 0.0)), walk(n, (1.0, 1.0, 1.0), (0.08, 0.0, 0.06)))
    out = apply_rules(DUEL, seq)
    cross = int(np.argmax(separation(seq) > 6.0))
    assert 30 < cross < 60
    for name in seq:
        np.testing.assert_array_equal(out[name][:cross], seq[name][:cross])
    d = separation(out)
    assert d[cross:].max() <= 6.0 + 1e-9 and d[cross:].min() >= 6.0 - 1e-9
    shift_m, shift_h = out["monster"][:, 0] - seq["monster"][:, 0], out["hunter"][:, 0] - seq["hunter"][:, 0]
    np.testing.assert_allclose(shift_m, -shift_h, atol=1e-12)  # both move, by half each, horizontally
    assert (shift_h[:, 1] == 0).all() and np.abs(shift_h).max() > 1.0


def test_cap_never_moves_a_far_pair_farther_apart_nor_pulls_it_together():
    n = 60
    apart = pair(walk(n, (0.0, 1.0, 0.0), (-0.02, 0.0, 0.01)), walk(n, (10.0, 1.0, 0.0), (0.05, 0.0, -0.02)))
    d = separation(apply_rules(DUEL, apart))
    assert d[0] == pytest.approx(10.0) and np.diff(d).max() <= 1e-9 and d.min() >= 10.0 - 1e-9
    closing = pair(walk(n, (0.0, 1.0, 0.0), (0.02, 0.0, 0.01)), walk(n, (10.0, 1.0, 0.0), (-0.05, 0.0, -0.02)))
    out = apply_rules(DUEL, closing)
    for name in closing:
        np.testing.assert_array_equal(out[name], closing[name])


def test_cap_leaves_a_pair_in_range_untouched():
    rng = np.random.default_rng(3)
    n = 80
    seq = pair(1.0 + np.cumsum(rng.uniform(-0.05, 0.05, (n, 3)), 0), np.cumsum(rng.uniform(-0.05, 0.05, (n, 3)), 0) + (3, 1, 0))
    assert separation(seq).max() < 6.0
    out = apply_rules(DUEL, seq)
    for name in seq:
        np.testing.assert_array_equal(out[name], seq[name])


# -- determinism, forms, configuration -------------------------------------------------------------------


def test_bit_identical_on_repeat_and_step_by_step_equals_the_sequence_form():
    seq, field = duel_course()
    before = {k: v.copy() for k, v in seq.items()}
    rules = Rules(DUEL, field)
    first, second = rules.apply(seq), rules.apply(seq)
    third = apply_rules(DUEL, seq, field_of(block(3.0, z0=40, z1=60)))  # a fresh field and a fresh Rules
    rules.reset()
    steps = [rules.step({k: v[t] for k, v in seq.items()}) for t in range(len(seq["hunter"]))]
    assert all(np.array_equal(steps[0][k], seq[k][0]) for k in seq)  # the first step returns the frame unchanged
    for k in seq:
        assert np.array_equal(first[k], second[k]) and np.array_equal(first[k], third[k])
        assert np.array_equal(np.stack([s[k] for s in steps]), first[k])
        assert np.array_equal(seq[k], before[k])  # inputs are not mutated
    np.testing.assert_allclose(rules.offsets["hunter"], (first["hunter"] - seq["hunter"])[-1, 0], atol=1e-12)


def test_enabled_rules_and_inapplicable_rules():
    field = field_of(floor)
    assert enabled_rules(DUEL, None) == ("cap",) and enabled_rules(DUEL, field) == ("collider", "cap")
    assert enabled_rules(SOLO, field) == ("collider",) and enabled_rules(SOLO, None) == ()
    assert Rules(DUEL, field, enabled=["cap", "collider"]).enabled == ("collider", "cap")
    assert Rules(DUEL, field, enabled=()).apply(duel_course()[0])["hunter"].shape == (120, 32, 3)
    with pytest.raises(ValueError, match="terrain field"):
        Rules(SOLO, enabled=("collider",))
    with pytest.raises(ValueError, match="two articulated"):
        Rules(SOLO, field, enabled=("cap",))
    with pytest.raises(ValueError, match="unknown"):
        Rules(DUEL, field, enabled=("gravity",))
    with pytest.raises(ValueError, match="lacks"):
        Rules(DUEL, field).step({"hunter": HUNTER})
    assert RuleParams().max_step_m == 1.5 and RuleParams().max_separation_m == 6.0


# -- extremes --------------------------------------------------------------------------------------------


def test_far_from_the_origin_gives_the_same_corrections():
    near, near_field = duel_course()
    far, far_field = duel_course(FAR)
    out_near, out_far = apply_rules(DUEL, near, near_field), apply_rules(DUEL, far, far_field)
    assert {(-1000, 1000)} <= far_field.loaded_chunks
    for k in near:
        np.testing.assert_allclose(out_far[k] - far[k], out_near[k] - near[k], rtol=0, atol=1e-6)
    assert np.abs(out_near["hunter"] - near["hunter"]).max() > 0.1


def test_absent_frames_stay_nan_and_do_not_poison_later_frames():
    seq, field = duel_course()
    for k in ("hunter", "weapon"):
        seq[k][60:65] = np.nan  # absent while pressed against the wall
    seq["monster"][80, 7] = np.nan  # one bad joint: the monster is absent at frame 80
    out = apply_rules(DUEL, seq, field)
    for k in ("hunter", "weapon"):
        assert np.isnan(out[k][60:65]).all() and np.isfinite(np.delete(out[k], range(60, 65), axis=0)).all()
    assert np.isnan(out["monster"][80, 7]).all() and np.isfinite(np.delete(out["monster"], 80, axis=0)).all()
    x = out["hunter"][:, 0, 0]
    assert np.nanmax(x) < 10.0 and x[-1] > 9.8  # still held at the wall after the gap
    both = np.setdiff1d(np.arange(65, 120), [80])  # frames where both are present: capped (an absence never loosens the cap)
    assert separation(out)[both].max() <= 6.0 + 1e-9 and separation(seq)[both].min() > 6.5


def test_an_empty_sequence_returns_empty_arrays():
    seq = {"monster": np.empty((0, 54, 3)), "hunter": np.empty((0, 32, 3)), "weapon": np.empty((0, 2, 3))}
    out = apply_rules(DUEL, seq, field_of(floor))
    assert {k: v.shape for k, v in out.items()} == {k: v.shape for k, v in seq.items()}
    assert all(v.dtype == np.float64 for v in out.values())


def test_a_foot_in_a_wall_cell_does_not_lift_the_body_onto_the_wall():
    """The root is held outside a 3 m wall while a foot reaches 0.3 m into the wall's cells: no lift."""
    n = 60
    reach = HUNTER.copy()
    reach[1] = (0.3, -1.0, 0.0)  # the foot 0.3 m ahead of the root along +x
    roots = walk(n, (8.0, 1.0, 50.3), (0.05, 0.0, 0.0))
    seq = {"hunter": posed(roots, reach), "weapon": posed(roots, WEAPON)}
    out = apply_rules(SOLO, seq, field_of(block(3.0)))
    assert out["hunter"][:, 0, 0].max() < 10.0  # blocked before the wall's first cell (x = 10)
    assert out["hunter"][:, 1, 0].max() > 10.0  # while the foot reaches into it
    assert np.abs(out["hunter"][..., 1] - seq["hunter"][..., 1]).max() < 1e-12  # and nothing was lifted


def test_a_hop_under_a_deck_is_not_pulled_up_to_it():
    n = 40
    t = np.arange(n)
    roots = walk(n, (15.03, 1.0, 50.3), (0.0, 0.0, 0.05))
    roots[:, 1] += np.clip(1.6 * np.sin(np.pi * t / 20), 0, None)  # a 1.6 m hop during frames 0–20
    seq = hunter(roots)
    out = apply_rules(SOLO, seq, field_of(floor, deck))
    np.testing.assert_array_equal(out["hunter"], seq["hunter"])
