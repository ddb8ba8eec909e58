"""The dynamics model: rollout speed at the paper's sizes, training speed, and what the window, the dtype and
the relative feature buy in accuracy.

    .venv/bin/python benchmarks/bench_dynamics.py [--part all|rollout|train|window|relative|heads|seeds|long]
        [--corpus DIR] [--scanned-corpus DIR] [--steps N] [--horizon 448] [--seeds 0 1 2 3] [--set KNOB=VALUE ...]

Inputs (made in a temp dir unless given): the *dynamics corpus* of the tests (ten 45 s synthetic
recordings, seed 11, one recording held out; ``tests/fixtures/corpora.py``), and a *scanned corpus* (two 20 s
recordings with the stage's terrain scanned, so the collider has a surface). Torch uses every core.

rollout. A paper-preset model (ActionGPT 4×256, PoseGPT 8×512, window 512; random weights: speed does
not depend on them) saved as a checkpoint for the scanned corpus; ``Rollout`` with the rules on
(collider + cap), temperature 1 so the streams of a batch differ, seeded with 64 recorded frames, then
``--horizon`` predicted frames; state frames/s over the whole horizon and over its last 128 frames (a
KV cache of ≥ 384 frames, near the full window). Recomputation (``ModelStream(cached=False)``) costs,
per frame, one ``forward`` per model over the frames that still reach the newest one; in steady state
that is layers·(window − 1) + 1 = 2,045 frames for ActionGPT and 4,089 for PoseGPT, timed directly.
The ceiling: the models' weights (fp32 bytes) read once per step at the memory bandwidth a large
``torch`` copy measures; "model only" steps both models at a full cache with no features, rules or
state conversion.

train. Training steps/s and samples/s (windows of length + 1 frames) of the tiny preset (window 64)
and the paper preset (window 128: the synthetic segments hold < 513 frames), batch 8, fp32, after two
warm-up steps.

window. The tiny preset trained ``--steps`` steps at windows 16 / 32 / 64; per model and dtype (fp32,
bf16 weights) the hunter RA-MPJPE of Force-GT rollouts (the recorded hunter tokens forced, rules off)
over every held-out seed (32 seed frames, 40 predicted, seeds every 20 frames), and rollout frames/s.

relative. The tiny preset (window 64) trained with and without the relative-position feature; free
rollouts of 2,000 frames from three held-out seeds, rules off (the separation cap would hide the
difference), 3-D separation of the two roots: mean, 95th percentile and share of frames beyond 6 m
(the cap's distance), beside the recorded held-out separation.

heads. The tiny preset (window 64) trained with residual heads on clean inputs (``residual=True,
input_noise=0``) and with absolute heads on noised inputs (the defaults); one 2,000-frame rollout from
the first held-out segment, temperature 0, rules on: how far the roots wander (largest extent of the
root path over the three axes) and the bone-length CV over the rollout (median and max over bones, both
entities), beside the recorded train split's.

seeds. The tests' tiny recipe (``TINY_DYNAMICS``: 1,000 steps, batch 8, window 64, lr 2e-3, one torch thread) with
the ``--set`` knobs, trained at each of ``--seeds``: per seed the held-out next-action accuracy, root and body MSE
(beside copy-last and constant velocity), the forcing test's rate (``eval.control.swing_rates``: the hunter's
swinging attack tokens forced for 10 frames from every held-out seed, tip > 5 m/s) and the probe's counts (48
windows of 64 + 120, Force-GT < Force-Shuf and < the run-level shuffle), and their means: a control figure from one
checkpoint moves by more between seeds than most options move it (docs/tradeoffs.md, "Seed to seed").

long. The tests' tiny recipe at seed 0, rolled out ``--long-frames`` (10,000) frames from the first held-out segment,
rules on (the suite's test rolls 3,000): whether every state is finite, frames/s, per entity the bone-length CV
(median, mean and max over bones, beside the recorded train split's) and how far the root wanders.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.checkpoint import save_checkpoint
from marionette.corpus import Corpus, fixed_rows, world_of_rows
from marionette.dynamics.config import DynamicsConfig, TrainConfig
from marionette.dynamics.controls import force_windows
from marionette.dynamics.data import ActionTokens, WindowData, WindowSampler
from marionette.dynamics.engine import ModelStream, Rollout, open_terrain_field
from marionette.dynamics.model import DynamicsModel, Frames, parameter_counts
from marionette.dynamics.normalise import Normaliser
from marionette.dynamics.rollout import rollout
from marionette.dynamics.train import batches_from, losses, make_optimizer, train
from marionette.eval.control import held_out_seeds, recorded_swingers, swing_rates
from marionette.ingest import IngestOptions, VideoSettings, build_corpus
from marionette.options import int_at_least

SEED = 32


# -- inputs ------------------------------------------------------------------------------------------


def make_corpus(root: Path, recordings: int, seconds: float, seed: int, scan: bool) -> Path:
    from marionette.synth import generate

    generate(
        root / "recordings",
        recordings=recordings,
        seconds=seconds,
        seed=seed,
        width=96 if not scan else 160,
        height=54 if not scan else 90,
        workers=2,
    )
    opts = IngestOptions(video=VideoSettings(height=36, width=64, chunk_frames=81, crf=28))
    build_corpus(root / "recordings", root / "corpus", opts, workers=2, progress=False)
    if scan:
        from terrain_scan.scan import scan_stages

        scan_stages(root / "corpus", incremental=True, log=lambda *_: None)
    return root / "corpus"


def paper_checkpoint(c: Corpus, out: Path) -> Path:
    """A randomly initialised paper-preset checkpoint that ``Rollout`` loads for ``c``."""
    tokens = ActionTokens.from_corpus(c)
    cfg = DynamicsConfig.preset("paper", c.layout, tokens.sizes)
    model = DynamicsModel(cfg, seed=0)
    meta = {
        "train_config": TrainConfig(preset="paper").to_json(),
        "dynamics_config": cfg.to_json(),
        "normaliser": Normaliser.from_corpus(c).to_json(),
        "vocab": {"hash": tokens.vocab_hash, "sizes": list(tokens.sizes), "entities": list(tokens.entities)},
    }
    return save_checkpoint(out, 0, model, meta=meta)


# -- rollout -----------------------------------------------------------------------------------------


def bandwidth_gbps() -> float:
    """Memory bandwidth (GB/s, read + write counted once each) of a 512 MiB torch copy, best of 5."""
    src = torch.ones(128 * 2**20)
    dst = torch.empty_like(src)
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        dst.copy_(src)
        best = min(best, time.perf_counter() - t0)
    return 2 * src.numel() * 4 / best / 1e9


def model_only_fps(model: DynamicsModel, batch: int, dtype: torch.dtype, steps: int = 20) -> float:
    """Frames/s of stepping both models (one frame each) at a full cache, no features or rules."""
    c = model.config
    g = torch.Generator().manual_seed(0)

    def frames(progress: bool) -> Frames:
        return Frames(
            root=torch.randn(batch, 1, c.root_dim, generator=g).to(dtype),
            body=torch.randn(batch, 1, c.body_dim, generator=g).to(dtype),
            tokens=torch.zeros(batch, 1, c.n_entities, dtype=torch.int64),
            progress=torch.zeros(batch, 1, c.n_entities, dtype=dtype) if progress else None,
            terrain=torch.zeros(batch, 1, c.n_entities, c.terrain_features, dtype=dtype),
        )

    streams = []
    for net in (model.action, model.pose):
        s = ModelStream(net)
        s.reset(batch)
        full = c.window - 1
        spec = net.spec
        kv = torch.randn(batch, spec.heads, c.window, spec.head_dim, generator=g).to(dtype)  # a full ring (window slots)
        s.cache = type(s.cache)(
            tuple(kv.clone() for _ in range(spec.layers)), tuple(kv.clone() for _ in range(spec.layers)), full, full
        )
        streams.append(s)
    with torch.inference_mode():  # as Rollout steps
        for _ in range(2):
            streams[0].step(frames(True))
            streams[1].step(frames(False))
        t0 = time.perf_counter()
        for _ in range(steps):
            streams[0].step(frames(True))
            streams[1].step(frames(False))
    return batch * steps / (time.perf_counter() - t0)


def recompute_seconds(model: DynamicsModel, batch: int, dtype: torch.dtype) -> float:
    """Seconds per frame of recomputing both models over their steady-state history (one forward each)."""
    c = model.config
    total = 0.0
    for net, progress in ((model.action, True), (model.pose, False)):
        T = net.spec.layers * (c.window - 1) + 1
        f = Frames(
            root=torch.zeros(batch, T, c.root_dim, dtype=dtype),
            body=torch.zeros(batch, T, c.body_dim, dtype=dtype),
            tokens=torch.zeros(batch, T, c.n_entities, dtype=torch.int64),
            progress=torch.zeros(batch, T, c.n_entities, dtype=dtype) if progress else None,
            terrain=torch.zeros(batch, T, c.n_entities, c.terrain_features, dtype=dtype),
        )
        with torch.no_grad():
            t0 = time.perf_counter()
            net(f)
            total += time.perf_counter() - t0
    return total


def part_rollout(scanned: Path, horizon: int, work: Path) -> None:
    c = Corpus(scanned)
    ckpt = paper_checkpoint(c, work / "paper")
    seg = max(c.segment_ids(), key=lambda s: c.dynamics_segment(s).num_rows)
    field = open_terrain_field(c, seg)
    seed_rows = c.dynamics_segment(seg).slice(0, 64)
    model = DynamicsModel(DynamicsConfig.preset("paper", c.layout, ActionTokens.from_corpus(c).sizes))
    counts = parameter_counts(model)
    n_params = counts["total"]
    bw = bandwidth_gbps()
    rows = []
    for batch in (1, 16):
        for dtype in (torch.float32, torch.bfloat16):
            ro = Rollout(ckpt, c, rules="auto", terrain_field=field, temperature=1.0, dtype=dtype)
            ro.start_batch([seed_rows] * batch)
            times = []
            for _ in range(horizon):
                t0 = time.perf_counter()
                ro.step_batch()
                times.append(time.perf_counter() - t0)
            times = np.asarray(times)
            overall = batch * horizon / times.sum()
            tail = batch * 128 / times[-128:].sum()
            only = model_only_fps(ro.model, batch, dtype)
            recompute = batch / recompute_seconds(ro.model, batch, dtype)
            ceiling = batch * bw * 1e9 / (n_params * (4 if dtype == torch.float32 else 2))
            name = "fp32" if dtype == torch.float32 else "bf16"
            rows.append(
                [
                    batch,
                    name,
                    f"{overall:.1f}",
                    f"{tail:.1f}",
                    f"{only:.1f}",
                    f"{recompute:.2f}",
                    f"{ceiling:.0f}",
                    ", ".join(ro.enabled),
                ]
            )
            print(f"batch {batch} {name}: {overall:.1f} frames/s", file=sys.stderr)
    print(
        f"\n### Rollout, paper preset ({counts['ActionGPT']:,} + {counts['PoseGPT']:,} parameters), seed 64 frames, "
        f"{horizon} predicted; memory copy {bw:.1f} GB/s\n"
    )
    print(
        table(
            [
                "batch",
                "dtype",
                "cached, frames/s (whole horizon)",
                "cached, last 128 frames",
                "model only, full cache",
                "recomputed, steady state",
                "weight-streaming ceiling",
                "rules",
            ],
            rows,
        )
    )


# -- training ----------------------------------------------------------------------------------------


def part_train(corpus: Path) -> None:
    c = Corpus(corpus)
    rows = []
    for preset, window in (("tiny", 64), ("paper", 128)):
        cfg = TrainConfig(preset=preset, window=window, batch_size=8, terrain=False)
        nz = Normaliser.from_corpus(c)
        data = WindowData(c, "train", normaliser=nz)
        sampler = WindowSampler(data, window, cfg.batch_size, seed=0)
        tokens = ActionTokens.from_corpus(c)
        dyn = DynamicsConfig.preset(
            preset, c.layout, tokens.sizes, window=window, terrain=(False,) * len(tokens.sizes), residual=cfg.residual
        )
        model = DynamicsModel(dyn)
        opt, _ = make_optimizer(model, cfg)
        it = batches_from(sampler, 0)
        batches = [next(it) for _ in range(7)]
        times = []
        for k, batch in enumerate(batches):
            t0 = time.perf_counter()
            terms = losses(model, model.action, model.pose, batch, nz, cfg, None, torch.Generator().manual_seed(k))
            opt.zero_grad()
            terms["total"].backward()
            opt.step()
            if k >= 2:
                times.append(time.perf_counter() - t0)
        step = float(np.median(times))
        rows.append(
            [
                preset,
                window,
                cfg.batch_size,
                f"{1 / step:.2f}",
                f"{cfg.batch_size / step:.1f}",
                f"{cfg.batch_size * (window + 1) / step:.0f}",
            ]
        )
    print("\n### Training speed (fp32, AdamW, all cores)\n")
    print(table(["preset", "window", "batch", "steps/s", "samples/s (windows)", "frames/s"], rows))


# -- accuracy knobs ----------------------------------------------------------------------------------


def force_gt(c: Corpus, ckpt: Path, seeds, horizon: int, dtype: torch.dtype) -> tuple[float, float]:
    """Mean hunter RA-MPJPE (m) of Force-GT rollouts over ``seeds``, and predicted frames/s."""
    tokens = ActionTokens.from_corpus(c)
    hi = tokens.entities.index("hunter")
    errs, frames, took = [], 0, 0.0
    for seg, start in seeds:
        rec = c.dynamics_segment(seg).slice(start + SEED, horizon)
        force = force_windows("hunter", tokens.encode(c.layout, rec)[0][:, hi])
        t0 = time.perf_counter()
        table_ = rollout(ckpt, c, seg, SEED, horizon, force=force, rules="none", start=start, dtype=dtype)
        took += time.perf_counter() - t0
        frames += horizon
        p = world_of_rows(c.layout, table_)["hunter"][SEED:]
        r = world_of_rows(c.layout, rec)["hunter"]
        errs.append(np.linalg.norm((p - p[:, :1]) - (r - r[:, :1]), axis=-1).mean())
    return float(np.mean(errs)), frames / took


def part_window(corpus: Path, steps: int, work: Path) -> None:
    c = Corpus(corpus)
    seeds = held_out_seeds(c, SEED, 40, 20)
    rows = []
    for window in (16, 32, 64):
        out = work / f"tiny-w{window}"
        t0 = time.perf_counter()
        s = train(
            c, out, TrainConfig(preset="tiny", steps=steps, batch_size=8, window=window, lr=2e-3, warmup=50), log=lambda *_: None
        )
        took = time.perf_counter() - t0
        for dtype in (torch.float32, torch.bfloat16):
            err, fps = force_gt(c, out, seeds, 40, dtype)
            rows.append(
                [
                    window,
                    "fp32" if dtype == torch.float32 else "bf16",
                    f"{err:.4f}",
                    f"{fps:.0f}",
                    f"{s['eval']['action_accuracy']:.4f}",
                    f"{took:.0f}",
                ]
            )
            print(f"window {window} {dtype}: {err:.4f}", file=sys.stderr)
    print(
        f"\n### Window and dtype against hunter RA-MPJPE (tiny preset, {steps} steps, Force-GT, {len(seeds)} held-out "
        "seeds, 32 + 40 frames)\n"
    )
    print(table(["window", "dtype", "RA-MPJPE (m)", "rollout frames/s", "held-out next-action acc.", "training s"], rows))


def separation(table_, layout) -> np.ndarray:
    w = world_of_rows(layout, table_)
    a, b = (w[e.name][:, 0] for e in layout.articulated[:2])
    return np.linalg.norm(a - b, axis=-1)


def part_relative(corpus: Path, steps: int, work: Path) -> None:
    c = Corpus(corpus)
    recorded = np.concatenate([separation(c.dynamics_segment(s), c.layout) for s in c.segment_ids("test")])
    rows = [
        [
            "recorded (held-out)",
            "",
            f"{recorded.mean():.2f}",
            f"{np.percentile(recorded, 95):.2f}",
            f"{(recorded > 6).mean():.1%}",
            f"{recorded.max():.1f}",
        ]
    ]
    segs = c.segment_ids("test")
    for relative in (False, True):
        out = work / f"tiny-rel{int(relative)}"
        train(
            c,
            out,
            TrainConfig(preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50, relative=relative),
            log=lambda *_: None,
        )
        seps = []
        for seg in segs[:3]:
            t = rollout(out, c, seg, SEED, 2000, rules="none", temperature=1.0, seed=1)
            seps.append(separation(t, c.layout)[SEED:])
        sep = np.concatenate(seps)
        rows.append(
            [
                f"relative feature {'on' if relative else 'off'}",
                len(seps),
                f"{sep.mean():.2f}",
                f"{np.percentile(sep, 95):.2f}",
                f"{(sep > 6).mean():.1%}",
                f"{sep.max():.1f}",
            ]
        )
        print(f"relative {relative}: {sep.mean():.2f}", file=sys.stderr)
    print(f"\n### Separation over 2,000-frame free rollouts (tiny preset, {steps} steps, temperature 1, rules off)\n")
    print(table(["model", "rollouts", "mean (m)", "p95 (m)", "share > 6 m", "max (m)"], rows))


def bone_cv(joints: np.ndarray, rig) -> np.ndarray:
    lengths = np.stack([np.linalg.norm(joints[:, a] - joints[:, b], axis=-1) for a, b in rig.bones], axis=1)
    return lengths.std(0) / lengths.mean(0)


def part_heads(corpus: Path, steps: int, work: Path) -> None:
    c = Corpus(corpus)
    seg = c.segment_ids("test")[0]
    rec = {e.name: [] for e in c.layout.articulated}
    for s in c.segment_ids("train"):
        w = world_of_rows(c.layout, c.dynamics_segment(s))
        for e in c.layout.articulated:
            rec[e.name].append(w[e.name])
    rec_cv = np.concatenate([bone_cv(np.concatenate(rec[e.name]), e.rig) for e in c.layout.articulated])
    rows = [["recorded (train split)", "", "", f"{np.median(rec_cv):.4f}", f"{rec_cv.max():.3f}"]]
    for residual, noise in ((True, 0.0), (False, 0.1)):
        out = work / f"tiny-res{int(residual)}"
        train(
            c,
            out,
            TrainConfig(
                preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50, residual=residual, input_noise=noise
            ),
            log=lambda *_: None,
        )
        t = rollout(out, c, seg, SEED, 2000, rules="auto")
        w = world_of_rows(c.layout, t)
        span = max(float(np.ptp(w[e.name][SEED:, 0], axis=0).max()) for e in c.layout.articulated)
        cv = np.concatenate([bone_cv(w[e.name][SEED:], e.rig) for e in c.layout.articulated])
        finite = bool(np.isfinite(fixed_rows(t["state"], c.layout.dim)).all())
        rows.append(
            [
                f"{'residual, clean inputs' if residual else 'absolute, input noise 0.1 (default)'}",
                f"{span:,.0f}",
                str(finite),
                f"{np.median(cv):.4f}",
                f"{cv.max():.3f}",
            ]
        )
        print(f"residual {residual}: span {span:.0f}", file=sys.stderr)
    print(f"\n### Heads: residual on clean inputs against absolute on noised inputs (tiny, {steps} steps, 2,000 frames)\n")
    print(table(["model", "root path extent (m)", "finite", "bone-length CV median", "max"], rows))


def part_seeds(corpus: Path, steps: int, work: Path, seeds: list[int], sets: dict) -> None:
    """The tests' tiny recipe (``TINY_DYNAMICS``, one torch thread) with ``sets`` overriding its knobs, trained at each
    seed: held-out one-step figures against the baselines, the forcing test's swing rate and the probe's counts."""
    from marionette.eval.config import PROTOCOLS
    from marionette.eval.probe import controllability_probe
    from marionette.eval.protocol import select_windows

    c = Corpus(corpus)
    paper = PROTOCOLS["paper"]
    attacks = recorded_swingers(c, "hunter", 10, 4)
    starts = held_out_seeds(c, SEED, 10)
    windows = select_windows(c, paper.probe_windows, paper.seed_frames, paper.horizon, seed=0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the tests train it: the tiny model is overhead-bound
    rows, cols = [], []
    try:
        for seed in seeds:
            cfg = TrainConfig(
                **{"preset": "tiny", "steps": steps, "batch_size": 8, "window": 64, "lr": 2e-3, "warmup": 50, "seed": seed} | sets
            )
            out = work / f"seed{seed}"
            t0 = time.perf_counter()
            s = train(c, out, cfg, log=lambda *_: None)
            ev, base = s["eval"], s["baselines"]
            rates = swing_rates(out, c, "hunter", attacks, starts, SEED, frames=10)
            probe = controllability_probe(out, c, windows, temperature=paper.temperature)
            forced = float(np.mean([rates[t] for t in attacks]))
            vals = [
                ev["action_accuracy"],
                ev["root_mse"],
                ev["body_mse"],
                forced,
                probe["force_gt_beats_shuf"],
                probe["force_gt_beats_shuf_runs"],
            ]
            cols.append(vals)
            rows.append(
                [str(seed), f"{vals[0]:.4f}", f"{vals[1]:.4f}", f"{vals[2]:.4f}", f"{forced:.2f} (free {rates[None]:.2f})"]
                + [f"{vals[4]} ({vals[5]})"]
            )
            print(f"seed {seed}: {rows[-1][1:]} in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    finally:
        torch.set_num_threads(threads)
    m = np.mean(np.asarray(cols, np.float64), axis=0)
    rows.append(["mean", f"{m[0]:.4f}", f"{m[1]:.4f}", f"{m[2]:.4f}", f"{m[3]:.2f}", f"{m[4]:.1f} ({m[5]:.1f})"])
    knobs = ", ".join(f"{k}={v}" for k, v in sets.items()) or "the defaults"
    print(f"\n### Seed to seed: the tests' tiny recipe ({steps} steps) with {knobs}\n")
    print(
        f"Baselines: copy-last action {base['copy_last_action_accuracy']:.4f}, constant-velocity root "
        f"{base['constant_velocity_root_mse']:.4f}, copy-last body {base['copy_last_body_mse']:.4f}; forcing: attack "
        f"tokens {attacks} over {len(starts)} held-out seeds; probe: {len(windows)} windows of {paper.seed_frames} + "
        f"{paper.horizon}.\n"
    )
    heads = ["seed", "action acc.", "root MSE", "body MSE", "forced attacks swing", "GT < Shuf (GT < run-shuffle)"]
    print(table(heads, rows))


def part_long(corpus: Path, steps: int, work: Path, frames: int) -> None:
    c = Corpus(corpus)
    out = work / "long"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the tests train it
    try:
        cfg = TrainConfig(preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50, seed=0)
        train(c, out, cfg, log=lambda *_: None)
    finally:
        torch.set_num_threads(threads)
    seg = c.segment_ids("test")[0]
    t0 = time.perf_counter()
    t = rollout(out, c, seg, SEED, frames, rules="auto")
    took = time.perf_counter() - t0
    finite = bool(np.isfinite(fixed_rows(t["state"], c.layout.dim)).all())
    w = world_of_rows(c.layout, t)
    train_world = [world_of_rows(c.layout, c.dynamics_segment(s)) for s in c.segment_ids("train")]
    rows = []
    for e in c.layout.articulated:
        rec = np.concatenate([world[e.name] for world in train_world])
        pred, recorded = bone_cv(w[e.name][SEED:], e.rig), bone_cv(rec, e.rig)
        span = float(np.ptp(w[e.name][SEED:, 0], axis=0).max())
        rows.append(
            [e.name, f"{np.median(pred):.4f} ({np.median(recorded):.4f})", f"{pred.mean():.4f} ({recorded.mean():.4f})"]
            + [f"{pred.max():.3f} ({recorded.max():.3f})", f"{span:,.0f}"]
        )
    print(f"\n### A long rollout: tiny ({steps} steps), {frames:,} frames, rules on\n")
    print(f"finite: {finite}; {frames / took:.0f} frames/s ({took:.1f} s)\n")
    print(table(["entity", "bone CV median (recorded)", "mean (recorded)", "max (recorded)", "root path extent (m)"], rows))


def knob_value(text: str) -> tuple[str, object]:
    """``key=value`` of a TrainConfig knob, the value read as JSON (true, 0.1, null) or else as a string."""
    import json

    key, sep, raw = text.partition("=")
    if not sep or key not in TrainConfig.__dataclass_fields__:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KNOB=VALUE with KNOB a TrainConfig field")
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="all", choices=["all", "rollout", "train", "window", "relative", "heads", "seeds", "long"])
    ap.add_argument("--corpus", type=Path, default=None, help="the dynamics corpus (default: made in a temp dir)")
    ap.add_argument("--scanned-corpus", type=Path, default=None, help="a corpus with scanned terrain (default: made)")
    ap.add_argument("--steps", type=int, default=None, help="training steps of the tiny models (1500; seeds: 1000)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="seeds of the seeds part")
    ap.add_argument("--set", type=knob_value, action="append", default=[], metavar="KNOB=VALUE", help="seeds: a knob")
    ap.add_argument("--horizon", type=int, default=448, help="predicted frames of the paper-preset rollouts")
    ap.add_argument("--long-frames", type=int_at_least(1), default=10_000, help="predicted frames of the long part's rollout")
    a = ap.parse_args()
    sets = dict(a.set)
    try:
        TrainConfig(**sets)  # every knob validated where it is parsed
    except (TypeError, ValueError) as err:
        ap.error(f"--set: {err}")
    steps = a.steps or 1500
    print(preamble("Dynamics: rollout and training speed, window / dtype / relative feature against accuracy"))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads\n")
    with tempfile.TemporaryDirectory(prefix="bench_dynamics_") as tmp:
        work = Path(tmp)
        if a.part in ("all", "rollout"):
            scanned = a.scanned_corpus or make_corpus(work / "scanned", 2, 20.0, 3, scan=True)
            part_rollout(scanned, a.horizon, work)
        corpus = None
        if a.part in ("all", "train", "window", "relative", "heads", "seeds", "long"):
            corpus = a.corpus or make_corpus(work / "dynamics", 10, 45.0, 11, scan=False)
        if a.part in ("all", "train"):
            part_train(corpus)
        if a.part in ("all", "window"):
            part_window(corpus, steps, work)
        if a.part in ("all", "relative"):
            part_relative(corpus, steps, work)
        if a.part in ("all", "heads"):
            part_heads(corpus, steps, work)
        if a.part in ("all", "seeds"):
            part_seeds(corpus, a.steps or 1000, work, a.seeds, sets)
        if a.part in ("all", "long"):
            part_long(corpus, a.steps or 1000, work, a.long_frames)


if __name__ == "__main__":
    main()
