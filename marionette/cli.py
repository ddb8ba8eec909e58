"""The ``marionette`` command."""

from __future__ import annotations

import argparse
import difflib
import json
import os
import sys
import time
from pathlib import Path

from marionette.dynamics.config import TrainConfig
from marionette.dynamics.controls import add_rollout_arguments
from marionette.eval.config import PROTOCOLS
from marionette.knobs import add_training_arguments
from marionette.observation.config import ObservationTrainConfig, WanTrainConfig
from marionette.options import (
    Parser,
    chunk_frames,
    even_int,
    even_size_hxw,
    int_at_least,
    int_in,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    size_hxw,
    x264_crf,
)
from marionette.play import add_arguments as play_arguments
from terrain_scan.knobs import KNOBS

DESCRIPTION = (
    "Game recordings into a corpus, terrain and pose-control targets; dynamics and observation models trained, rolled out, "
    "painted and evaluated. `marionette COMMAND --help` lists a command's options and their defaults."
)


def near_ids(ids: list[str], wrong: str) -> str:
    """``; did you mean a, b?`` naming the ids closest to ``wrong``, or nothing when none is close."""
    near = difflib.get_close_matches(wrong, ids, n=3, cutoff=0.6)
    return f"; did you mean {', '.join(near)}?" if near else ""


def segment_row(c, segment: str) -> dict:
    """The corpus's row of ``segment``; a wrong id is a ValueError that suggests near ones and the command listing them."""
    try:
        return c.segment_row(segment)
    except KeyError:
        ids = c.segment_ids()
        raise ValueError(
            f"{c.path}: no segment {segment!r}{near_ids(ids, segment)} "
            f"(`marionette inspect {c.path} --segments` lists all {len(ids)})"
        ) from None


def cmd_synth(a: argparse.Namespace) -> int:
    from marionette.synth import generate

    t0 = time.time()
    dirs = generate(
        a.out,
        recordings=a.recordings,
        seconds=a.seconds,
        seed=a.seed,
        width=a.width,
        height=a.height,
        workers=a.workers,
        hidden_depth=a.hidden_depth,
        species=a.species,
        players=a.players,
        weapons=a.weapons,
        stages=a.stages,
        skins=a.skins,
        camera_pans=a.camera_pans,
    )
    print(f"wrote {len(dirs)} recordings under {a.out} in {time.time() - t0:.1f} s")
    return 0


def cmd_survey(a: argparse.Namespace) -> int:
    """Report what a recording tree holds (``marionette.ingest.survey``) and, with --rigs-out, draft its rigs and scenes."""
    from marionette.ingest.survey import DraftRules, draft_rigs, survey, write_drafts
    from marionette.io import write_json

    bars = None if a.quiet else ProgressBars()
    report = survey(a.source, progress=bars)
    for line in report.lines():
        print(line)
    out = report.to_json()
    status = 0
    if a.rigs_out is not None:
        rules = DraftRules(drop_shorter_than=a.drop_shorter_than, frames_per_type=a.frames_per_type)
        rigs, scenes, problems = draft_rigs(a.source, report, rules, progress=bars)
        written = write_drafts(a.rigs_out, rigs, scenes)
        for name, rig in sorted(rigs.items()):
            m = rig["measured"]
            agree = m.get("forward_agreement")
            print(
                f"rig      {name:<8} {len(rig['keep']):>3} of {len(rig['source_joints'])} joints kept, root {rig['root']}, "
                f"forward {rig['forward_axis']}"
                + (f" (motion agrees {agree:.2f})" if agree is not None else "")
                + f", contacts {' '.join(rig['contact_joints']) or '-'}, radius {rig['capsule_radius_m']} m, {m['frames']} frames"
            )
        for name in sorted(scenes):
            print(f"scene    {name}")
        for key, why in sorted(problems.items()):
            print(f"no draft {key}: {why}")
        print(
            f"wrote {len(written)} drafts under {a.rigs_out}: review them, then `marionette ingest --rigs {a.rigs_out} --scene NAME`"
        )
        out["drafts"] = {"rigs": sorted(rigs), "scenes": sorted(scenes), "problems": problems}
        status = 1 if problems and a.strict else 0
    if a.out is not None:
        write_json(a.out, out)
        print(f"wrote {a.out}")
    return 1 if a.strict and report.problems else status


def _progress(items, total: int, desc: str, quiet: bool):
    """``items`` as they come, behind a progress bar of ``total`` recordings unless ``quiet``."""
    if quiet:
        yield from items
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="recording") as bar:
        for item in items:
            bar.update(1)
            yield item


def cmd_calibrate_depth(a: argparse.Namespace) -> int:
    """Fit the 8-bit depth mapping from a recording tree's skeletons and depth (``terrain_scan.calibrate``); write
    it as JSON, plot it, and make it the scan decoder of a corpus."""
    from marionette.ingest.wildworld import discover
    from marionette.io import write_json
    from terrain_scan import calibrate

    refs = discover(a.source)
    if not refs:
        raise ValueError(f"{a.source}: no recordings (data_part*/<id>/ with state.csv) under it")
    refs = refs[: a.max_recordings] if a.max_recordings else refs
    if a.scene == "auto":  # each recording's own rigs (the tree may hold many species)
        from marionette.ingest.survey import recording_layout, rig_index

        index = rig_index(a.rigs)
        layout = lambda ref: recording_layout(ref, a.rigs, index)  # noqa: E731
    else:
        layout = checked_scene(a)
    knobs = None
    if a.contact_scale:  # where the characters stood, the depth must show ground (terrain_scan.calibrate)
        from terrain_scan.options import ScanOptions

        knobs = (ScanOptions.of_corpus(a.corpus) if a.corpus is not None else ScanOptions()).scan_kwargs()
    progress = lambda items, total, desc: _progress(items, total, desc, a.quiet)  # noqa: E731
    cal, failed = calibrate.calibrate_recordings(refs, layout, a.frame_stride, a.family, knobs, progress)
    for why in failed:
        print(f"skipped: {why}")
    for line in cal.lines():
        print(line)
    if a.out is not None:
        write_json(a.out, {"decoder": cal.chosen.to_json(), "report": cal.report()})
        print(f"wrote {a.out}")
    if a.plot is not None:
        print(f"plotted {calibrate.plot(cal, a.plot)}")
    if a.corpus is not None:
        from marionette.corpus import Corpus
        from marionette.corpus.lock import corpus_lock
        from terrain_scan.options import ScanOptions

        Corpus(a.corpus)  # a corpus, or a clear error
        with corpus_lock(a.corpus, "calibrate-depth"):
            ScanOptions.of_corpus(a.corpus).updated(decoder=cal.chosen.to_json()).store(a.corpus)
        print(
            f"{a.corpus}: its scans decode depth with this mapping now (meta/scan.json); rescan with `marionette terrain scan {a.corpus}`"
        )
    return 0


def _options(a: argparse.Namespace):
    from marionette.ingest import IngestOptions, VideoSettings

    h, w = a.video_size
    if a.scene != "auto":
        checked_scene(a)
    return IngestOptions(
        scene=a.scene,
        rigs=None if a.rigs is None else str(a.rigs),
        monster_species=a.monster_species,
        weapon=a.weapon,
        min_segment_frames=a.min_segment_frames,
        video=VideoSettings(height=h, width=w, chunk_frames=a.chunk_frames, crf=a.crf),
        compression=a.compression,
        max_member_bytes=a.max_member_bytes,
    )


