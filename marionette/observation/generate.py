"""``marionette generate``: a trained observation model, a pose-control video and a first frame → an RGB mp4.

The pose video is a bridge G-buffer (``marionette render``'s ``.mkv`` or ``.gbz``, or a corpus's ``pose.gbz``) whose size is a
whole multiple of the model's; it is reduced like the training clips (``data.reduce_codes``). The first
frame is an image file (PNG, JPEG; read with PyAV) of the pose video's size, area-averaged to the
model's. Both are checked before any compute. The output is H.264 at the model's size (the frames the
model made, first frame included), at ``fps``.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import av
import numpy as np
import torch

from marionette.bridge.gbuffer import iter_codes, read_gbuffer_meta
from marionette.chunks import is_clip_length
from marionette.io import read_json, write_bytes
from marionette.observation.data import check_size, pose_frames, rgb_frames
from marionette.observation.relay import generate
from marionette.observation.train import load_model
from marionette.video import VideoSettings, encode_mp4


def read_image(path: Path) -> np.ndarray:
    """An image file → (H, W, 3) uint8 RGB; a clear error naming the file if it is not one."""
    try:
        with av.open(str(path)) as c:
            frame = next(c.decode(video=0))
    except (av.error.FFmpegError, OSError, StopIteration) as err:
        raise ValueError(f"{path}: cannot read as an image: {err}") from err
    return frame.to_ndarray(format="rgb24")


def write_image(path: Path, rgb: np.ndarray) -> None:
    """(H, W, 3) uint8 RGB → a PNG file (PyAV), written atomically."""

    buf = io.BytesIO()
    with av.open(buf, "w", format="image2pipe") as c:
        s = c.add_stream("png")
        s.width, s.height, s.pix_fmt = rgb.shape[1], rgb.shape[0], "rgb24"
        for p in [*s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")), *s.encode()]:
            c.mux(p)
    write_bytes(path, buf.getvalue())


def load_inputs(pose_path: Path, first_path: Path, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose frames (T, 3, h, w) in [0, 1] and the first frame (3, h, w) in [−1, 1] at the model's ``size``."""
    meta = read_gbuffer_meta(pose_path)
    first = read_image(first_path)
    if first.shape[:2] != (meta.height, meta.width):
        raise ValueError(
            f"{first_path}: a {first.shape[0]}×{first.shape[1]} first frame for a {meta.height}×{meta.width} pose video"
        )
    f = check_size((meta.height, meta.width), size, str(pose_path))
    return pose_frames(np.stack(list(iter_codes(pose_path))), f), rgb_frames(first[None], f)[0]


WAN_SETTINGS = "marionette-wan.json"  # in a fine-tuned Wan model directory: {"frames", "shift"} it was trained with


def wan_directory(path: Path) -> bool:
    """Whether ``path`` is a Wan2.2-Fun-Control model directory (a transformer config and a ``vae/``)."""
    return (path / "vae").is_dir() and ((path / "config.json").is_file() or (path / "transformer" / "config.json").is_file())


def wan_settings(path: Path) -> dict:
    """The chunk length and timestep shift a Wan model directory was fine-tuned with (``WAN_SETTINGS``), else the
    release's (81 frames, shift 5)."""

    d = read_json(path / WAN_SETTINGS) if (path / WAN_SETTINGS).is_file() else {}
    frames, shift = d.get("frames", 81), d.get("shift", 5.0)
    if not isinstance(frames, int) or isinstance(frames, bool) or not is_clip_length(frames):
        raise ValueError(f"{path / WAN_SETTINGS}: frames {frames!r} is not 4k + 1 ≥ 5")
    if not isinstance(shift, int | float) or isinstance(shift, bool) or not shift > 0:
        raise ValueError(f"{path / WAN_SETTINGS}: shift {shift!r} is not a positive number")
    bands = d.get("reference_bands", [])
    ok = isinstance(bands, list) and all(
        isinstance(b, list)
        and len(b) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) for x in b)
        and 1 <= b[0] <= b[1] <= 254
        for b in bands
    )
    if not ok:
        raise ValueError(f"{path / WAN_SETTINGS}: reference_bands {bands!r} is not a list of [first, last] render ids in 1..254")
    return {"frames": frames, "shift": float(shift), "reference_bands": [tuple(b) for b in bands]}


def paint_video(
    ckpt: Path,
    pose: Path,
    first_frame: Path,
    out: Path,
    *,
    chunks: int | None = None,
    steps: int = 20,
    seed: int = 0,
    fps: float = 30.0,
    references: bool = True,
) -> Path:
    """Paint the pose video ``pose`` from ``first_frame`` with the observation model at ``ckpt`` into the mp4 ``out``
    (``chunks`` model chunks relayed, default as many as the pose video holds)."""
    if wan_directory(Path(ckpt)):  # a fine-tuned (or released) Wan2.2-Fun-Control, at the pose video's own size
        from marionette.observation.wan import WanFunControl

        settings = wan_settings(Path(ckpt))
        wan = WanFunControl.from_pretrained(Path(ckpt), frames=settings["frames"], shift=settings["shift"])
        m = read_gbuffer_meta(pose)
        pose_t, first_t = load_inputs(pose, first_frame, (m.height, m.width))
        t0 = time.perf_counter()
        bands = settings["reference_bands"] if references else ()
        video = wan.generate(pose_t, first_t, chunks=chunks, steps=steps, seed=seed, references=bands)
    else:
        model = load_model(ckpt)
        pose_t, first_t = load_inputs(pose, first_frame, model.config.size)
        t0 = time.perf_counter()
        video = generate(model, pose_t, first_t, chunks=chunks, steps=steps, seed=seed, references=references)
    took = time.perf_counter() - t0
    frames = ((video.permute(0, 2, 3, 1).numpy() + 1.0) * 127.5).round().clip(0, 255).astype(np.uint8)
    h, w = frames.shape[1:3]
    write_bytes(out, encode_mp4(frames, fps, VideoSettings(height=h, width=w, crf=18)))
    print(f"wrote {out}: {len(frames)} frames {w}×{h} ({(len(frames) - 1) / took:.1f} generated frames/s, {steps} steps)")
    return Path(out)
