"""The demo command: the pipeline end to end on synthetic data."""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from marionette.commands import command
from marionette.commands.corpus import SyntheticData, export_chunk, joined_chunks
from marionette.commands.render import render_source
from marionette.commands.summary import inspect_text
from marionette.corpus import Corpus
from marionette.corpus.video_shards import POSE_KIND
from marionette.corpus.vocab import ActionTokens
from marionette.dynamics.config import TrainConfig
from marionette.knobs import add_options, option
from marionette.observation.config import ObservationTrainConfig
from marionette.options import (
    positive_int,
)
from marionette.pipeline import build
from marionette.progress import ProgressBars

# The demo's video chunks: half the default size, so its ten minutes of play ingest and render their pose targets in
# under twice the time 80 s took at full size; the tiny observation models paint 22 × 40 either way.
DEMO_VIDEO_SIZE = (88, 160)  # (height, width)


def cmd_demo(a: argparse.Namespace) -> int:
    """Synthetic recordings → corpus → 20 fps view → terrain → pose targets → dynamics → a rollout → observation model →
    evaluation report, end to end."""
    from marionette.eval.report import evaluate
    from marionette.ingest import IngestOptions, VideoSettings
    from marionette.synth import generate
    from terrain_scan.options import ScanOptions

    out = Path(a.out)
    src, corpus = out / "recordings", out / "corpus"
    t0 = time.time()
    print(f"[1/9] synthesising {a.recordings} recordings × {a.seconds:g} s into {src}")
    generate(src, recordings=a.recordings, seconds=a.seconds, seed=a.seed, width=a.width, height=a.height, workers=a.workers)
    print(f"    {time.time() - t0:.0f} s")
    t = time.time()
    print(
        f"[2/9] building the corpus {corpus} with {a.workers} workers, its stages' terrain (every {a.scan_stride}th "
        "depth frame) and its pose-control targets"
    )
    scan = ScanOptions(frame_stride=a.scan_stride)
    video = VideoSettings(height=DEMO_VIDEO_SIZE[0], width=DEMO_VIDEO_SIZE[1])
    built = build(src, corpus, IngestOptions(video=video), workers=a.workers, progress=True, scan_options=scan)
    print(f"    {time.time() - t:.0f} s")
    c = Corpus(corpus)
    rows = sum(c.dynamics_shard(s).num_rows for s in c.shard_ids())
    print(f"[3/9] dynamics view at 20 fps: {rows} rows under {c.dynamics_dir()}")
    terrain, pose = built["refresh"].terrain, built["refresh"].pose
    for st, r in terrain.items():
        scanned, chunks, layers = len(r["scanned"]), len(r["chunks_written"]) + len(r["chunks_unchanged"]), r["layers"]
        print(f"[4/9] terrain of stage {st}: {scanned} recordings scanned, {layers} layers in {chunks} chunks under {r['dir']}")
    print("[5/9] the bridge: pose-control targets for every video chunk, and one segment seen by the follow camera")
    if pose is not None:
        print(f"    {len(pose['rendered'])} of {pose['chunks']} video chunks rendered ({pose['frames_rendered']} frames)")
    seg = c.segment_ids()[0]
    follow = out / f"{seg}-follow.mkv"
    render_source(corpus, follow, seg, camera="follow", size=(352, 640))
    print(inspect_text(corpus))
    _demo_dynamics(c, out, a.dynamics_steps)
    _demo_observation(c, out, a.observation_steps)
    print("[9/9] evaluation (quick protocol): Tables 1–3, long-horizon curves, the state layer")
    bars = ProgressBars()
    try:
        models = dict(observation=out / "observation", baseline=out / "observation-baseline")
        report = evaluate(
            out / "dynamics", corpus, out / "evaluation", protocol="quick", **models, log=lambda m: print("   ", m), progress=bars
        )
    finally:
        bars.close()
    print(f"    report: {report['report_md']} (plots beside it)")
    print(f"demo finished in {time.time() - t0:.1f} s; corpus at {corpus}")
    print(
        f"play it: marionette play {out / 'dynamics'} {corpus} --observation {out / 'observation'}  (then open http://127.0.0.1:8765/)"
    )
    return 0


def _demo_dynamics(c, out: Path, steps: int) -> None:
    """The demo's dynamics stages: train the tiny preset, then roll it out with an attack forced and render it."""
    from marionette.dynamics.rollout import write_rollout
    from marionette.dynamics.train import train

    runs = out / "dynamics"
    t = time.time()
    print(f"[6/9] training ActionGPT + PoseGPT (tiny preset, {steps} steps) into {runs}")

    def log(m: str) -> None:
        if m.startswith(("window", "baselines", "eval")):
            print("   ", m)

    config = TrainConfig(preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50)
    s = train(c, runs, config, log=log, progress=True)
    print(f"    {s['steps']} steps in {time.time() - t:.1f} s; checkpoint {s['checkpoint']}")
    held = c.segment_ids("test") or c.segment_ids()
    seg = max(held, key=lambda x: c.dynamics_segment(x).num_rows)
    tokens = ActionTokens.from_corpus(c)
    hunter = tokens.entities.index("hunter") if "hunter" in tokens.entities else 0
    entity = tokens.entities[hunter]
    type_key = tokens.type_keys[hunter][1] if tokens.sizes[hunter] > 1 else ""
    classes = {x["composite"]: x.get("class") for x in c.vocab["entity_types"].get(type_key, {}).get("actions", [])}
    attack = next((k for k in range(1, tokens.sizes[hunter]) if classes.get(int(tokens.composites[hunter][k])) == "attack"), None)
    states, video = out / f"{seg}-rollout.arrow", out / f"{seg}-rollout.mkv"
    force = [(entity, 40, 60, attack)] if attack is not None else []
    print(f"[7/9] rollout of {seg}: 32 seed frames, 200 predicted (10 s), {entity} forced to attack over frames 40–59, rules on")
    write_rollout(
        runs,
        c,
        seg,
        states,
        horizon=200,
        seed_frames=32,
        force=force,
        render=video,
        size=(352, 640),
        log=lambda m: print("   ", m),
    )


