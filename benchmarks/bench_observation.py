"""The observation model: sampling steps against quality against time, generated frames/s, training samples/s.

    .venv/bin/python benchmarks/bench_observation.py [--corpus DIR] [--train-steps 300,1000] [--sampling-steps 2,4,8,16,32]

Input (made in a temp dir unless given): the tests' observation corpus — three 10 s synthetic
recordings (seed 7) ingested at 72×128, terrain scanned, pose targets rendered, recording
``data_part1/rec0001`` held out. The model: the tiny preset at 18×32 (``reduce`` 4), 5-frame clips,
patch 2, batch 4, lr 1e-3 (as ``tests/test_observation.py``), trained for each ``--train-steps``; the
pixel-AR baseline (``control="actions"``) alike. Quality: per held-out chunk, one chunk generated
from its first frame (seed 0) under its control; mean |generated − recorded| over the generated frames
in [−1, 1] units, beside "copy the first frame" (the error of repeating frame 0). Time: wall time of
``generate`` per generated frame (torch on all cores). Training: steps/s and clips/s over the run.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.observation.config import ObservationTrainConfig
from marionette.observation.data import ClipSource
from marionette.observation.relay import generate
from marionette.observation.train import load_model, train

CONFIG = ObservationTrainConfig(preset="tiny", batch_size=4, frames=5, reduce=4, patch=2, lr=1e-3, warmup=20)


def make_corpus(root: Path) -> Path:
    """The benchmark corpus under ``root`` (module doc)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from marionette.bridge.targets import render_pose_targets
    from marionette.ingest import IngestOptions, VideoSettings, build_corpus
    from marionette.synth import generate as synth
    from terrain_scan.scan import scan_stages

    synth(root / "recordings", recordings=3, seconds=10.0, seed=7, width=160, height=90, workers=2)
    build_corpus(
        root / "recordings",
        root / "corpus",
        IngestOptions(video=VideoSettings(height=72, width=128, crf=23)),
        workers=2,
        progress=False,
    )
    scan_stages(root / "corpus", incremental=True, log=lambda *_: None)
    render_pose_targets(root / "corpus")
    path = root / "corpus" / "meta" / "segments.parquet"
    seg = pq.read_table(path)
    split = pc.if_else(pc.equal(seg["sample"], "data_part1/rec0001"), pa.scalar("test"), seg["split"])
    pq.write_table(seg.set_column(seg.schema.get_field_index("split"), "split", split), path)
    return root / "corpus"


def quality(model, held, steps: int) -> tuple[float, float]:
    """Mean |generated − recorded| over the held-out chunks' first clips, and seconds per generated frame."""
    T = model.config.frames
    errs, took = [], 0.0
    for ch in held:
        control = ch.pose if model.config.control == "pose" else ch.actions
        t0 = time.perf_counter()
        video = generate(model, control[:T], ch.rgb[0], chunks=1, steps=steps, seed=0)
        took += time.perf_counter() - t0
        errs.append(float((video[1:] - ch.rgb[1:T]).abs().mean()))
    return float(np.mean(errs)), took / (len(held) * (T - 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", type=Path, default=None)
    ap.add_argument("--train-steps", default="300,1000")
    ap.add_argument("--sampling-steps", default="2,4,8,16,32")
    a = ap.parse_args()
    print(preamble("Observation model: sampling steps, quality, time"))
    with tempfile.TemporaryDirectory(prefix="bench_observation_") as tmp:
        work = Path(tmp)
        corpus = a.corpus or make_corpus(work)
        held = None
        rows, train_rows = [], []
        for n in (int(x) for x in a.train_steps.split(",")):
            for control in ("pose", "actions"):
                out = work / f"{control}-{n}"
                shutil.rmtree(out, ignore_errors=True)
                t0 = time.perf_counter()
                s = train(corpus, out, replace(CONFIG, steps=n, control=control), log=lambda *_: None)
                took = time.perf_counter() - t0
                train_rows.append(
                    [
                        control,
                        n,
                        f"{n / took:.2f}",
                        f"{n * CONFIG.batch_size / took:.1f}",
                        f"{s['evals'][-1]['held_out_loss']:.4f}",
                    ]
                )
                model = load_model(out)
                held = list(ClipSource(corpus, "test", model.config.frames, model.config.size, actions=True).chunks())
                for k in (int(x) for x in a.sampling_steps.split(",")):
                    err, spf = quality(model, held, k)
                    rows.append([control, n, k, f"{err:.4f}", f"{1 / spf:.1f}"])
        T = CONFIG.frames
        copy = float(np.mean([float((h.rgb[0][None] - h.rgb[1:T]).abs().mean()) for h in held]))
        print(f"\n### Training (tiny, 18×32, 5-frame clips, batch {CONFIG.batch_size}; includes decoding the chunks once)\n")
        print(table(["control", "steps", "steps/s", "clips/s", "held-out flow loss"], train_rows))
        print(
            f"\n### Sampling steps against quality and speed ({len(held)} held-out chunks; copying the first frame: {copy:.4f})\n"
        )
        print(table(["control", "training steps", "sampling steps", "mean |generated − recorded|", "generated frames/s"], rows))


if __name__ == "__main__":
    main()