def cmd_ingest(a: argparse.Namespace) -> int:
    """Ingest, then scan the terrain and render the pose targets (``marionette.pipeline.build``); 1 with --strict when anything failed."""
    from marionette.pipeline import build

    t0 = time.time()
    report = build(a.src, a.corpus, _options(a), workers=a.workers, terrain=a.terrain, pose=a.pose, progress=not a.quiet)
    counts: dict[str, int] = {}
    for r in report["results"]:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
        if r["status"] in ("quarantined", "skipped"):
            print(f"{r['status']}: {r['sample']}: {r['reason']}")
    for path, why in report["skipped"]:
        print(f"not a sample: {path}: {why}")
    info = report["info"]
    print(
        f"corpus {a.corpus}: {info['total_segments']} segments, {info['total_frames']} frames, "
        f"{', '.join(f'{v} {k}' for k, v in sorted(counts.items()))} in {time.time() - t0:.1f} s"
    )
    for line in report["refresh"].lines():
        print(line)
    return _strict_status(a.strict, report["failures"])


def _strict_status(strict: bool, failures: dict[str, int]) -> int:
    """The exit status of a build: 1 under --strict when any sample was quarantined or any scan or pose target failed."""
    if strict and any(failures.values()):
        print("--strict: " + ", ".join(f"{n} {kind}" for kind, n in failures.items() if n) + " failed", file=sys.stderr)
        return 1
    return 0


def inspect_text(corpus_path: Path, play_shards: int = 64, scene: str | None = None) -> str:
    """A human summary of a corpus: segments, frames, hours, splits, vocab, recorded play statistics (separation,
    class mix, tokens played; read from the first ``play_shards`` state shards), layout, shards, quarantine. In a
    corpus of several scenes: the scenes, and with ``scene`` that scene's layout, vocab and play."""
    from marionette.corpus import Corpus
    from marionette.corpus.play_stats import play_stats, play_stats_lines

    c = Corpus(corpus_path, scene=scene)
    info, seg = c.info, c.segments
    lines = [f"corpus   {c.path}"]
    if c.many:
        counts = {}
        for sc in c.all_segments["scene"].to_pylist():
            counts[sc] = counts.get(sc, 0) + 1
        lines.append("scenes   " + ", ".join(f"{n} (dim {x.dim}, {counts.get(n, 0)} segments)" for n, x in c.layouts.items()))
        if c.scene is None:
            lines.append("           (--scene NAME shows one scene's layout, vocab and play)")
    one = c.scene is not None
    if one:
        lines.append(f"layout   {c.layout.scene} dim={c.layout.dim} hash={c.layout.hash}")
        for name, (s0, s1) in c.layout.slices.items():
            lines.append(f"           {name:<20} [{s0}, {s1})")
    frames = info.total_frames
    lines.append(
        f"samples  {info.total_samples} ({info.total_ingested} ingested, {info.total_quarantined} quarantined, {info.total_skipped} skipped)"
    )
    lines.append(
        f"segments {info.total_segments}  frames {frames}  hours {frames / c.fps / 3600:.4f}  fps {c.fps:g}  video chunks {info.total_chunks}"
    )
    splits: dict[str, list[int]] = {}
    for sp, fr in zip(seg["split"].to_pylist(), seg["frames"].to_pylist()):
        splits.setdefault(sp, [0, 0])
        splits[sp][0] += 1
        splits[sp][1] += fr
    lines.append("splits   " + ", ".join(f"{k}: {v[0]} segments / {v[1]} frames" for k, v in sorted(splits.items())))
    for etype, v in (c.vocab["entity_types"] if one else {}).items():
        kinds: dict[str, int] = {}
        for act in v["actions"][1:]:
            kinds[act["class"]] = kinds.get(act["class"], 0) + 1
        lines.append(f"vocab    {etype}: {v['size']} tokens ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))})")
    if info.total_segments and one:
        lines += play_stats_lines(play_stats(c, max_shards=play_shards))
    lines.append(f"shards   {len(info.shards)} state + video: {c.path / 'state'}, {c.path / 'video'}")
    from terrain_scan.options import ScanOptions

    scanned = ScanOptions.stored(c.path)
    if scanned is None:
        lines.append("terrain  not scanned yet")
    else:
        lines.append(f"terrain  scanned with {scanned.describe()} ({c.path / 'meta' / 'scan.json'})")
    q = c.quarantine.to_pylist()
    lines.append(f"quarantine {len(q)}")
    for r in q:
        lines.append(f"  {r['sample']}: {r['reason']}")
    skipped = [r for r in c.samples.to_pylist() if r["status"] == "skipped"]
    if skipped:
        lines.append(f"skipped  {len(skipped)} (outside the requested slice)")
        for r in skipped:
            lines.append(f"  {r['sample']}: {r['reason']}")
    return "\n".join(lines)


SEGMENT_COLUMNS = ("segment", "split", "frames", "stage", "chunks")


def segment_rows(corpus_path: Path, split: str | None = None) -> list[dict]:
    """The corpus's segments (id, split, frames, stage, video chunks), of one split when given; an unknown split is a ValueError."""
    from marionette.corpus import Corpus

    c = Corpus(corpus_path)
    rows = [{k: r[k] for k in SEGMENT_COLUMNS} for r in c.segments.select(list(SEGMENT_COLUMNS)).to_pylist()]
    if split is not None:
        splits = sorted({r["split"] for r in rows})
        if split not in splits:
            raise ValueError(f"{c.path}: no segment in split {split!r}; its splits are {', '.join(splits) or 'none'}")
        rows = [r for r in rows if r["split"] == split]
    return rows


def segments_text(rows: list[dict]) -> str:
    """Segment rows as an aligned table, one segment a line, with a count at the end."""
    table = [list(SEGMENT_COLUMNS)] + [[str(r[k]) for k in SEGMENT_COLUMNS] for r in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(SEGMENT_COLUMNS))]
    numeric = {SEGMENT_COLUMNS.index("frames"), SEGMENT_COLUMNS.index("chunks")}
    lines = ["  ".join(v.rjust(w) if i in numeric else v.ljust(w) for i, (v, w) in enumerate(zip(row, widths))) for row in table]
    lines = [line.rstrip() for line in lines]
    frames = sum(int(r["frames"]) for r in rows)
    return "\n".join([*lines, f"{len(rows)} segments, {frames} frames"])


def cmd_inspect(a: argparse.Namespace) -> int:
    if a.segments or a.split is not None:
        rows = segment_rows(a.corpus, a.split)
        print(json.dumps(rows, indent=1) if a.json else segments_text(rows))
    elif a.json:
        from marionette.corpus import Corpus

        print(json.dumps(Corpus(a.corpus).info.to_json(), indent=1))
    else:
        print(inspect_text(a.corpus, scene=a.scene))
    return 0


def segment_chunks(c, segment: str, kinds: tuple[str, ...]) -> tuple[Path, dict[int, dict[str, bytes]]]:
    """The video shard holding ``segment`` and the segment's chunks there, joined with their current pose targets
    (``video_shards.read_joined``): chunk number → {kind → bytes} of ``kinds``."""
    from marionette.corpus.paths import parse_chunk_key
    from marionette.corpus.video_shards import read_joined

    n = segment_row(c, segment)["shard"]
    shard = c.video_path(n)
    if not shard.exists():
        raise FileNotFoundError(f"{shard}: the video shard of segment {segment!r} is missing")
    joined = read_joined(shard, c.pose_path(n), c.shard_hash(n), segment, kinds)
    chunks = {parse_chunk_key(k)[1]: v for k, v in joined.items()}
    return shard, dict(sorted(chunks.items()))


