"""Querying the layered height field: exact bilinear values, continuity across cells and chunks, layer
selection, holes, lazy loading, the stage reader, the torch path and the dynamics features."""

import numpy as np
import pytest
import torch

from terrain_scan.field import (
    MATCH_M,
    DenseRegion,
    LayeredField,
    egocentric_patch,
    egocentric_patch_torch,
    joint_clearances,
    joint_clearances_torch,
    normal_torch,
    open_stage,
    query_torch,
)
from terrain_scan.trn2 import FLAG_VALID, Chunk, chunk_filename, write_chunk

FACING_PLUS_X = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # yaw +90°: local +Z → world +x
FORWARD = np.array([0.0, 0.0, 1.0])


def cell_centres(cx: int, cz: int) -> tuple[np.ndarray, np.ndarray]:
    """World (x, z) of the centres of a chunk's 10000 cells, in cell-index order."""
    idx = np.arange(10000)
    return cx * 100 + idx % 100 + 0.5, cz * 100 + idx // 100 + 0.5


def make_chunk(cx, cz, surfaces, max_layers=4):
    """A chunk whose slot s holds surfaces[s](x, z) at every cell centre where it is finite."""
    c = Chunk.empty(cx, cz, max_layers)
    x, z = cell_centres(cx, cz)
    for s, f in enumerate(surfaces):
        h = np.broadcast_to(np.asarray(f(x, z), np.float64), x.shape)
        ok = np.isfinite(h)
        c.cells["h"][ok, max_layers - 1 - s] = h[ok]  # slot order carries no meaning: fill from the back
        c.cells["n"][ok, max_layers - 1 - s] = (0.0, 1.0, 0.0)
        c.cells["flags"][ok, max_layers - 1 - s] = FLAG_VALID
    return c


def field_of(keys, *surfaces, **kw):
    return LayeredField.from_chunks({k: make_chunk(*k, surfaces, **kw) for k in keys})


def plane(x, z):
    return 3.0 + 0.1 * x - 0.05 * z


def smooth(x, z):
    return 2.0 * np.sin(x / 7.0) + 1.5 * np.cos(z / 5.0) + 0.02 * x


NEG = [(cx, cz) for cx in (-11, -10, -9) for cz in (7, 8)]  # x in [−1100, −800), z in [700, 900)


def assert_continuous(field, x, z, ref, truth):
    """No jump between consecutive samples larger than the true terrain change + 2 cm."""
    q = field.query(x, z, ref)
    assert np.isfinite(q).all()
    jump = np.abs(np.diff(q))
    allowed = np.abs(np.diff(truth(x, z))) + 0.02
    assert (jump <= allowed).all(), f"jump {jump.max():.4f} m at x={x[np.argmax(jump - allowed)]:.3f}"


def test_bilinear_reproduces_a_plane_exactly():
    field = field_of([(0, 0), (-1, 0), (0, -1), (-1, -1)], plane)
    rng = np.random.default_rng(0)
    x, z = rng.uniform(-99, 99, 20000), rng.uniform(-99, 99, 20000)
    q = field.query(x, z, np.full_like(x, 5.0))
    assert q.dtype == np.float64 and q.shape == x.shape
    np.testing.assert_allclose(q, plane(x, z), atol=2e-6)  # float32 storage of heights up to ~18 m
    # broadcasting: a (3, 1) against a (4,) grid, scalar ref
    grid = field.query(np.array([[-50.2], [0.0], [37.7]]), np.array([-3.0, 0.5, 1.0, 60.1]), 0.0)
    np.testing.assert_allclose(grid, plane(np.array([[-50.2], [0.0], [37.7]]), np.array([-3.0, 0.5, 1.0, 60.1])), atol=2e-6)


