"""Every heavy stage against the corpus's size: wall time, cost per recorded hour and peak RSS.

    .venv/bin/python benchmarks/bench_scale.py [--hours 0.25,1,4] [--seconds 90] [--workers 1]
        [--frame-stride 4] [--depth-subsample 1] [--video-size 36x64] [--source-size 54x96] [--keep DIR]
        [--project-hours 574] [--project-cores 64]

Input: for each size in ``--hours``, a seeded synthetic source of recordings of ``--seconds`` each
(``marionette synth``, ``--source-size``; enough recordings to make the hours), made in a temp dir and
not timed. Each stage then runs in a fresh process (the CLI, or ``python -c`` for the stages the CLI
has no command for), one after another on the same corpus, as a user's build would:

- ingest: ``marionette ingest SRC CORPUS --no-terrain --no-pose`` (every sample staged, then finalize);
- view: the 20 fps dynamics view of every shard (``Corpus.dynamics_shard``);
- scan: ``marionette terrain scan CORPUS --no-pose --frame-stride N`` (every recording, full);
- pose: the pose targets of every chunk (``render_pose_targets``);
- dynamics epoch: every batch of ``WindowSampler`` epoch 0 (window 64, batch 8) through
  ``train_batches`` with the terrain features, as training reads them (no model: the data's cost);
- observation pass: every train chunk indexed and decoded once through ``ChunkStore`` at cache 0 (at
  the video size divided by 4, as the demo trains), as observation training reads them.

Measured per stage: wall seconds, seconds per recorded hour, core-seconds per recorded hour (user +
system CPU time of the stage's process and the descendants it waited for) and the peak resident set of
its largest process (``ru_maxrss``; both from ``os.wait4``). The summary rows give, per stage, the
spread of cost per hour (largest / smallest) and the RSS ratio between the largest and the smallest
corpus, beside the targets of issue 16 (cost per hour within 15 %, RSS within 1.25×). The projection
rows scale the largest corpus's core-seconds per recorded hour to ``--project-hours`` (WildWorld part
1: 574 h) on ``--project-cores`` cores, assuming the fan-out keeps every core busy; "the build" is
ingest, view, scan and pose (the training passes are listed apart). ``--workers`` is the processes of
ingest, scan and pose.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, size_hw, table  # noqa: E402

VIEW = "from marionette.corpus import Corpus\nc = Corpus({corpus!r})\nfor s in c.shard_ids():\n    c.dynamics_shard(s)\n"
POSE = "from marionette.bridge.targets import render_pose_targets\nrender_pose_targets({corpus!r}, workers={workers})\n"
EPOCH = """
import torch
from marionette.dynamics.data import WindowData, WindowSampler, train_batches
torch.set_num_threads(1)
data = WindowData({corpus!r}, "train", terrain=True)
sampler = WindowSampler(data, 64, 8)
n = 0
for _ in train_batches(sampler, 0, 0):
    n += 1
    if n >= sampler.batches(0):
        break
