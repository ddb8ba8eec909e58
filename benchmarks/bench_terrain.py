"""The layered height field: query speed and accuracy (bilinear vs nearest), and the scan's speed and accuracy by knob.

    .venv/bin/python benchmarks/bench_terrain.py [--points 1000000] [--repeats 3] [--seconds 10]
        [--voxels 0.1,0.25,0.5] [--strides 1,2,4] [--subsamples 1,2,4] [--combos 4:2,4:4] [--source-size 180x320]
        [--max-depths 10,20,30] [--image-normal-ys 0,0.8] [--edge-ms 0,0.1]
        [--part all|queries|stage|scan|fanout|rebuild] [--recordings 4] [--workers 1,2]
        [--stage-chunks 10x6] [--stage-recordings 12]

Input: one seeded synthetic recording (``marionette.synth.generate``, ``--source-size``, default 320×180
(H×W 180x320; WildWorld's 1280×720 is 720x1280), ``--seconds`` long),
made in a temp dir; every figure is per core (BLAS/OpenMP pools and torch at one thread).

Queries. Four fields: hand-built 4 × 4 chunks (400 m × 400 m around the arena) holding the analytic
ground (``terrain.ground_height`` at every cell centre, normals from ``ground_normal``) with one layer
per cell, and with a second layer ``ROOF_M`` above it in every cell (two layers per cell); the field
a scan of the recording gives (``scan_recording`` at defaults, then a ``Stage`` rebuild: merge and
hole fill); and a stage shaped like a real one (``realistic_stage``: 54 chunks far from the origin,
8 layer slots per cell, about half the cells empty and a quarter multi-layer, in patches). Speed:
``--points`` uniform random points over the field (over every chunk of the realistic stage; ref_y
within 1 m of a random layer of the point's cell, or of the unstored ground under an empty one),
``LayeredField.query`` (bilinear) against ``LayeredField.cell_height`` (the containing cell's
nearest layer) and ``query_torch`` on a float32 CPU ``DenseRegion`` (inputs already float32
tensors); median wall and process CPU time of ``--repeats`` after one warm-up run that also loads
the chunks (the CPU time is the figure per core on a shared machine). ``--part stage`` runs the
queries on the hand-built fields and the realistic stage alone (no recording, no scan). Accuracy
(not on the realistic stage, which has no analytic surface): the same points against the analytic
surface (the hand-built fields: the ground, or the roof ``ROOF_M`` above it, whichever layer ref_y
was drawn near; the scanned field: ``terrain.surface_height`` at the point, ref_y the height of a
layer of the scanned cell, points drawn uniformly inside cells the scan observed, not hole-filled). "away from steps" leaves out points within ``STEP_MARGIN_M`` of the
wall's sides, the deck's edges or the terraces' ledges (``terrain.near_step``), where the 2 × 2 cells
a bilinear query reads hold two heights whatever the query does.

Scan. ``scan_recording(ref, load_scene("duel"), DepthDecoder.synthetic(), ...)`` then
``layers.merge``, one factor at a time from the defaults (voxel 0.25 m, stride 1, depth subsample 1 —
every pixel; f keeps one pixel per f × f block, ``image_points.subsampled`` — max depth 20 m, image-normal
test 0.8, edge-leak test 0.1 m; 0 turns a test off), then the ``--combos`` of stride and subsample together:
the CPU time of the whole scan (process time over all threads: sample read, video decode,
back-projection, open3d pass, contacts, merge; one run each, a scan takes seconds) as depth frames
scanned per CPU second and core-ms per recorded frame, and height error of the merged layers at
their cell centres against ``terrain.surface_height`` (as ``tests/test_terrain_accumulate.py``):
all observed cells, and those away from the vertical steps (cell centre more than 0.6 m outside /
inside the wall's, the deck's and the terraces' edges). The edges lie on integer metres, so no cell
straddles one: a layer of a cell touching an edge that reads the level across it is a leak, and
counts in "RMSE all" and "max all".

Fan-out (``--part fanout``, not in "all"). ``--recordings`` seeded recordings of ``--seconds`` at
320×180 ingested into a corpus (ingest defaults, video 176×320; not timed), then for each of
``--workers``: a full scan of its stage (``scan_stages(incremental=False)``, defaults, a recording a
job on forked processes): wall time of the whole scan (jobs, the in-order commit, the chunk rebuild),
depth frames/s, whether the stage's files are byte-identical to the first row's; and the pose pass
over the scanned corpus (``render_pose_targets``, a shard a job on spawned processes; one worker: the
one-process pass): wall time (process start-up included), frames rendered per second, and whether the
video shards are byte-identical to the first row's. BLAS/OpenMP pools are at one thread (inherited by
the workers); llvmpipe and the encoders use what the library gives them.

Rebuild (``--part rebuild``, not in "all"). A generated stage of ``--stage-chunks`` (X×Z chunks, the
first at chunk (−3, −2)) covered by ``--stage-recordings`` seeded recordings on a grid, each a patch of
1.5 grid steps a side (so neighbours overlap) holding 70 % of its cells (the rest are holes for the
fill) on a gentle slope, a deck 5.5 m over every seventh row; then one small recording (20 × 20
cells inside chunk (0, 0)) added. Not timed: making the observations, ``Stage.put`` and the first
rebuild. Timed, each on a fresh copy of that stage (the copy not timed): ``Stage.rebuild`` whole (all
contributions at once: the reference), full (every chunk, one neighbourhood at a time) and
incremental (the chunks whose neighbourhood holds the new recording), then an incremental rebuild
with nothing changed; median wall time of ``--repeats``, and the peak of memory traced by
``tracemalloc`` (Python objects and numpy buffers) in a separate run; whether the chunk files and the
manifest's chunk entries equal the whole rebuild's.
"""

