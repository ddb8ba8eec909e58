"""The evaluation's costs and knobs: minutes per table at the quick and paper protocols, how the probe's headline
numbers move with the number of windows, and what proxy-FVD's sampling steps and clip length cost and change.

    .venv/bin/python benchmarks/bench_eval.py protocol --corpus C --dynamics D --observation O [--baseline B]
    .venv/bin/python benchmarks/bench_eval.py knobs --run demo-run [--steps 4,8,20] [--frames 21,41,81]

``protocol``: the quick protocol run whole through ``report.evaluate``'s steps, timed per table; the paper's Table 2
run whole (48 windows); the paper's long rollouts (Table 3's states) and paintings (Tables 1 and 3) timed on the
quick protocol's and extrapolated per window-frame and per painted model chunk (the corpus may hold no 16 s
window, and the paintings take hours on a CPU), FVD scoring timed at the paper's clip counts on random video.
Then the paper probe's per-window values resampled at fewer windows (1,000 draws with replacement): the spread
of the GT < Shuf share and of the Shuf/GT ratio a smaller protocol gives.

``knobs`` input: a demo output directory (``marionette demo --out DIR``: its corpus, ``dynamics/`` and
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
from marionette.eval.clips import _corpus_clips, observation_fvd
from marionette.eval.i3d import I3DExtractor, InceptionI3d
from marionette.observation.train import load_model


def knobs(a: argparse.Namespace) -> None:
    """Proxy-FVD against sampling steps and clip length on a demo run, and the extractors' speed."""
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


def _timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t0