def _demo_observation(c, out: Path, steps: int) -> None:
    """The demo's observation stage: train the tiny video model and its pixel-AR baseline side by side (one torch
    thread each, the baseline in a child process: the tiny models are overhead-bound, so two at once finish in about
    the time one takes on two threads), then paint a held-out chunk's pose video from its first frame."""

    import torch

    from marionette.observation.generate import paint_video
    from marionette.observation.train import train

    runs, base = out / "observation", out / "observation-baseline"
    video = c.info.video
    # the tiny models paint about 22 × 40: the largest reduction of the chunk size that keeps that
    reduce = next(
        r for r in (8, 4, 2, 1) if r == 1 or (video["height"] % r == 0 and video["width"] % r == 0 and video["height"] // r >= 22)
    )
    tiny = dict(preset="tiny", steps=steps, batch_size=4, frames=5, reduce=reduce, patch=2, lr=1e-3, warmup=20)
    t = time.time()
    print(
        f"[8/9] training the observation model (tiny video DiT, control pose) into {runs} and, beside it, its pixel-AR "
        f"baseline (control actions) into {base}: {steps} steps each, 1/{reduce} of the chunk size"
    )
    threads = torch.get_num_threads()
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        baseline = pool.submit(_train_quietly, str(c.path), str(base), {**tiny, "control": "actions"})
        torch.set_num_threads(1)
        try:
            train(
                c,
                runs,
                ObservationTrainConfig(**tiny, control="pose"),
                log=lambda m: print("   ", m) if not m.startswith("step ") else None,
                progress=True,
            )
        finally:
            torch.set_num_threads(threads)
        print(f"    the observation model: {steps} steps in {time.time() - t:.1f} s; waiting for the baseline")
        for m in baseline.result():
            print("    baseline:", m)
    print(f"    both trained in {time.time() - t:.1f} s")
    split = "test" if c.segment_ids("test") else None
    for seg in (r["segment"] for r in c.segments.to_pylist() if r["chunks"] and split in (None, r["split"])):
        posed = list(joined_chunks(c, seg, (POSE_KIND,))[1])  # the chunks holding a pose target
        if posed:
            chunk = posed[0]
            break
    else:
        print("    no held-out chunk with a pose target: nothing to generate")
        return
    export_chunk(c, seg, chunk, out)  # out/pose.gbz, out/first.png (and the recorded out/rgb.mp4)
    print(f"    painting chunk {chunk} of held-out segment {seg} from its first frame")
    paint_video(runs, out / POSE_KIND, out / "first.png", out / "generated.mp4", chunks=4, steps=8, seed=0, fps=30.0)


def _train_quietly(corpus: str, out: str, config: dict) -> list[str]:
    """Train a tiny observation model on one torch thread without a progress bar (the demo's child process); returns
    its log lines but the per-step ones."""
    import torch

    from marionette.observation.train import train

    torch.set_num_threads(1)
    lines: list[str] = []
    started = time.time()
    s = train(corpus, out, ObservationTrainConfig(**config), log=lambda m: None if m.startswith("step ") else lines.append(m))
    return [*lines, f"{s['steps']} steps in {time.time() - started:.1f} s"]


# ten minutes of play: the dynamics model needs minutes to beat its baselines and to show control (80 s do not;
# docs/tradeoffs.md, "The demo's ten minutes"); at 160×90 they synthesise in about twice the time 80 s take at 320×180
DEMO_DATA = {"recordings": 20, "workers": 2, "seconds": 30.0, "width": 160, "height": 90}


@dataclass(frozen=True, kw_only=True)
class DemoOptions:
    """``marionette demo``'s own options (beside the synthetic data's, ``DEMO_DATA``)."""

    out: Path = option(Path("demo-run"), "directory for everything the demo writes", parse=Path)
    scan_stride: int = option(4, "scan every Nth depth frame (docs/tradeoffs.md: 4 keeps the RMSE)", parse=positive_int)
    dynamics_steps: int = option(1000, "training steps of the tiny dynamics model", parse=positive_int)
    observation_steps: int = option(
        300, "training steps of each tiny observation model (the pose model and its baseline)", parse=positive_int
    )


def register(sub) -> None:
    """Add demo to ``sub`` (the ``marionette`` subparsers)."""
    s = command("demo", "run the pipeline end to end on synthetic data", sub)
    add_options(s, SyntheticData, defaults=DEMO_DATA)
    add_options(s, DemoOptions)
    s.set_defaults(fn=cmd_demo)