print("batches", n)
"""
OBSERVATION = """
import torch
from marionette.corpus import Corpus
from marionette.observation.data import ChunkStore, ClipSource
torch.set_num_threads(1)
c = Corpus({corpus!r})
v = c.info.video
store = ChunkStore(ClipSource(c, "train", 5, (v["height"] // 4, v["width"] // 4)), budget_bytes=0)
print("chunks", sum(1 for _ in store))
"""


def run_stage(cmd: list[str], log: Path) -> tuple[float, float, float]:
    """Run ``cmd`` (output to ``log``); (wall seconds, core-seconds, peak RSS MiB of its largest process)."""
    t = time.perf_counter()
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"})
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {os.waitstatus_to_exitcode(status)}); its output: {log}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=lambda s: [float(v) for v in s.split(",")], default=[0.25, 1.0, 4.0])
    ap.add_argument("--seconds", type=float, default=90.0, help="length of each synthetic recording")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--frame-stride", type=int, default=4, help="the scan's depth frame stride (the demo's)")
    ap.add_argument("--depth-subsample", type=int, default=1, help="the scan's depth subsample (1: every pixel)")
    ap.add_argument("--video-size", type=size_hw, default=(36, 64), help="video chunks' size HxW")
    ap.add_argument("--source-size", type=size_hw, default=(54, 96), help="synthetic recordings' size HxW")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, default=None, help="build the corpora here and keep them (default: a temp dir)")
    ap.add_argument("--project-hours", type=float, default=574.0, help="recorded hours to project to (part 1: 574)")
    ap.add_argument("--project-cores", type=int, default=64, help="cores to project onto")
    args = ap.parse_args()
    if any(h <= 0 for h in args.hours) or args.seconds <= 0 or min(args.workers, args.frame_stride, args.depth_subsample) < 1:
        ap.error("--hours, --seconds, --workers, --frame-stride and --depth-subsample must be positive")
    if args.project_hours <= 0 or args.project_cores < 1:
        ap.error("--project-hours and --project-cores must be positive")
    py = sys.executable
    cli = str(Path(py).with_name("marionette"))
    stages = ["ingest", "view", "scan", "pose", "dynamics epoch", "observation pass"]
    rows, results = [], {}
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        root = args.keep or Path(tmp)
        for hours in args.hours:
            recordings = max(1, math.ceil(hours * 3600 / args.seconds))
            recorded_h = recordings * args.seconds / 3600
            here = root / f"{hours:g}h"
            src, corpus, log = here / "src", here / "corpus", here / "log.txt"
            here.mkdir(parents=True, exist_ok=True)
            sh, sw = args.source_size
            gen = [cli, "synth", str(src), "--recordings", str(recordings), "--seconds", str(args.seconds)]
            gen += ["--seed", str(args.seed), "--width", str(sw), "--height", str(sh), "--workers", "2"]
            if not src.exists():
                run_stage(gen, log)
            vh, vw = args.video_size
            commands = {
                "ingest": [cli, "ingest", str(src), str(corpus), "--no-terrain", "--no-pose", "--quiet"]
                + ["--video-size", f"{vh}x{vw}", "--workers", str(args.workers)],
                "view": [py, "-c", VIEW.format(corpus=str(corpus))],
                "scan": [cli, "terrain", "scan", str(corpus), "--no-pose", "--quiet", "--frame-stride", str(args.frame_stride)]
                + ["--depth-subsample", str(args.depth_subsample), "--workers", str(args.workers)],
                "pose": [py, "-c", POSE.format(corpus=str(corpus), workers=args.workers)],
                "dynamics epoch": [py, "-c", EPOCH.format(corpus=str(corpus))],
                "observation pass": [py, "-c", OBSERVATION.format(corpus=str(corpus))],
            }
            for stage in stages:
                wall, cpu, rss = run_stage(commands[stage], log)
                results[(hours, stage)] = (wall / recorded_h, rss, cpu / recorded_h)
                rows.append(
                    [
                        f"{recorded_h:.3f}",
                        stage,
                        f"{wall:.1f}",
                        f"{wall / recorded_h:.0f}",
                        f"{cpu / recorded_h:.0f}",
                        f"{rss:.0f}",
                    ]
                )
                print(f"{recorded_h:.3f} h {stage}: {wall:.1f} s, {cpu:.1f} core-s, {rss:.0f} MiB", file=sys.stderr, flush=True)
    summary = []
    lo, hi = min(args.hours), max(args.hours)
    for stage in stages:
        per_h = [results[(h, stage)][0] for h in args.hours]
        spread = max(per_h) / min(per_h)
        rss = results[(hi, stage)][1] / results[(lo, stage)][1]
        summary.append(
            [stage, f"{spread:.2f}", "met" if spread <= 1.15 else "not met", f"{rss:.2f}", "met" if rss <= 1.25 else "not met"]
        )
    print(preamble("Every stage against the corpus's size"))
    print(
        f"Recordings of {args.seconds:g} s at {args.source_size[0]}×{args.source_size[1]}, video {args.video_size[0]}×"
        f"{args.video_size[1]}, scan stride {args.frame_stride} and depth subsample {args.depth_subsample}, "
        f"{args.workers} worker(s); each stage a fresh process.\n"
    )
    print(table(["recorded h", "stage", "wall s", "s per recorded h", "core-s per recorded h", "peak RSS MiB"], rows))
    if len(args.hours) > 1:
        print()
        print(
            table(
                ["stage", "cost per h, max / min", "within 15 %", f"peak RSS {hi:g} h / {lo:g} h", "within 1.25×"],
                summary,
            )
        )
    print()
    print(table(PROJECTION_HEADER, projection(results, hi, stages, args.project_hours, args.project_cores)))


BUILD = ("ingest", "view", "scan", "pose")
PROJECTION_HEADER = ["stage", "core-h per recorded h", "projected core-h", "projected wall h", "target"]


def projection(results: dict, hours: float, stages: list[str], project_hours: float, cores: int) -> list[list[str]]:
    """Rows scaling the ``hours`` corpus's core-seconds per recorded hour to ``project_hours`` on ``cores`` cores."""
    rows = []
    build = 0.0
    for stage in stages:
        per_h = results[(hours, stage)][2] / 3600
        if stage in BUILD:
            build += per_h
        rows.append([stage, f"{per_h:.3f}", f"{per_h * project_hours:,.0f}", f"{per_h * project_hours / cores:.1f}", ""])
    ok = build <= 1.0 and build * project_hours / cores <= 10.0
    rows.append(
        [
            "the build (" + ", ".join(BUILD) + ")",
            f"{build:.3f}",
            f"{build * project_hours:,.0f}",
            f"{build * project_hours / cores:.1f}",
            f"≤ 1 core-h per recorded h, ≤ 10 h on {cores} cores: {'met' if ok else 'not met'}",
        ]
    )
    return rows


if __name__ == "__main__":
    main()
