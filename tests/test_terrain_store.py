"""The stage store: order independence, re-scan without double counting, incremental = full, fill."""

import json

import numpy as np
import pytest

from terrain_scan.fill import fill_holes
from terrain_scan.layers import Observations
from terrain_scan.store import Stage, derive
from terrain_scan.trn2 import FLAG_FILLED, read_chunk


def _obs(rng, x0, z0, size, base, ts, deck=False):
    gx, gz = np.meshgrid(np.arange(x0, x0 + size), np.arange(z0, z0 + size), indexing="ij")
    gx, gz = gx.ravel(), gz.ravel()
    keep = rng.random(len(gx)) < 0.8  # holes
    gx, gz = gx[keep], gz[keep]
    h = base + 0.05 * gx + rng.normal(0, 0.02, len(gx))
    if deck:
        on = (gz % 7) < 2
        gx, gz, h = np.r_[gx, gx[on]], np.r_[gz, gz[on]], np.r_[h, h[on] + 5.5]
    n = np.tile([0.0, 1.0, 0.0], (len(gx), 1))
    return Observations(
        gx.astype(np.int64), gz.astype(np.int64), h, n, rng.integers(1, 20, len(gx)), np.full(len(gx), ts, np.int64)
    )


def _recordings():
    rng = np.random.default_rng(0)
    return {
        "data_part1/rec0000": _obs(rng, -960, 840, 30, 20.0, 1767225600, deck=True),
        "data_part1/rec0001": _obs(rng, -945, 830, 30, 20.0, 1767312000),
        "data_part1/rec0002": _obs(rng, -1100, 905, 25, 35.0, 1767398400),  # only chunk (-11, 9)
    }


def _chunk_bytes(d):
    return {p.name: p.read_bytes() for p in sorted((d / "chunks").glob("*.trn2"))}


def test_any_order_and_incremental_equal_full(tmp_path):
    recs = _recordings()
    full = Stage(tmp_path / "full")
    for name, o in recs.items():
        full.put(name, o, f"hash-{name}", int(o.ts[0]))
    full.rebuild()
    rev = Stage(tmp_path / "rev")
    for name in reversed(list(recs)):
        rev.put(name, recs[name], f"hash-{name}", int(recs[name].ts[0]))
        rev.rebuild()  # incremental: a rebuild after every recording
    assert _chunk_bytes(tmp_path / "full") == _chunk_bytes(tmp_path / "rev")
    assert len(_chunk_bytes(tmp_path / "full")) >= 2


def test_rescan_replaces_and_untouched_chunks_keep_bytes_and_mtime(tmp_path):
    recs = _recordings()
    st = Stage(tmp_path / "s")
    for name, o in list(recs.items())[:2]:
        st.put(name, o, "h", int(o.ts[0]))
    st.rebuild()
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in (tmp_path / "s" / "chunks").glob("*")}
    # scanning the same recording again changes nothing (hits are not counted twice)
    name, o = next(iter(recs.items()))
    st.put(name, o, "h", int(o.ts[0]))
    rep = st.rebuild()
    assert (
        rep.written == []
        and {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in (tmp_path / "s" / "chunks").glob("*")} == before
    )
    # a recording in another chunk: only that chunk is written
    name3 = "data_part1/rec0002"
    st.put(name3, recs[name3], "h", int(recs[name3].ts[0]))
    rep = st.rebuild()
    after = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in (tmp_path / "s" / "chunks").glob("*")}
    for k, v in before.items():
        assert after[k] == v
    assert (-11, 9) in rep.written and len(after) == len(before) + len(rep.written)  # new chunks only (fill may spill over)
    assert st.manifest["chunks"]["-11_9"]["recordings"] == [name3]
    # removing it removes its chunk file
    added = set(rep.written)
    st.remove(name3)
    rep = st.rebuild()
    assert set(rep.removed) == added and {p.name for p in (tmp_path / "s" / "chunks").glob("*")} == set(before)