def test_cells_use_floor_and_minus_half_is_in_cell_minus_one():
    field = field_of([(-1, 0), (0, 0)], lambda x, z: np.where(x < 0, 4.0, 3.0))
    assert field.cell_height(-0.5, 0.5, 0.0) == 4.0
    assert field.cell_height(-1e-9, 0.5, 0.0) == 4.0
    assert field.cell_height(0.0, 0.5, 0.0) == 3.0
    h, n = field.cell_layers(np.array([-1, 0]), np.array([0, 0]))
    assert h.shape == (2, 1) and list(h[:, 0]) == [4.0, 3.0]
    np.testing.assert_array_equal(n[:, 0], [[0, 1, 0], [0, 1, 0]])
    # at the boundary between the two cells' centres the surface is halfway
    assert field.query(0.0, 0.5, 0.0) == pytest.approx(3.5)
    assert field.query(-0.5, 0.5, 0.0) == pytest.approx(4.0)


def test_continuous_across_cells_and_chunks_at_negative_coordinates():
    field = field_of(NEG, smooth)
    t = np.linspace(-3.0, 3.0, 6001)  # 1 mm steps
    for x0, z0 in [(-1000.0, 850.3), (-950.0, 800.0), (-900.0, 799.75)]:
        ref = np.full_like(t, smooth(x0, z0))
        assert_continuous(field, x0 + t, np.full_like(t, z0), ref, smooth)  # along x
        assert_continuous(field, np.full_like(t, x0), z0 + t, ref, smooth)  # along z
        assert_continuous(field, x0 + t, z0 - t, ref, smooth)  # diagonally through a chunk corner
    # and the surface follows the terrain it interpolates
    x = np.linspace(-1050.0, -850.0, 2001)
    z = np.full_like(x, 812.4)
    assert np.abs(field.query(x, z, smooth(x, z)) - smooth(x, z)).max() < 0.05


def deck_field():
    """Ground sloping gently along x; a flat deck at 5 m over cells x, z in [40, 60)."""

    def deck(x, z):
        return np.where((x >= 40) & (x < 60) & (z >= 40) & (z < 60), 5.0, np.nan)

    return field_of([(0, 0)], lambda x, z: 0.02 * x, deck)


def test_ref_y_selects_ground_under_the_deck_or_the_deck():
    field = deck_field()
    rng = np.random.default_rng(1)
    x, z = rng.uniform(30, 70, 20000), rng.uniform(30, 70, 20000)
    np.testing.assert_allclose(field.query(x, z, 0.02 * x + 0.3), 0.02 * x, atol=1e-6)  # ground, also under the deck
    on_deck = (x >= 40) & (x < 60) & (z >= 40) & (z < 60)
    top = field.query(x, z, np.full_like(x, 5.2))
    np.testing.assert_allclose(top[on_deck], 5.0, atol=1e-9)
    np.testing.assert_allclose(top[~on_deck], 0.02 * x[~on_deck], atol=1e-6)  # no deck there: the ground
    assert field.cell_height(50.5, 50.5, 4.0) == 5.0 and field.cell_height(50.5, 50.5, 1.0) == pytest.approx(1.01)
    assert field.width == 2


def test_floor_and_roof_never_mix():
    field = deck_field()
    rng = np.random.default_rng(2)
    x, z, ref = rng.uniform(30, 70, 50000), rng.uniform(30, 70, 50000), rng.uniform(-2, 8, 50000)
    q = field.query(x, z, ref)
    assert np.isfinite(q).all()
    assert ((np.abs(q - 0.02 * x) < 1e-6) | (np.abs(q - 5.0) < 1e-9)).all()
    # walking under the deck at ground height: continuous; walking on it: flat to its edge
    t = np.linspace(35.0, 65.0, 3001)
    assert_continuous(field, t, np.full_like(t, 50.2), 0.02 * t + 0.5, lambda x, z: 0.02 * x)
    on = field.query(np.linspace(40.0, 59.999, 500), 50.2, 5.0)
    np.testing.assert_allclose(on, 5.0, atol=1e-9)


