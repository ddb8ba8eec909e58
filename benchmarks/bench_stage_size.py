"""A pose frame's cost against the size of its stage's terrain: the rasterizer drawing the tiles a frame may see
against drawing the whole mesh.

    .venv/bin/python benchmarks/bench_stage_size.py [--chunks 1,3,6,10] [--size 704x1280] [--frames 60] [--repeats 3]

Input: for each count n in ``--chunks``, a seeded stage of n × n terrain chunks of 100 m (1 m cells: a rolling
ground, 20,000 triangles a chunk, as ``terrain_scan.mesh.tessellate`` makes of a full layer), its centre 3 km from
the origin at negative x; a camera walking 2 m above the ground through the centre of the stage and turning (a full
turn over the frames), looking 10° down, the render's defaults (``RenderSettings``: z_near 0.3 m, z_far 100 m, the
terrain's near cull 3 m), no bones. Per frame: ``Rasterizer.render_packed`` at ``--size`` (draw and read back), Mesa
llvmpipe on the calling thread (``LP_NUM_THREADS=0``, what a worker allotted one core uses), the median of
``--repeats`` passes after a warm-up one; (a) the rasterizer as it is (the tiles of ``TERRAIN_TILE_M`` whose box may
meet the frame's view); (b) the whole mesh as one tile (drawn whenever any of it is seen). Reported: milliseconds a
frame, the triangles a frame draws (mean), and whether every frame's codes are the same both ways (asserted after
the table).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, single_thread_env, size_hw, table  # noqa: E402

CHUNK_M = 100


def stage(n: int, seed: int = 0):
    """Vertices (V, 3) float64 and faces (F, 3) of an n × n-chunk rolling ground, and its centre."""
    import numpy as np

    rng = np.random.default_rng(seed)
    centre = np.array([-3000.0, 40.0, 1500.0])
    side = n * CHUNK_M
    xs = np.arange(side + 1, dtype=np.float64) - side / 2
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    waves = rng.uniform(15.0, 60.0, size=(3, 2))
    Y = sum(a * np.sin(X / wx) * np.cos(Z / wz) for a, (wx, wz) in zip((4.0, 2.0, 1.0), waves))
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], -1) + centre
    i = np.arange(X.size).reshape(X.shape)
    a, b, c, d = i[:-1, :-1], i[1:, :-1], i[:-1, 1:], i[1:, 1:]
    F = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return V, F, centre


def walk(centre, frames: int, H: int, W: int):
    """Cameras walking 60 m through the centre, turning once, 2 m above the mean ground, 10° down."""
    import numpy as np

    from marionette.bridge.camera import Cameras, intrinsics_for, look_at

    s = np.linspace(-30.0, 30.0, frames)
    yaw = np.linspace(0.0, 2 * np.pi, frames, endpoint=False)
    eye = centre + np.stack([s, np.full(frames, 2.0), 0.3 * s], -1)
    fwd = np.stack([np.cos(yaw), np.full(frames, -np.tan(np.radians(10.0))), np.sin(yaw)], -1)
    K = np.repeat(intrinsics_for(W, H)[None], frames, 0)
    return Cameras(K, eye, look_at(eye, eye + fwd), np.ones(frames, bool), W, H)


def measure(V, F, cams, repeats: int, whole: bool):
    """(median ms a frame, mean triangles drawn a frame, the frames' codes)."""
    import numpy as np

    import marionette.bridge.render as render
    from marionette.bridge.targets import RenderSettings

    s = RenderSettings()
    tile = render.TERRAIN_TILE_M
    if whole:
        render.TERRAIN_TILE_M = 1e9  # one tile: the whole mesh
    try:
        rast = render.Rasterizer(cams.width, cams.height)
        rast.set_terrain(V, F)
    finally:
        render.TERRAIN_TILE_M = tile
    none = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    lo, hi = float(V[:, 1].min()) - 2, float(V[:, 1].max()) + 10

    def one_pass():
        return [rast.render_packed(cams, i, none, lo, hi, s.z_near, s.z_far, s.cull_m) for i in range(len(cams))]

    frames = one_pass()
    times = []
    for _ in range(repeats):
        t = time.process_time()
        one_pass()
        times.append((time.process_time() - t) / len(cams) * 1000)
    drawn = np.mean([sum(c for _, c in rast.terrain_ranges(cams, i, s.z_near, s.z_far, s.cull_m)) // 3 for i in range(len(cams))])
    rast.release()
    return float(np.median(times)), float(drawn), frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chunks", type=lambda t: [int(v) for v in t.split(",")], default=[1, 3, 6, 10])
    ap.add_argument("--size", type=size_hw, default=(704, 1280))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if min(args.chunks) < 1 or args.frames < 1 or args.repeats < 1:
        ap.error("--chunks, --frames and --repeats must be positive")
    single_thread_env()
    os.environ["LP_NUM_THREADS"] = "0"  # before the first GL context
    import numpy as np

    H, W = args.size
    rows, same = [], []
    for n in args.chunks:
        V, F, centre = stage(n)
        cams = walk(centre, args.frames, H, W)
        t_tiles, d_tiles, a = measure(V, F, cams, args.repeats, whole=False)
        t_whole, d_whole, b = measure(V, F, cams, args.repeats, whole=True)
        ok = all(np.array_equal(x, y) for x, y in zip(a, b))
        same.append(ok)
        rows.append(
            [f"{n}×{n}", f"{len(F):,}", f"{t_tiles:.2f}", f"{d_tiles:,.0f}", f"{t_whole:.2f}", f"{d_whole:,.0f}"]
            + [f"{t_whole / t_tiles:.2f}×", "yes" if ok else "NO"]
        )
        print(f"{n}×{n} chunks: tiles {t_tiles:.2f} ms, whole {t_whole:.2f} ms", file=sys.stderr, flush=True)
    print(preamble("A pose frame against its stage's size"))
    print(f"{H}×{W}, {args.frames} frames, llvmpipe on the drawing thread, median of {args.repeats} passes.\n")
    header = ["stage (chunks of 100 m)", "triangles", "tiles ms/frame", "tiles: triangles drawn/frame"]
    header += ["whole ms/frame", "whole: triangles drawn/frame", "whole / tiles", "codes identical"]
    print(table(header, rows))
    assert all(same), "the tiles drew other codes than the whole mesh"


if __name__ == "__main__":
    main()
