"""The terrain commands: terrain scan, terrain import, terrain export."""

from __future__ import annotations

import argparse
from dataclasses import MISSING, dataclass
from pathlib import Path

from marionette.commands import command, strict_status
from marionette.commands.args import id_string, scan_option
from marionette.commands.summary import check_stage
from marionette.corpus import Corpus, paths
from marionette.corpus.lock import corpus_lock
from marionette.io import read_json
from marionette.knobs import add_options, option
from marionette.options import mesh_path, positive_float, positive_int
from marionette.pipeline import refresh
from terrain_scan.knobs import KNOBS
from terrain_scan.mesh import export
from terrain_scan.store import Stage, import_chunks, stage_terrain


def cmd_terrain_scan(a: argparse.Namespace) -> int:
    """Scan the corpus's stages, then bring the pose targets up to date (``marionette.pipeline.refresh``)."""
    from terrain_scan.depth import DepthDecoder
    from terrain_scan.options import ScanOptions

    options = ScanOptions.of_corpus(a.corpus)
    if a.scan_config is not None:
        options = options.merged(read_json(a.scan_config), str(a.scan_config))
    decoder = None if a.depth_decoder is None else DepthDecoder.from_json(read_json(a.depth_decoder)).to_json()
    given = {"decoder": decoder, "frame_stride": a.frame_stride, "voxel_m": a.voxel, "depth_subsample": a.depth_subsample}
    given["max_depth_m"] = a.max_depth
    options = options.updated(**{**dict(a.scan_option), **{k: v for k, v in given.items() if v is not None}})
    if a.stage is not None:
        check_stage(a.corpus, a.stage)
    if not a.quiet:
        print(f"scanning with {options.describe()}")
    report = refresh(a.corpus, a.stage, a.incremental, options, pose=a.pose, progress=not a.quiet, workers=a.workers)
    for line in report.lines():
        print(line)
    failed = report.failures()
    return strict_status(a.strict, {"terrain": len(failed["terrain"]), "pose": len(failed["pose"])})


def cmd_terrain_import(a: argparse.Namespace) -> int:
    """Make a directory of TRN2 chunks (the upstream release's ``c_<cx>_<cz>.bin``, or a stage's) a contribution
    of one of the corpus's stages, rebuild the stage, then bring the pose targets up to date."""
    from terrain_scan.options import ScanOptions

    check_stage(a.corpus, a.stage)
    alias = ScanOptions.of_corpus(a.corpus).alias()  # the stage's derivation as its scans set it
    with corpus_lock(a.corpus, "terrain import"):
        r = import_chunks(Stage(paths.stage_dir(a.corpus, a.stage), alias=alias), a.src, a.name)
    rb = r.rebuild
    what = "already imported, unchanged" if r.unchanged else f"{r.layers} measured layers"
    print(
        f"{r.name}: {r.chunks} chunk files from {a.src}, {what} ({r.skipped_filled} hole-filled layers left to the "
        f"rebuild); stage {a.stage!r}: {len(rb.written)} chunks written, {len(rb.unchanged)} unchanged, {rb.layers} layers"
    )
    if a.pose:
        for line in refresh(a.corpus, a.stage, terrain=False, pose=True, progress=not a.quiet).lines():
            print(line)
    return 0


def cmd_terrain_export(a: argparse.Namespace) -> int:
    """Export a stage's scanned terrain as a mesh, its vertices relative to the terrain's middle."""
    import numpy as np

    check_stage(a.corpus, a.stage)
    c = Corpus(a.corpus)
    st = stage_terrain(c.path, a.stage)
    layers = st.layers()[0] if st is not None else ()
    if not len(layers):
        raise ValueError(f"{c.path}: stage {a.stage!r} has no terrain yet (run `marionette terrain scan {c.path}` first)")
    origin = np.array([np.floor(layers.gx.mean()), 0.0, np.floor(layers.gz.mean())])
    export(layers, a.out, origin=origin)
    print(f"wrote {a.out} ({len(layers)} layers; vertices relative to x={origin[0]:g}, z={origin[2]:g})")
    return 0


