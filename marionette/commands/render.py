"""The render command: a corpus segment or a rollout table to a lossless G-buffer video."""

from __future__ import annotations

import argparse
import time
from dataclasses import MISSING, dataclass
from pathlib import Path

from marionette.bridge.jitter import Jitter
from marionette.commands import command
from marionette.commands.summary import segment_row
from marionette.corpus import Corpus
from marionette.io import read_ipc
from marionette.knobs import add_options, option
from marionette.options import (
    gbuffer_path,
    near_ids,
    non_negative_float,
    non_negative_int,
    positive_float,
    size_hxw,
)
from marionette.schema import layout_of_schema
from terrain_scan.store import segment_terrain


def render_source(
    source: Path,
    out: Path,
    segment: str | None = None,
    camera: str | None = None,
    size: tuple[int, int] = (704, 1280),
    fps: float | None = None,
    terrain: Path | None = None,
    jitter: tuple[float, float, float, int] = (0.0, 0.0, 0.0, 0),
) -> None:
    """Render one corpus segment, or a rollout table, to a G-buffer video at ``out`` (``camera``: recorded for a
    corpus, follow for a rollout by default; ``jitter``: root metres, joint degrees, time seconds, seed)."""
    from marionette.bridge.targets import TerrainScene, render_rows, source_size

    src = Path(source)
    t0 = time.time()
    camera = camera or ("recorded" if src.is_dir() else "follow")
    if src.is_dir():
        if segment is None:
            raise ValueError(f"{src}: a corpus needs --segment ID")
        c = Corpus(src)
        segment_row(c, segment)
        rows, layout = c.read_segment(segment), c.layout
        scene = TerrainScene.of_stage(terrain or segment_terrain(c, segment))
        size_src = source_size(c, segment) if camera == "recorded" else None
    else:
        rows = read_ipc(src)
        layout = layout_of_schema(rows.schema, str(src))
        if segment is not None:
            import pyarrow.compute as pc

            ids = pc.unique(rows["segment"]).to_pylist()
            if segment not in ids:
                raise ValueError(f"{src}: no segment {segment!r}{near_ids(ids, segment)} (it holds {', '.join(ids)})")
            rows = rows.filter(pc.equal(rows["segment"], segment))
        scene = TerrainScene.of_stage(terrain) if terrain else TerrainScene.empty()
        if camera == "recorded":
            raise ValueError(f"{src}: a rollout has no recorded camera to follow; use --camera follow")
        size_src = None
    meta = render_rows(layout, rows, out, scene, camera, size, fps, size_src, jitter=Jitter(*jitter), key=segment or "")
    took = time.time() - t0
    heights = f"heights {meta.h_min:g}..{meta.h_max:g} m"
    print(f"wrote {out}: {meta.width}×{meta.height} at {meta.fps:g} fps, {heights}, {took:.1f} s")


def cmd_render(a: argparse.Namespace) -> int:
    """Render one corpus segment, or a rollout table, to a G-buffer video."""
    jitter = (a.jitter_root, a.jitter_joint_deg, a.jitter_time, a.jitter_seed)
    render_source(a.source, a.out, a.segment, a.camera, a.size, a.fps, a.terrain, jitter)
    return 0


JITTER = ("jitter", "move the state before it is rendered, as training targets can be (bridge.jitter)")


@dataclass(frozen=True, kw_only=True)
class RenderOptions:
    """``marionette render``'s options."""

    source: Path = option(MISSING, "a corpus directory or a STATES.arrow rollout", parse=Path, positional=True)
    segment: str | None = option(None, "segment id (required for a corpus; `inspect CORPUS --segments` lists them)")
    camera: str | None = option(None, "default: recorded for a corpus, follow for a rollout", choices=["recorded", "follow"])
    out: Path = option(MISSING, "output G-buffer file: .mkv (FFV1, any player opens it) or .gbz", parse=gbuffer_path)
    size: tuple[int, int] = option((704, 1280), "output size, HxW", parse=size_hxw, metavar="HxW")
    fps: float | None = option(None, "output rate (default: the state's)", parse=positive_float)
    terrain: Path | None = option(None, "a stage directory (default: the segment's stage)", parse=Path)
    jitter_root: float = option(0.0, "shift each character by M metres", parse=non_negative_float, metavar="M", group=JITTER)
    jitter_joint_deg: float = option(0.0, "turn each bone by up to D°", parse=non_negative_float, metavar="D", group=JITTER)
    jitter_time: float = option(0.0, "warp time by up to S seconds", parse=non_negative_float, metavar="S", group=JITTER)
    jitter_seed: int = option(0, "seed of the jitter's draws", parse=non_negative_int, metavar="N", group=JITTER)


def register(sub) -> None:
    """Add render to ``sub`` (the ``marionette`` subparsers)."""
    s = command("render", "render a corpus segment or a rollout table to a lossless G-buffer video", sub)
    add_options(s, RenderOptions)
    s.set_defaults(fn=cmd_render)
