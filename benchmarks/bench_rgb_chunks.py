"""RGB chunks at the training size: core-ms per frame of each step, and each x264 setting's quality against the source.

    .venv/bin/python benchmarks/bench_rgb_chunks.py SRC [--size 704x1280] [--chunks 2] [--rounds 2] [--ssim-every 3]
    .venv/bin/python benchmarks/bench_rgb_chunks.py SRC --part ingest [--size 704x1280] [--workers 1,2]

SRC is a WildWorld tree (``<root>/data_part<x>/<sample>/rgb.mp4``, e.g. ``marionette synth SRC --width 1280 --height
720``). Times are CPU time (``time.process_time``; a subprocess's from ``os.wait4``), so other work on the machine
changes them less than it changes wall time; they are core-milliseconds.

Part ``chunks`` (default), one thread: the first ``--chunks`` chunks of every recording, cut as ingest cuts them.
- steps: decoding the source; making chunk frames the reference way (RGB24, crop, AREA resize in RGB: what ingest did
  before ``ChunkFrames``) and with ``ChunkFrames``; encoding them (RGB frames through ``encode_mp4`` with the preset
  alone, and yuv420p frames with the default settings);
- settings: every chunk encoded under each setting (settings interleaved, the fastest of ``--rounds`` kept), then
  decoded as a reader decodes it (``decode_frames``) and compared with the reference frames in RGB: PSNR over the
  chunk (every frame), SSIM (Wang et al. 2004: 11 × 11 Gaussian window, σ 1.5, per channel, averaged) over every
  ``--ssim-every``-th frame; the min and mean over chunks, and the bytes of a chunk. The default setting is checked
  against the bound ``--min-psnr`` / ``--min-ssim`` on every chunk.

Part ``ingest``: ``marionette ingest SRC CORPUS --no-terrain --no-pose --video-size HxW --quiet --workers n`` for each
n, a fresh process and corpus each, everything included (start-up, state, video, finalize); core-ms per recorded frame
(every frame of every rgb.mp4) and its ratio to one worker's (linear scaling: 1.00).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, preamble, psnr, single_thread_env, size_hw, table  # noqa: E402

single_thread_env()

import av  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from av.video.reformatter import VideoReformatter  # noqa: E402

from marionette import video as V  # noqa: E402

cv2.setNumThreads(1)


@dataclass(frozen=True)
class Setting:
    """One row of the settings table: how chunk frames are made (``rgb``: the reference route, encoded from RGB;
    ``planes``: ``ChunkFrames``) and the encoder's settings."""

    name: str
    route: str
    crf: int
    preset: str
    x264_options: str


def settings_tried(size: tuple[int, int]) -> list[Setting]:
    """The rows of the settings table; the default settings at ``size`` are the row named ``default``."""
    d = V.VideoSettings(*size)
    fast = V.X264_OPTIONS  # superfast's analysis with veryfast's rate control
    return [
        Setting("before: RGB round trip, veryfast", "rgb", 20, "veryfast", ""),
        Setting("planes, veryfast", "planes", 20, "veryfast", ""),
        Setting("planes, veryfast + dia", "planes", 20, "veryfast", "me=dia:subme=1"),
        Setting("planes, veryfast + dia + i-partitions (`X264_OPTIONS`)", "planes", 20, "veryfast", fast),
        Setting("… + b-adapt=0", "planes", 20, "veryfast", f"{fast}:b-adapt=0"),
        Setting("… + bframes=1", "planes", 20, "veryfast", f"{fast}:bframes=1"),
        Setting("… + bframes=0", "planes", 20, "veryfast", f"{fast}:bframes=0"),
        Setting("… + subme=0, b-adapt=0", "planes", 20, "veryfast", f"{fast}:subme=0:b-adapt=0"),
        Setting("… + subme=0, b-adapt=0, aq-mode=0, crf 19", "planes", 19, "veryfast", f"{fast}:subme=0:b-adapt=0:aq-mode=0"),
        Setting("default", "planes", d.crf, d.preset, d.x264_options),
        Setting("default, crf 18", "planes", 18, d.preset, d.x264_options),
        Setting("default, crf 22", "planes", 22, d.preset, d.x264_options),
        Setting("default + subme=0", "planes", d.crf, d.preset, f"{d.x264_options}:subme=0"),
        Setting("superfast (no mb-tree)", "planes", 20, "superfast", ""),
        Setting("ultrafast", "planes", 20, "ultrafast", ""),
    ]


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two (H, W, 3) uint8 images: Gaussian-weighted local statistics (11 × 11, σ 1.5), per channel."""
    x, y = a.astype(np.float32), b.astype(np.float32)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(z: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(z, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(s.mean())


def recordings(src: Path) -> list[Path]:
    """Every rgb.mp4 of a WildWorld tree."""
    found = sorted(src.glob("data_part*/*/rgb.mp4"))
    if not found:
        raise SystemExit(f"{src}: no data_part*/*/rgb.mp4 (a WildWorld tree, e.g. from `marionette synth`)")
    return found


def decode_source(path: Path, n: int) -> tuple[list[av.VideoFrame], av.VideoCodecContext, float, float]:
    """The first ``n`` frames of ``path`` on one codec thread, the stream's codec context, its rate, CPU seconds."""
    t = time.process_time()
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        s.codec_context.thread_count = 1
        frames = [f for _, f in zip(range(n), c.decode(s))]
        ctx, fps = s.codec_context, float(s.average_rate)
    return frames, ctx, fps, time.process_time() - t


