"""Does the observation model follow the pose? Reference swap against quality; pose control against the pixel-AR
baseline over short and long horizons; silhouettes under a swapped pose video.

    .venv/bin/python benchmarks/bench_observation_follow.py [--corpus DIR] [--steps 1000] [--swap 0,0.1,0.2] [--pairs 24]

Data (made in a temp dir unless ``--corpus`` names one with pose targets): the tests' dynamics corpus —
ten 45 s synthetic recordings (seed 11) ingested at 36×64, terrain scanned from every depth frame
(``tests/test_observation_follow.py`` scans every 4th), pose targets rendered, one recording held out. Models (``marionette train observation``'s trainer): the tiny video DiT at 18×32
(``reduce`` 2), 5-frame clips, patch 2, batch 8, lr 1e-3, warm-up 20, for each ``--swap`` (the probability
that a training clip's first frame comes from another chunk), and the pixel-AR baseline (no swap). On the
held-out chunks, 16 Euler steps (``marionette.observation.quality``):

- short: mean |generated − recorded| over frames 1–4 of each chunk's first clip;
- relayed: the same over whole chunks relayed from their first frame (20 chunks of 5 frames);
- copy: repeating the first frame, over the same frames;
- IoU vs B / vs A: first frame of chunk A, pose frames of chunk B (the ``--pairs`` pairs whose id masks
  overlap least); silhouettes of the generated frames read by a segmenter fitted to the train frames,
  against B's id masks (followed) and A's (the first frame's bodies).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.observation.config import ObservationTrainConfig
from marionette.observation.data import Clip, ClipSource
from marionette.observation.quality import Segmenter, copy_error, follow_scores, relay_error, swap_pairs
from marionette.observation.train import load_model, train

CONFIG = ObservationTrainConfig(preset="tiny", batch_size=8, frames=5, reduce=2, patch=2, lr=1e-3, warmup=20)


def make_corpus(root: Path) -> Path:
    """The tests' dynamics corpus (module doc), its terrain scanned and its pose targets rendered."""
    from marionette.bridge.targets import render_pose_targets
    from marionette.ingest import IngestOptions, VideoSettings, build_corpus
    from marionette.synth import generate as synth
    from terrain_scan.scan import scan_stages

    synth(root / "recordings", recordings=10, seconds=45.0, seed=11, width=96, height=54, workers=2)
    build_corpus(
        root / "recordings",
        root / "corpus",
        IngestOptions(video=VideoSettings(height=36, width=64, chunk_frames=81, crf=28)),
        workers=2,
        progress=False,
    )
    scan_stages(root / "corpus", incremental=True, log=lambda *_: None)
    render_pose_targets(root / "corpus")
    return root / "corpus"


def first_clips(chunks: list[Clip], frames: int) -> list[Clip]:
    return [
        Clip(
            rgb=c.rgb[:frames],
            pose=c.pose[:frames],
            key=c.key,
            start=0,
            actions=None if c.actions is None else c.actions[:frames],
        )
        for c in chunks
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", type=Path, default=None)
    ap.add_argument("--steps", default="1000")
    ap.add_argument("--swap", default="0,0.1,0.2")
    ap.add_argument("--pairs", type=int, default=24)
    a = ap.parse_args()
    print(preamble("Observation model: reference swap, pose control against the baseline, silhouettes under a swapped pose"))
    with tempfile.TemporaryDirectory(prefix="bench_follow_") as tmp:
        work = Path(tmp)
        corpus = a.corpus or make_corpus(work)
        size, T = (18, 32), CONFIG.frames
        train_chunks = list(ClipSource(corpus, "train", T, size).chunks())
        held = [c for c in ClipSource(corpus, "test", T, size, actions=True).chunks() if len(c.rgb) == 81]
        t0 = time.perf_counter()
        seg = Segmenter(train_chunks)
        pairs = swap_pairs(held, T, a.pairs)
        if not pairs:
            raise SystemExit("no two held-out chunks both show bodies: nothing to swap")
        print(
            f"{len(train_chunks)} train / {len(held)} held-out chunks; segmenter fitted in {time.perf_counter() - t0:.0f} s, IoU on "
            f"held-out recorded frames {seg.iou_on(held):.3f}; {len(pairs)} swap pairs, id-mask overlap "
            f"{min(p.overlap for p in pairs):.3f}–{max(p.overlap for p in pairs):.3f}"
        )
        print(f"copying the first frame: short {copy_error(first_clips(held, T), T):.4f}, relayed {copy_error(held, T):.4f}\n")
        rows = []
        for steps in (int(x) for x in a.steps.split(",")):
            runs = [("pose", float(s)) for s in a.swap.split(",")] + [("actions", 0.0)]
            for control, swap in runs:
                out = work / f"{control}-{swap}-{steps}"
                t0 = time.perf_counter()
                s = train(corpus, out, replace(CONFIG, steps=steps, control=control, reference_swap=swap), log=lambda *_: None)
                took = time.perf_counter() - t0
                model = load_model(out)
                short, relayed = relay_error(model, first_clips(held, T)), relay_error(model, held)
                f = follow_scores(model, held, pairs, seg) if control == "pose" else None
                rows.append(
                    [
                        control,
                        swap,
                        steps,
                        f"{took:.0f}",
                        f"{s['evals'][-1]['held_out_loss']:.4f}",
                        f"{short:.4f}",
                        f"{relayed:.4f}",
                        f"{f['iou_pose']:.3f}" if f else "–",
                        f"{f['iou_first_frame']:.3f}" if f else "–",
                    ]
                )
                print(f"  {rows[-1]}", flush=True)
    print()
    print(
        table(
            [
                "control",
                "reference swap",
                "steps",
                "train s",
                "held-out flow loss",
                "short |Δ|",
                "relayed |Δ| (81 frames)",
                "IoU vs B (pose given)",
                "IoU vs A (first frame)",
            ],
            rows,
        )
    )


if __name__ == "__main__":
    main()
