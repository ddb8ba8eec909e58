"""Layouts generated from scenes; rigs; foreign layouts rejected."""

import numpy as np
import pyarrow as pa
import pytest

from marionette.schema import SchemaError, check_layout, layout_of_schema, load_rig, load_scene, rig_from_json, state_schema

DUEL_SLICES = {
    "monster.root": (0, 3),
    "monster.joints": (3, 162),
    "hunter.root": (162, 165),
    "hunter.joints": (165, 258),
    "weapon.points": (258, 264),
    "monster.rot6d": (264, 270),
    "hunter.rot6d": (270, 276),
}


def test_duel_layout_matches_design():
    L = load_scene("duel")
    assert L.dim == 276
    assert L.slices == DUEL_SLICES
    assert list(L.slices) == list(DUEL_SLICES)  # order too
    assert L.entity("monster").rig.n_keep == 54 and len(L.entity("monster").rig.source_joints) > 54
    assert L.entity("hunter").rig.n_keep == 32
    assert L.entity("weapon").rig.keep == ("base", "tip")
    names = L.dim_names()
    assert len(names) == 276 and len(set(names)) == 276
    assert names[162:165] == ["hunter.root.x", "hunter.root.y", "hunter.root.z"]
    assert names[258] == "weapon.base.x" and names[263] == "weapon.tip.z"


def test_other_scenes_get_their_own_layouts():
    solo = load_scene("hunter_solo")
    assert solo.dim == 3 + 93 + 6 + 6
    assert "monster.root" not in solo.slices  # no padding for absent entities
    two = load_scene("two_hunters")
    assert two.dim == 276 + 3 + 93 + 6 + 6
    assert two.slices["hunter2.rot6d"] == (378, 384)
    assert len({solo.hash, two.hash, load_scene("duel").hash}) == 3


def test_rig_parents_skip_dropped_joints():
    r = load_rig("drake")
    parents = r.parents
    assert parents[0] == -1 and all(-1 <= p < i for i, p in enumerate(parents))
    # a kept joint whose source parent was dropped hangs from the nearest kept ancestor
    src_parent = {n: (r.source_joints[p] if p >= 0 else None) for n, p in zip(r.source_joints, r.source_parents)}
    for i, name in enumerate(r.keep[1:], start=1):
        anc = src_parent[name]
        while anc not in r.keep:
            anc = src_parent[anc]
        assert r.keep[parents[i]] == anc
    assert len(r.contact_joints) == 11


def test_bad_rigs_rejected():
    good = load_rig("hunter").to_json()
    with pytest.raises(SchemaError, match="not among the source joints"):
        rig_from_json({**good, "keep": ["pelvis", "tail_of_nothing"]})
    with pytest.raises(SchemaError, match="first kept joint"):
        rig_from_json({**good, "keep": ["head", "pelvis"]})


def test_shard_schema_carries_layout_and_foreign_layouts_fail():
    duel, solo = load_scene("duel"), load_scene("hunter_solo")
    schema = state_schema(duel)
    assert schema.field("state").type == pa.list_(pa.float32(), 276)
    assert layout_of_schema(schema).slices == duel.slices
    check_layout(schema, duel)
    with pytest.raises(SchemaError) as ei:
        check_layout(state_schema(solo), duel, "shard-000001.arrow")
    msg = str(ei.value)
    assert "hunter_solo" in msg and "duel" in msg and "shard-000001.arrow" in msg
    with pytest.raises(SchemaError, match="not a Marionette state shard"):
        check_layout(pa.schema([("x", pa.int32())]), duel)
    assert np.all(np.diff([a for a, _ in duel.slices.values()]) > 0)