def test_two_levels_and_hits_saturate(tmp_path):
    o = _recordings()["data_part1/rec0000"]
    o.hits[:] = 60000
    st = Stage(tmp_path / "s")
    st.put("a", o, "h", 5)
    st.put("b", o, "h", 7)
    st.rebuild()
    for p in (tmp_path / "s" / "chunks").glob("*.trn2"):
        c = read_chunk(p)
        v = c.valid()
        assert c.cells["hits"][v].max() == 65535
        assert (v.sum(1) == 2).any()  # deck over ground
        both = v.sum(1) == 2
        gap = c.cells["h"][both, 1] - c.cells["h"][both, 0]
        assert np.all(gap > 5.0)
        assert set(np.unique(c.cells["ts"][v])) == {7}


def test_hole_fill_needs_three_agreeing_neighbours():
    n = np.tile([0.0, 1.0, 0.0], (8, 1))
    ring = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
    gx = np.array([x for x, _ in ring], np.int64)
    gz = np.array([z for _, z in ring], np.int64)
    h = np.array([10.0, 10.5, 11.0, 10.2, 30.0, 31.0, 29.5, 10.1])
    layers = Observations(gx, gz, h, n, np.ones(8, np.int64), np.arange(8, dtype=np.int64))
    out, filled = fill_holes(layers, rounds=1)
    cells = {(int(x), int(z)): (h, t, k) for x, z, h, t, k in zip(out.gx, out.gz, out.h, out.ts, out.hits)}
    f = {(int(x), int(z)) for x, z in zip(out.gx[filled], out.gz[filled])}
    assert (0, 0) in f
    # the centre takes the 5 neighbours within 2 m of each other (10.0..11.0), not the 3 high ones,
    # through a least-squares plane evaluated at the centre
    pts = np.array([[1, -1, -1, 10.0], [1, -1, 0, 10.5], [1, -1, 1, 11.0], [1, 0, -1, 10.2], [1, 1, 1, 10.1]])
    plane = np.linalg.lstsq(pts[:, :3], pts[:, 3], rcond=None)[0]
    np.testing.assert_allclose(cells[(0, 0)][0], plane[0])
    assert cells[(0, 0)][2] == 0 and cells[(0, 0)][1] == 7
    # (2, 0) sees 31.0, 29.5 (agreeing, but only 2) and 10.1: not filled
    assert (2, 0) not in f
    # (-2, 0) sees 10.0, 10.5, 11.0 — three, but all on one line: a border is not extrapolated
    assert (-2, 0) not in f
    # only two agreeing neighbours: nothing filled
    two = layers.take(np.array([0, 1]))
    assert fill_holes(two, rounds=3)[1].sum() == 0


def test_hole_fill_is_exact_on_a_slope():
    gx, gz = np.meshgrid(np.arange(-953, -946), np.arange(846, 853), indexing="ij")
    gx, gz = gx.ravel(), gz.ravel()
    hole = ((gx == -950) & (gz == 849)) | ((gx == -949) & (gz == 849))
    h = 20.0 + 0.45 * gx - 0.2 * gz  # a 25° slope: a mean of one-sided neighbours would be off by ~0.45 m
    o = Observations(
        gx[~hole].astype(np.int64),
        gz[~hole].astype(np.int64),
        h[~hole],
        np.tile([0.0, 1, 0], ((~hole).sum(), 1)),
        np.ones((~hole).sum(), np.int64),
        np.zeros((~hole).sum(), np.int64),
    )
    out, filled = fill_holes(o, rounds=1)
    got = {(int(x), int(z)): v for x, z, v in zip(out.gx[filled], out.gz[filled], out.h[filled])}
    assert set(got) == {(-950, 849), (-949, 849)}
    for (x, z), v in got.items():
        np.testing.assert_allclose(v, 20.0 + 0.45 * x - 0.2 * z, atol=1e-9)


def test_filled_flag_reaches_the_chunk(tmp_path):
    st = Stage(tmp_path / "s")
    gx, gz = np.meshgrid(np.arange(-3, 4), np.arange(-3, 4), indexing="ij")
    keep = ~((gx == 0) & (gz == 0))
    o = Observations(
        gx[keep].astype(np.int64),
        gz[keep].astype(np.int64),
        np.full(keep.sum(), 2.0),
        np.tile([0.0, 1, 0], (keep.sum(), 1)),
        np.ones(keep.sum(), np.int64),
        np.ones(keep.sum(), np.int64),
    )
    st.put("r", o, "h", 1)
    st.rebuild()
    c = read_chunk(tmp_path / "s" / "chunks" / "chunk_0_0.trn2")
    assert c.cells["flags"][0, 0] & FLAG_FILLED and c.cells["h"][0, 0] == np.float32(2.0)


