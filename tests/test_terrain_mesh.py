"""Tessellation: flat field closed, no triangle bridges a floor and a roof, normals up, export."""

import numpy as np
import trimesh

from terrain_scan.layers import Observations
from terrain_scan.mesh import export, tessellate


def grid(x0, z0, nx, nz, h):
    gx, gz = np.meshgrid(np.arange(x0, x0 + nx), np.arange(z0, z0 + nz), indexing="ij")
    gx, gz = gx.ravel().astype(np.int64), gz.ravel().astype(np.int64)
    hh = h(gx, gz) if callable(h) else np.full(len(gx), float(h))
    return Observations(
        gx, gz, hh, np.tile([0.0, 1.0, 0.0], (len(gx), 1)), np.ones(len(gx), np.int64), np.zeros(len(gx), np.int64)
    )


def test_flat_grid_is_a_full_upward_sheet():
    v, f = tessellate(grid(-955, 845, 10, 8, 20.0))
    assert len(v) == 80 and len(f) == 2 * 9 * 7
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (n[:, 1] > 0).all()  # counter-clockwise seen from above
    np.testing.assert_allclose(np.abs(n).sum(1), n[:, 1])  # flat: normals straight up


def test_no_triangle_bridges_levels_and_walls_leave_steps():
    ground = grid(0, 0, 10, 10, 0.0)
    deck = grid(3, 0, 4, 10, 5.5)
    wall = grid(0, 20, 10, 4, lambda gx, gz: np.where(gx >= 5, 3.0, 0.0))
    layers = Observations.concat([ground, deck, wall])
    v, f = tessellate(layers)
    span = v[f][:, :, 1].max(1) - v[f][:, :, 1].min(1)
    assert span.max() <= 1.0  # every triangle lies on one level
    # both levels are meshed
    ys = v[f][:, :, 1]
    assert (ys == 5.5).all(1).any() and (ys == 0.0).all(1).any()


def test_export_ply_and_glb(tmp_path):
    layers = grid(-955, 845, 5, 5, lambda gx, gz: 20.0 + 0.1 * gx)
    for name in ("t.ply", "t.glb"):
        p = export(layers, tmp_path / name, origin=np.array([-950.0, 0.0, 850.0]))
        m = trimesh.load(p, force="mesh")
        assert len(m.faces) == 32 and abs(m.vertices[:, 0].min() - (-4.5)) < 1e-4
