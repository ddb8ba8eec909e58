"""The layer merge rule: order independence, hit weighting, layer cap, no NaN."""

import numpy as np

from terrain_scan.layers import Observations, merge


def obs(rows):
    a = np.asarray(rows, np.float64).reshape(-1, 6)  # gx, gz, h, ny, hits, ts
    n = np.zeros((len(a), 3))
    n[:, 1] = a[:, 3]
    return Observations(
        a[:, 0].astype(np.int64), a[:, 1].astype(np.int64), a[:, 2], n, a[:, 4].astype(np.int64), a[:, 5].astype(np.int64)
    )


def as_rows(o):
    return sorted(zip(o.gx.tolist(), o.gz.tolist(), np.round(o.h, 9).tolist(), o.hits.tolist(), o.ts.tolist()))


def test_hit_weighted_merge_within_half_a_metre_and_separate_levels():
    o = obs(
        [[-951, 850, 10.0, 1, 3, 100], [-951, 850, 10.4, 1, 1, 200], [-951, 850, 15.2, 1, 5, 50], [-951, 850, 15.0, 1, 5, 60]]
    )
    L = merge(o)
    assert as_rows(L) == [(-951, 850, 10.1, 4, 200), (-951, 850, 15.1, 10, 60)]
    np.testing.assert_allclose(L.n, [[0, 1, 0], [0, 1, 0]])


def test_order_of_arrival_does_not_matter():
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(400):
        gx, gz = rng.integers(-3, 3), rng.integers(-3, 3)
        base = 20.0 + (6.0 if rng.random() < 0.3 else 0.0)
        rows.append([gx, gz, base + rng.normal(0, 0.1), 1, rng.integers(1, 9), rng.integers(0, 1000)])
    o = obs(rows)
    ref = merge(o)
    for seed in range(5):
        perm = np.random.default_rng(seed).permutation(len(o))
        got = merge(o.take(perm))
        assert as_rows(got) == as_rows(ref)
        np.testing.assert_array_equal(got.n, ref.n)
    # merging per-part results again equals merging everything at once (contributions compose)
    half = len(o) // 2
    two_step = merge(Observations.concat([merge(o.take(np.arange(half))), merge(o.take(np.arange(half, len(o))))]))
    assert {(r[0], r[1]) for r in as_rows(two_step)} == {(r[0], r[1]) for r in as_rows(ref)}
    assert sum(r[3] for r in as_rows(two_step)) == sum(r[3] for r in as_rows(ref))


def test_layer_cap_drops_the_least_hit_and_nan_never_enters():
    rows = [[0, 0, 2.0 * k, 1, k + 1, 0] for k in range(10)] + [[0, 0, float("nan"), 1, 50, 0], [0, 0, 1.0, float("nan"), 50, 0]]
    L = merge(obs(rows), max_layers=8)
    assert len(L) == 8 and sorted(L.hits.tolist()) == list(range(3, 11))
    assert np.isfinite(L.h).all() and np.isfinite(L.n).all()
    assert len(merge(Observations.empty())) == 0