# -- chunk by chunk and incremental: byte-identical to the whole-stage derivation --------------------


def _spread(ox, oz):
    """Recordings across chunk corners and edges around cell (ox, oz) (a chunk corner), overlapping at
    other heights: hole fill and edge aliases at chunk borders, where the halo matters."""
    rng = np.random.default_rng(1)
    recs = {
        "p/a": _obs(rng, ox - 20, oz - 20, 40, 20.0, 1767225600, deck=True),
        "p/b": _obs(rng, ox - 35, oz + 70, 45, 21.0, 1767225700),
        "p/c": _obs(rng, ox + 88, oz - 12, 24, 19.0, 1767225800, deck=True),
        "p/d": _obs(rng, ox - 8, oz - 30, 25, 26.0, 1767225900),
    }
    leak = recs["p/a"]  # the deck seen across its cells' north edge, hugging the south edge of the cell beyond: an alias
    on = (leak.h - 0.05 * leak.gx > 24.0) & (leak.gz % 7 == 1)
    south = np.full(on.sum(), 1 << 2, np.uint8)  # layers.EDGES: west, east, south, north
    recs["p/e"] = Observations(
        leak.gx[on], leak.gz[on] + 1, leak.h[on], leak.n[on], np.ones(on.sum(), np.int64), leak.ts[on], south
    )
    return recs


def _stage(path, recs, mode):
    st = Stage(path)
    for name, o in recs.items():
        st.put(name, o, f"hash-{name}", int(o.ts[0]))
    return st, st.rebuild(mode)