def protocol(a: argparse.Namespace) -> None:
    """Minutes per table at the quick and paper protocols, and the probe's headline numbers against the window count."""
    import numpy as np

    from marionette.eval.ablation import ablation_rollouts, rule_ablation
    from marionette.eval.config import PROTOCOLS
    from marionette.eval.probe import controllability_probe
    from marionette.eval.protocol import model_fps, run_windows, select_windows, state_layer
    from marionette.eval.report import long_windows, painted_rollouts
    from marionette.eval.video import long_horizon, paint_frames, score_videos, video_tables

    print(preamble("Evaluation protocol: minutes per table (quick and paper) and confidence against windows"))
    c = Corpus(a.corpus)
    fps, vfps = model_fps(a.dynamics), float(c.fps)
    obs = load_model(a.observation)
    base = load_model(a.baseline) if a.baseline else None
    models = [m for m in (obs, base) if m is not None]
    cost: dict[str, dict[str, float]] = {}
    probes = {}
    for name in ("quick", "paper"):
        p = PROTOCOLS[name]
        w = select_windows(c, p.probe_windows, p.seed_frames, p.horizon, 0, fps=fps)
        (free, _), t_free = _timed(run_windows, a.dynamics, c, w, temperature=p.temperature)
        _, t_state = _timed(state_layer, a.dynamics, c, w, free)
        probes[name], t_probe = _timed(controllability_probe, a.dynamics, c, w, free=free, temperature=p.temperature)
        cost[name] = {"Table 2 (probe, 4 conditions)": t_free + t_probe, "state layer (Free)": t_state}
        per_frame = (t_free + t_probe) / (4 * len(w) * p.horizon)  # s per predicted window-frame, batched
        print(
            f"  {name}: Table 2 {t_free + t_probe:.1f} s over {len(w)} windows ({per_frame * 1e3:.2f} ms per window-frame)",
            flush=True,
        )
        if name == "quick":
            H = long_horizon(p, vfps, fps, [m.config.frames for m in models])
            split = "test" if c.segment_ids("test") else "train"
            states_at, _ = long_windows(c, p, H, 1, split, fps)  # Table 3's state rollouts, as evaluate takes them
            states, t_roll = _timed(ablation_rollouts, a.dynamics, c, states_at, temperature=p.temperature)
            _, t_rows = _timed(rule_ablation, a.dynamics, c, states_at, rollouts=states)
            long, tables = painted_rollouts(states_at, {k: v["tables"] for k, v in states.items()}, p.rollouts, H)
            video, t_video = _timed(video_tables, c, long, tables, p, obs, base)
            roll_rate = t_roll / (3 * sum(w.horizon for w in states_at))
            per = {id(m): (paint_frames(p.video_frames(vfps), m.config.frames) - 1) // (m.config.frames - 1) for m in models}
            chunks = len(tables) * per[id(obs)] + (per[id(base)] if base is not None else 0)  # model chunks per rollout
            paint_rate = t_video / (len(long) * chunks * p.fvd_steps)  # s per model chunk and sampling step (incl. render, score)
            cost[name]["Table 3 (3 rolled-out states)"] = t_roll + t_rows
            cost[name]["Tables 1 + 3 video (render, paint, score)"] = t_video
            print(
                f"  quick: long rollouts {roll_rate * 1e3:.2f} ms per window-frame, painting {paint_rate * 1e3:.1f} ms per chunk-step",
                flush=True,
            )
        else:
            H = long_horizon(p, vfps, fps, [m.config.frames for m in models])
            cost[name]["Table 3 (3 rolled-out states)"] = per_frame * 3 * p.state_count * H
            T = p.video_frames(vfps)
            n_chunks = 4 * (paint_frames(T, obs.config.frames) - 1) // (obs.config.frames - 1)
            if base is not None:
                n_chunks += (paint_frames(T, base.config.frames) - 1) // (base.config.frames - 1)
            g = torch.Generator().manual_seed(0)
            real, gen = (torch.rand(p.rollouts, T, 3, *obs.config.size, generator=g) * 2 - 1 for _ in range(2))
            _, t_score = _timed(score_videos, real, gen, p, vfps, fvd.ProxyExtractor())
            cost[name]["Tables 1 + 3 video (render, paint, score)"] = (
                paint_rate * p.rollouts * n_chunks * p.fvd_steps + t_score * (4 + (base is not None))
            )
            print(f"  paper: one score_videos at {p.rollouts} rollouts × {T} frames: {t_score:.1f} s", flush=True)
    rows = [[k, f"{cost['quick'][k] / 60:.2f}", f"{cost['paper'][k] / 60:.1f}"] for k in cost["quick"]]
    rows.append(["all", f"{sum(cost['quick'].values()) / 60:.2f}", f"{sum(cost['paper'].values()) / 60:.1f}"])
    print(
        f"\n### Minutes per table (observation model {obs.config.height}×{obs.config.width_px}, {obs.config.frames}-frame chunks)\n"
    )
    print(table(["table", "quick (measured)", "paper (Table 2 measured; rest extrapolated)"], rows))

    pr = probes["paper"]
    gt = np.array(pr["conditions"]["force_gt"]["per_window"])
    sh = np.array(pr["conditions"]["force_shuf"]["per_window"])
    rng = np.random.default_rng(0)
    rows = []
    for n in (4, 8, 16, 24, 48):
        share, ratio = [], []
        for _ in range(1000):
            k = rng.integers(0, len(gt), n)
            share.append(float((gt[k] < sh[k]).mean()))
            ratio.append(float(sh[k].mean() / gt[k].mean()))
        lo, hi = np.quantile(share, [0.05, 0.95])
        rlo, rhi = np.quantile(ratio, [0.05, 0.95])
        rows.append([n, f"{np.mean(share):.2f}", f"[{lo:.2f}, {hi:.2f}]", f"{np.mean(ratio):.2f}", f"[{rlo:.2f}, {rhi:.2f}]"])
    print(f"\n### The probe's headline against the window count (resampled from the paper's {len(gt)} windows)\n")
    print(table(["windows", "GT < Shuf share", "90 % of draws", "Shuf/GT (window means)", "90 % of draws"], rows))
    print(
        f"\npaper probe: GT < Shuf on {pr['force_gt_beats_shuf']} of {pr['compared']}, GT < run-shuffle on {pr['force_gt_beats_shuf_runs']}"
    )
    print(
        table(
            ["class", "frames", "Shuf/GT", "run-shuffle/GT"],
            [
                [k, v["frames"], f"{v['force_shuf/force_gt']:.2f}", f"{v['force_shuf_runs/force_gt']:.2f}"]
                for k, v in pr["class_ratios"].items()
            ],
        )
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="part", required=True)
    k = sub.add_parser("knobs", help="proxy-FVD sampling steps and clip length on a demo run; extractor speed")
    k.add_argument("--run", type=Path, required=True, help="a demo output directory")
    k.add_argument("--steps", default="4,8,20")
    k.add_argument("--frames", default="21,41,81")
    pp = sub.add_parser("protocol", help="minutes per table at the quick and paper protocols; confidence against windows")
    pp.add_argument("--corpus", type=Path, required=True)
    pp.add_argument("--dynamics", type=Path, required=True)
    pp.add_argument("--observation", type=Path, required=True)
    pp.add_argument("--baseline", type=Path)
    a = ap.parse_args()
    (knobs if a.part == "knobs" else protocol)(a)


if __name__ == "__main__":
    main()