def export_chunk(c, segment: str, chunk: int, out: Path) -> tuple[int, int]:
    """Write chunk ``chunk`` of ``segment`` as ``out``/pose.mkv (its pose target), first.png (its first RGB frame) and
    rgb.mp4 (the recorded RGB); returns the frame's (height, width). A chunk without a pose target says how to render one."""
    from marionette.corpus.paths import chunk_key
    from marionette.ingest.video import decode_frames
    from marionette.io import write_bytes
    from marionette.observation.generate import write_image

    shard, chunks = segment_chunks(c, segment, ("rgb.mp4", "pose.mkv"))
    if chunk not in chunks:
        have = ", ".join(map(str, chunks)) or "none"
        raise ValueError(f"{shard}: segment {segment!r} has no chunk {chunk} (its chunks: {have})")
    m = chunks[chunk]
    if "pose.mkv" not in m:
        raise ValueError(
            f"{shard}: chunk {chunk} of segment {segment!r} has no pose target; render the targets with "
            f"`marionette terrain scan {c.path}` (or ingest without --no-pose)"
        )
    if "rgb.mp4" not in m:
        raise ValueError(f"{shard}: chunk {chunk} of segment {segment!r} has no rgb.mp4")
    first = decode_frames(m["rgb.mp4"], {0}).get(0)
    if first is None:
        raise ValueError(f"{shard}: {chunk_key(segment, chunk)}.rgb.mp4 holds no frame")
    out = Path(out)
    write_bytes(out / "pose.mkv", m["pose.mkv"])
    write_bytes(out / "rgb.mp4", m["rgb.mp4"])
    write_image(out / "first.png", first)
    return first.shape[0], first.shape[1]


def cmd_export_chunk(a: argparse.Namespace) -> int:
    """Take one video chunk's pose target and first RGB frame out of a corpus (the inputs of ``marionette generate``), or
    list the segment's chunks."""
    from marionette.corpus import Corpus
    from marionette.corpus.paths import chunk_key
    from marionette.corpus.video_shards import chunk_record

    c = Corpus(a.corpus)
    if a.chunk is None:
        shard, chunks = segment_chunks(c, a.segment, ("json", "pose.mkv"))
        if not chunks:
            raise ValueError(f"{shard}: segment {a.segment!r} has no video chunks (it is shorter than one chunk)")
        print(f"segment {a.segment}: {len(chunks)} video chunks in {shard}")
        for k, m in chunks.items():
            rec = chunk_record(m["json"], chunk_key(a.segment, k), str(shard)) if "json" in m else {}
            f0, f1 = rec.get("frames", ("?", "?"))
            print(f"  --chunk {k}: source frames [{f0}, {f1}), {'pose target' if 'pose.mkv' in m else 'no pose target'}")
        return 0
    if a.out is None:
        raise ValueError("export-chunk --chunk N needs --out DIR")
    out = Path(a.out)
    h, w = export_chunk(c, a.segment, a.chunk, out)
    print(f"wrote {out / 'pose.mkv'}, {out / 'first.png'} ({h}x{w}) and {out / 'rgb.mp4'} (the recorded RGB)")
    print(f"next: marionette generate RUNS --pose {out / 'pose.mkv'} --first-frame {out / 'first.png'} --out painted.mp4")
    return 0


def check_stage(corpus_path: Path, stage: str) -> None:
    """A ValueError naming the corpus's stages (the nearest first) when ``stage`` is none of them."""
    from marionette.corpus import Corpus

    c = Corpus(corpus_path)
    stages = sorted(set(c.segments["stage"].to_pylist()))
    if stage not in stages:
        raise ValueError(f"{c.path}: no stage {stage!r}{near_ids(stages, stage)} (its stages: {', '.join(stages) or 'none'})")


def cmd_terrain_scan(a: argparse.Namespace) -> int:
    """Scan the corpus's stages, then bring the pose targets up to date (``marionette.pipeline.refresh``)."""
    from marionette.io import read_json
    from marionette.pipeline import refresh
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
    return _strict_status(a.strict, {"terrain": len(failed["terrain"]), "pose": len(failed["pose"])})


def cmd_terrain_import(a: argparse.Namespace) -> int:
    """Make a directory of TRN2 chunks (the upstream release's ``c_<cx>_<cz>.bin``, or a stage's) a contribution
    of one of the corpus's stages, rebuild the stage, then bring the pose targets up to date."""
    from marionette.corpus import paths
    from marionette.corpus.lock import corpus_lock
    from marionette.pipeline import refresh
    from terrain_scan.options import ScanOptions
    from terrain_scan.store import Stage, import_chunks

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

    from marionette.corpus import Corpus
    from terrain_scan.mesh import export

    check_stage(a.corpus, a.stage)
    c = Corpus(a.corpus)
    st = c.stage_terrain(a.stage)
    layers = st.layers()[0] if st is not None else ()
    if not len(layers):
        raise ValueError(f"{c.path}: stage {a.stage!r} has no terrain yet (run `marionette terrain scan {c.path}` first)")
    origin = np.array([np.floor(layers.gx.mean()), 0.0, np.floor(layers.gz.mean())])
    export(layers, a.out, origin=origin)
    print(f"wrote {a.out} ({len(layers)} layers; vertices relative to x={origin[0]:g}, z={origin[2]:g})")
    return 0


def cmd_render(a: argparse.Namespace) -> int:
    """Render one corpus segment, or a rollout table, to a G-buffer video."""
    from marionette.bridge.jitter import Jitter
    from marionette.bridge.targets import TerrainScene, render_rows, source_size
    from marionette.corpus import Corpus
    from marionette.io import read_ipc
    from marionette.schema import layout_of_schema

    src = Path(a.source)
    t0 = time.time()
    a.camera = a.camera or ("recorded" if src.is_dir() else "follow")
    if src.is_dir():
        if a.segment is None:
            raise ValueError(f"{src}: a corpus needs --segment ID")
        c = Corpus(src)
        segment_row(c, a.segment)
        rows, layout = c.read_segment(a.segment), c.layout
        terrain = TerrainScene.of_stage(a.terrain or c.terrain(a.segment))
        size_src = source_size(c, a.segment) if a.camera == "recorded" else None
    else:
        rows = read_ipc(src)
        layout = layout_of_schema(rows.schema, str(src))
        if a.segment is not None:
            import pyarrow.compute as pc

            ids = pc.unique(rows["segment"]).to_pylist()
            if a.segment not in ids:
                raise ValueError(f"{src}: no segment {a.segment!r}{near_ids(ids, a.segment)} (it holds {', '.join(ids)})")
            rows = rows.filter(pc.equal(rows["segment"], a.segment))
        terrain = TerrainScene.of_stage(a.terrain) if a.terrain else TerrainScene.empty()
        if a.camera == "recorded":
            raise ValueError(f"{src}: a rollout has no recorded camera to follow; use --camera follow")
        size_src = None
    jitter = Jitter(a.jitter_root, a.jitter_joint_deg, a.jitter_time, a.jitter_seed)
    meta = render_rows(layout, rows, a.out, terrain, a.camera, a.size, a.fps, size_src, jitter=jitter, key=a.segment or "")
    took = time.time() - t0
    heights = f"heights {meta.h_min:g}..{meta.h_max:g} m"
    print(f"wrote {a.out}: {meta.width}×{meta.height} at {meta.fps:g} fps, {heights}, {took:.1f} s")
    return 0