from __future__ import annotations

import argparse
import inspect
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, single_thread_env, table  # noqa: E402

single_thread_env()
os.environ["NUMBA_NUM_THREADS"] = "1"  # the query kernel is serial; this keeps numba's pool at one thread too

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

from marionette import synth  # noqa: E402
from marionette.recordings.wildworld import discover  # noqa: E402
from marionette.schema import load_scene  # noqa: E402
from marionette.synth import terrain  # noqa: E402
from terrain_scan.accumulate import scan_recording, scan_sample  # noqa: E402
from terrain_scan.depth import DepthDecoder  # noqa: E402
from terrain_scan.field import DenseRegion, LayeredField, open_stage, query_torch  # noqa: E402
from terrain_scan.layers import Observations, merge  # noqa: E402
from terrain_scan.store import Stage  # noqa: E402
from terrain_scan.trn2 import CELLS, FLAG_VALID, Chunk  # noqa: E402

SCAN_DEFAULTS = {k: v.default for k, v in inspect.signature(scan_sample).parameters.items()}
TARGET_QPS = 5e6  # bilinear queries/s per core (the target this benchmark checks)
STAGE_TARGET_QPS = 20e6  # the same on the realistic stage
ROOF_M = 6.0  # the hand-built second layer lies this far above the ground (> 2 · MATCH_M: never mixed)
CHUNKS_X, CHUNKS_Z = range(-12, -8), range(6, 10)  # 4 × 4 chunks: x ∈ [−1200, −800), z ∈ [600, 1000)
STAGE_X, STAGE_Z = range(-31, -22), range(40, 46)  # the realistic stage, 9 × 6 chunks: x ∈ [−3100, −2200), z ∈ [4000, 4600)
STAGE_SLOTS = 8  # layer slots per cell in its files; a multi-layer cell holds 2 to 8 layers
STAGE_KINDS = [0.5, 0.25, 0.25]  # share of cells empty, with the ground only, multi-layer
THREADS = f"one thread (BLAS/OpenMP, torch; numba's pool at {numba.config.NUMBA_NUM_THREADS}, the query kernel serial)"
STEP_MARGIN_M = 1.5  # a query reads the 2 × 2 cells around it: within 1.5 m of a step they may straddle it
CELL_STEP_MARGIN_M = 0.6  # the scan test's margin: the cells whose sides or corners touch a step edge
SCAN_HEADER = [
    "varied",
    "voxel m",
    "stride",
    "depth subsample",
    "max depth m",
    "image ny",
    "edge m",
    "frames",
    "CPU s",
    "frames/s",
    "core-ms / recorded frame",
    "points kept",
    "leaked",
    "cells",
    "layers",
    "RMSE all m",
    "max all m",
    "layers away",
    "RMSE away m",
    "p99 away m",
]


# -- fields -------------------------------------------------------------------------------------------