def test_a_hole_uses_the_remaining_neighbours_and_far_away_is_nan():
    def with_hole(x, z):
        return np.where((np.floor(x) == 50) & (np.floor(z) == 50), np.nan, plane(x, z))

    field = field_of([(0, 0)], with_hole)
    assert np.isnan(field.cell_height(50.5, 50.5, 0.0))
    x = np.array([50.5, 50.2, 50.9, 49.8, 51.3])
    z = np.array([50.5, 50.7, 50.1, 50.5, 49.6])
    q = field.query(x, z, np.zeros(5))
    assert np.isfinite(q).all()
    # each value is a weighted mean of the plane at the neighbours that hold data
    lo, hi = plane(np.floor(x - 0.5) + 0.5, np.floor(z - 0.5) + 0.5 + 1), plane(np.floor(x - 0.5) + 1.5, np.floor(z - 0.5) + 0.5)
    assert ((q >= np.minimum(lo, hi) - 1e-6) & (q <= np.maximum(lo, hi) + 1e-6)).all()
    # at the data's edge only the cells with data count; beyond half a cell outside it there is nothing
    assert field.query(0.2, 40.5, 0.0) == pytest.approx(plane(0.5, 40.5), abs=1e-6)
    assert np.isnan(field.query(-0.6, 40.5, 0.0))
    assert np.isnan(field.query(5000.0, 40.5, 0.0))
    assert np.isnan(field.query(np.nan, 40.5, 0.0)) and np.isnan(field.query(10.0, 40.5, np.inf))


def test_only_the_chunks_a_query_touches_are_loaded():
    calls = []
    chunks = {k: make_chunk(*k, [plane]) for k in [(0, 0), (1, 0), (0, 1), (-1, -1)]}

    def load(cx, cz):
        calls.append((cx, cz))
        return chunks.get((cx, cz))

    field = LayeredField(load)
    field.query(np.array([10.0, 50.0]), np.array([10.0, 50.0]), 0.0)
    assert field.loaded_chunks == {(0, 0)}
    field.query(99.8, 50.0, 0.0)  # the cell centre at x = 100.5 is in chunk (1, 0)
    assert field.loaded_chunks == {(0, 0), (1, 0)}
    assert np.isnan(field.query(-350.0, 1230.0, 0.0))
    assert field.loaded_chunks == {(0, 0), (1, 0), (-4, 12)}
    field.query(np.array([10.0, 99.8]), np.array([10.0, 50.0]), 0.0)
    assert sorted(calls) == sorted(field.loaded_chunks)  # each chunk asked for once


def test_open_stage_reads_chunk_files(tmp_path):
    chunks = {k: make_chunk(*k, [smooth, lambda x, z: smooth(x, z) + 6.0]) for k in [(-10, 8), (-9, 8)]}
    for (cx, cz), c in chunks.items():
        write_chunk(tmp_path / "chunks" / chunk_filename(cx, cz), c)
    stage, mem = open_stage(tmp_path), LayeredField.from_chunks(chunks)
    rng = np.random.default_rng(3)
    x, z, ref = rng.uniform(-1010, -890, 5000), rng.uniform(795, 905, 5000), rng.uniform(-5, 12, 5000)
    np.testing.assert_array_equal(stage.query(x, z, ref), mem.query(x, z, ref))
    assert {(-10, 8), (-9, 8)} <= stage.loaded_chunks <= {(cx, cz) for cx in (-11, -10, -9, -8) for cz in (7, 8, 9)}
    assert np.isnan(stage.query(-1050.0, 850.0, 0.0))  # chunk (-11, 8) has no file


