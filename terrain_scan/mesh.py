"""Tessellating a layered height field into a triangle mesh (multi-layer aware).

Every layer of every cell is a vertex at its cell centre (gx + 0.5, h, gz + 0.5). For each 2 × 2
block of cells anchored at (gx, gz), each layer of the anchor cell looks, in each of the three other
cells, for the layer nearest its own height; a neighbour joins only when that layer is within
JOIN_M of the anchor. Four joined corners give two triangles, three give one, fewer none — so no
triangle ever bridges a floor to a roof, and a wall taller than JOIN_M leaves an open step rather
than a ramp. Triangles wind counter-clockwise seen from above (normals point up).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from terrain_scan.layers import DenseGrid, Observations

JOIN_M = 1.0


def tessellate(layers: Observations, join_m: float = JOIN_M) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 world metres, faces (F, 3) int64) of the layers' surface."""
    if not len(layers):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    g = DenseGrid.of(layers, margin=1)  # the margin row/column stays empty: neighbours past the edge
    cx, cz = g.cx, g.cz
    H = g.scatter(layers.h, np.nan)
    V = g.scatter(np.arange(len(layers)), -1)
    verts = np.stack([layers.gx + 0.5, layers.h, layers.gz + 0.5], axis=1).astype(np.float64)

    def match(dx: int, dz: int) -> np.ndarray:
        """Vertex of the neighbour (dx, dz) matched to each layer, -1 when none is within join_m."""
        nx, nz = cx + dx, cz + dz
        nh = H[nx, nz]  # (N, L); the padding row/column (index X-1, Z-1) is empty
        d = np.abs(nh - layers.h[:, None])
        d = np.where(np.isnan(d), np.inf, d)
        j = d.argmin(axis=1)
        ok = d[np.arange(len(j)), j] <= join_m
        return np.where(ok, V[nx, nz, j], -1)

    a = np.arange(len(layers))
    b, c, d = match(1, 0), match(0, 1), match(1, 1)  # +x, +z, diagonal
    faces = []
    # corners: a (x, z), b (x+1, z), c (x, z+1), d (x+1, z+1); counter-clockwise seen from +Y is a→c→b
    full = (b >= 0) & (c >= 0) & (d >= 0)
    faces += [np.stack([a[full], c[full], b[full]], 1), np.stack([b[full], c[full], d[full]], 1)]
    for m, tri in (
        ((b >= 0) & (c >= 0) & (d < 0), (a, c, b)),
        ((b >= 0) & (d >= 0) & (c < 0), (a, d, b)),
        ((c >= 0) & (d >= 0) & (b < 0), (a, c, d)),
    ):
        faces.append(np.stack([t[m] for t in tri], 1))
    return verts, np.concatenate(faces).astype(np.int64)


def to_trimesh(layers: Observations, join_m: float = JOIN_M):
    """The tessellation as a ``trimesh.Trimesh`` (for rendering and export)."""
    import trimesh

    v, f = tessellate(layers, join_m)
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def export(layers: Observations, path: Path, join_m: float = JOIN_M, origin: np.ndarray | None = None) -> Path:
    """Write the mesh as PLY or GLB (by suffix). ``origin`` is subtracted first: float32 formats lose
    centimetres a kilometre from the origin, so inspection files are stored stage-relative."""
    mesh = to_trimesh(layers, join_m)
    if origin is not None:
        mesh.vertices = mesh.vertices - np.asarray(origin, np.float64)
    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in ("ply", "glb"):
        raise ValueError(f"{path}: export as .ply or .glb")
    from marionette.io import write_bytes

    write_bytes(path, mesh.export(file_type=suffix))
    return path
