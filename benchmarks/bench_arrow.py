"""Arrow IPC compression of state shards: none / lz4 / zstd — file size, write time, full-read throughput.

    .venv/bin/python benchmarks/bench_arrow.py [--recordings 2] [--seconds 300] [--repeats 5]

Each shard is what ingest writes for one seeded synthetic recording (``read_sample`` →
``world_to_state`` → ``_segment_table`` per segment, concatenated), i.e. a realistic
``--seconds``-long recording's shard. Per codec: ``marionette.io.write_ipc`` (atomic: temp file,
fsync, rename), then ``marionette.io.read_ipc`` (memory-mapped) alone and followed by materialising
the ``state`` column as a float32 numpy array and summing it (so every state byte is touched even
when the read is zero-copy). Median of ``--repeats`` runs, one thread, files in the page cache.
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

pa.set_cpu_count(1)
pa.set_io_thread_count(1)

from marionette import synth  # noqa: E402
from marionette.ingest.sample import IngestOptions, segment_states, valid_runs  # noqa: E402
from marionette.io import read_ipc, write_ipc  # noqa: E402
from marionette.recordings import wildworld as ww  # noqa: E402

CODECS = ("none", "lz4", "zstd")


def shard_table(ref: ww.SampleRef, layout, min_frames: int) -> pa.Table:
    """The state-shard table ingest builds for one recording."""
    sample = ww.read_sample(ref, layout)
    tables = [t for _, _, _, t in segment_states(layout, sample, valid_runs(sample.valid, min_frames))]
    return pa.concat_tables(tables)


def read_state(path: Path, dim: int) -> float:
    """Read a shard and touch every state value; returns their sum."""
    t = read_ipc(path)
    col = t["state"].combine_chunks()
    state = col.values.to_numpy(zero_copy_only=False).reshape(-1, dim)
    return float(state.sum(dtype=np.float64))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    options = IngestOptions()
    layout = options.layout
    with tempfile.TemporaryDirectory(prefix="bench_arrow_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        synth.generate(tmp / "src", recordings=args.recordings, seconds=args.seconds, seed=args.seed, width=64, height=36)
        tables = [shard_table(r, layout, options.min_segment_frames) for r in ww.discover(tmp / "src")]
        setup_s = time.perf_counter() - t0
        n_rows = sum(t.num_rows for t in tables)
        mem_mb = sum(t.nbytes for t in tables) / 1e6
        state_mb = n_rows * layout.dim * 4 / 1e6
        rows = []
        for codec in CODECS:
            size = t_write = t_read = t_state = 0.0
            for i, tab in enumerate(tables):
                path = tmp / codec / f"shard-{i:06d}.arrow"
                dt, _ = time_call(lambda p=path, t=tab, c=codec: write_ipc(p, t, c), args.repeats)
                t_write += dt
                size += path.stat().st_size / 1e6
                dt, back = time_call(lambda p=path: read_ipc(p), args.repeats)
                t_read += dt
                assert back.equals(tab), f"{path}: read back differs"
                dt, _ = time_call(lambda p=path: read_state(p, layout.dim), args.repeats)
                t_state += dt
            rows.append(
                [
                    codec,
                    f"{size:.2f}",
                    f"{size / mem_mb:.2f}",
                    f"{t_write * 1e3:.1f}",
                    f"{mem_mb / t_write:.0f}",
                    f"{t_read * 1e3:.2f}",
                    f"{n_rows / t_read / 1e6:.2f}",
                    f"{mem_mb / t_read:,.0f}",
                    f"{t_state * 1e3:.2f}",
                    f"{n_rows / t_state / 1e6:.2f}",
                    f"{state_mb / t_state:,.0f}",
                ]
            )
        print(preamble("Arrow IPC compression of state shards"))
        print(
            f"{len(tables)} shards from {args.recordings} × {args.seconds:g} s synthetic recordings (seed {args.seed}, 30 fps): "
            f"{n_rows:,} rows, {mem_mb:.1f} MB in memory ({state_mb:.1f} MB of it the float32 state, D = {layout.dim}); "
            f"built in {setup_s:.0f} s (not timed); one thread; median of {args.repeats} runs; page cache warm. "
            f"MB/s are of the in-memory table (write, read) or of the state values (read + state).\n"
        )
        print(
            table(
                [
                    "codec",
                    "file MB",
                    "size / in-memory",
                    "write ms",
                    "write MB/s",
                    "read ms",
                    "read Mrows/s",
                    "read MB/s",
                    "read + state→numpy ms",
                    "Mrows/s",
                    "state MB/s",
                ],
                rows,
            )
        )


if __name__ == "__main__":
    main()