def test_normals_of_a_plane():
    c = make_chunk(0, 0, [plane])
    up = np.array([-0.1, 1.0, 0.05]) / np.linalg.norm([-0.1, 1.0, 0.05])
    c.cells["n"][c.valid()] = up
    field = LayeredField.from_chunks({(0, 0): c})
    n = field.normal(np.array([[10.3, 20.7], [55.0, 70.1]]), np.array([[3.2, 80.0], [44.4, 12.5]]), 0.0)
    assert n.shape == (2, 2, 3)
    np.testing.assert_allclose(n, np.broadcast_to(up, (2, 2, 3)), atol=1e-6)
    assert np.isnan(field.normal(500.0, 3.0, 0.0)).all()


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_torch_agrees_with_numpy(dtype, tol):
    def holes(x, z):  # 3 × 3-cell holes: points near a hole's middle cell have no data around them
        return np.where((np.floor(x) % 9 < 3) & (np.floor(z) % 7 < 3), np.nan, smooth(x, z))

    def deck(x, z):
        return np.where((x > -960) & (x < -940) & (z > 840) & (z < 860), smooth(x, z) + 5.0, np.nan)

    field = field_of(NEG, holes, deck)
    region = DenseRegion.from_field(field, -990.0, -910.0, 790.0, 870.0, dtype=dtype)
    rng = np.random.default_rng(4)
    x, z = rng.uniform(-990, -910, 40000), rng.uniform(790, 870, 40000)
    x, z = x.astype(np.float32).astype(np.float64), z.astype(np.float32).astype(np.float64)  # same points in both dtypes
    ref = smooth(x, z) + rng.choice([0.3, 5.2, -1.0, 3.0], x.size)
    q = field.query(x, z, ref)
    qt = query_torch(region, torch.from_numpy(x), torch.from_numpy(z), torch.from_numpy(ref))
    assert qt.dtype == dtype
    np.testing.assert_array_equal(np.isnan(qt.numpy()), np.isnan(q))
    np.testing.assert_allclose(qt.numpy(), q, atol=tol, rtol=0)
    assert 0.9 < np.isfinite(q).mean() < 1.0  # the holes leave a few points without data
    nt = normal_torch(region, torch.from_numpy(x), torch.from_numpy(z), torch.from_numpy(ref))
    np.testing.assert_allclose(nt.numpy(), field.normal(x, z, ref), atol=tol, rtol=0)
    # outside the region: nan
    assert torch.isnan(query_torch(region, torch.tensor([-1050.0]), torch.tensor([800.0]), torch.tensor([0.0]))).all()

    # the features on both paths, on a field without holes or edges (their float32 sample points differ
    # from the float64 ones by ~1e-5 m, which near a hole's corner can move the value more than 1e-4)
    field = field_of(NEG, smooth, lambda x, z: smooth(x, z) + 5.0)
    region = DenseRegion.from_field(field, -990.0, -910.0, 790.0, 870.0, dtype=dtype)
    n = 64
    root = np.stack([rng.uniform(-970, -930, n), np.zeros(n), rng.uniform(810, 850, n)], axis=1)
    root[:, 1] = smooth(root[:, 0], root[:, 2]) + rng.uniform(0.5, 3.0, n)
    root = root.astype(np.float32).astype(np.float64)
    yaw = rng.uniform(-np.pi, np.pi, n)
    R = np.zeros((n, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = np.cos(yaw), np.sin(yaw), 1.0, -np.sin(yaw), np.cos(yaw)
    patch, known = egocentric_patch(field, root, R, FORWARD)
    patch_t, known_t = egocentric_patch_torch(region, torch.from_numpy(root), torch.from_numpy(R), torch.from_numpy(FORWARD))
    np.testing.assert_array_equal(known_t.numpy(), known)
    np.testing.assert_allclose(patch_t.numpy(), patch, atol=tol, rtol=0)
    joints = root[:, None, :] + rng.normal(0, 1.0, (n, 11, 3))
    clear = joint_clearances(field, joints, root[:, 1])
    clear_t = joint_clearances_torch(region, torch.from_numpy(joints), torch.from_numpy(root[:, 1]))
    np.testing.assert_allclose(clear_t.numpy(), clear, atol=tol, rtol=0)


def test_patch_turns_with_the_heading():
    field = field_of([(0, 0)], lambda x, z: 0.1 * x)  # up along +x
    root = np.array([[50.0, 6.0, 50.0]])
    patch, known = egocentric_patch(field, root, FACING_PLUS_X[None], FORWARD)
    assert patch.shape == (1, 11, 11) and known.all()
    assert (np.diff(patch[0], axis=0) > 0.03).all()  # rows run forward: uphill
    np.testing.assert_allclose(np.diff(patch[0], axis=1), 0.0, atol=1e-6)  # columns run across the slope
    # centred 1 m ahead, root-relative
    assert patch[0, 5, 5] == pytest.approx(0.1 * 51.0 - 6.0)
    facing_minus_x = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    back, _ = egocentric_patch(field, root, facing_minus_x[None], FORWARD)
    assert (np.diff(back[0], axis=0) < -0.03).all()
    # facing +z the slope runs along the columns; the body's right is world −x, so heights fall to the right
    side, _ = egocentric_patch(field, root, np.eye(3)[None], FORWARD)
    assert (np.diff(side[0], axis=1) < -0.03).all()
    # off the data: nan and not known
    edge, known = egocentric_patch(field, np.array([[99.0, 0.0, 50.0]]), FACING_PLUS_X[None], FORWARD)
    assert np.isnan(edge[0, -1]).all() and not known[0, -1].any() and known[0, 0].all()


def test_clearance_is_signed_against_the_layer_nearest_the_root():
    field = deck_field()
    joints = np.array([[[20.0, -0.3 + 0.4, 20.0], [20.0, 0.4 + 0.25, 20.5]], [[50.0, 5.1, 50.0], [50.0, 0.9, 50.0]]])
    ref = np.array([1.3, 6.5])  # first entity on the ground, second on the deck
    c = joint_clearances(field, joints, ref)
    np.testing.assert_allclose(c[0], [-0.3, 0.25], atol=1e-6)
    np.testing.assert_allclose(c[1], [0.1, -4.1], atol=1e-6)  # a joint hanging through the deck is below it
    assert MATCH_M < 5.0 / 2
    flat = field_of([(0, 0)], lambda x, z: np.full_like(x, 2.0))
    assert joint_clearances(flat, np.array([[[30.2, 1.7, 60.9]]]), np.array([3.0]))[0, 0] == pytest.approx(-0.3)


def test_compiled_query_matches_the_numpy_reference_bit_for_bit():
    def holes(x, z):
        return np.where((np.floor(x) % 9 < 3) & (np.floor(z) % 7 < 3), np.nan, smooth(x, z))

    def deck(x, z):  # a second layer over part of the field, within MATCH_M of the ground near its rim
        return np.where((x > -960) & (x < -940) & (z > 840) & (z < 860), smooth(x, z) + 1.5 + 0.1 * (x + 960), np.nan)

    def roof(x, z):
        return np.where(np.floor(x) % 5 == 0, smooth(x, z) + 9.0, np.nan)

    field = field_of(NEG, holes, deck, roof)
    rng = np.random.default_rng(11)
    n = 200_000
    x = rng.uniform(-1105, -795, n)  # past the loaded chunks on both sides, across chunk edges
    z = rng.uniform(695, 905, n)
    x[:2000] = np.round(x[:2000])  # on cell edges, and exactly on cell centres
    z[2000:4000] = np.round(z[2000:4000]) + 0.5
    ref = smooth(x, z) + rng.choice([0.3, 1.6, 5.2, -1.0, 9.5, 30.0], n)
    ref[4000:4100] = np.nan
    x[4100:4200] = np.inf
    got = field.query(x, z, ref)
    want = field.query_reference(x, z, ref)
    np.testing.assert_array_equal(got, want)  # NaN in the same places, equal bits elsewhere
    assert 0.5 < np.isfinite(got).mean() < 1.0
    assert field.query(x[:7].reshape(7, 1), z[:3], ref[0]).shape == (7, 3)
    assert np.isnan(field.query(np.nan, 0.0, 0.0)) and np.ndim(field.query(-1000.0, 800.0, 0.0)) == 0


FAR = [(cx, cz) for cx in (-731, -730, -729) for cz in (-412, -411)]  # x ∈ [−73100, −72800), z ∈ [−41200, −41000)


def stage_chunk(cx, cz, rng, slots=8):
    """A chunk shaped like a real stage's: in 10 × 10-cell patches, half the cells empty, a quarter with
    one layer and a quarter with 2 to ``slots`` layers 0.5–6 m apart (so a neighbour's layer is often,
    not always, within MATCH_M of the anchor), written to the slots in a random order."""
    x, z = cell_centres(cx, cz)
    idx = np.arange(10000)
    kind = rng.choice(3, 100, p=[0.5, 0.25, 0.25])[(idx // 100) // 10 * 10 + (idx % 100) // 10]
    count = np.where(kind == 0, 0, np.where(kind == 1, 1, rng.integers(2, slots + 1, 10000)))
    h = smooth(x, z)[:, None] + np.cumsum(np.c_[np.zeros(10000), rng.uniform(0.5, 6.0, (10000, slots - 1))], axis=1)
    used = np.arange(slots) < count[:, None]
    order = np.argsort(rng.random((10000, slots)), axis=1)
    used, h = np.take_along_axis(used, order, axis=1), np.take_along_axis(h, order, axis=1)
    c = Chunk.empty(cx, cz, slots)
    c.cells["h"][used] = h[used]
    c.cells["n"][used] = (0.0, 1.0, 0.0)
    c.cells["flags"][used] = FLAG_VALID
    return c


def test_compiled_query_matches_the_reference_on_a_realistic_stage_far_out():
    rng = np.random.default_rng(12)
    chunks = {k: stage_chunk(*k, rng) for k in FAR}
    chunks[(-731, -412)] = make_chunk(-731, -412, [smooth], max_layers=8)  # one layer in every cell
    field = LayeredField.from_chunks(chunks)
    n = 200_000
    x, z = rng.uniform(-73105, -72795, n), rng.uniform(-41205, -40995, n)  # past the stage on every side
    x[:10000] = np.round(x[:10000])  # on cell edges and chunk edges
    z[5000:15000] = np.round(z[5000:15000]) + 0.5  # on cell centres
    x[15000:15100], z[15000:15100] = -73000.0 + rng.uniform(-1, 1, 100), -41100.0 + rng.uniform(-1, 1, 100)  # a chunk corner
    layers, _ = field.cell_layers(np.floor(x).astype(np.int64), np.floor(z).astype(np.int64))
    pick = np.floor(rng.random(n) * np.maximum(np.isfinite(layers).sum(axis=1), 1)).astype(np.int64)
    ref = np.where(np.isfinite(layers[:, 0]), layers[np.arange(n), pick], smooth(x, z)) + rng.uniform(-3.0, 3.0, n)
    two = np.flatnonzero(np.isfinite(layers[:, 1]))[:3000]
    ref[two] = (layers[two, 0] + layers[two, 1]) / 2  # exactly between two layers: a tie, to break alike
    ref[-100:], x[-200:-100] = np.nan, -np.inf
    want = field.query_reference(x, z, ref)
    assert 0.4 < np.isfinite(want).mean() < 0.9

    lazy = LayeredField.from_chunks(chunks)
    lazy.query(rng.uniform(-73090, -73010, 1000), rng.uniform(-41190, -41110, 1000), 0.0)
    assert lazy.loaded_chunks == {(-731, -412)} and lazy.width == 1
    got = lazy.query(x, z, ref)  # loads the other chunks inside the query, the slab widening to 8 slots
    assert lazy.width == 8 and lazy.loaded_chunks == field.loaded_chunks
    np.testing.assert_array_equal(got, want)  # NaN in the same places, equal bits elsewhere
    np.testing.assert_array_equal(lazy.query(x, z, ref), want)  # and again, every chunk loaded
    np.testing.assert_array_equal(field.query(x[::-1], z[::-1], ref[::-1]), want[::-1])  # in any order
