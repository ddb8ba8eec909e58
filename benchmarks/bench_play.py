"""``marionette play`` with the paper-size dynamics models: frames/s it can make, and what a browser gets.

    .venv/bin/python benchmarks/bench_play.py [--frames 400] [--seconds 20] [--recordings 2]

A synthetic corpus (``--recordings`` × 30 s, 176 × 320 video, its terrain scanned so that both rules run) and a
randomly initialised paper-preset dynamics checkpoint (ActionGPT 4×256, PoseGPT 8×512, window 512; speed does not
depend on the weights). The painting model is a randomly initialised small observation DiT of the demo's
configuration (22 × 40, 5-frame chunks, 3 layers × 96), 4 sampling steps a chunk.

- **Capacity** (in process, unpaced): ``LiveSession.advance`` — a rollout step with the rules, the bridge's render
  at 176 × 320 and the frame's bookkeeping — for ``--frames`` frames after the seed: frames/s, step and render
  milliseconds (p50, p95), with painting off and on (the painter's thread shares the two cores).
- **Served** (real time): the page in Debian's Chromium (Playwright), the server pacing at the model's 20 fps, a bound
  attack key pressed every 0.5–0.9 s for ``--seconds``: the frames/s the page receives, and key-to-frame latency (the
  page's clock from the key's message to the first frame that answers it) p50 / p95; with painting off and on
  (painted frames/s as the painter reports).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from common import preamble, table

from marionette.corpus import Corpus
from marionette.ingest import IngestOptions, VideoSettings, build_corpus

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync"]  # fmt: skip


def make_inputs(work: Path, recordings: int) -> tuple[Corpus, Path, Path]:
    """(corpus, paper checkpoint, painting model) under ``work``."""
    from bench_dynamics import paper_checkpoint

    from marionette.checkpoint import save_checkpoint
    from marionette.observation.config import ObservationConfig
    from marionette.observation.model import VideoDiT
    from marionette.synth import generate
    from terrain_scan.options import ScanOptions
    from terrain_scan.scan import scan_stages

    generate(work / "recordings", recordings=recordings, seconds=30.0, seed=3, width=320, height=180, workers=2)
    opts = IngestOptions(video=VideoSettings(height=176, width=320, chunk_frames=81, crf=28))
    build_corpus(work / "recordings", work / "corpus", opts, workers=2, progress=False)
    scan_stages(work / "corpus", incremental=True, options=ScanOptions(frame_stride=4), log=lambda *_: None)
    c = Corpus(work / "corpus")
    ckpt = paper_checkpoint(c, work / "paper")
    cfg = ObservationConfig(frames=5, height=22, width_px=40, patch=2, width=96, layers=3, heads=4)
    save_checkpoint(work / "paint", 0, VideoDiT(cfg), meta={"kind": "observation", "observation_config": cfg.to_json()})
    return c, ckpt, work / "paint"


def session(c: Corpus, ckpt: Path, paint: Path | None, work: Path):
    from marionette.play.session import LiveSession

    return LiveSession(ckpt, c, seed_frames=64, record_dir=work / "sessions", observation=paint, log=lambda *_: None)


def capacity(c: Corpus, ckpt: Path, paint: Path | None, frames: int, work: Path) -> list[object]:
    s = session(c, ckpt, paint, work)
    try:
        s.advance()  # the seed
        steps, renders = [], []
        t0 = time.perf_counter()
        for _ in range(frames):
            meta, _ = s.advance()
            steps.append(meta["step_ms"])
            renders.append(meta["render_ms"])
        took = time.perf_counter() - t0
        painted = s.painter.painted_fps if s.painter is not None else None
    finally:
        s.close()
    return [
        "on" if paint else "off",
        f"{frames / took:.1f}",
        f"{np.percentile(steps, 50):.1f} / {np.percentile(steps, 95):.1f}",
        f"{np.percentile(renders, 50):.1f} / {np.percentile(renders, 95):.1f}",
        "–" if painted is None else f"{painted:.1f}",
    ]


def served(c: Corpus, ckpt: Path, paint: Path | None, seconds: float, work: Path) -> list[object]:
    from playwright.sync_api import sync_playwright

    from marionette.eval.control import recorded_swingers
    from marionette.play.server import Server

    s = session(c, ckpt, paint, work)
    server = Server(s, port=0, log=lambda *_: None).start()
    attack = (recorded_swingers(c, "hunter", 10, 1) or [1])[0]
    s.bind("hunter", "J", attack)
    rng = np.random.default_rng(0)
    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS, headless=True)
            pg = b.new_page(viewport={"width": 1400, "height": 1100})
            pg.goto(server.url)
            pg.wait_for_function("window.marionette && window.marionette.ready && window.marionette.frames > 20", timeout=120_000)
            n0, t0 = pg.evaluate("window.marionette.frames"), time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                pg.keyboard.press("j")
                time.sleep(float(rng.uniform(0.5, 0.9)))
            took = time.perf_counter() - t0
            n = pg.evaluate("window.marionette.frames") - n0
            lat = pg.evaluate("window.marionette.latencies")
            b.close()
        painted = s.painter.painted_fps if s.painter is not None else None
    finally:
        server.stop()
    return [
        "on" if paint else "off",
        f"{n / took:.1f}",
        f"{np.percentile(lat, 50):.0f} / {np.percentile(lat, 95):.0f}",
        len(lat),
        "–" if painted is None else f"{painted:.1f}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400, help="frames per capacity run")
    ap.add_argument("--seconds", type=float, default=20.0, help="seconds per served run")
    ap.add_argument("--recordings", type=int, default=2, help="synthetic recordings of 30 s")
    a = ap.parse_args()
    print(preamble("marionette play: paper-preset dynamics, 176 × 320 bridge view"))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        c, ckpt, paint = make_inputs(work, a.recordings)
        rows = [capacity(c, ckpt, p, a.frames, work) for p in (None, paint)]
        print(f"\n### Capacity: `LiveSession.advance`, unpaced, {a.frames} frames, rules on (collider, cap)\n")
        print(table(["painting", "frames/s", "step ms p50 / p95", "render ms p50 / p95", "painted frames/s"], rows))
        rows = [served(c, ckpt, p, a.seconds, work) for p in (None, paint)]
        print(f"\n### Served at 20 fps to Chromium, a key every 0.5–0.9 s for {a.seconds:g} s\n")
        print(table(["painting", "page frames/s", "key → frame ms p50 / p95", "keys", "painted frames/s"], rows))


if __name__ == "__main__":
    main()
