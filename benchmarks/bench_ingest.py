"""Ingest throughput per core: state.csv + skeleton.npz → state shard, against pyarrow's CSV parse.

    .venv/bin/python benchmarks/bench_ingest.py [--recordings 2] [--seconds 120] [--repeats 5]

Everything runs on one thread (pyarrow CPU and IO pools of 1, BLAS/OpenMP pools of 1), so the
figures are per core. Inputs are seeded synthetic recordings at a tiny video size (video is not
measured; ``read_sample`` still counts rgb.mp4's packets, which is included). Files are read from
the page cache (each measurement is the median of ``--repeats`` runs after a warm-up).

- ceiling: ``pyarrow.csv.read_csv`` of the whole state.csv (all columns, type inference,
  ``use_threads=False``);
- end-to-end: ``read_sample`` + ``valid_runs`` + ``world_to_state`` per segment + the shard table
  (``_segment_table`` per segment, concatenated) + ``write_ipc`` (zstd, the default);
- stages: each piece of that timed on its own.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, single_thread_env, table, time_call  # noqa: E402

single_thread_env()

import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402
import pyarrow.csv as pacsv  # noqa: E402

pa.set_cpu_count(1)
pa.set_io_thread_count(1)

from marionette import geometry as geo  # noqa: E402
from marionette import synth  # noqa: E402
from marionette.ingest.sample import IngestOptions, _segment_table, action_stats, moments, segment_states, valid_runs  # noqa: E402
from marionette.io import write_ipc  # noqa: E402
from marionette.recordings import wildworld as ww  # noqa: E402
from marionette.recordings.wildworld import SampleRef  # noqa: E402


def needed_columns(layout) -> list[str]:
    """The state.csv columns read_sample asks for (same order)."""
    cols = ["camera.K", "camera.pos", "camera.rot"]
    for e in layout.entities:
        cols += list(ww._entity_columns(e, layout).values())
    return cols


def end_to_end(ref: SampleRef, layout, out: Path, compression: str, min_frames: int) -> int:
    """read → segment → derive → table → IPC file; returns rows written."""
    sample = ww.read_sample(ref, layout)
    tables = [t for _, _, _, t in segment_states(layout, sample, valid_runs(sample.valid, min_frames))]
    t = pa.concat_tables(tables)
    write_ipc(out, t, compression)
    return t.num_rows


def stages(ref: SampleRef, layout, out: Path, compression: str, min_frames: int, repeats: int) -> dict[str, float]:
    """Median seconds of each stage of ``end_to_end`` measured on its own."""
    csv_path = ref.path / "state.csv"
    cols = needed_columns(layout)
    s: dict[str, float] = {}
    s["csv parse (needed columns, as strings)"], (raw, _) = time_call(lambda: ww.read_state_csv(csv_path, cols), repeats)

    def parse_all() -> None:
        for c in cols:
            width = ww.FLOAT_TUPLE_WIDTH.get(c) or ww.FLOAT_TUPLE_WIDTH.get(c.rsplit(".", 1)[-1])
            if width:
                ww.tuple_column(raw[c], width, csv_path, c)
            else:
                ww.scalar_column(raw[c], csv_path, c)

    s["tuple + scalar parsing"], _ = time_call(parse_all, repeats)
    s["skeleton.npz load"], _ = time_call(lambda: ww.load_skeletons(ref.path / "skeleton.npz"), repeats)
    s["rgb.mp4 packet count (video_info)"], _ = time_call(lambda: ww.video_info(ref.path / "rgb.mp4"), repeats)
    t_read, sample = time_call(lambda: ww.read_sample(ref, layout), repeats)
    s["read_sample rest (gather, checks)"] = t_read - sum(s.values())
    s["segmenting (valid_runs)"], runs = time_call(lambda: valid_runs(sample.valid, min_frames), repeats)

    def derive() -> list[np.ndarray]:
        out_states = []
        for a, b in runs:
            joints = {e.name: sample.entities[e.name].joints_world[a:b] for e in layout.entities}
            rots = {e.name: sample.entities[e.name].rot[a:b] for e in layout.articulated}
            out_states.append(geo.world_to_state(layout, joints, rots))
        return out_states

    s["state derivation (world_to_state)"], states = time_call(derive, repeats)
    s["table build (_segment_table + concat)"], tab = time_call(
        lambda: pa.concat_tables(
            [_segment_table(layout, sample, f"seg-{k:03d}", a, b, st) for k, ((a, b), st) in enumerate(zip(runs, states))]
        ),
        repeats,
    )
    s[f"IPC write ({compression})"], _ = time_call(lambda: write_ipc(out, tab, compression), repeats)

    # not in end-to-end: what ingest_sample adds for finalize (shown so the full per-sample cost is known)
    def extras() -> None:
        for (a, b), st in zip(runs, states):
            action_stats(layout, st, sample, a, b, sample.fps)
            moments(st.astype(np.float64))

    s["_(ingest_sample extra: action_stats + moments)_"], _ = time_call(extras, repeats)
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--compression", default="zstd", choices=["none", "lz4", "zstd"])
    args = ap.parse_args()
    options = IngestOptions()
    layout = options.layout
    with tempfile.TemporaryDirectory(prefix="bench_ingest_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        synth.generate(tmp / "src", recordings=args.recordings, seconds=args.seconds, seed=args.seed, width=64, height=36)
        gen_s = time.perf_counter() - t0
        refs = ww.discover(tmp / "src")
        rows = []
        totals = {"frames": 0, "mb": 0.0, "ceil": 0.0, "e2e": 0.0}
        stage_sum: dict[str, float] = {}
        for ref in refs:
            csv_path = ref.path / "state.csv"
            mb = csv_path.stat().st_size / 1e6
            t_ceil, ceil_tab = time_call(
                lambda p=csv_path: pacsv.read_csv(p, read_options=pacsv.ReadOptions(use_threads=False)),
                4 * args.repeats,  # a few ms each: more runs for a stable median
            )
            out = tmp / f"{ref.sample_id}.arrow"
            t_e2e, n_rows = time_call(
                lambda r=ref, o=out: end_to_end(r, layout, o, args.compression, options.min_segment_frames), args.repeats
            )
            n_frames = ceil_tab.num_rows
            rows.append(
                [
                    ref.name,
                    n_frames,
                    n_rows,
                    f"{mb:.2f}",
                    f"{n_frames / t_ceil:,.0f}",
                    f"{mb / t_ceil:.1f}",
                    f"{n_frames / t_e2e:,.0f}",
                    f"{mb / t_e2e:.1f}",
                    f"{t_ceil / t_e2e:.2f}",
                ]
            )
            totals["frames"] += n_frames
            totals["mb"] += mb
            totals["ceil"] += t_ceil
            totals["e2e"] += t_e2e
            for k, v in stages(ref, layout, out, args.compression, options.min_segment_frames, args.repeats).items():
                stage_sum[k] = stage_sum.get(k, 0.0) + v
        ratio = totals["ceil"] / totals["e2e"]
        rows.append(
            [
                "**all**",
                totals["frames"],
                "",
                f"{totals['mb']:.2f}",
                f"{totals['frames'] / totals['ceil']:,.0f}",
                f"{totals['mb'] / totals['ceil']:.1f}",
                f"{totals['frames'] / totals['e2e']:,.0f}",
                f"{totals['mb'] / totals['e2e']:.1f}",
                f"**{ratio:.2f}**",
            ]
        )
        print(preamble("Ingest throughput per core (state.csv + skeleton.npz, no video)"))
        print(
            f"{args.recordings} × {args.seconds:g} s synthetic recordings (seed {args.seed}, 30 fps, video 64×36, "
            f"generated in {gen_s:.0f} s, not timed); one thread everywhere; median of {args.repeats} runs "
            f"({4 * args.repeats} for the ceiling); "
            f"shard compression {args.compression}.\n"
        )
        print(
            table(
                [
                    "recording",
                    "frames",
                    "rows kept",
                    "state.csv MB",
                    "ceiling frames/s",
                    "ceiling MB/s",
                    "end-to-end frames/s",
                    "end-to-end MB/s",
                    "ratio",
                ],
                rows,
            )
        )
        verdict = "met" if ratio >= 0.5 else "NOT met"
        print(f"\nTarget end-to-end ≥ 0.5 × ceiling per core: ratio {ratio:.2f} → **{verdict}**.\n")
        e2e_ms = totals["e2e"] * 1e3
        stage_rows = []
        in_e2e = sum(v for k, v in stage_sum.items() if not k.startswith("_("))
        for k, v in stage_sum.items():
            share = "" if k.startswith("_(") else f"{100 * v / in_e2e:.0f} %"
            stage_rows.append([k, f"{v * 1e3:.1f}", f"{v * 1e6 / totals['frames']:.1f}", share])
        stage_rows.append(
            ["**sum of stages (end-to-end)**", f"{in_e2e * 1e3:.1f}", f"{in_e2e * 1e6 / totals['frames']:.1f}", "100 %"]
        )
        stage_rows.append(["end-to-end measured", f"{e2e_ms:.1f}", f"{totals['e2e'] * 1e6 / totals['frames']:.1f}", ""])
        stage_rows.append(
            ["ceiling: read_csv all columns", f"{totals['ceil'] * 1e3:.1f}", f"{totals['ceil'] * 1e6 / totals['frames']:.1f}", ""]
        )
        print("Per-stage breakdown (all recordings, summed):\n")
        print(table(["stage", "ms", "µs/frame", "share of stages"], stage_rows))


if __name__ == "__main__":
    main()
