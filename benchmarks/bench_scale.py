"""Every heavy stage against the corpus's size: wall time, cost per recorded hour and peak RSS.

    .venv/bin/python benchmarks/bench_scale.py [--hours 0.25,1,4] [--seconds 90] [--workers 1[,2]]
        [--frame-stride 4] [--depth-subsample 1] [--video-size 36x64] [--source-size 54x96] [--keep DIR]
        [--project-hours 574] [--project-cores 64] [--compare-with CHECKOUT]

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
corpus (targets: cost per hour within 15 %, RSS within 1.25×). The projection rows scale the largest
corpus's core-seconds per recorded hour to ``--project-hours`` (WildWorld part 1: 574 h) on
``--project-cores`` cores, assuming the fan-out keeps every core busy, beside each build stage's budget
(``BUDGET``); "the build" is ingest, view, scan and pose (the training passes are listed apart).

``--workers``: the processes of ingest, scan and pose, one count or several (``1,2``): each count builds a
corpus of its own on as many cores (every stage's process and its workers confined to the first n cores this
process may use: n workers on n cores), and a table compares the core-seconds per recorded hour of every count
with one worker's (linear scaling: within 15 %). ``--compare-with CHECKOUT``: a directory holding another
revision of the project (``git worktree add /tmp/base REV``); every stage also runs with that code
(``PYTHONPATH=CHECKOUT``, this venv's packages), on a corpus of its own built from the same recordings,
one code after the other stage by stage, and the projection shows both.
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

from marionette.fanout import usable_cores  # noqa: E402

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


def run_stage(cmd: list[str], log: Path, code: Path | None = None, cores: set[int] | None = None) -> tuple[float, float, float]:
    """Run ``cmd`` (output to ``log``; with ``code``, that checkout's package first on the path; with ``cores``, on
    those cores only, its descendants too); (wall seconds, core-seconds, peak RSS MiB of its largest process)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if code is not None:
        env["PYTHONPATH"] = str(code)
    pin = None if cores is None else (lambda: os.sched_setaffinity(0, cores))
    t = time.perf_counter()
    with open(log, "ab") as out:
        # run beside the log, not in a checkout: a `python -c` puts its working directory first on the path
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=log.parent, preexec_fn=pin)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
        raise RuntimeError(
            f"{' '.join(cmd)} failed (exit {os.waitstatus_to_exitcode(status)}): {lines[-1] if lines else 'no output'}\n"
            f"its output: {log}"
        )
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


STAGES = ["ingest", "view", "scan", "pose", "dynamics epoch", "observation pass"]
BUILD = ("ingest", "view", "scan", "pose")
BUDGET = {"ingest": 0.35, "scan": 0.35, "pose": 0.3}  # core-h per recorded h at the paper's size; the build ≤ 1.0


def worker_cores(workers: int) -> set[int] | None:
    """The cores ``workers`` workers run on: the first ``workers`` of this process's (n workers on n cores, so one
    worker's figures are one core's and each stage sizes its threads to them: ``fanout.threads_per_worker``, Mesa's
    llvmpipe); None (every core) where this process has no more cores than that."""
    mine = usable_cores()
    return set(mine[:workers]) if len(mine) > workers and hasattr(os, "sched_setaffinity") else None