@pytest.mark.parametrize("ox, oz", [(0, 0), (-1_234_500, 987_600)])
def test_chunk_by_chunk_equals_the_whole_stage(tmp_path, ox, oz):
    recs = _spread(ox, oz)
    whole, rw = _stage(tmp_path / "whole", recs, "whole")
    each, re_ = _stage(tmp_path / "each", recs, "full")
    assert _chunk_bytes(tmp_path / "each") == _chunk_bytes(tmp_path / "whole")
    assert each.manifest["chunks"] == whole.manifest["chunks"] and (re_.layers, re_.filled) == (rw.layers, rw.filled)
    touched = {(cx - ox // 100, cz - oz // 100) for r in each.recordings().values() for cx, cz in r["chunks"]}
    assert touched == {(-1, -1), (0, -1), (1, -1), (-1, 0), (0, 0), (1, 0), (-1, 1), (0, 1)} and re_.filled > 0
    lw, fw = whole.layers(whole=True)
    le, fe = each.layers()
    assert all(np.array_equal(getattr(lw, f), getattr(le, f)) for f in Observations.FIELDS)
    assert np.array_equal(fw, fe)


def test_a_chunk_needs_its_whole_halo(tmp_path):
    """Cell (0, 2) of chunk (0, 0) depends on an observation three cells west, in chunk (-1, 0):
    (-3, 2)'s layer makes (-2, 2)'s one at its height, hugging their shared edge, an edge alias; without it,
    round 1 of the hole fill gives (-1, 3) another height, which round 2's fill of (0, 2) reads."""
    rows = [(-2, 2, 0.2, 10, 0), (-1, 2, 0.2, 10, 0), (0, 3, 0.3, 10, 0), (-2, 2, 1.8, 1, 1), (-3, 2, 1.8, 50, 0)]
    gx, gz, h, hits, hugs = (np.array(c) for c in zip(*rows))
    o = Observations(gx, gz, h, np.tile([0.0, 1.0, 0.0], (len(h), 1)), hits, np.zeros(len(h), np.int64), hugs.astype(np.uint8))
    each, _ = _stage(tmp_path / "each", {"r": o}, "full")
    _stage(tmp_path / "whole", {"r": o}, "whole")
    assert _chunk_bytes(tmp_path / "each") == _chunk_bytes(tmp_path / "whole")
    cell = read_chunk(tmp_path / "each" / "chunks" / "chunk_0_0.trn2").cells[2 * 100 + 0, 0]
    assert cell["flags"] & FLAG_FILLED and cell["h"] == np.float32(0.2)
    assert each.halo == 3
    short, filled = derive(o.take(np.flatnonzero(o.gx >= -(each.halo - 1))), each.max_layers, each.fill_rounds)
    at = np.flatnonzero((short.gx == 0) & (short.gz == 2))
    assert filled[at].all() and abs(short.h[at[0]] - 0.2) > 1.0


def test_incremental_derives_only_the_changed_neighbourhood(tmp_path):
    recs = _spread(0, 0)
    st, first = _stage(tmp_path / "s", recs, "incremental")  # no record of a last rebuild: every chunk
    assert first.full and first.derived == st.covered()
    rng = np.random.default_rng(2)
    new = _obs(rng, 320, -170, 12, 30.0, 1767226000)  # inside chunk (3, -2), away from the others
    st.put("p/new", new, "hash-new", int(new.ts[0]))
    added = st.rebuild()
    around = [(3 + dx, -2 + dz) for dx in (-1, 0, 1) for dz in (-1, 0, 1)]
    assert not added.full and added.derived == around and added.written == [(3, -2)] and added.removed == []
    ref, _ = _stage(tmp_path / "ref", {**recs, "p/new": new}, "whole")
    assert _chunk_bytes(tmp_path / "s") == _chunk_bytes(tmp_path / "ref") and st.manifest["chunks"] == ref.manifest["chunks"]
    # the same contribution again: nothing to derive
    st.put("p/new", new, "hash-new", int(new.ts[0]))
    assert st.rebuild().derived == []
    # removing a recording re-derives the chunks it touched and their halo
    touched = st.manifest["recordings"]["p/c"]["chunks"]
    st.remove("p/c")
    gone = st.rebuild()
    assert gone.derived == sorted({(cx + dx, cz + dz) for cx, cz in touched for dx in (-1, 0, 1) for dz in (-1, 0, 1)})
    assert gone.removed and not gone.full
    recs.pop("p/c")
    ref, _ = _stage(tmp_path / "ref2", {**recs, "p/new": new}, "whole")
    assert _chunk_bytes(tmp_path / "s") == _chunk_bytes(tmp_path / "ref2") and st.manifest["chunks"] == ref.manifest["chunks"]


def test_incremental_falls_back_to_full(tmp_path):
    st, _ = _stage(tmp_path / "s", _spread(0, 0), "full")
    # a missing chunk file is derived again
    (tmp_path / "s" / "chunks" / "chunk_0_0.trn2").unlink()
    rep = Stage(tmp_path / "s").rebuild()
    assert rep.derived == [(0, 0)] and rep.written == [(0, 0)]
    # other settings, or a stage rebuilt before the record of what it was derived from: every chunk
    assert Stage(tmp_path / "s", fill_rounds=1).rebuild().full
    legacy = json.loads((tmp_path / "s" / "manifest.json").read_text())
    del legacy["rebuilt"]
    for rec in legacy["recordings"].values():
        del rec["sha256"]
    (tmp_path / "s" / "manifest.json").write_text(json.dumps(legacy))
    old = Stage(tmp_path / "s")
    rep = old.rebuild()
    assert rep.full and rep.derived == old.covered() and all("sha256" in r for r in old.manifest["recordings"].values())
    assert not Stage(tmp_path / "s").rebuild().derived
    # a manifest entry that hides a chunk its contribution holds is an error, not a silently missing piece
    legacy = json.loads((tmp_path / "s" / "manifest.json").read_text())
    legacy["recordings"]["p/a"]["chunks"].remove([0, 0])
    (tmp_path / "s" / "manifest.json").write_text(json.dumps(legacy))
    with pytest.raises(ValueError, match="chunk \\(0, 0\\)"):
        Stage(tmp_path / "s").rebuild("full")
