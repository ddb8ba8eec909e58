"""Rotation conventions, golden vectors, numpy/torch agreement, extremes, reconstruction, resampling."""

import numpy as np
import pytest
import torch

from marionette import geometry as geo
from marionette.schema import load_scene

YAW90_Q = np.array([0.0, 0.7071068, 0.0, 0.7071068])
YAW90_R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_golden_vectors():
    assert np.array_equal(geo.matrix_to_rot6d(np.eye(3)), [1, 0, 0, 0, 1, 0])
    assert np.array_equal(geo.matrix_to_rot6d(YAW90_R), [0, 0, -1, 0, 1, 0])
    np.testing.assert_allclose(geo.quat_to_matrix(YAW90_Q), YAW90_R, atol=1e-7)
    np.testing.assert_allclose(geo.quat_to_rot6d(YAW90_Q), [0, 0, -1, 0, 1, 0], atol=1e-7)
    np.testing.assert_allclose(geo.rot6d_to_matrix(np.array([0.0, 0, -1, 0, 1, 0])), YAW90_R, atol=0)
    # +90° yaw turns the +Z forward axis to +X
    np.testing.assert_allclose(YAW90_R @ [0, 0, 1], [1, 0, 0], atol=0)


def test_round_trips_and_orthonormality():
    q = random_quats(2000)
    R = geo.quat_to_matrix(q)
    np.testing.assert_allclose(R @ geo.transpose(R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(geo.rot6d_to_matrix(geo.matrix_to_rot6d(R)), R, atol=1e-12)
    q2 = geo.matrix_to_quat(R)
    np.testing.assert_allclose(np.abs(np.sum(q2 * q, axis=1)), 1.0, atol=1e-12)  # same rotation up to sign


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_numpy_and_torch_agree(dtype):
    q = random_quats(500, seed=1)
    d6 = np.random.default_rng(2).normal(size=(7, 3, 6))
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for fn, x in [
        (geo.quat_to_matrix, q),
        (geo.matrix_to_quat, geo.quat_to_matrix(q)),
        (geo.matrix_to_rot6d, geo.quat_to_matrix(q)),
        (geo.rot6d_to_matrix, d6),
    ]:
        got = fn(torch.tensor(x, dtype=dtype)).double().numpy()
        np.testing.assert_allclose(got, fn(x), atol=tol, err_msg=fn.__name__)
    t = np.linspace(0, 1, 500)
    got = geo.quat_slerp(torch.tensor(q), torch.tensor(q[::-1].copy()), torch.tensor(t)).numpy()
    np.testing.assert_allclose(got, geo.quat_slerp(q, q[::-1], t), atol=1e-12)


def test_degenerate_6d_gives_rotations():
    cases = np.array(
        [
            [0, 0, 0, 0, 0, 0],  # all zero
            [0, 1, 0, 0, 2, 0],  # parallel columns
            [1e-30, 0, 0, 0, 1e-30, 0],  # tiny
            [1e30, 0, 0, 0, 1e30, 0],  # huge
            [1, 0, 0, -1, 1e-9, 0],  # nearly antiparallel
            [np.float64(3), 4, 0, 8, 6, 0],  # non-unit, non-orthogonal
        ],
        dtype=np.float64,
    )
    for backend in (lambda x: x, torch.tensor):
        R = np.asarray(geo.rot6d_to_matrix(backend(cases)))
        assert np.isfinite(R).all()
        np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_half_precision_6d():
    q = random_quats(256, seed=3)
    d6 = torch.tensor(geo.quat_to_rot6d(q), dtype=torch.float16)
    R = geo.rot6d_to_matrix(d6.float())
    np.testing.assert_allclose(R.numpy(), geo.quat_to_matrix(q), atol=5e-3)
    Rh = geo.rot6d_to_matrix(d6)  # computed in float16 throughout
    assert torch.isfinite(Rh).all()
    np.testing.assert_allclose(Rh.float().numpy(), geo.quat_to_matrix(q), atol=2e-2)


def test_zero_quaternion_is_identity_and_slerp_handles_equal_and_opposite():
    np.testing.assert_allclose(geo.quat_to_matrix(np.zeros(4)), np.eye(3))
    q = random_quats(10, seed=4)
    np.testing.assert_allclose(geo.quat_slerp(q, q, np.full(10, 0.3)), q, atol=1e-12)
    # -q is the same rotation: slerp must not travel the long way round
    mid = geo.quat_slerp(q, -q, np.full(10, 0.5))
    np.testing.assert_allclose(geo.quat_to_matrix(mid), geo.quat_to_matrix(q), atol=1e-12)


def test_quat_continuity_flips_signs():
    yaw = np.linspace(0, 6 * np.pi, 400)
    q = geo.yaw_quat(yaw)
    q[::3] *= -1
    c = geo.quat_continuity(q)
    assert (np.sum(c[1:] * c[:-1], axis=1) > 0).all()
    np.testing.assert_allclose(geo.quat_to_matrix(c), geo.quat_to_matrix(q), atol=1e-12)


def synthetic_world(n=1200, offset=(-950.0, 40.0, 850.0), seed=0):
    """A smooth random walk of every duel entity, far from the origin."""
    rng = np.random.default_rng(seed)
    layout = load_scene("duel")
    joints, rots = {}, {}
    for e in layout.articulated:
        yaw = np.cumsum(rng.normal(0, 0.05, n))
        pitch = 0.2 * np.sin(np.linspace(0, 20, n))
        q = geo.quat_continuity(
            np.stack(
                [
                    np.sin(pitch / 2) * np.cos(yaw / 2),
                    np.sin(yaw / 2) * np.cos(pitch / 2),
                    -np.sin(pitch / 2) * np.sin(yaw / 2),
                    np.cos(yaw / 2) * np.cos(pitch / 2),
                ],
                1,
            )
        )
        root = np.asarray(offset) + np.cumsum(rng.normal(0, 0.1, (n, 3)), axis=0)
        local = rng.normal(0, 1.0, (e.rig.n_keep - 1, 3)) + 0.05 * rng.normal(size=(n, e.rig.n_keep - 1, 3))
        R = geo.quat_to_matrix(q)
        joints[e.name] = np.concatenate([root[:, None], geo.to_world(local, root, R)], axis=1)
        rots[e.name] = q
    hun = joints["hunter"]
    joints["weapon"] = hun[:, [10, 12]] + np.array([0.0, 1.6, 0.0])
    return layout, joints, rots


def test_world_state_round_trip_far_from_origin():
    layout, joints, rots = synthetic_world(offset=(-950.0, 40.0, 850.0))
    # The recording itself is float32 (skeleton.npz): quantise first, as ingest sees it.
    joints = {k: v.astype(np.float32).astype(np.float64) for k, v in joints.items()}
    state = geo.world_to_state(layout, joints, rots)
    assert state.shape == (1200, 276) and state.dtype == np.float32
    np.testing.assert_array_equal(state[0, layout.slice("monster.root")], 0)
    back = geo.state_to_world(layout, state, {e.name: joints[e.name][0, 0] for e in layout.articulated})
    for name in ("monster", "hunter", "weapon"):
        err = np.abs(back[name]["joints"] - joints[name]).max()
        assert err < 1e-4, (name, err)


def test_negative_and_huge_coordinates_reconstruct():
    for offset in [(-100_000.0, -5_000.0, -100_000.0), (0.0, 0.0, 0.0)]:
        layout, joints, rots = synthetic_world(n=300, offset=offset, seed=5)
        state = geo.world_to_state(layout, joints, rots)
        # state is local: independent of where in the world the scene is
        assert np.abs(state).max() < 50
        back = geo.state_to_world(layout, state, {e.name: joints[e.name][0, 0] for e in layout.articulated})
        assert np.abs(back["hunter"]["joints"] - joints["hunter"]).max() < 1e-4


def test_resampling_linear_motion_is_exact_and_discrete_fields_hold():
    t30 = np.arange(91) / 30
    x = np.stack([3 * t30 - 950, 0.5 * t30, -2 * t30 + 850], 1)
    t20 = np.arange(61) / 20
    got = geo.resample_positions(t30, x, t20)
    want = np.stack([3 * t20 - 950, 0.5 * t20, -2 * t20 + 850], 1)
    np.testing.assert_allclose(got, want, atol=1e-9)
    idx = geo.index_at_or_before(t30, t20)
    assert (t30[idx] <= t20 + 1e-9).all() and (t20 - t30[idx] < 1 / 30 + 1e-9).all()
    # constant-rate yaw: slerp reproduces it exactly
    q = geo.yaw_quat(1.3 * t30)
    np.testing.assert_allclose(
        geo.quat_to_matrix(geo.resample_quats(t30, q, t20)), geo.quat_to_matrix(geo.yaw_quat(1.3 * t20)), atol=1e-9
    )


def test_empty_and_single_frame_sequences():
    layout = load_scene("duel")
    empty = {e.name: np.zeros((0, e.rig.n_keep, 3)) for e in layout.entities}
    rots = {e.name: np.zeros((0, 4)) for e in layout.articulated}
    state = geo.world_to_state(layout, empty, rots)
    assert state.shape == (0, 276)
    back = geo.state_to_world(layout, state, {e.name: np.zeros(3) for e in layout.articulated})
    assert back["hunter"]["joints"].shape == (0, 32, 3)
    t = np.array([0.5])
    np.testing.assert_allclose(geo.resample_positions(t, np.ones((1, 3)), np.array([0.0, 0.5, 1.0])), np.ones((3, 3)))
    np.testing.assert_allclose(
        geo.resample_quats(t, geo.yaw_quat(np.array([0.3])), np.array([0.0, 1.0])), geo.yaw_quat(np.array([0.3, 0.3]))
    )
