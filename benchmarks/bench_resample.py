"""The 20 fps dynamics view: resampling speed and joint error, linear vs nearest, against analytic truth.

    .venv/bin/python benchmarks/bench_resample.py [--recordings 2] [--seconds 60] [--fps 20] [--repeats 5]

Builds a corpus from seeded synthetic recordings (video 64×36, not measured), then for every
segment runs ``marionette.corpus.resample_segment(layout, rows, fps, method)``. Speed: source rows
in and view rows out per second (median of ``--repeats``, one thread). Accuracy: the view's world
joints (``world_of_rows``: recorded roots and rotations + re-derived state) against the synthetic
game's analytic skeletons (``world_skeletons_at``, kept joints) at the view's times, in metres.
The row "source 30 fps" is the same error for the stored source-rate rows at their own times: the
floor set by float32 state storage.
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
from marionette.corpus import Corpus, resample_segment, world_of_rows  # noqa: E402
from marionette.ingest import IngestOptions, VideoSettings, build_corpus  # noqa: E402


def joint_errors(layout, src_root: Path, rows: pa.Table) -> dict[str, np.ndarray]:
    """Per entity: Euclidean error (m) of every kept joint of every row against the analytic truth."""
    sample = rows["sample"][0].as_py()
    part, sample_id = sample.split("/")
    t = rows["t"].to_numpy()
    truth = synth.world_skeletons_at(src_root, part, sample_id, t)
    got = world_of_rows(layout, rows)
    out = {}
    for e in layout.entities:
        want = truth[e.name][:, list(e.rig.keep_source_index)]
        out[e.name] = np.linalg.norm(got[e.name] - want, axis=-1).reshape(-1)
    return out


def stats_row(label: str, entity: str, err: np.ndarray) -> list[object]:
    return [
        label,
        entity,
        f"{err.size:,}",
        f"{1e3 * err.mean():.2f}",
        f"{1e3 * np.percentile(err, 99):.2f}",
        f"{1e3 * err.max():.2f}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_resample_") as tmp:
        tmp = Path(tmp)
        src, corpus_dir = tmp / "src", tmp / "corpus"
        t0 = time.perf_counter()
        synth.generate(src, recordings=args.recordings, seconds=args.seconds, seed=args.seed, width=64, height=36)
        build_corpus(src, corpus_dir, IngestOptions(video=VideoSettings(height=36, width=64)), workers=1, progress=False)
        setup_s = time.perf_counter() - t0
        corpus = Corpus(corpus_dir)
        layout = corpus.layout
        segs = {s: corpus.read_segment(s) for s in corpus.segment_ids()}
        n_src = sum(t.num_rows for t in segs.values())

        speed_rows, err_rows = [], []
        floor: dict[str, list[np.ndarray]] = {}
        for rows in segs.values():
            for k, v in joint_errors(layout, src, rows).items():
                floor.setdefault(k, []).append(v)
        for e in layout.entities:
            err_rows.append(stats_row("source 30 fps (floor)", e.name, np.concatenate(floor[e.name])))
        err_rows.append(
            stats_row("source 30 fps (floor)", "**all**", np.concatenate([np.concatenate(v) for v in floor.values()]))
        )

        for method in ("linear", "nearest"):
            t_total, n_out = 0.0, 0
            errs: dict[str, list[np.ndarray]] = {}
            for rows in segs.values():
                dt, view = time_call(lambda r=rows, m=method: resample_segment(layout, r, args.fps, m), args.repeats)
                t_total += dt
                n_out += view.num_rows
                for k, v in joint_errors(layout, src, view).items():
                    errs.setdefault(k, []).append(v)
            speed_rows.append(
                [method, f"{n_src:,}", f"{n_out:,}", f"{t_total * 1e3:.1f}", f"{n_src / t_total:,.0f}", f"{n_out / t_total:,.0f}"]
            )
            for e in layout.entities:
                err_rows.append(stats_row(method, e.name, np.concatenate(errs[e.name])))
            err_rows.append(stats_row(method, "**all**", np.concatenate([np.concatenate(v) for v in errs.values()])))

        print(preamble(f"Dynamics view: resampling to {args.fps:g} fps, linear vs nearest"))
        print(
            f"{args.recordings} × {args.seconds:g} s synthetic recordings (seed {args.seed}, 30 fps); {len(segs)} segments; "
            f"corpus built in {setup_s:.0f} s (not timed); one thread; median of {args.repeats} runs per segment.\n"
        )
        print(table(["method", "source rows", "view rows", "time ms", "source rows/s", "view rows/s"], speed_rows))
        print("\nJoint position error against the analytic skeletons (kept joints, world metres; shown in mm):\n")
        print(table(["rows", "entity", "joint samples", "mean mm", "p99 mm", "max mm"], err_rows))


if __name__ == "__main__":
    main()
