"""Peak memory of the dynamics training data against the corpus's size: one epoch of training windows.

    .venv/bin/python benchmarks/bench_memory.py [--corpora 10x30,20x90] [--window 64] [--batch 8]

Input: synthetic corpora made in a temp dir (``bench_dynamics.make_corpus``: recordings × seconds, 96×54,
video 36×64), one recording held out. For each corpus, in a fresh process: ``WindowData(corpus, "train")``
(the window arrays computed and stored on first use, then memory-mapped: ``marionette.dynamics.data``,
"Window arrays on disk"), then every batch of ``WindowSampler`` epoch 0 (the tiny preset's window, batch
8) stacked into tensors, as training reads them. Measured from ``/proc/self/status``: RssAnon (the
process's own memory: what would grow with the corpus if the split were held in memory) after import,
after opening the data, and its peak over the epoch sampled at every batch; RssFile at the end (mapped
file pages: page cache, shared between the ranks of one machine and reclaimable). "split bytes" is the
size of the train split's arrays, what a process holding them in memory would hold. A first run builds
the arrays (timed apart), the measured run opens them.
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
import json, sys, time
def status():
    out = {}
    for line in open("/proc/self/status"):
        k, _, v = line.partition(":")
        if k in ("RssAnon", "RssFile"):
            out[k] = int(v.split()[0]) / 1024
    return out
import torch
from marionette.dynamics.data import WindowData, WindowSampler
torch.set_num_threads(1)
base = status()["RssAnon"]
t = time.perf_counter()
data = WindowData(sys.argv[1], "train")
opened_s = time.perf_counter() - t
opened = status()["RssAnon"]
sampler = WindowSampler(data, int(sys.argv[2]), int(sys.argv[3]), seed=0)
peak, batches = opened, 0
for batch in sampler.epoch(0):
    batches += 1
    peak = max(peak, status()["RssAnon"])
split = sum(a.nbytes for arrays in (data.root, data.body, data.action, data.progress) for a in arrays)
print(json.dumps({"import": base, "opened": opened, "peak": peak, "file": status()["RssFile"], "batches": batches,
                  "frames": int(data.lengths.sum()), "split_mib": split / 2**20, "opened_s": opened_s}))
"""


def measure(corpus: Path, window: int, batch: int) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(corpus), str(window), str(batch)], capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpora", default="10x30,20x90", help="recordings x seconds per corpus, comma-separated")
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    args = ap.parse_args()
    from bench_dynamics import make_corpus

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        for k, spec in enumerate(args.corpora.split(",")):
            n, secs = (float(v) for v in spec.split("x"))
            t = time.perf_counter()
            corpus = make_corpus(Path(tmp) / f"c{k}", int(n), secs, 11, scan=False)
            made = time.perf_counter() - t
            first = measure(corpus, args.window, args.batch)  # builds the window arrays
            m = measure(corpus, args.window, args.batch)
            rows.append(
                [
                    f"{int(n)} × {secs:g} s",
                    f"{n * secs / 60:.0f}",
                    m["frames"],
                    f"{m['split_mib']:.1f}",
                    f"{m['import']:.0f}",
                    f"{m['opened']:.0f}",
                    f"{m['peak']:.0f}",
                    f"{m['file']:.0f}",
                    m["batches"],
                    f"{first['opened_s']:.1f} / {m['opened_s']:.2f}",
                    f"{made:.0f}",
                ]
            )
    print(preamble("Dynamics training data: peak memory against corpus size"))
    print(f"window {args.window} (+1 frame), batch {args.batch}; MiB from /proc/self/status; one thread.\n")
    header = ["corpus", "minutes", "train frames (20 fps)", "split MiB", "RssAnon import", "RssAnon opened"]
    header += ["RssAnon peak", "RssFile end", "batches", "open s (build / reopen)", "corpus made s"]
    print(table(header, rows))


if __name__ == "__main__":
    main()