def stage_commands(py: str, src: Path, corpus: Path, args, workers: int) -> dict[str, list[str]]:
    """Each stage's command line (the CLI through ``python -m marionette.cli``, so a compared checkout runs its own)."""
    cli = [py, "-m", "marionette.cli"]
    vh, vw = args.video_size
    return {
        "ingest": cli
        + ["ingest", str(src), str(corpus), "--no-terrain", "--no-pose", "--quiet"]
        + ["--video-size", f"{vh}x{vw}", "--workers", str(workers)],
        "view": [py, "-c", VIEW.format(corpus=str(corpus))],
        "scan": cli
        + ["terrain", "scan", str(corpus), "--no-pose", "--quiet", "--frame-stride", str(args.frame_stride)]
        + ["--depth-subsample", str(args.depth_subsample), "--workers", str(workers)],
        "pose": [py, "-c", POSE.format(corpus=str(corpus), workers=workers)],
        "dynamics epoch": [py, "-c", EPOCH.format(corpus=str(corpus))],
        "observation pass": [py, "-c", OBSERVATION.format(corpus=str(corpus))],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=lambda s: [float(v) for v in s.split(",")], default=[0.25, 1.0, 4.0])
    ap.add_argument("--seconds", type=float, default=90.0, help="length of each synthetic recording")
    ap.add_argument("--workers", type=lambda s: [int(v) for v in s.split(",")], default=[1], help="one count or several: 1,2")
    ap.add_argument("--frame-stride", type=int, default=4, help="the scan's depth frame stride (the demo's)")
    ap.add_argument("--depth-subsample", type=int, default=1, help="the scan's depth subsample (1: every pixel)")
    ap.add_argument("--video-size", type=size_hw, default=(36, 64), help="video chunks' size HxW")
    ap.add_argument("--source-size", type=size_hw, default=(54, 96), help="synthetic recordings' size HxW")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, default=None, help="build the corpora here and keep them (default: a temp dir)")
    ap.add_argument("--project-hours", type=float, default=574.0, help="recorded hours to project to (part 1: 574)")
    ap.add_argument("--project-cores", type=int, default=64, help="cores to project onto")
    ap.add_argument("--compare-with", type=Path, default=None, help="a checkout of another revision, run beside this one")
    args = ap.parse_args()
    if any(h <= 0 for h in args.hours) or args.seconds <= 0 or min(*args.workers, args.frame_stride, args.depth_subsample) < 1:
        ap.error("--hours, --seconds, --workers, --frame-stride and --depth-subsample must be positive")
    if args.project_hours <= 0 or args.project_cores < 1:
        ap.error("--project-hours and --project-cores must be positive")
    if args.compare_with is not None and not (args.compare_with / "marionette" / "cli.py").is_file():
        ap.error(f"--compare-with {args.compare_with}: not a checkout of this project (no marionette/cli.py)")
    py = sys.executable
    codes = [("this", None)] + ([("compared", args.compare_with.resolve())] if args.compare_with else [])
    rows, results = [], {}
    with tempfile.TemporaryDirectory(prefix="bench_scale_") as tmp:
        root = (args.keep or Path(tmp)).resolve()
        for hours in args.hours:
            recordings = max(1, math.ceil(hours * 3600 / args.seconds))
            recorded_h = recordings * args.seconds / 3600
            here = root / f"{hours:g}h"
            src, log = here / "src", here / "log.txt"
            here.mkdir(parents=True, exist_ok=True)
            sh, sw = args.source_size
            gen = [py, "-m", "marionette.cli", "synth", str(src), "--recordings", str(recordings), "--seconds", str(args.seconds)]
            gen += ["--seed", str(args.seed), "--width", str(sw), "--height", str(sh), "--workers", "2"]
            if not src.exists():
                run_stage(gen, log)
            for workers in args.workers:
                commands = {
                    label: stage_commands(py, src, here / f"corpus-{label}-w{workers}", args, workers) for label, _ in codes
                }
                cores = worker_cores(workers)
                for stage in STAGES:
                    for label, code in codes:  # the codes one after the other, stage by stage: the same machine state
                        wall, cpu, rss = run_stage(commands[label][stage], log, code, cores)
                        results[(hours, label, workers, stage)] = (wall / recorded_h, rss, cpu / recorded_h)
                        rows.append(
                            [f"{recorded_h:.3f}", label, str(workers), stage, f"{wall:.1f}", f"{wall / recorded_h:.0f}"]
                            + [f"{cpu / recorded_h:.0f}", f"{rss:.0f}"]
                        )
                        print(
                            f"{recorded_h:.3f} h {label} w{workers} {stage}: {wall:.1f} s, {cpu:.1f} core-s, {rss:.0f} MiB",
                            file=sys.stderr,
                            flush=True,
                        )
    print(preamble("Every stage against the corpus's size"))
    compared = f"; compared with the checkout {args.compare_with}" if args.compare_with else ""
    print(
        f"Recordings of {args.seconds:g} s at {args.source_size[0]}×{args.source_size[1]}, video {args.video_size[0]}×"
        f"{args.video_size[1]}, scan stride {args.frame_stride} and depth subsample {args.depth_subsample}, "
        f"{','.join(map(str, args.workers))} worker(s), n workers on n cores; each stage a fresh process{compared}.\n"
    )
    header = ["recorded h", "code", "workers", "stage", "wall s", "s per recorded h", "core-s per recorded h", "peak RSS MiB"]
    print(table(header, rows))
    lo, hi, w0 = min(args.hours), max(args.hours), args.workers[0]
    if len(args.hours) > 1:
        summary = []
        for stage in STAGES:
            per_h = [results[(h, "this", w0, stage)][0] for h in args.hours]
            spread = max(per_h) / min(per_h)
            rss = results[(hi, "this", w0, stage)][1] / results[(lo, "this", w0, stage)][1]
            summary.append(
                [
                    stage,
                    f"{spread:.2f}",
                    "met" if spread <= 1.15 else "not met",
                    f"{rss:.2f}",
                    "met" if rss <= 1.25 else "not met",
                ]
            )
        print()
        print(table(["stage", "cost per h, max / min", "within 15 %", f"peak RSS {hi:g} h / {lo:g} h", "within 1.25×"], summary))
    for label, _ in codes:
        print(f"\nProjection, {label} code ({w0} worker(s)):\n")
        print(table(PROJECTION_HEADER, projection(results, hi, label, w0, args.project_hours, args.project_cores)))
    if len(args.workers) > 1:
        print()
        print(table(*scaling(results, hi, args.workers)))


PROJECTION_HEADER = ["stage", "core-h per recorded h", "projected core-h", "projected wall h", "target"]


def projection(results: dict, hours: float, label: str, workers: int, project_hours: float, cores: int) -> list[list[str]]:
    """Rows scaling the ``hours`` corpus's core-seconds per recorded hour to ``project_hours`` on ``cores`` cores."""
    rows = []
    build = 0.0
    for stage in STAGES:
        per_h = results[(hours, label, workers, stage)][2] / 3600
        if stage in BUILD:
            build += per_h
        target = f"≤ {BUDGET[stage]}: {'met' if per_h <= BUDGET[stage] else 'not met'}" if stage in BUDGET else ""
        rows.append([stage, f"{per_h:.3f}", f"{per_h * project_hours:,.0f}", f"{per_h * project_hours / cores:.1f}", target])
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


def scaling(results: dict, hours: float, workers: list[int]) -> tuple[list[str], list[list[str]]]:
    """(header, rows): each build stage's core-seconds per recorded hour at every worker count against one worker's
    (``workers[0]``); n workers on n cores are linear when the cost per hour stays within 15 %."""
    header = ["stage"] + [f"core-s per recorded h, {w} worker(s)" for w in workers] + ["worst / first", "within 15 %"]
    rows = []
    for stage in ("ingest", "scan", "pose"):
        costs = [results[(hours, "this", w, stage)][2] for w in workers]
        worst = max(costs) / costs[0]
        rows.append([stage, *(f"{c:.0f}" for c in costs), f"{worst:.2f}", "met" if worst <= 1.15 else "not met"])
    return header, rows


if __name__ == "__main__":
    main()
