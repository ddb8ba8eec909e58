"""The chunk frames ingest encodes (``marionette.video.ChunkFrames``): a yuv420p source cropped plane by plane, exactly;
every route gives the reference image (RGB24, crop, AREA resize, then 4:2:0 as the encoder takes it) up to rounding."""

from __future__ import annotations

import io

import av
import numpy as np
import pytest

from marionette.video import ChunkEncoder, ChunkFrames, CropResize, VideoSettings


def _decoded_source(h: int, w: int, frames: int = 3) -> tuple[list[av.VideoFrame], av.VideoCodecContext]:
    """A small yuv420p H.264 video of smooth random images, decoded: its frames and its stream's codec context."""
    rng = np.random.default_rng(0)
    enc = ChunkEncoder(w, h, 30.0, VideoSettings(crf=10))
    for _ in range(frames):
        coarse = rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8)
        rgb = av.VideoFrame.from_ndarray(coarse, format="rgb24").reformat(w, h, "yuv420p", interpolation="BILINEAR")
        enc.add(rgb)
    c = av.open(io.BytesIO(enc.finish()))
    s = c.streams.video[0]
    return list(c.decode(s)), s.codec_context


def _reference(frame: av.VideoFrame, cr: CropResize) -> np.ndarray:
    """The reference chunk frame in RGB: RGB24, crop, AREA resize in RGB, through yuv420p (what an encoder is fed)."""
    rgb = frame.to_ndarray(format="rgb24")[cr.y0 : cr.y0 + cr.h, cr.x0 : cr.x0 + cr.w]
    crop = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
    small = crop.reformat(width=cr.out_w, height=cr.out_h, interpolation="AREA")
    return small.reformat(format="yuv420p").to_ndarray(format="rgb24")


def _planes(frame: av.VideoFrame) -> list[np.ndarray]:
    return [np.frombuffer(p, np.uint8).reshape(p.height, p.line_size)[:, : p.width] for p in frame.planes]


def test_an_even_crop_of_a_yuv420p_source_is_its_planes_window_exactly():
    frames, ctx = _decoded_source(100, 160)
    cr = CropResize.fit(100, 160, 88, 160)  # 6 rows off each edge, no resize
    to_chunk = ChunkFrames(cr, ctx)
    assert to_chunk.planar and to_chunk.colour["colorspace"] == ctx.colorspace
    for f in frames:
        out = to_chunk(f)
        assert (out.format.name, out.height, out.width) == ("yuv420p", 88, 160)
        y, u, v = _planes(f)
        oy, ou, ov = _planes(out)
        assert np.array_equal(oy, y[6:94]) and np.array_equal(ou, u[3:47]) and np.array_equal(ov, v[3:47])


@pytest.mark.parametrize(
    ("src", "dst", "planar"),
    [((100, 160), (44, 80), True), ((90, 160), (176, 320), False)],  # even crop, resized; odd crop (row 1): RGB route
)
def test_every_route_gives_the_reference_image(src, dst, planar):
    frames, ctx = _decoded_source(*src)
    cr = CropResize.fit(*src, *dst)
    to_chunk = ChunkFrames(cr, ctx)
    assert to_chunk.planar is planar
    for f in frames:
        out = to_chunk(f)
        assert (out.format.name, out.height, out.width) == ("yuv420p", *dst)
        diff = out.to_ndarray(format="rgb24").astype(float) - _reference(f, cr)
        assert 10 * np.log10(255**2 / np.mean(diff**2)) > 30  # dB: the same image, up to 4:2:0 and rounding