def reference_frames(frames: list[av.VideoFrame], cr: V.CropResize) -> np.ndarray:
    """(T, H, W, 3) uint8: the source frames in RGB24, cropped, AREA-resized in RGB — the reference of every chunk."""
    to_rgb, to_size = VideoReformatter(), VideoReformatter()
    out = []
    for f in frames:
        rgb = to_rgb.reformat(f, format="rgb24", threads=1).to_ndarray()[cr.y0 : cr.y0 + cr.h, cr.x0 : cr.x0 + cr.w]
        crop = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        out.append(to_size.reformat(crop, width=cr.out_w, height=cr.out_h, interpolation="AREA", threads=1).to_ndarray())
    return np.stack(out)


def encode(setting: Setting, size: tuple[int, int], fps: float, rgb: np.ndarray, planes: list, colour: dict) -> bytes:
    """One chunk under ``setting``: RGB frames through ``encode_mp4``, or yuv420p frames through ``ChunkEncoder``."""
    vs = V.VideoSettings(*size, crf=setting.crf, preset=setting.preset, x264_options=setting.x264_options)
    if setting.route == "rgb":
        return V.encode_mp4(rgb, fps, vs)
    enc = V.ChunkEncoder(size[1], size[0], fps, vs, colour=colour)
    for f in planes:
        enc.add(f)
    return enc.finish()


def part_chunks(args: argparse.Namespace) -> None:
    size = args.size
    settings = settings_tried(size)
    cf = V.VideoSettings().chunk_frames
    steps = {"decode": [0.0, 0], "reference": [0.0, 0], "planes": [0.0, 0]}
    rows: dict[str, dict[str, list]] = {s.name: {"t": [], "psnr": [], "ssim": [], "bytes": []} for s in settings}
    n_chunks = 0
    for path in recordings(args.src):
        frames, ctx, fps, t_dec = decode_source(path, args.chunks * cf)
        steps["decode"][0] += t_dec
        steps["decode"][1] += len(frames)
        cr = V.CropResize.fit(ctx.height, ctx.width, *size)
        t = time.process_time()
        ref = reference_frames(frames, cr)
        steps["reference"][0] += time.process_time() - t
        steps["reference"][1] += len(frames)
        to_chunk = V.ChunkFrames(cr, ctx)
        t = time.process_time()
        planes = [to_chunk(f) for f in frames]
        steps["planes"][0] += time.process_time() - t
        steps["planes"][1] += len(frames)
        for a, b in V.chunk_spans(len(frames), cf):
            n_chunks += 1
            best: dict[str, float] = {}
            data: dict[str, bytes] = {}
            for _ in range(args.rounds):
                for s in settings:
                    t = time.process_time()
                    data[s.name] = encode(s, size, fps, ref[a:b], planes[a:b], to_chunk.colour)
                    best[s.name] = min(best.get(s.name, np.inf), time.process_time() - t)
            for s in settings:
                got = np.stack(V.decode_frames(data[s.name]))  # as a reader gets them
                r = rows[s.name]
                r["t"].append(best[s.name] / (b - a))
                r["bytes"].append(len(data[s.name]))
                r["psnr"].append(psnr(ref[a:b], got))
                r["ssim"].append(np.mean([ssim(x, y) for x, y in zip(ref[a : b : args.ssim_every], got[:: args.ssim_every])]))
        del frames, ref, planes  # before the next recording's are decoded
        print(f"{path}: {n_chunks} chunks so far", file=sys.stderr, flush=True)
    print(preamble(f"RGB chunks at {size[0]}×{size[1]}: CPU per step and quality per x264 setting"))
    print(
        f"{n_chunks} chunks of {cf} frames (the first {args.chunks} of each of {len(recordings(args.src))} recordings), "
        f"one thread; encode times the fastest of {args.rounds} interleaved rounds; SSIM on one frame in {args.ssim_every}; "
        f"x264 asm {V.x264_cpu_flags()}.\n"
    )
    before, default = rows[settings[0].name], rows["default"]
    step_rows = [
        ["decode the source (H.264, one thread)", f"{1e3 * steps['decode'][0] / steps['decode'][1]:.2f}", "same"],
        [
            "chunk frames: RGB24 + crop + AREA resize (before) / `ChunkFrames` (after)",
            f"{1e3 * steps['reference'][0] / steps['reference'][1]:.2f}",
            f"{1e3 * steps['planes'][0] / steps['planes'][1]:.2f}",
        ],
        [
            "encode: RGB → yuv420p, veryfast (before) / yuv420p, default settings (after)",
            f"{1e3 * np.mean(before['t']):.2f}",
            f"{1e3 * np.mean(default['t']):.2f}",
        ],
    ]
    print(table(["step", "before: core-ms per frame", "after: core-ms per frame"], step_rows))
    print()
    out = []
    for s in settings:
        r = rows[s.name]
        out.append(
            [
                f"**{s.name}**" if s.name == "default" else s.name,
                s.preset,
                s.crf,
                f"`{s.x264_options}`" if s.x264_options else "",
                f"{1e3 * np.mean(r['t']):.2f}",
                f"{min(r['psnr']):.2f} / {np.mean(r['psnr']):.2f}",
                f"{min(r['ssim']):.4f} / {np.mean(r['ssim']):.4f}",
                f"{np.mean(r['bytes']) / 1e3:.0f}",
            ]
        )
    header = ["setting", "preset", "crf", "x264 options", "encode core-ms/frame", "PSNR dB min / mean", "SSIM min / mean"]
    print(table([*header, "KB per chunk"], out))
    ok = min(default["psnr"]) >= args.min_psnr and min(default["ssim"]) >= args.min_ssim
    print(
        f"\nBound PSNR ≥ {args.min_psnr} dB and SSIM ≥ {args.min_ssim} on every chunk, default settings: "
        f"**{'met' if ok else 'NOT met'}**."
    )