@dataclass(frozen=True, kw_only=True)
class TerrainScanOptions:
    """``marionette terrain scan``'s options: which stages, how (the scan's knobs, each left as the corpus last
    scanned when not given), and the pose pass after it."""

    corpus: Path = option(MISSING, "a corpus directory", parse=Path, positional=True)
    stage: str | None = option(None, "one stage id (default: every stage)")
    incremental: bool = option(False, "scan only recordings that are new or changed", switch=True)
    frame_stride: int | None = option(None, "use every Nth depth frame (default: as last scanned, else 1)", parse=positive_int)
    depth_subsample: int | None = option(
        None,
        "use every Nth depth pixel of every Nth row (a 1280x720 depth video at 4 is scanned at 320x180; default: as "
        "last scanned, else 1)",
        parse=positive_int,
    )
    voxel: float | None = option(None, "voxel size of the point down-sampling, metres (default: 0.25)", parse=positive_float)
    max_depth: float | None = option(None, "depth pixels beyond this are dropped, metres (20)", parse=positive_float)
    depth_decoder: Path | None = option(
        None, "8-bit depth mapping JSON (default: as last scanned, else the synthetic game's)", parse=Path
    )
    scan_config: Path | None = option(None, "a JSON object of scan options (the keys of --scan-option)", parse=Path)
    scan_option: tuple[tuple[str, float | int], ...] = option(
        (),
        "set one scan knob (repeatable): " + ", ".join(KNOBS) + "; the corpus keeps what its last scan used "
        "(meta/scan.json, shown by `marionette inspect`)",
        parse=scan_option,
        metavar="KNOB=VALUE",
        append=True,
    )
    workers: int = option(1, "parallel processes: recordings scanned, video shards rendered", parse=positive_int)
    pose: bool = option(True, "do not bring the pose-control targets up to date", flag="--no-pose", switch=True)
    quiet: bool = option(False, "no progress bars", switch=True)
    strict: bool = option(False, "exit 1 when any recording's scan or any pose target fails", switch=True)


@dataclass(frozen=True, kw_only=True)
class TerrainImportOptions:
    """``marionette terrain import``'s options."""

    src: Path = option(MISSING, "a directory of TRN2 chunk files", parse=Path, positional=True)
    corpus: Path = option(MISSING, "a corpus directory", parse=Path, positional=True)
    stage: str = option(MISSING, "the stage id they belong to (`marionette inspect CORPUS` lists them)")
    name: str | None = option(None, "the contribution's name (default: the directory's)", parse=id_string)
    pose: bool = option(True, "do not bring the pose-control targets up to date", flag="--no-pose", switch=True)
    quiet: bool = option(False, "no progress bars", switch=True)


@dataclass(frozen=True, kw_only=True)
class TerrainExportOptions:
    """``marionette terrain export``'s options."""

    corpus: Path = option(MISSING, "a corpus directory", parse=Path, positional=True)
    stage: str = option("default", "stage id")
    out: Path = option(MISSING, "output mesh, .ply or .glb", parse=mesh_path)


def register(sub) -> None:
    """Add terrain scan, terrain import, terrain export to ``sub`` (the ``marionette`` subparsers)."""
    t = command("terrain", "terrain scans: scan a corpus's stages, export meshes", sub)
    tsub = t.add_subparsers(dest="terrain_cmd", required=True, metavar="COMMAND")
    s = command("scan", "scan the stages of a corpus into layered height-field chunks", tsub)
    add_options(s, TerrainScanOptions)
    s.set_defaults(fn=cmd_terrain_scan)
    s = command("import", "make a directory of TRN2 chunks (upstream c_<cx>_<cz>.bin) part of a corpus's stage", tsub)
    add_options(s, TerrainImportOptions)
    s.set_defaults(fn=cmd_terrain_import)
    s = command("export", "export a stage's terrain as a PLY or GLB mesh", tsub)
    add_options(s, TerrainExportOptions)
    s.set_defaults(fn=cmd_terrain_export)