def cmd_train_dynamics(a: argparse.Namespace) -> int:
    """Train ActionGPT + PoseGPT on a corpus (resuming from --out when it holds a checkpoint)."""
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.train import run
    from marionette.knobs import config_from_args, nodes_from_args

    config = config_from_args(TrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def cmd_train_observation(a: argparse.Namespace) -> int:
    """Train the observation model on a corpus's video shards (resuming from --out)."""
    from marionette.knobs import config_from_args, nodes_from_args
    from marionette.observation.config import ObservationTrainConfig
    from marionette.observation.train import run

    config = config_from_args(ObservationTrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def cmd_train_wan(a: argparse.Namespace) -> int:
    """Fine-tune Wan2.2-Fun-Control on a corpus's pose-control chunks (resuming from --out)."""
    from marionette.knobs import config_from_args, nodes_from_args
    from marionette.observation.config import WanTrainConfig
    from marionette.observation.wan_train import run

    config = config_from_args(WanTrainConfig, a)
    summary = run(a.corpus, a.out, config, nproc=a.nproc, nodes=nodes_from_args(a), progress=a.progress)
    print(json.dumps({k: v for k, v in summary.items() if k != "losses"}, indent=1))
    return 0


def cmd_generate(a: argparse.Namespace) -> int:
    """Paint RGB onto a pose-control video with a trained observation model."""
    from marionette.observation.generate import paint_video

    paint_video(
        a.ckpt, a.pose, a.first_frame, a.out, chunks=a.chunks, steps=a.steps, seed=a.seed, fps=a.fps, references=a.references
    )
    return 0


def cmd_rollout(a: argparse.Namespace) -> int:
    """Roll a trained dynamics model out from a recorded segment's first frames."""
    from marionette.corpus import Corpus
    from marionette.dynamics.rollout import ARGUMENTS, write_rollout

    segment_row(Corpus(a.corpus), a.segment)
    write_rollout(**{k: getattr(a, k) for k in ARGUMENTS})
    return 0


def cmd_play(a: argparse.Namespace) -> int:
    """Serve the play page (live or replay) on 127.0.0.1 until interrupted."""
    from marionette.play import ARGUMENTS, serve

    serve(**{k: getattr(a, k) for k in ARGUMENTS})
    return 0


class ProgressBars:
    """A ``progress(phase, done, total)`` callback drawing one tqdm bar per phase on stderr (a new phase closes the last bar)."""

    def __init__(self) -> None:
        self.phase: str | None = None
        self.bar = None

    def __call__(self, phase: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if phase != self.phase or self.bar is None:
            self.close()
            self.phase, self.bar = phase, tqdm(total=total, desc=phase, leave=True, dynamic_ncols=True)
        self.bar.update(done - self.bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        """Close the open bar, if any."""
        if self.bar is not None:
            self.bar.close()
        self.phase, self.bar = None, None


def cmd_eval(a: argparse.Namespace) -> int:
    """Run the evaluation protocol on a dynamics checkpoint (and an observation model) and write the report."""
    from marionette.eval.report import evaluate

    bars = None if a.quiet else ProgressBars()
    fields = ("probe_windows", "seed_frames", "horizon", "rollouts", "rollout_seconds", "state_rollouts", "state_seconds")
    fields += ("fvd_steps",)
    overrides = {k: getattr(a, k) for k in fields if getattr(a, k) is not None}
    try:
        options = dict(protocol=a.protocol, observation=a.observation, baseline=a.baseline, seed=a.seed, i3d=a.i3d)
        s = evaluate(a.dynamics, a.corpus, a.out, **options, **overrides, progress=bars)
    finally:
        if bars is not None:
            bars.close()
    print(f"report: {s['report_md']}")
    return 0


# The demo's video chunks: half the default size, so its ten minutes of play ingest and render their pose targets in
# under twice the time 80 s took at full size; the tiny observation models paint 22 × 40 either way.
DEMO_VIDEO_SIZE = (88, 160)  # (height, width)


def cmd_demo(a: argparse.Namespace) -> int:
    """Synthetic recordings → corpus → 20 fps view → terrain → pose targets → dynamics → a rollout → observation model →
    evaluation report, end to end."""
    from marionette.corpus import Corpus
    from marionette.eval.report import evaluate
    from marionette.ingest import IngestOptions, VideoSettings
    from marionette.pipeline import build
    from marionette.synth import generate
    from terrain_scan.options import ScanOptions

    out = Path(a.out)
    src, corpus = out / "recordings", out / "corpus"
    t0 = time.time()
    print(f"[1/9] synthesising {a.recordings} recordings × {a.seconds:g} s into {src}")
    generate(src, recordings=a.recordings, seconds=a.seconds, seed=a.seed, width=a.width, height=a.height, workers=a.workers)
    print(f"    {time.time() - t0:.0f} s")
    t = time.time()
    print(
        f"[2/9] building the corpus {corpus} with {a.workers} workers, its stages' terrain (every {a.scan_stride}th "
        "depth frame) and its pose-control targets"
    )
    scan = ScanOptions(frame_stride=a.scan_stride)
    video = VideoSettings(height=DEMO_VIDEO_SIZE[0], width=DEMO_VIDEO_SIZE[1])
    built = build(src, corpus, IngestOptions(video=video), workers=a.workers, progress=True, scan_options=scan)
    print(f"    {time.time() - t:.0f} s")
    c = Corpus(corpus)
    rows = sum(c.dynamics_shard(s).num_rows for s in c.shard_ids())
    print(f"[3/9] dynamics view at 20 fps: {rows} rows under {c.dynamics_dir()}")
    terrain, pose = built["refresh"].terrain, built["refresh"].pose
    for st, r in terrain.items():
        scanned, chunks, layers = len(r["scanned"]), len(r["chunks_written"]) + len(r["chunks_unchanged"]), r["layers"]
        print(f"[4/9] terrain of stage {st}: {scanned} recordings scanned, {layers} layers in {chunks} chunks under {r['dir']}")
    print("[5/9] the bridge: pose-control targets for every video chunk, and one segment seen by the follow camera")
    if pose is not None:
        print(f"    {len(pose['rendered'])} of {pose['chunks']} video chunks rendered ({pose['frames_rendered']} frames)")
    seg = c.segment_ids()[0]
    follow = out / f"{seg}-follow.mkv"
    cmd_render(
        build_parser().parse_args(
            ["render", str(corpus), "--segment", seg, "--camera", "follow", "--out", str(follow), "--size", "352x640"]
        )
    )
    print(inspect_text(corpus))
    _demo_dynamics(c, out, a.dynamics_steps)
    _demo_observation(c, out, a.observation_steps)
    print("[9/9] evaluation (quick protocol): Tables 1–3, long-horizon curves, the state layer")
    bars = ProgressBars()
    try:
        models = dict(observation=out / "observation", baseline=out / "observation-baseline")
        report = evaluate(
            out / "dynamics", corpus, out / "evaluation", protocol="quick", **models, log=lambda m: print("   ", m), progress=bars
        )
    finally:
        bars.close()
    print(f"    report: {report['report_md']} (plots beside it)")
    print(f"demo finished in {time.time() - t0:.1f} s; corpus at {corpus}")
    print(
        f"play it: marionette play {out / 'dynamics'} {corpus} --observation {out / 'observation'}  (then open http://127.0.0.1:8765/)"
    )
    return 0


def _demo_dynamics(c, out: Path, steps: int) -> None:
    """The demo's dynamics stages: train the tiny preset, then roll it out with an attack forced and render it."""
    from marionette.corpus.vocab import ActionTokens
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.rollout import write_rollout
    from marionette.dynamics.train import train

    runs = out / "dynamics"
    t = time.time()
    print(f"[6/9] training ActionGPT + PoseGPT (tiny preset, {steps} steps) into {runs}")

    def log(m: str) -> None:
        if m.startswith(("window", "baselines", "eval")):
            print("   ", m)

    config = TrainConfig(preset="tiny", steps=steps, batch_size=8, window=64, lr=2e-3, warmup=50)
    s = train(c, runs, config, log=log, progress=True)
    print(f"    {s['steps']} steps in {time.time() - t:.1f} s; checkpoint {s['checkpoint']}")
    held = c.segment_ids("test") or c.segment_ids()
    seg = max(held, key=lambda x: c.dynamics_segment(x).num_rows)
    tokens = ActionTokens.from_corpus(c)
    hunter = tokens.entities.index("hunter") if "hunter" in tokens.entities else 0
    entity = tokens.entities[hunter]
    type_key = tokens.type_keys[hunter][1] if tokens.sizes[hunter] > 1 else ""
    classes = {x["composite"]: x.get("class") for x in c.vocab["entity_types"].get(type_key, {}).get("actions", [])}
    attack = next((k for k in range(1, tokens.sizes[hunter]) if classes.get(int(tokens.composites[hunter][k])) == "attack"), None)
    states, video = out / f"{seg}-rollout.arrow", out / f"{seg}-rollout.mkv"
    force = [(entity, 40, 60, attack)] if attack is not None else []
    print(f"[7/9] rollout of {seg}: 32 seed frames, 200 predicted (10 s), {entity} forced to attack over frames 40–59, rules on")
    write_rollout(
        runs,
        c,
        seg,
        states,
        horizon=200,
        seed_frames=32,
        force=force,
        render=video,
        size=(352, 640),
        log=lambda m: print("   ", m),
    )


def _demo_observation(c, out: Path, steps: int) -> None:
    """The demo's observation stage: train the tiny video model and its pixel-AR baseline side by side (one torch
    thread each, the baseline in a child process: the tiny models are overhead-bound, so two at once finish in about
    the time one takes on two threads), then paint a held-out chunk's pose video from its first frame."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    import torch

    from marionette.observation.config import ObservationTrainConfig
    from marionette.observation.generate import paint_video
    from marionette.observation.train import train

    runs, base = out / "observation", out / "observation-baseline"
    video = c.info.video
    # the tiny models paint about 22 × 40: the largest reduction of the chunk size that keeps that
    reduce = next(
        r for r in (8, 4, 2, 1) if r == 1 or (video["height"] % r == 0 and video["width"] % r == 0 and video["height"] // r >= 22)
    )
    tiny = dict(preset="tiny", steps=steps, batch_size=4, frames=5, reduce=reduce, patch=2, lr=1e-3, warmup=20)
    t = time.time()
    print(
        f"[8/9] training the observation model (tiny video DiT, control pose) into {runs} and, beside it, its pixel-AR "
        f"baseline (control actions) into {base}: {steps} steps each, 1/{reduce} of the chunk size"
    )
    threads = torch.get_num_threads()
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        baseline = pool.submit(_train_quietly, str(c.path), str(base), {**tiny, "control": "actions"})
        torch.set_num_threads(1)
        try:
            train(
                c,
                runs,
                ObservationTrainConfig(**tiny, control="pose"),
                log=lambda m: print("   ", m) if not m.startswith("step ") else None,
                progress=True,
            )
        finally:
            torch.set_num_threads(threads)
        print(f"    the observation model: {steps} steps in {time.time() - t:.1f} s; waiting for the baseline")
        for m in baseline.result():
            print("    baseline:", m)
    print(f"    both trained in {time.time() - t:.1f} s")
    split = "test" if c.segment_ids("test") else None
    for seg in (r["segment"] for r in c.segments.to_pylist() if r["chunks"] and split in (None, r["split"])):
        posed = list(segment_chunks(c, seg, ("pose.mkv",))[1])  # the chunks holding a pose target
        if posed:
            chunk = posed[0]
            break
    else:
        print("    no held-out chunk with a pose target: nothing to generate")
        return
    export_chunk(c, seg, chunk, out)  # out/pose.mkv, out/first.png (and the recorded out/rgb.mp4)
    print(f"    painting chunk {chunk} of held-out segment {seg} from its first frame")
    paint_video(runs, out / "pose.mkv", out / "first.png", out / "generated.mp4", chunks=4, steps=8, seed=0, fps=30.0)


def _train_quietly(corpus: str, out: str, config: dict) -> list[str]:
    """Train a tiny observation model on one torch thread without a progress bar (the demo's child process); returns
    its log lines but the per-step ones."""
    import torch

    from marionette.observation.config import ObservationTrainConfig
    from marionette.observation.train import train

    torch.set_num_threads(1)
    lines: list[str] = []
    started = time.time()
    s = train(corpus, out, ObservationTrainConfig(**config), log=lambda m: None if m.startswith("step ") else lines.append(m))
    return [*lines, f"{s['steps']} steps in {time.time() - started:.1f} s"]


def scene_name(s: str) -> str:
    """An argparse type: the name of a scene, built in (``schemas/scenes/``) or among a user's (``--rigs DIR``;
    ``checked_scene`` looks it up once both options are parsed)."""
    from marionette.schema import NAME_PATTERN, SCHEMA_DIR

    if not NAME_PATTERN.fullmatch(s):
        names = sorted(f.stem for f in (SCHEMA_DIR / "scenes").glob("*.json"))
        raise argparse.ArgumentTypeError(f"{s!r} is not a scene name{near_ids(names, s)} (built-in scenes: {', '.join(names)})")
    return s


def rigs_dir(s: str) -> Path:
    """An argparse type: a directory of user rigs and scenes (``rigs/``, ``scenes/``, as ``marionette survey`` drafts)."""
    p = Path(s)
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{s}: not a directory")
    if not (p / "rigs").is_dir() and not (p / "scenes").is_dir():
        raise argparse.ArgumentTypeError(
            f"{s}: holds neither rigs/ nor scenes/ (write one with `marionette survey SOURCE --rigs-out {s}`)"
        )
    return p


def scene_missing(a: argparse.Namespace) -> str | None:
    """A parser check: why ``--scene`` names no scene, built in or under ``--rigs``, or None."""
    from marionette.schema import scene_names

    names = scene_names(rigs=getattr(a, "rigs", None))
    if a.scene in names or a.scene == "auto":
        return None
    where = "built in" + (f" or under {a.rigs}/scenes" if getattr(a, "rigs", None) is not None else "")
    return f"argument --scene: no scene {a.scene!r} {where}{near_ids(names, a.scene)} (scenes: {', '.join(names)})"


def _scene_arguments(s: argparse.ArgumentParser, default: str, help: str) -> None:
    """``--scene`` (a scene name, or auto) and ``--rigs DIR``, checked together once parsed (``scene_missing``)."""
    s.add_argument("--scene", type=scene_name, default=default, help=help)
    s.add_argument(
        "--rigs",
        type=rigs_dir,
        default=None,
        help="user rigs and scenes looked up before the built-in ones (DIR/rigs, DIR/scenes)",
    )
    s.add_check(scene_missing)


def checked_scene(a: argparse.Namespace):
    """The layout of ``--scene`` with ``--rigs``; an unknown scene or a bad rig is an error naming the file."""
    from marionette.schema import load_scene

    return load_scene(a.scene, rigs=getattr(a, "rigs", None))


def scan_option(s: str) -> tuple[str, float | int]:
    """An argparse type: ``KNOB=VALUE`` for one of ``terrain_scan.scan.KNOBS``, the value checked as the knob needs."""
    from terrain_scan.knobs import KNOBS, knob_ok

    name, eq, raw = s.partition("=")
    if not eq or name not in KNOBS:
        raise argparse.ArgumentTypeError(
            f"{s!r}: give KNOB=VALUE with KNOB one of {', '.join(KNOBS)}{near_ids(list(KNOBS), name)}"
        )
    check = KNOBS[name][0]
    try:
        value: float | int = int(raw) if check.startswith("an int") else float(raw)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r}: {name} must be {check}") from None
    if not knob_ok(check, value):
        raise argparse.ArgumentTypeError(f"{s!r}: {name} must be {check}")
    return name, value


def id_string(s: str) -> str:
    """An argparse type: a name of 1–200 letters, digits, '_' or '-' (a corpus id)."""
    from marionette.corpus.paths import ID_PATTERN

    if not ID_PATTERN.fullmatch(s):
        raise argparse.ArgumentTypeError(f"{s!r}: a name is 1-200 letters, digits, '_' or '-'")
    return s


def png_path(s: str) -> Path:
    """An argparse type: an output path ending in .png."""
    if Path(s).suffix.lower() != ".png":
        raise argparse.ArgumentTypeError(f"{s!r}: a plot is written as .png")
    return Path(s)


def mesh_path(s: str) -> Path:
    """An argparse type: an output path ending in .ply or .glb."""
    if Path(s).suffix.lower() not in (".ply", ".glb"):
        raise argparse.ArgumentTypeError(f"{s!r}: a mesh is written as .ply or .glb")
    return Path(s)


def _synthetic_arguments(
    s: argparse.ArgumentParser, recordings: int, workers: int, seconds: float = 20.0, size: tuple[int, int] = (320, 180)
) -> None:
    """The synthetic recordings' options (``synth`` and ``demo``)."""
    s.add_argument("--recordings", type=positive_int, default=recordings, help="recordings to write")
    s.add_argument("--seconds", type=positive_float, default=seconds, help="length of each recording, seconds")
    s.add_argument("--seed", type=non_negative_int, default=0, help="seed of the synthetic game")
    s.add_argument("--width", type=even_int, default=size[0], help="source video width, pixels (even)")
    s.add_argument("--height", type=even_int, default=size[1], help="source video height, pixels (even)")
    s.add_argument("--workers", type=positive_int, default=workers, help="parallel worker processes")


def generate_arguments(ap: argparse.ArgumentParser) -> None:
    """The generate command's arguments."""
    ap.add_argument(
        "ckpt",
        type=Path,
        help="an observation checkpoint or training directory, or a Wan2.2-Fun-Control model directory (`train wan`'s OUT/model)",
    )
    pose_help = "a pose-control G-buffer video (.mkv), from `marionette export-chunk` or `marionette render`"
    ap.add_argument("--pose", type=Path, required=True, help=pose_help)
    ap.add_argument("--first-frame", type=Path, required=True, help="the first frame: an image of the pose video's size")
    ap.add_argument("--out", type=Path, required=True, help="output .mp4")
    ap.add_argument("--chunks", type=positive_int, default=None, help="chunks to relay (default: all the pose video holds)")
    ap.add_argument("--steps", type=positive_int, default=20, help="sampling steps per chunk")
    ap.add_argument("--seed", type=non_negative_int, default=0, help="seed of the sampling noise")
    ap.add_argument("--fps", type=positive_float, default=30.0, help="frame rate of the output video")
    ap.add_argument(
        "--no-references",
        dest="references",
        action="store_false",
        help="a model trained with entity references paints without them (each chunk sees only its first frame)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``marionette`` command line: every subcommand, each option validated as it is parsed and its default shown.
    It imports no heavy library (torch, open3d, prefect, diffusers, moderngl): each command imports what it runs."""

    p = Parser(prog="marionette", description=DESCRIPTION)
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    def command(name: str, help: str, group=sub) -> argparse.ArgumentParser:
        return group.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".")

    s = command("survey", "report what a recording tree holds without building anything; draft rigs for its skeletons")
    s.add_argument("source", type=Path, help="a WildWorld recording tree (data_part*/<id>/)")
    s.add_argument("--rigs-out", type=Path, default=None, help="draft a rig per skeleton type and a scene per combination here")
    s.add_argument(
        "--drop-shorter-than",
        type=non_negative_float,
        default=0.0,
        help="drafts drop helper joints whose median distance to their parent is below this, metres (0: keep all)",
    )
    s.add_argument("--frames-per-type", type=int_at_least(10), default=3000, help="frames of each skeleton type read to draft it")
    s.add_argument("--out", type=Path, default=None, help="write the report (and the drafts' names) as JSON here")
    s.add_argument("--strict", action="store_true", help="exit 1 when a sample has missing or unreadable files or a draft failed")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(fn=cmd_survey)

    s = command("calibrate-depth", "fit the unpublished 8-bit depth mapping from recorded skeletons and cameras")
    s.add_argument("source", type=Path, help="a WildWorld recording tree (data_part*/<id>/)")
    _scene_arguments(
        s,
        "auto",
        "scene layout: which rigs the skeletons are (auto: each recording's own, its types' rigs found by their edges key)",
    )
    s.add_argument("--frame-stride", type=positive_int, default=5, help="use every Nth frame")
    s.add_argument("--max-recordings", type=positive_int, default=None, help="use the first N recordings (default: all)")
    s.add_argument(
        "--family",
        choices=("auto", "inverse", "log", "linear", "table"),
        default="auto",
        help="the mapping's form (auto: the parametric one whose inliers scatter least)",
    )
    s.add_argument("--out", type=Path, default=None, help="write the mapping and the fit's report here (JSON)")
    s.add_argument("--plot", type=png_path, default=None, help="plot the pairs, the fits and the residuals here (.png)")
    s.add_argument("--corpus", type=Path, default=None, help="make the mapping this corpus's scan decoder (meta/scan.json)")
    s.add_argument(
        "--no-contact-scale",
        dest="contact_scale",
        action="store_false",
        help="keep the joints' fit as it is (by default every depth is scaled so that the ground stands where the "
        "characters' contact joints stood; a second pass over the recordings)",
    )
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(fn=cmd_calibrate_depth)

    s = command("synth", "write synthetic WildWorld-format recordings")
    s.add_argument("out", type=Path, help="directory to write the recordings under")
    _synthetic_arguments(s, recordings=2, workers=1)
    s.add_argument(
        "--hidden-depth",
        action="store_true",
        help="encode depth with a mapping drawn from a family by --seed, written only to the truth (calibrate it with "
        "`marionette calibrate-depth`)",
    )
    s.add_argument(
        "--species",
        type=int_in(0, 20),
        default=0,
        help="monster species with generated skeletons (40–80 joints, recorded in no tree order); 0: the drake alone",
    )
    s.add_argument("--players", type=int_in(1, 4), default=1, help="player characters (one npc skeleton, each its own size)")
    s.add_argument(
        "--weapons", type=int_in(1, 2), default=1, help="weapon types: the 5-point greatsword, then a 2-point short blade"
    )
    s.add_argument(
        "--stages", type=int_in(1, 4), default=1, help="stages: each further one the first's map turned 90° and raised 1.5 m"
    )
    s.add_argument(
        "--skins",
        action="store_true",
        help="each recording's monster and player in colours of their own (appearance a model must read from the "
        "video, as between the real game's variants and armour)",
    )
    s.add_argument(
        "--camera-pans",
        action="store_true",
        help="the player looks around now and then (the camera turned 120–180° for 2.5–4 s every 2–5 s): the bodies "
        "leave the view and come back",
    )
    s.set_defaults(fn=cmd_synth)

    s = command("ingest", "ingest WildWorld recordings into a corpus (then finalize, scan terrain, render pose targets)")
    s.add_argument("src", type=Path, help="the source tree: a directory holding sample directories")
    s.add_argument("corpus", type=Path, help="the corpus directory (created, or updated incrementally)")
    _scene_arguments(
        s,
        "duel",
        "the scene layout (schemas/scenes/NAME.json, or DIR/scenes/NAME.json of --rigs); auto: each recording the "
        "layout of what it holds (its species', player's and weapon's rigs: one corpus, many scenes)",
    )
    species_help = "ingest only recordings whose monster has this species id (default: every species the rig declares)"
    s.add_argument("--monster-species", type=non_negative_int, help=species_help)
    s.add_argument("--weapon", type=non_negative_int, help="ingest only recordings whose hunter has this weapon (default: any)")
    s.add_argument(
        "--workers", type=positive_int, default=1, help="samples ingested (then recordings scanned) in parallel processes"
    )
    s.add_argument("--min-segment-frames", type=positive_int, default=30, help="shortest segment kept, frames")
    s.add_argument("--video-size", type=even_size_hxw, default=(176, 320), metavar="HxW", help="video chunks' size, HxW (even)")
    s.add_argument("--chunk-frames", type=chunk_frames, default=81, help="frames per video chunk (4k + 1, at least 5)")
    s.add_argument("--crf", type=x264_crf, default=20, help="x264 quality of the video chunks, 0..51 (lower is better)")
    s.add_argument("--compression", choices=["none", "lz4", "zstd"], default="zstd", help="codec of the Arrow state shards")
    s.add_argument(
        "--max-member-bytes",
        type=positive_int,
        default=2 << 30,
        help="largest skeleton.npz array a sample may declare, bytes (checked before it is inflated)",
    )
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.add_argument("--no-terrain", dest="terrain", action="store_false", help="skip the incremental terrain scan after ingest")
    s.add_argument("--no-pose", dest="pose", action="store_false", help="skip rendering the pose-control targets after ingest")
    s.add_argument("--strict", action="store_true", help="exit 1 when any sample is quarantined or any scan or pose target fails")
    s.set_defaults(fn=cmd_ingest)

    s = command("inspect", "summarise a corpus, or list its segments")
    s.add_argument("corpus", type=Path, help="a corpus directory")
    s.add_argument("--segments", action="store_true", help="list the segments: id, split, frames, stage, video chunks")
    s.add_argument("--split", default=None, help="list only this split's segments, e.g. test (implies --segments)")
    s.add_argument("--json", action="store_true", help="print info.json (with --segments: the segment rows) as JSON")
    s.add_argument("--scene", type=scene_name, default=None, help="in a corpus of several scenes: show this one's")
    s.set_defaults(fn=cmd_inspect)

    s = command("export-chunk", "take a video chunk's pose target and first frame out of a corpus (the inputs of generate)")
    s.add_argument("corpus", type=Path, help="a corpus directory")
    s.add_argument("--segment", required=True, help="segment id (`marionette inspect CORPUS --segments` lists them)")
    s.add_argument("--chunk", type=non_negative_int, default=None, help="chunk number in the segment (default: list its chunks)")
    s.add_argument("--out", type=Path, default=None, help="directory for pose.mkv, first.png and rgb.mp4 (required with --chunk)")
    s.set_defaults(fn=cmd_export_chunk)

    t = command("terrain", "terrain scans: scan a corpus's stages, export meshes")
    tsub = t.add_subparsers(dest="terrain_cmd", required=True, metavar="COMMAND")
    s = command("scan", "scan the stages of a corpus into layered height-field chunks", tsub)
    s.add_argument("corpus", type=Path, help="a corpus directory")
    s.add_argument("--stage", default=None, help="one stage id (default: every stage)")
    s.add_argument("--incremental", action="store_true", help="scan only recordings that are new or changed")
    s.add_argument(
        "--frame-stride", type=positive_int, default=None, help="use every Nth depth frame (default: as last scanned, else 1)"
    )
    s.add_argument(
        "--depth-subsample",
        type=positive_int,
        default=None,
        help="use every Nth depth pixel of every Nth row (a 1280x720 depth video at 4 is scanned at 320x180; default: as "
        "last scanned, else 1)",
    )
    s.add_argument(
        "--voxel", type=positive_float, default=None, help="voxel size of the point down-sampling, metres (default: 0.25)"
    )
    s.add_argument("--max-depth", type=positive_float, default=None, help="depth pixels beyond this are dropped, metres (20)")
    s.add_argument(
        "--depth-decoder",
        type=Path,
        default=None,
        help="8-bit depth mapping JSON (default: as last scanned, else the synthetic game's)",
    )
    s.add_argument("--scan-config", type=Path, default=None, help="a JSON object of scan options (the keys of --scan-option)")
    s.add_argument(
        "--scan-option",
        type=scan_option,
        action="append",
        default=[],
        metavar="KNOB=VALUE",
        help="set one scan knob (repeatable): " + ", ".join(KNOBS) + "; the corpus keeps what its last scan used "
        "(meta/scan.json, shown by `marionette inspect`)",
    )
    s.add_argument(
        "--workers", type=positive_int, default=1, help="parallel processes: recordings scanned, video shards rendered"
    )
    s.add_argument("--no-pose", dest="pose", action="store_false", help="do not bring the pose-control targets up to date")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.add_argument("--strict", action="store_true", help="exit 1 when any recording's scan or any pose target fails")
    s.set_defaults(fn=cmd_terrain_scan)
    s = command("import", "make a directory of TRN2 chunks (upstream c_<cx>_<cz>.bin) part of a corpus's stage", tsub)
    s.add_argument("src", type=Path, help="a directory of TRN2 chunk files")
    s.add_argument("corpus", type=Path, help="a corpus directory")
    s.add_argument("--stage", required=True, help="the stage id they belong to (`marionette inspect CORPUS` lists them)")
    s.add_argument("--name", type=id_string, default=None, help="the contribution's name (default: the directory's)")
    s.add_argument("--no-pose", dest="pose", action="store_false", help="do not bring the pose-control targets up to date")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(fn=cmd_terrain_import)
    s = command("export", "export a stage's terrain as a PLY or GLB mesh", tsub)
    s.add_argument("corpus", type=Path, help="a corpus directory")
    s.add_argument("--stage", default="default", help="stage id")
    s.add_argument("--out", type=mesh_path, required=True, help="output mesh, .ply or .glb")
    s.set_defaults(fn=cmd_terrain_export)

    s = command("render", "render a corpus segment or a rollout table to a lossless G-buffer video")
    s.add_argument("source", type=Path, help="a corpus directory or a STATES.arrow rollout")
    s.add_argument("--segment", default=None, help="segment id (required for a corpus; `inspect CORPUS --segments` lists them)")
    s.add_argument("--camera", choices=["recorded", "follow"], help="default: recorded for a corpus, follow for a rollout")
    s.add_argument("--out", type=Path, required=True, help="output .mkv")
    s.add_argument("--size", type=size_hxw, default=(704, 1280), metavar="HxW", help="output size, HxW")
    s.add_argument("--fps", type=positive_float, default=None, help="output rate (default: the state's)")
    s.add_argument("--terrain", type=Path, default=None, help="a stage directory (default: the segment's stage)")
    jit = s.add_argument_group("jitter", "move the state before it is rendered, as training targets can be (bridge.jitter)")
    jit.add_argument("--jitter-root", type=non_negative_float, default=0.0, metavar="M", help="shift each character by M metres")
    jit.add_argument("--jitter-joint-deg", type=non_negative_float, default=0.0, metavar="D", help="turn each bone by up to D°")
    jit.add_argument("--jitter-time", type=non_negative_float, default=0.0, metavar="S", help="warp time by up to S seconds")
    jit.add_argument("--jitter-seed", type=non_negative_int, default=0, metavar="N", help="seed of the jitter's draws")
    s.set_defaults(fn=cmd_render)

    t = command("train", "train a model on a corpus")
    tsub = t.add_subparsers(dest="train_cmd", required=True, metavar="COMMAND")
    s = command("dynamics", "train ActionGPT + PoseGPT (a rerun with the same --out resumes)", tsub)
    add_training_arguments(s, TrainConfig)
    s.set_defaults(fn=cmd_train_dynamics)

    s = command("observation", "train the observation model (pose video + first frame → RGB) on the video shards", tsub)
    add_training_arguments(s, ObservationTrainConfig)
    s.set_defaults(fn=cmd_train_observation)

    s = command(
        "wan", "fine-tune Wan2.2-Fun-Control on the corpus's pose-control chunks (latent cache, full or LoRA; resumes)", tsub
    )
    add_training_arguments(s, WanTrainConfig)
    s.set_defaults(fn=cmd_train_wan)

    s = command("generate", "paint RGB onto a pose-control video with a trained observation model")
    generate_arguments(s)
    s.set_defaults(fn=cmd_generate)

    s = command("rollout", "roll a trained dynamics model out from a recorded segment, with forced tokens and scripted roots")
    add_rollout_arguments(s)
    s.set_defaults(fn=cmd_rollout)

    s = command("play", "play the world model in a browser (keys force tokens, WASD moves a root), or replay state with no model")
    play_arguments(s)
    s.set_defaults(fn=cmd_play)

    s = command("eval", "evaluate a dynamics checkpoint: the paper's three tables, long-horizon curves, state metrics")

    at_least_two = int_at_least(2)
    s.add_argument("dynamics", type=Path, help="a dynamics checkpoint or training directory")
    s.add_argument("corpus", type=Path, help="a corpus directory (its test split, else train, gives the windows)")
    s.add_argument("--out", type=Path, required=True, help="the report directory")
    s.add_argument("--protocol", choices=sorted(PROTOCOLS), default="paper", help="counts and lengths (quick: the demo's)")
    s.add_argument("--observation", type=Path, help="observation checkpoint or training directory (default: no FVD columns)")
    s.add_argument("--baseline", type=Path, help="pixel-AR baseline checkpoint (control actions) for Table 1 (default: none)")
    s.add_argument(
        "--segments", dest="probe_windows", type=positive_int, metavar="N", help="probe windows (default: the protocol's)"
    )
    s.add_argument("--seed-frames", type=positive_int, help="recorded frames seeding every rollout (default: the protocol's)")
    s.add_argument("--horizon", type=positive_int, help="predicted frames of each probe window (default: the protocol's)")
    s.add_argument("--rollouts", type=at_least_two, help="long rollouts of Tables 1 and 3 (default: the protocol's)")
    s.add_argument("--rollout-seconds", type=positive_float, help="length of each long rollout, s (default: the protocol's)")
    s.add_argument(
        "--state-rollouts",
        type=at_least_two,
        help="long rollouts of Table 3's state columns, ≥ --rollouts; the first are painted (default: the protocol's)",
    )
    s.add_argument("--state-seconds", type=positive_float, help="their length, s, ≥ --rollout-seconds (default: the protocol's)")
    s.add_argument("--fvd-steps", type=positive_int, help="sampling steps of the observation models (default: the protocol's)")
    s.add_argument("--seed", type=non_negative_int, default=0, help="seed of the window choice and the samplers")
    s.add_argument("--i3d", type=Path, help="Inception-I3D weights (safetensors) for FVD proper (default: the labelled proxy)")
    s.add_argument("--quiet", action="store_true", help="no progress bars")
    s.set_defaults(fn=cmd_eval)

    s = command("demo", "run the pipeline end to end on synthetic data")
    s.add_argument("--out", type=Path, default=Path("demo-run"), help="directory for everything the demo writes")
    # ten minutes of play: the dynamics model needs minutes to beat its baselines and to show control (80 s did not;
    # docs/tradeoffs.md, "The demo's ten minutes"); at 160×90 they synthesise in about twice the time 80 s took at 320×180
    _synthetic_arguments(s, recordings=20, workers=2, seconds=30.0, size=(160, 90))
    s.add_argument(
        "--scan-stride", type=positive_int, default=4, help="scan every Nth depth frame (docs/tradeoffs.md: 4 keeps the RMSE)"
    )
    s.add_argument("--dynamics-steps", type=positive_int, default=1000, help="training steps of the tiny dynamics model")
    s.add_argument(
        "--observation-steps",
        type=positive_int,
        default=300,
        help="training steps of each tiny observation model (the pose model and its baseline)",
    )
    s.set_defaults(fn=cmd_demo)
    return p


def error_message(exc: BaseException) -> str | None:
    """What the command prints for an error it expects (bad input, a file it cannot read or write), or None
    for one it does not (a bug: its traceback is shown)."""
    if isinstance(exc, OSError):
        if exc.filename is None:
            return str(exc)
        where = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 is not None else "")
        return f"{where}: {exc.strerror or exc}"
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        return exc.args[0]  # str(KeyError) would quote the message
    if isinstance(exc, ValueError | RuntimeError | KeyError):
        return str(exc)
    safetensors = sys.modules.get("safetensors")  # an error of it can only come once it was imported
    if safetensors is not None and isinstance(exc, safetensors.SafetensorError):
        return f"not a readable safetensors file: {exc}"
    return None


def main(argv: list[str] | None = None) -> int:
    """Run one command; an expected error is one line on stderr and exit status 2 (MARIONETTE_DEBUG=1 raises it instead)."""
    args = build_parser().parse_args(argv)
    name = " ".join(n for n in (args.cmd, getattr(args, "terrain_cmd", None), getattr(args, "train_cmd", None)) if n)
    try:
        return args.fn(args)
    except BrokenPipeError:  # the reader of stdout left (`| head`): nothing to say, and no one to say it to
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE
    except KeyboardInterrupt:
        if os.environ.get("MARIONETTE_DEBUG") == "1":
            raise
        print(f"marionette {name}: interrupted", file=sys.stderr)
        return 130  # 128 + SIGINT, as a shell reports it
    except Exception as exc:
        message = error_message(exc)
        if message is None or os.environ.get("MARIONETTE_DEBUG") == "1":
            raise
        print(f"marionette {name}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