def recorded_frames(src: Path) -> int:
    """Frames of every rgb.mp4 under ``src``: its non-empty packets, demuxed (nothing decoded)."""
    n = 0
    for path in recordings(src):
        with av.open(str(path)) as c:
            n += sum(1 for p in c.demux(c.streams.video[0]) if p.size)
    return n


def part_ingest(args: argparse.Namespace) -> None:
    frames = recorded_frames(args.src)
    h, w = args.size
    rows, base = [], None
    with tempfile.TemporaryDirectory(prefix="bench_rgb_chunks_") as tmp:
        for run, n in enumerate(args.workers):
            corpus = Path(tmp) / f"corpus-{run}"  # a clean build every run
            cmd = [str(ROOT / ".venv/bin/marionette"), "ingest", str(args.src), str(corpus), "--no-terrain", "--no-pose"]
            cmd += ["--video-size", f"{h}x{w}", "--quiet", "--workers", str(n)]
            t0 = time.perf_counter()
            p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
            _, status, use = os.wait4(p.pid, 0)
            wall = time.perf_counter() - t0
            if os.waitstatus_to_exitcode(status):
                raise SystemExit(f"{' '.join(cmd)}: exit {os.waitstatus_to_exitcode(status)}")
            ms = 1e3 * (use.ru_utime + use.ru_stime) / frames
            base = base or ms
            rows.append(
                [n, f"{use.ru_utime + use.ru_stime:.2f}", f"{ms:.2f}", f"{ms / base:.2f}", f"{ms * 30 / 1e3:.3f}", f"{wall:.1f}"]
            )
    print(preamble(f"`marionette ingest` at {h}×{w}: core-ms per recorded frame against workers"))
    print(f"{frames} recorded frames ({len(recordings(args.src))} recordings); CPU of the command and its workers.\n")
    print(
        table(["workers", "core-s", "core-ms per frame", "ratio to 1 worker", "core-h per recorded h (30 fps)", "wall s"], rows)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path, help="a WildWorld tree")
    ap.add_argument("--part", choices=("chunks", "ingest"), default="chunks")
    ap.add_argument("--size", type=size_hw, default=(704, 1280), help="chunk size HxW")
    ap.add_argument("--chunks", type=int, default=2, help="chunks measured per recording (part chunks)")
    ap.add_argument("--rounds", type=int, default=2, help="encodes of every chunk per setting; the fastest counts")
    ap.add_argument("--ssim-every", type=int, default=3, help="SSIM on every k-th frame of a chunk")
    ap.add_argument("--min-psnr", type=float, default=41.5, help="the bound on every chunk's PSNR, dB (chosen at 704x1280)")
    ap.add_argument("--min-ssim", type=float, default=0.975, help="the bound on every chunk's SSIM (chosen at 704x1280)")
    ap.add_argument("--workers", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2], help="part ingest")
    args = ap.parse_args()
    part_chunks(args) if args.part == "chunks" else part_ingest(args)


if __name__ == "__main__":
    main()
