"""Peak memory of the dynamics training data against the corpus's size: one epoch of training windows.

    .venv/bin/python benchmarks/bench_memory.py [--corpora 10x30,20x90] [--window 64] [--batch 8]
                                                [--workers 0,2] [--terrain] [--in-memory]

Input: synthetic corpora made in a temp dir (``bench_dynamics.make_corpus``: recordings × seconds, 96×54,
video 36×64), one recording held out. For each corpus and each loader worker count, in a fresh process:
``WindowData(corpus, "train")`` (the window arrays computed and stored on first use, then memory-mapped:
``marionette.dynamics.data``, "Window arrays on disk"; with ``--terrain`` the terrain features too, as
training reads them by default), then every batch of ``WindowSampler`` epoch 0 (window 64, batch 8)
through ``train_batches``: stacked in the process (0 workers) or by DataLoader worker processes, as
training reads them. Measured from ``/proc/<pid>/status`` of the process and its workers: RssAnon +
RssShmem (anonymous memory, what would grow with the corpus if the split were held in memory, and the
shared-memory batches workers hand over) after import (per process), after opening the data, and its
peak summed over the processes, sampled at every batch; "above import" is that peak less each process's
memory after import (a forked worker starts from the parent's, and its RSS counts the pages it shares
with the parent: an upper bound); RssFile summed at the end (mapped file pages: page cache, shared
between the ranks and workers of one machine and reclaimable). "split MiB" is the size of the train
split's arrays, what a process holding them in memory would hold. ``--in-memory`` adds the control: the
same run with the split copied into the process before the epoch (the loader this replaced). A first
run builds the arrays (timed apart), the measured runs open them.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, table  # noqa: E402

CHILD = r"""
import gc, json, os, sys, time
import numpy as np
import torch
from marionette.dynamics.data import WindowData, WindowSampler, train_batches

def status(pid):
    # MiB of RssAnon, RssShmem and RssFile of a process; None once it has exited
    try:
        lines = open(f"/proc/{pid}/status").read().splitlines()
    except (FileNotFoundError, ProcessLookupError):
        return None
    keys = ("RssAnon", "RssShmem", "RssFile")
    return {k: int(v.split()[0]) / 1024 for k, _, v in (line.partition(":") for line in lines) if k in keys}

def children():
    me = os.getpid()
    return [int(p) for t in os.listdir(f"/proc/{me}/task") for p in open(f"/proc/{me}/task/{t}/children").read().split()]

def own(s):
    return s["RssAnon"] + s["RssShmem"]

corpus, window, batch, workers, mode, terrain = sys.argv[1], *map(int, sys.argv[2:5]), sys.argv[5], sys.argv[6] == "1"
torch.set_num_threads(1)
gc.collect()
me = os.getpid()
base = own(status(me))
t = time.perf_counter()
data = WindowData(corpus, "train", terrain=terrain)
opened_s = time.perf_counter() - t
names = ("root", "body", "action", "progress") + (("features", "known") if terrain else ())
if mode == "memory":  # the loader this replaced: the split's arrays in the process
    for k in names:
        setattr(data, k, [np.array(a) for a in getattr(data, k)])
opened = own(status(me))
sampler = WindowSampler(data, window, batch, seed=0)
loader, peak, procs, file = train_batches(sampler, 0, workers), opened, {me}, 0.0
for _ in range(sampler.batches(0)):
    next(loader)
    pids = [me, *children()]
    procs |= set(pids)
    st = [s for s in map(status, pids) if s is not None]
    peak, file = max(peak, sum(map(own, st))), sum(s["RssFile"] for s in st)
loader.close()
split = sum(a.nbytes for k in names for a in getattr(data, k))
print(json.dumps({"import": base, "opened": opened, "peak": peak, "above": peak - len(procs) * base, "file": file,
                  "processes": len(procs), "batches": sampler.batches(0), "frames": int(data.lengths.sum()),
                  "split_mib": split / 2**20, "opened_s": opened_s}))
"""


def measure(corpus: Path, window: int, batch: int, workers: int = 0, mode: str = "mapped", terrain: bool = False) -> dict:
    cmd = [sys.executable, "-c", CHILD, str(corpus), str(window), str(batch), str(workers), mode, str(int(terrain))]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpora", default="10x30,20x90", help="recordings x seconds per corpus, comma-separated")
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--workers", default="0", help="DataLoader worker counts, comma-separated (0: in the process)")
    ap.add_argument("--terrain", action="store_true", help="read the terrain features too (training's default)")
    ap.add_argument("--in-memory", action="store_true", help="also run the control: the split held in memory")
    args = ap.parse_args()
    from bench_dynamics import make_corpus

    rows = []
    modes = ["mapped", "memory"] if args.in_memory else ["mapped"]
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        for k, spec in enumerate(args.corpora.split(",")):
            n, secs = (float(v) for v in spec.split("x"))
            t = time.perf_counter()
            corpus = make_corpus(Path(tmp) / f"c{k}", int(n), secs, 11, scan=False)
            made = time.perf_counter() - t
            first = measure(corpus, args.window, args.batch, terrain=args.terrain)  # builds the window arrays
            for mode in modes:
                for workers in (int(w) for w in args.workers.split(",")):
                    m = measure(corpus, args.window, args.batch, workers, mode, args.terrain)
                    rows.append(
                        [
                            f"{int(n)} × {secs:g} s",
                            f"{n * secs / 60:.0f}",
                            m["frames"],
                            f"{m['split_mib']:.1f}",
                            "mapped" if mode == "mapped" else "in memory",
                            workers,
                            f"{m['import']:.0f}",
                            f"{m['opened']:.0f}",
                            f"{m['peak']:.0f}",
                            f"{m['above']:.1f}",
                            f"{m['file']:.0f}",
                            m["batches"],
                            f"{first['opened_s']:.1f} / {m['opened_s']:.2f}",
                            f"{made:.0f}",
                        ]
                    )
    print(preamble("Dynamics training data: peak memory against corpus size"))
    terrain = ", terrain features read" if args.terrain else ""
    print(f"window {args.window} (+1 frame), batch {args.batch}{terrain}; MiB from /proc/<pid>/status; one thread.\n")
    header = ["corpus", "minutes", "train frames (20 fps)", "split MiB", "loader", "workers", "RssAnon+Shmem import"]
    header += ["opened", "peak Σ", "Σ above import", "RssFile end Σ", "batches", "open s (build / reopen)", "corpus made s"]
    print(table(header, rows))


if __name__ == "__main__":
    main()
