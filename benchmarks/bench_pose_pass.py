"""The pose-target pass over a corpus: the encoder on a thread of its own against the serial loop, by frame size.

    .venv/bin/python benchmarks/bench_pose_pass.py [--sizes 36x64,72x128,176x320] [--recordings 3] [--seconds 15]

For each size, a synthetic source (``--recordings`` × ``--seconds`` of play, seed 11, rendered at 1.5× the size) is
ingested at that video size (not timed); then ``render_pose_targets`` renders and encodes every shard's targets
twice in this process, once with every ``write_gbuffer`` of the pass overlapped (the encoder on a thread of its own)
and once serial, and the table gives wall, user and system seconds and frames/s of each, and which one the pass
uses (``write_gbuffer``'s default for a ``.gbz`` target: serial). The two passes write the same bytes. Run it with
``LP_NUM_THREADS`` set, or not, to see llvmpipe's threads at each size; the default is the process's (Mesa's own
default unless the environment sets it).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

from common import preamble, size_hw, table  # noqa: I001  (benchmarks/ on sys.path)

import marionette.bridge.targets as targets
from marionette.bridge.gbuffer import write_gbuffer
from marionette.bridge.targets import render_pose_targets
from marionette.ingest import IngestOptions, VideoSettings, build_corpus
from marionette.synth import generate


def size(text: str) -> tuple[int, int]:
    """``size_hw``, even and at least 8 on each side (the synthetic source is rendered at 1.5× it)."""
    h, w = size_hw(text)
    if h < 8 or w < 8 or h % 2 or w % 2:
        raise argparse.ArgumentTypeError(f"{text!r}: both sides even and at least 8")
    return h, w


def timed_pass(corpus: Path, overlap: bool) -> tuple[float, float, float, int, str]:
    """(wall, user, system seconds, frames, digest of the targets) of one pass over a fresh copy of ``corpus``."""
    work = corpus.parent / f"pass-{int(overlap)}"
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(corpus, work)
    targets.write_gbuffer = lambda path, frames, meta: write_gbuffer(path, frames, meta, overlap=overlap)
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    report = render_pose_targets(work)
    wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sorted((work / "pose").glob("*.tar")))).hexdigest()[:12]
    return wall, r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime, report.frames_rendered, digest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=lambda s: [size(v) for v in s.split(",")], default=[(36, 64), (72, 128), (176, 320)])
    ap.add_argument("--recordings", type=int, default=3, choices=range(1, 65), metavar="N")
    ap.add_argument("--seconds", type=float, default=15.0)
    args = ap.parse_args()
    if not 2.0 <= args.seconds <= 600.0:
        ap.error("--seconds: between 2 and 600")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for h, w in args.sizes:
            root = Path(tmp) / f"{h}x{w}"
            src_w, src_h = (w * 3 // 2 + 1) // 2 * 2, (h * 3 // 2 + 1) // 2 * 2
            generate(root / "source", recordings=args.recordings, seconds=args.seconds, seed=11, width=src_w, height=src_h)
            options = IngestOptions(video=VideoSettings(height=h, width=w, chunk_frames=81, crf=28))
            build_corpus(root / "source", root / "corpus", options, workers=1, progress=False)
            results = {overlap: timed_pass(root / "corpus", overlap) for overlap in (True, False)}
            assert results[True][4] == results[False][4], f"{h}×{w}: the two passes wrote different targets"
            for overlap, (wall, user, system, frames, _) in results.items():
                chosen = not overlap  # a .gbz target is encoded on the rendering thread
                rows.append(
                    [
                        f"{h}×{w}",
                        "overlapped" if overlap else "serial",
                        f"{wall:.1f}",
                        f"{user:.1f}",
                        f"{system:.1f}",
                        frames,
                        f"{frames / wall:.0f}",
                        "yes" if chosen else "",
                    ]
                )
    print(preamble("The pose-target pass: encoder thread against the serial loop"))
    print(f"LP_NUM_THREADS: {os.environ.get('LP_NUM_THREADS', 'unset (Mesa: one per core)')}\n")
    header = ["video", "encoder", "wall s", "user s", "system s", "frames", "frames/s", "the default"]
    print(table(header, rows))


if __name__ == "__main__":
    main()