def hand_built_field(n_layers: int) -> LayeredField:
    """Analytic ground at every cell centre of 4 × 4 chunks; with 2 layers, a roof ROOF_M above it."""
    chunks = {}
    col, row = np.meshgrid(np.arange(CELLS), np.arange(CELLS))  # (100, 100): cell index = row·100 + col
    col, row = col.ravel(), row.ravel()
    for cx in CHUNKS_X:
        for cz in CHUNKS_Z:
            xc, zc = cx * CELLS + col + 0.5, cz * CELLS + row + 0.5
            g, n = terrain.ground_height(xc, zc), terrain.ground_normal(xc, zc)
            ch = Chunk.empty(cx, cz, max_layers=n_layers)
            for s in range(n_layers):
                ch.cells["h"][:, s] = g + s * ROOF_M
                ch.cells["n"][:, s] = n
                ch.cells["hits"][:, s] = 1
                ch.cells["flags"][:, s] = FLAG_VALID
            chunks[(cx, cz)] = ch
    return LayeredField.from_chunks(chunks)


def stage_ground(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The realistic stage's lowest layer (m): rolling ground, ±20 m."""
    return 12.0 * np.sin(x / 37.0) + 8.0 * np.cos(z / 23.0) + 0.01 * (x + 2650.0)


def realistic_stage(rng: np.random.Generator) -> tuple[dict[tuple[int, int], Chunk], np.ndarray, np.ndarray]:
    """54 chunks of STAGE_SLOTS slots: each 10 × 10-cell patch is empty, ground only or multi-layer
    (STAGE_KINDS), a tenth of the cells redrawn one by one (ragged patch edges); a multi-layer cell
    holds 2–8 layers 2.5–8 m apart above the ground, written to its slots in a random order.
    Returns the chunks, and per chunk (in STAGE_X-major order) the cells' layers (54, 10000, 8) sorted
    ascending and their counts (54, 10000)."""
    idx = np.arange(CELLS * CELLS)
    col, row = idx % CELLS, idx // CELLS
    patch = (row // 10) * 10 + col // 10
    chunks, layers, counts = {}, [], []
    for cx in STAGE_X:
        for cz in STAGE_Z:
            kind = rng.choice(3, 100, p=STAGE_KINDS)[patch]
            redraw = rng.random(idx.size) < 0.1
            kind[redraw] = rng.choice(3, int(redraw.sum()), p=STAGE_KINDS)
            count = np.where(kind == 0, 0, np.where(kind == 1, 1, rng.integers(2, STAGE_SLOTS + 1, idx.size)))
            gaps = rng.uniform(2.5, 8.0, (idx.size, STAGE_SLOTS))
            gaps[:, 0] = 0.0
            ground = stage_ground(cx * CELLS + col + 0.5, cz * CELLS + row + 0.5)
            h = (ground[:, None] + np.cumsum(gaps, axis=1)).astype(np.float32)
            used = np.arange(STAGE_SLOTS) < count[:, None]
            order = np.argsort(rng.random(used.shape), axis=1)  # slot order carries no meaning
            ch = Chunk.empty(cx, cz, max_layers=STAGE_SLOTS)
            slot_used = np.take_along_axis(used, order, axis=1)
            ch.cells["h"] = np.where(slot_used, np.take_along_axis(h, order, axis=1), 0.0)
            ch.cells["n"][slot_used] = (0.0, 1.0, 0.0)
            ch.cells["hits"][slot_used] = 3
            ch.cells["flags"][slot_used] = FLAG_VALID
            chunks[(cx, cz)] = ch
            layers.append(h)
            counts.append(count)
    return chunks, np.stack(layers), np.stack(counts)


def realistic_points(layers: np.ndarray, counts: np.ndarray, n: int, rng: np.random.Generator):
    """Uniform points over every chunk of the realistic stage, ref_y within 1 m of a random layer of the
    point's cell (of the unstored ground under an empty cell)."""
    k = rng.integers(0, len(STAGE_X) * len(STAGE_Z), n)
    x = STAGE_X[0] * CELLS + (k // len(STAGE_Z)) * CELLS + rng.random(n) * CELLS
    z = STAGE_Z[0] * CELLS + (k % len(STAGE_Z)) * CELLS + rng.random(n) * CELLS
    cell = (np.floor(z).astype(np.int64) % CELLS) * CELLS + np.floor(x).astype(np.int64) % CELLS
    count = counts[k, cell]
    slot = np.floor(rng.random(n) * np.maximum(count, 1)).astype(np.int64)
    base = np.where(count > 0, layers[k, cell, slot], stage_ground(x, z))
    return x, z, base + rng.uniform(-1.0, 1.0, n), None


def hand_built_points(n: int, n_layers: int, rng: np.random.Generator):
    """Uniform points over the 4 × 4 chunks, ref_y within 1 m of a random layer, and the true height."""
    x = rng.uniform(CHUNKS_X[0] * CELLS, (CHUNKS_X[-1] + 1) * CELLS, n)
    z = rng.uniform(CHUNKS_Z[0] * CELLS, (CHUNKS_Z[-1] + 1) * CELLS, n)
    truth = terrain.ground_height(x, z) + ROOF_M * rng.integers(0, n_layers, n)
    return x, z, truth + rng.uniform(-1.0, 1.0, n), truth


def scanned_points(stage: Stage, n: int, rng: np.random.Generator):
    """Uniform points inside observed (not hole-filled) layers' cells, ref_y = the layer's height."""
    layers, filled = stage.layers()
    pick = rng.choice(np.flatnonzero(~filled), n)
    x = layers.gx[pick] + rng.random(n)
    z = layers.gz[pick] + rng.random(n)
    ref = layers.h[pick]
    return x, z, ref, terrain.surface_height(x, z, ref)


# -- queries -------------------------------------------------------------------------------------------


def err_cells(err: np.ndarray) -> list[str]:
    ok = np.isfinite(err)
    e = np.abs(err[ok])
    if not e.size:
        return ["0", "—", "—", "—", f"{(~ok).sum():,}"]
    return [
        f"{e.size:,}",
        f"{1e3 * np.sqrt(np.mean(e**2)):.1f}",
        f"{1e3 * np.percentile(e, 99):.1f}",
        f"{1e3 * e.max():.1f}",
        f"{(~ok).sum():,}",
    ]


def time_call(fn, repeats: int) -> tuple[float, float, object]:
    """Median wall time and median process CPU time (s) of ``fn()`` over ``repeats`` runs after one
    warm-up run; and its last result."""
    out = fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu), out


def bench_queries(fields, n: int, repeats: int):
    """fields: [(name, field, (x, z, ref, truth), target queries/s)], truth None where there is none.
    Returns the speed and accuracy rows."""
    speed, acc = [], []
    for name, field, (x, z, ref, truth), target in fields:
        tx, tz, tr = (torch.from_numpy(v.astype(np.float32)) for v in (x, z, ref))
        pts = (x, z, ref)
        t_bil = time_call(lambda f=field, p=pts: f.query(*p), repeats)  # the warm-up loads the chunks (and compiles)
        t_ref = time_call(lambda f=field, p=pts: f.query_reference(*p), repeats)
        assert np.array_equal(t_bil[2], t_ref[2], equal_nan=True), "the compiled query differs from the numpy reference"
        t_near = time_call(lambda f=field, p=pts: f.cell_height(*p), repeats)
        t0 = time.perf_counter()
        region = DenseRegion.from_field(field, float(x.min()), float(x.max()), float(z.min()), float(z.max()), torch.float32)
        t_region = time.perf_counter() - t0
        t_tor = time_call(lambda r=region, p=(tx, tz, tr): query_torch(r, *p), repeats)
        width = field.width
        for method, (wall, cpu, _) in (
            ("bilinear `query`", t_bil),
            ("bilinear `query_reference` (numpy)", t_ref),
            ("nearest `cell_height`", t_near),
            ("bilinear `query_torch` f32", t_tor),
        ):
            qps = n / cpu
            met = ""
            if method == "bilinear `query`":
                met = f"≥ {target / 1e6:g} M: " + ("**met**" if qps >= target else "**not met**")
            extra = f"{region.nx}×{region.nz} cells, built in {1e3 * t_region:.0f} ms" if "torch" in method else ""
            speed.append([name, width, method, f"{1e3 * wall:.0f}", f"{1e3 * cpu:.0f}", f"{qps / 1e6:.2f}", met, extra])
        if truth is None:
            continue
        h_bil, h_near, h_tor = t_bil[2], t_near[2], t_tor[2].numpy().astype(np.float64)
        away = ~terrain.near_step(x, z, STEP_MARGIN_M)
        for method, h in (("bilinear `query`", h_bil), ("nearest `cell_height`", h_near), ("bilinear `query_torch` f32", h_tor)):
            acc.append([name, method, "all", *err_cells(h - truth)])
            acc.append([name, method, "away from steps", *err_cells((h - truth)[away])])
    return speed, acc


# -- scan ----------------------------------------------------------------------------------------------


def scan_row(ref, layout, decoder, label: str, **kw) -> tuple[list[object], object]:
    t0 = time.process_time()
    res = scan_recording(ref, layout, decoder, **kw)
    obs = merge(res.observations)
    dt = time.process_time() - t0
    recorded = res.frames_total * kw.get("frame_stride", 1)  # the recording's frames (its length is a multiple of 4)
    x, z = obs.gx + 0.5, obs.gz + 0.5
    d = obs.h - terrain.surface_height(x, z, obs.h)
    away = ~terrain.near_step(x, z, CELL_STEP_MARGIN_M)
    cells = len(set(zip(obs.gx.tolist(), obs.gz.tolist())))
    row = [
        label,
        f"{kw.get('voxel_m', 0.25):g}",
        kw.get("frame_stride", 1),
        kw.get("depth_subsample", 1),
        f"{kw.get('max_depth_m', SCAN_DEFAULTS['max_depth_m']):g}",
        f"{kw.get('image_normal_y', SCAN_DEFAULTS['image_normal_y']):g}",
        f"{kw.get('edge_m', SCAN_DEFAULTS['edge_m']):g}",
        res.frames_total,
        f"{dt:.1f}",
        f"{res.frames_total / dt:.1f}",
        f"{1000 * dt / recorded:.1f}",
        f"{res.points_kept:,}",
        f"{res.points_leaked:,}",
        f"{cells:,}",
        f"{len(obs):,}",
        f"{np.sqrt(np.mean(d**2)):.3f}",
        f"{np.abs(d).max():.2f}",
        f"{away.sum():,}",
        f"{np.sqrt(np.mean(d[away] ** 2)):.3f}",
        f"{np.percentile(np.abs(d[away]), 99):.3f}",
    ]
    return row, res


def bench_fanout(args) -> None:
    from marionette.bridge.targets import render_pose_targets
    from marionette.ingest import IngestOptions, build_corpus
    from terrain_scan.scan import scan_stages

    def files(corpus: Path, sub: str, pattern: str = "*") -> dict[str, bytes]:
        root = corpus / sub
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob(pattern)) if p.is_file()}

    scan_rows, pose_rows = [], []
    with tempfile.TemporaryDirectory(prefix="bench_terrain_fanout_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        synth.generate(tmp / "src", recordings=args.recordings, seconds=args.seconds, seed=args.seed, width=320, height=180)
        build_corpus(tmp / "src", tmp / "base", IngestOptions(), workers=2, progress=False)
        setup_s = time.perf_counter() - t0
        frames = args.recordings * round(args.seconds * 30)
        reference = None
        for k in args.workers:
            corpus = tmp / f"scan-{k}"
            shutil.copytree(tmp / "base", corpus)
            t = time.perf_counter()
            report = scan_stages(corpus, incremental=False, log=lambda *_: None, workers=k)
            wall = time.perf_counter() - t
            got = files(corpus, "terrain")
            reference = reference or got
            used = sum(r["frames_used"] for st in report.values() for r in st["scanned"])
            scan_rows.append([k, f"{wall:.1f}", f"{frames / wall:.1f}", used, "yes" if got == reference else "NO"])
        scanned, reference = tmp / f"scan-{args.workers[0]}", None
        for k in args.workers:
            corpus = tmp / f"pose-{k}"
            shutil.copytree(scanned, corpus)
            t = time.perf_counter()
            r = render_pose_targets(corpus, workers=k)
            wall = time.perf_counter() - t
            got = files(corpus, "pose", "*.tar")
            reference = reference or got
            row = [k, f"{wall:.1f}", f"{r.frames_rendered / wall:.1f}", r.frames_rendered, len(r.failed)]
            pose_rows.append(row + ["yes" if got == reference else "NO"])
    print(preamble("Terrain scan and pose targets fanned out over local processes"))
    print(
        f"{args.recordings} × {args.seconds:g} s synthetic recordings at 320×180 (seed {args.seed}), ingested with the "
        f"defaults (video 176×320) in {setup_s:.0f} s (not timed).\n"
    )
    print(f"### Full scan of the stage ({frames} depth frames), defaults\n")
    print(table(["workers", "wall s", "depth frames/s", "frames used", "bytes = 1st row"], scan_rows))
    print("\n### Pose pass: every chunk's target rendered (176×320), a shard a job, fresh (spawned) processes\n")
    print(table(["workers", "wall s", "frames/s", "frames", "failed", "shards = 1st row"], pose_rows))


def realistic_field(args) -> tuple[str, LayeredField, tuple, float]:
    """The realistic stage and its points, from a generator of its own (the same whichever part runs)."""
    rng = np.random.default_rng([args.seed, 1])
    chunks, layers, counts = realistic_stage(rng)
    name = (
        f"realistic stage: {len(chunks)} chunks, {STAGE_SLOTS} slots, {(counts == 0).mean():.0%} of cells empty, "
        f"{(counts > 1).mean():.0%} multi-layer"
    )
    return name, LayeredField.from_chunks(chunks), realistic_points(layers, counts, args.points, rng), STAGE_TARGET_QPS


def print_queries(args, speed_rows: list, acc_rows: list) -> None:
    print(f"### Queries: speed ({args.points:,} random points, median of {args.repeats}, one thread)\n")
    print(
        f"Target: ≥ {TARGET_QPS / 1e6:g} M bilinear queries/s per core, ≥ {STAGE_TARGET_QPS / 1e6:g} M on the realistic "
        "stage (M queries/s: points over CPU time).\n"
    )
    print(table(["field", "W (slots)", "method", "wall ms", "CPU ms", "M queries/s", "target", "torch region"], speed_rows))
    print("\n### Queries: height error against the analytic terrain (mm)\n")
    print(table(["field", "method", "subset", "points", "RMSE mm", "p99 mm", "max mm", "NaN"], acc_rows))


def hand_built_fields(points: int, rng) -> list[tuple[str, LayeredField, tuple, float]]:
    """The hand-built fields with one and two layers per cell, each with its points and target."""
    return [
        (f"hand-built, {k} layer{'s' if k > 1 else ''}/cell", hand_built_field(k), hand_built_points(points, k, rng), TARGET_QPS)
        for k in (1, 2)
    ]


def bench_stage(args) -> None:
    """``--part stage``: the query speed on the hand-built fields and the realistic stage."""
    rng = np.random.default_rng(args.seed)
    fields = hand_built_fields(args.points, rng)
    fields.append(realistic_field(args))
    speed_rows, acc_rows = bench_queries(fields, args.points, args.repeats)
    print(preamble("Terrain: layered height field queries on the hand-built fields and a realistic stage"))
    print(f"Seed {args.seed}; {THREADS}.\n")
    print_queries(args, speed_rows, acc_rows)


def stage_recordings(chunks_x: int, chunks_z: int, n: int, seed: int) -> dict[str, Observations]:
    """``n`` seeded recordings on a grid over chunks_x × chunks_z chunks from chunk (−3, −2), each a patch
    of 1.5 grid steps a side (clipped to the stage) holding 70 % of its cells."""
    rng = np.random.default_rng(seed)
    nx = max(1, round(np.sqrt(n * chunks_x / chunks_z)))
    nz = -(-n // nx)
    x0, z0 = -3 * CELLS, -2 * CELLS
    sx, sz = chunks_x * CELLS / nx, chunks_z * CELLS / nz
    out = {}
    for i in range(n):
        ix, iz = i % nx, i // nx
        ax, az = int(x0 + (ix - 0.25) * sx), int(z0 + (iz - 0.25) * sz)
        gx, gz = np.meshgrid(np.arange(ax, ax + int(1.5 * sx)), np.arange(az, az + int(1.5 * sz)), indexing="ij")
        gx, gz = gx.ravel(), gz.ravel()
        inside = (gx >= x0) & (gx < x0 + chunks_x * CELLS) & (gz >= z0) & (gz < z0 + chunks_z * CELLS)
        keep = inside & (rng.random(len(gx)) < 0.7)
        out[f"bench/rec{i:04d}"] = patch(rng, gx[keep], gz[keep], 1767225600 + 3600 * i)
    return out


def patch(rng: np.random.Generator, gx: np.ndarray, gz: np.ndarray, ts: int) -> Observations:
    """Ground on a gentle slope (2 cm of noise) at cells (gx, gz), a deck 5.5 m up over every 7th row."""
    h = 20.0 + 0.05 * gx - 0.03 * gz + rng.normal(0, 0.02, len(gx))
    deck = (gz % 7) == 0
    gx, gz, h = np.r_[gx, gx[deck]], np.r_[gz, gz[deck]], np.r_[h, h[deck] + 5.5]
    n = np.tile([0.0, 1.0, 0.0], (len(gx), 1))
    return Observations(
        gx.astype(np.int64), gz.astype(np.int64), h, n, rng.integers(1, 20, len(gx)), np.full(len(gx), ts, np.int64)
    )


REBUILDS = [  # (row label, Stage.rebuild mode, rebuilt once before the timed run)
    ("whole stage at once (reference)", "whole", False),
    ("full, chunk by chunk", "full", False),
    ("incremental, one small recording added", "incremental", False),
    ("incremental, nothing changed", "incremental", True),
]


def bench_rebuild(args) -> None:
    import json
    import tracemalloc

    chunks_x, chunks_z = (int(v) for v in args.stage_chunks.split("x"))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_terrain_rebuild_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        recs = stage_recordings(chunks_x, chunks_z, args.stage_recordings, args.seed)
        base = Stage(tmp / "base")
        for name, obs in recs.items():
            base.put(name, obs, name, int(obs.ts[0]))
        first = base.rebuild()
        gx, gz = np.meshgrid(np.arange(40, 60), np.arange(40, 60), indexing="ij")  # inside chunk (0, 0)
        small = patch(np.random.default_rng(args.seed + 1), gx.ravel(), gz.ravel(), 1767225600 + 3600 * len(recs))
        base.put("bench/small", small, "bench/small", int(small.ts[0]))
        setup_s = time.perf_counter() - t0

        def fresh(name: str, mode: str, again: bool) -> Stage:
            """A copy of the stage with the small recording put (and rebuilt once, with ``again``)."""
            shutil.copytree(tmp / "base", tmp / name)
            if again:
                Stage(tmp / name).rebuild(mode)
            return Stage(tmp / name)

        reference = None
        for label, mode, again in REBUILDS:
            times = []
            for k in range(args.repeats):
                stage = fresh(f"{mode}-{again}-{k}", mode, again)
                t = time.perf_counter()
                rep = stage.rebuild(mode)
                times.append(time.perf_counter() - t)
            chunks = {p.name: p.read_bytes() for p in sorted((stage.dir / "chunks").glob("*.trn2"))}
            got = (chunks, json.loads((stage.dir / "manifest.json").read_text())["chunks"])
            reference = reference or got
            stage = fresh(f"{mode}-{again}-mem", mode, again)
            tracemalloc.start()
            stage.rebuild(mode)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            same = "yes" if got == reference else "NO"
            rows.append(
                [label, len(rep.derived), len(rep.written), rep.read, f"{np.median(times):.2f}", f"{peak / 2**20:.0f}", same]
            )
    print(preamble("Terrain: rebuilding a stage's chunks, whole against chunk by chunk and incremental"))
    print(
        f"A generated stage of {chunks_x} × {chunks_z} chunks ({len(first.written)} chunk files, {first.layers:,} layers, "
        f"{first.filled:,} filled) from {len(recs)} recordings ({sum(len(o) for o in recs.values()):,} cell observations), "
        f"then one recording of {len(small):,} observations in chunk (0, 0) added; made in {setup_s:.0f} s (not timed). "
        f"One thread; median of {args.repeats}, each on a fresh copy of the stage.\n"
    )
    header = ["rebuild", "chunks derived", "written", "contributions read", "wall s", "peak traced MiB", "bytes = whole"]
    print(table(header, rows))


def floats(s: str) -> list[float]:
    return [float(v) for v in s.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--voxels", type=floats, default=[0.1, 0.25, 0.5])
    ap.add_argument("--strides", type=lambda s: [int(v) for v in s.split(",")], default=[1, 2, 4])
    ap.add_argument("--subsamples", type=lambda s: [int(v) for v in s.split(",")], default=[1, 2, 4])
    ap.add_argument(
        "--combos",
        type=lambda s: [tuple(int(x) for x in v.split(":")) for v in s.split(",")],
        default=[(4, 2), (4, 4)],
        help="stride:subsample pairs scanned together",
    )
    ap.add_argument("--source-size", default="180x320", help="the recording's size HxW (WildWorld's: 720x1280)")
    ap.add_argument("--max-depths", type=floats, default=[10.0, 20.0, 30.0])
    ap.add_argument("--image-normal-ys", type=floats, default=[0.0, 0.8])
    ap.add_argument("--edge-ms", type=floats, default=[0.0, 0.1])
    ap.add_argument(
        "--part",
        choices=("all", "queries", "stage", "scan", "fanout", "rebuild"),
        default="all",
        help="stage: the queries on the hand-built fields and the realistic stage only (no recording, no scan)",
    )
    ap.add_argument("--recordings", type=int, default=4, help="recordings in the fan-out corpus")
    ap.add_argument("--workers", type=lambda s: [int(v) for v in s.split(",")], default=[1, 2], help="fan-out worker counts")
    ap.add_argument("--stage-chunks", default="10x6", help="rebuild: the generated stage's extent in chunks, X×Z")
    ap.add_argument("--stage-recordings", type=int, default=12, help="rebuild: recordings over the generated stage")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.part == "rebuild":
        bench_rebuild(args)
        return
    if args.part == "fanout":
        bench_fanout(args)
        return
    if args.part == "stage":
        bench_stage(args)
        return
    rng = np.random.default_rng(args.seed)
    layout, decoder = load_scene("duel"), DepthDecoder.synthetic()
    with tempfile.TemporaryDirectory(prefix="bench_terrain_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        sh, sw = (int(v) for v in args.source_size.split("x"))
        synth.generate(tmp / "src", recordings=1, seconds=args.seconds, seed=args.seed, width=sw, height=sh)
        ref = discover(tmp / "src")[0]
        setup_s = time.perf_counter() - t0

        scan_rows = []
        default_row, default_res = scan_row(ref, layout, decoder, "defaults")
        if args.part in ("all", "scan"):
            scan_rows.append(default_row)
            for v in args.voxels:
                if v != 0.25:
                    scan_rows.append(scan_row(ref, layout, decoder, "voxel", voxel_m=v)[0])
            for s in args.strides:
                if s != 1:
                    scan_rows.append(scan_row(ref, layout, decoder, "stride", frame_stride=s)[0])
            for f in args.subsamples:
                if f != 1:
                    scan_rows.append(scan_row(ref, layout, decoder, "depth subsample", depth_subsample=f)[0])
            for st, f in args.combos:
                scan_rows.append(scan_row(ref, layout, decoder, "stride + subsample", frame_stride=st, depth_subsample=f)[0])
            for m in args.max_depths:
                if m != SCAN_DEFAULTS["max_depth_m"]:
                    scan_rows.append(scan_row(ref, layout, decoder, "max depth", max_depth_m=m)[0])
            for ny in args.image_normal_ys:
                if ny != SCAN_DEFAULTS["image_normal_y"]:
                    scan_rows.append(scan_row(ref, layout, decoder, "image normal", image_normal_y=ny)[0])
            for e in args.edge_ms:
                if e != SCAN_DEFAULTS["edge_m"]:
                    scan_rows.append(scan_row(ref, layout, decoder, "edge leak", edge_m=e)[0])

        speed_rows, acc_rows = [], []
        if args.part in ("all", "queries"):
            stage = Stage(tmp / "stage")
            stage.put(f"{ref.part}/{ref.sample_id}", default_res.observations, "bench", default_res.recording_ts)
            stage.rebuild()
            fields = hand_built_fields(args.points, rng)
            fields.append(("scanned (defaults)", open_stage(tmp / "stage"), scanned_points(stage, args.points, rng), TARGET_QPS))
            fields.append(realistic_field(args))
            speed_rows, acc_rows = bench_queries(fields, args.points, args.repeats)

        print(preamble("Terrain: layered height field queries and the scan"))
        print(
            f"1 × {args.seconds:g} s synthetic recording at {sw}×{sh} (seed {args.seed}, 30 fps), made in {setup_s:.0f} s "
            f"(not timed); {THREADS}.\n"
        )
        if speed_rows:
            print_queries(args, speed_rows, acc_rows)
        if scan_rows:
            print("\n### Scan: speed and height error by knob (one run each; error in m at cell centres)\n")
            print(table(SCAN_HEADER, scan_rows))


if __name__ == "__main__":
    main()
