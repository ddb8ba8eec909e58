"""Cost of the deterministic RGB-chunk encoder: time per chunk, bytes, PSNR and repeatability against x264's
other settings.

    .venv/bin/python benchmarks/bench_encoder.py [--seconds 20] [--repeats 5]

Synthesises one recording (320 × 180), cuts it into 81-frame chunks at the default training size
(176 × 320, crf 20, veryfast) and encodes every chunk under each setting, the settings interleaved so
each sees the same machine load. "Distinct bitstreams" counts, for the worst chunk, how many different
byte strings the repeats produced in this one process (1 = deterministic).
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import av  # noqa: E402
import numpy as np  # noqa: E402
from common import preamble, psnr, table  # noqa: E402

from marionette import video as V  # noqa: E402
from marionette.synth import generate  # noqa: E402


def chunks_of(rgb: Path, settings: V.VideoSettings) -> list[np.ndarray]:
    """The recording's frames cropped and resized as ingest does, cut into chunks."""
    with av.open(str(rgb)) as c:
        raw = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    cr = V.CropResize.fit(raw[0].shape[0], raw[0].shape[1], settings.height, settings.width)
    small = np.stack(
        [
            av.VideoFrame.from_ndarray(np.ascontiguousarray(f[cr.y0 : cr.y0 + cr.h, cr.x0 : cr.x0 + cr.w]), format="rgb24")
            .reformat(width=settings.width, height=settings.height, interpolation="AREA")
            .to_ndarray(format="rgb24")
            for f in raw
        ]
    )
    return [small[a:b] for a, b in V.chunk_spans(len(small), settings.chunk_frames)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the synthetic recording")
    ap.add_argument("--repeats", type=int, default=5, help="encodes of every chunk per setting")
    args = ap.parse_args()
    settings = V.VideoSettings()
    if args.seconds * 30 < settings.chunk_frames or args.repeats < 1:
        ap.error(f"--seconds must hold one chunk ({settings.chunk_frames} frames at 30 fps) and --repeats be positive")
    with tempfile.TemporaryDirectory() as tmp:
        (rec,) = generate(Path(tmp), recordings=1, seconds=args.seconds, seed=0, width=320, height=180)
        chunks = chunks_of(Path(rec) / "rgb.mp4", settings)
    configs = {
        "threads=1, lookahead-threads=1 (AVX-512 on)": "threads=1:lookahead-threads=1",
        "shipped: + sliced-threads=0, asm without AVX-512": V.x264_params(),
        "mbtree=0 (AVX-512 on)": "threads=1:lookahead-threads=1:sliced-threads=0:mbtree=0",
        "asm=0 (plain C)": "threads=1:lookahead-threads=1:sliced-threads=0:asm=0",
    }
    stats = {n: {"t": [], "bytes": [], "psnr": [], "digests": [set() for _ in chunks]} for n in configs}
    for r in range(args.repeats):
        for name, params in configs.items():
            s = stats[name]
            for i, ch in enumerate(chunks):
                t = time.perf_counter()
                data = V.encode_mp4(ch, 30.0, settings, params)
                s["t"].append(time.perf_counter() - t)
                s["digests"][i].add(hashlib.sha256(data).hexdigest())
                if r == 0:
                    s["bytes"].append(len(data))
                    s["psnr"].append(np.mean([psnr(x, y) for x, y in zip(V.decode_frames(data), ch)]))
    print(preamble("Deterministic RGB chunk encoding"))
    print(
        f"{len(chunks)} chunks of {settings.chunk_frames} frames at {settings.width}×{settings.height}, crf {settings.crf}, "
        f"{settings.preset}; x264 asm: {V.x264_cpu_flags()}\n"
    )
    rows = [
        [
            name,
            f"{statistics.median(s['t']) * 1e3:.0f}",
            f"{np.mean(s['bytes']) / 1e3:.1f}",
            f"{np.mean(s['psnr']):.2f}",
            max(len(d) for d in s["digests"]),
        ]
        for name, s in stats.items()
    ]
    print(table(["x264-params", "ms per chunk (median)", "KB per chunk", "PSNR dB", "distinct bitstreams"], rows))


if __name__ == "__main__":
    main()
