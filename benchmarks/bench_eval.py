"""The evaluation's knobs: what proxy-FVD's sampling steps and clip length cost and change, and the extractors' speed.

    .venv/bin/python benchmarks/bench_eval.py --run demo-run [--steps 4,8,20] [--frames 21,41,81]

Input: a demo output directory (``marionette demo --out DIR``: its corpus, ``dynamics/`` and
``observation/``). Part 1: ``report.observation_fvd`` on the held-out video chunks (recorded pose, painted
from each chunk's first frame) for every (sampling steps, clip frames) pair — the proxy-FVD with its 95 %
interval, and the wall time. Part 2: the proxy and I3D extractors (I3D with random weights built here:
speed only) on 8 clips of 16 frames at 36×64, and the bootstrap at 200 resamples.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.corpus import Corpus
from marionette.eval import fvd
from marionette.eval.i3d import I3DExtractor, InceptionI3d
from marionette.eval.report import _corpus_clips, observation_fvd
from marionette.observation.train import load_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a demo output directory")
    ap.add_argument("--steps", default="4,8,20")
    ap.add_argument("--frames", default="21,41,81")
    a = ap.parse_args()
    print(preamble("Evaluation: proxy-FVD sampling steps and clip length; extractor speed"))
    c = Corpus(a.run / "corpus")
    model = load_model(a.run / "observation")
    held = set(c.segment_ids("test"))
    clips, _ = _corpus_clips(c, held, model.config.frames, model.config.size, 8)
    rows = []
    for frames in (int(x) for x in a.frames.split(",")):
        for steps in (int(x) for x in a.steps.split(",")):
            t0 = time.perf_counter()
            r = observation_fvd(model, clips, steps=steps, seed=0, max_frames=frames)
            w = r["whole"]
            rows.append(
                [frames, steps, f"{w['value']:.2f}", f"[{w['low']:.2f}, {w['high']:.2f}]", f"{time.perf_counter() - t0:.1f}"]
            )
            print(f"  {rows[-1]}", flush=True)
    print(
        f"\n### proxy-FVD of the observation model ({len(clips)} held-out chunks at {model.config.height}×{model.config.width_px})\n"
    )
    print(table(["clip frames", "sampling steps", "proxy-FVD", "95 % interval", "seconds"], rows))
    g = torch.Generator().manual_seed(0)
    videos = torch.rand(8, 16, 3, 36, 64, generator=g) * 2 - 1
    speed = []
    for ex in (fvd.ProxyExtractor(), I3DExtractor(InceptionI3d())):
        ex.extract(videos[:2])
        t0 = time.perf_counter()
        feats = ex.extract(videos)
        speed.append([ex.name, feats.shape[1], f"{8 / (time.perf_counter() - t0):.2f}"])
        if ex.is_fvd:
            t0 = time.perf_counter()
            fvd.fvd_with_interval(feats, feats[::-1].copy(), resamples=200, seed=0)
            boot = time.perf_counter() - t0
    print("\n### Extractors (8 clips × 16 frames at 36×64) and the bootstrap\n")
    print(table(["extractor", "features", "clips/s"], speed))
    print(f"\nbootstrap, 200 resamples of 8 + 8 clips of 400 features: {boot:.2f} s")


if __name__ == "__main__":
    main()
