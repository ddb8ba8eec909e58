"""The corpus commands: survey, calibrate-depth, synth, ingest, inspect, export-chunk."""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import MISSING, dataclass
from pathlib import Path

from marionette.commands import command, strict_status
from marionette.commands.args import RIGS_HELP, checked_scene, rigs_dir, scene_missing, scene_name
from marionette.commands.summary import inspect_text, segment_row, segment_rows, segments_text
from marionette.corpus import Corpus
from marionette.corpus.paths import chunk_key, parse_chunk_key
from marionette.corpus.video_shards import CHUNK_KIND, POSE_KIND, RGB_KIND, chunk_record, read_joined
from marionette.io import printable, write_bytes, write_json
from marionette.knobs import add_options, option, options_from_args
from marionette.options import (
    chunk_frames,
    even_int,
    even_size_hxw,
    int_at_least,
    int_in,
    non_negative_float,
    non_negative_int,
    png_path,
    positive_float,
    positive_int,
    x264_crf,
)
from marionette.pipeline import build
from marionette.progress import ProgressBars, progress_items
from marionette.schema import load_scene


@dataclass(frozen=True, kw_only=True)
class SyntheticData:
    """The synthetic recordings' options, ``synth``'s defaults (``demo`` gives its own, ``DEMO_DATA``)."""

    recordings: int = option(2, "recordings to write", parse=positive_int)
    seconds: float = option(20.0, "length of each recording, seconds", parse=positive_float)
    seed: int = option(0, "seed of the synthetic game", parse=non_negative_int)
    width: int = option(320, "source video width, pixels (even)", parse=even_int)
    height: int = option(180, "source video height, pixels (even)", parse=even_int)
    workers: int = option(1, "parallel worker processes", parse=positive_int)


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


def cmd_calibrate_depth(a: argparse.Namespace) -> int:
    """Fit the 8-bit depth mapping from a recording tree's skeletons and depth (``terrain_scan.calibrate``); write
    it as JSON, plot it, and make it the scan decoder of a corpus."""
    from marionette.recordings.wildworld import discover
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
    if a.contact_scale:  # where the characters stood, the depth must show ground (terrain_scan.contact_scale)
        from terrain_scan.options import ScanOptions

        knobs = (ScanOptions.of_corpus(a.corpus) if a.corpus is not None else ScanOptions()).scan_kwargs()
    progress = lambda items, total, desc: progress_items(items, total, desc, a.quiet)  # noqa: E731
    cal, failed = calibrate.calibrate_recordings(refs, layout, a.frame_stride, a.family, knobs, progress)
    for why in failed:
        print(printable(f"skipped: {why}"))
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


@dataclass(frozen=True, kw_only=True)
class IngestCommand:
    """``marionette ingest``'s options, each checked as it is parsed (``--scene`` with ``--rigs`` once both are):
    the ingest options of the corpus (``ingest_options``) and how the build runs."""

    src: Path = option(MISSING, "the source tree: a directory holding sample directories", parse=Path, positional=True)
    corpus: Path = option(MISSING, "the corpus directory (created, or updated incrementally)", parse=Path, positional=True)
    scene: str = option(
        "duel",
        "the scene layout (schemas/scenes/NAME.json, or DIR/scenes/NAME.json of --rigs); auto: each recording the "
        "layout of what it holds (its species', player's and weapon's rigs: one corpus, many scenes)",
        parse=scene_name,
    )
    rigs: Path | None = option(None, RIGS_HELP, parse=rigs_dir)
    monster_species: int | None = option(
        None,
        "ingest only recordings whose monster has this species id (default: every species the rig declares)",
        parse=non_negative_int,
    )
    weapon: int | None = option(
        None, "ingest only recordings whose hunter has this weapon (default: any)", parse=non_negative_int
    )
    workers: int = option(1, "samples ingested (then recordings scanned) in parallel processes", parse=positive_int)
    min_segment_frames: int = option(30, "shortest segment kept, frames", parse=positive_int)
    video_size: tuple[int, int] = option((176, 320), "video chunks' size, HxW (even)", parse=even_size_hxw, metavar="HxW")
    chunk_frames: int = option(81, "frames per video chunk (4k + 1, at least 5)", parse=chunk_frames)
    crf: int = option(20, "x264 quality of the video chunks, 0..51 (lower is better)", parse=x264_crf)
    compression: str = option("zstd", "codec of the Arrow state shards", choices=("none", "lz4", "zstd"))
    max_member_bytes: int = option(
        2 << 30,
        "largest skeleton.npz array a sample may declare, bytes (checked before it is inflated)",
        parse=positive_int,
    )
    max_frame_pixels: int = option(
        3840 * 2160,
        "largest video frame a sample may hold, pixels (read from the headers before any frame is decoded)",
        parse=positive_int,
    )
    quiet: bool = option(False, "no progress bars", switch=True)
    terrain: bool = option(True, "skip the incremental terrain scan after ingest", flag="--no-terrain", switch=True)
    pose: bool = option(True, "skip rendering the pose-control targets after ingest", flag="--no-pose", switch=True)
    strict: bool = option(False, "exit 1 when any sample is quarantined or any scan or pose target fails", switch=True)

    def ingest_options(self):
        """The corpus's ``IngestOptions`` (the scene looked up now: an unknown one or a bad rig names the file)."""
        from marionette.ingest import IngestOptions, VideoSettings

        h, w = self.video_size
        if self.scene != "auto":
            load_scene(self.scene, rigs=self.rigs)
        return IngestOptions(
            scene=self.scene,
            rigs=None if self.rigs is None else str(self.rigs),
            monster_species=self.monster_species,
            weapon=self.weapon,
            min_segment_frames=self.min_segment_frames,
            video=VideoSettings(height=h, width=w, chunk_frames=self.chunk_frames, crf=self.crf),
            compression=self.compression,
            max_member_bytes=self.max_member_bytes,
            max_frame_pixels=self.max_frame_pixels,
        )


def cmd_ingest(a: argparse.Namespace) -> int:
    """Ingest, then scan the terrain and render the pose targets (``marionette.pipeline.build``); 1 with --strict when anything failed."""

    t0 = time.time()
    o = options_from_args(IngestCommand, a)
    report = build(o.src, o.corpus, o.ingest_options(), workers=o.workers, terrain=o.terrain, pose=o.pose, progress=not o.quiet)
    counts: dict[str, int] = {}
    for r in report["results"]:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
        if r["status"] in ("quarantined", "skipped"):
            print(printable(f"{r['status']}: {r['sample']}: {r['reason']}"))
    for path, why in report["skipped"]:
        print(printable(f"not a sample: {path}: {why}"))
    info = report["info"]
    print(
        f"corpus {o.corpus}: {info['total_segments']} segments, {info['total_frames']} frames, "
        f"{', '.join(f'{v} {k}' for k, v in sorted(counts.items()))} in {time.time() - t0:.1f} s"
    )
    for line in report["refresh"].lines():
        print(line)
    return strict_status(o.strict, report["failures"])


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


def joined_chunks(c, segment: str, kinds: tuple[str, ...]) -> tuple[Path, dict[int, dict[str, bytes]]]:
    """The video shard holding ``segment`` and the segment's chunks there, joined with their current pose targets
    (``video_shards.read_joined``): chunk number → {kind → bytes} of ``kinds``."""

    n = segment_row(c, segment)["shard"]
    shard = c.video_path(n)
    if not shard.exists():
        raise FileNotFoundError(f"{shard}: the video shard of segment {segment!r} is missing")
    joined = read_joined(shard, c.pose_path(n), c.shard_hash(n), segment, kinds)
    chunks = {parse_chunk_key(k)[1]: v for k, v in joined.items()}
    return shard, dict(sorted(chunks.items()))


def export_chunk(c, segment: str, chunk: int, out: Path) -> tuple[int, int]:
    """Write chunk ``chunk`` of ``segment`` as ``out``/pose.gbz (its pose target), first.png (its first RGB frame) and
    rgb.mp4 (the recorded RGB); returns the frame's (height, width). A chunk without a pose target says how to render one."""
    from marionette.observation.generate import write_image
    from marionette.video import decode_frames

    shard, chunks = joined_chunks(c, segment, (RGB_KIND, POSE_KIND))
    if chunk not in chunks:
        have = ", ".join(map(str, chunks)) or "none"
        raise ValueError(f"{shard}: segment {segment!r} has no chunk {chunk} (its chunks: {have})")
    m = chunks[chunk]
    if POSE_KIND not in m:
        raise ValueError(
            f"{shard}: chunk {chunk} of segment {segment!r} has no pose target; render the targets with "
            f"`marionette terrain scan {c.path}` (or ingest without --no-pose)"
        )
    if RGB_KIND not in m:
        raise ValueError(f"{shard}: chunk {chunk} of segment {segment!r} has no rgb.mp4")
    first = decode_frames(m[RGB_KIND], {0}).get(0)
    if first is None:
        raise ValueError(f"{shard}: {chunk_key(segment, chunk)}.rgb.mp4 holds no frame")
    out = Path(out)
    write_bytes(out / POSE_KIND, m[POSE_KIND])
    write_bytes(out / RGB_KIND, m[RGB_KIND])
    write_image(out / "first.png", first)
    return first.shape[0], first.shape[1]


def cmd_export_chunk(a: argparse.Namespace) -> int:
    """Take one video chunk's pose target and first RGB frame out of a corpus (the inputs of ``marionette generate``), or
    list the segment's chunks."""

    c = Corpus(a.corpus)
    if a.chunk is None:
        shard, chunks = joined_chunks(c, a.segment, (CHUNK_KIND, POSE_KIND))
        if not chunks:
            raise ValueError(f"{shard}: segment {a.segment!r} has no video chunks (it is shorter than one chunk)")
        print(f"segment {a.segment}: {len(chunks)} video chunks in {shard}")
        for k, m in chunks.items():
            rec = chunk_record(m[CHUNK_KIND], chunk_key(a.segment, k), str(shard)) if CHUNK_KIND in m else {}
            f0, f1 = rec.get("frames", ("?", "?"))
            print(f"  --chunk {k}: source frames [{f0}, {f1}), {'pose target' if POSE_KIND in m else 'no pose target'}")
        return 0
    if a.out is None:
        raise ValueError("export-chunk --chunk N needs --out DIR")
    out = Path(a.out)
    h, w = export_chunk(c, a.segment, a.chunk, out)
    print(f"wrote {out / POSE_KIND}, {out / 'first.png'} ({h}x{w}) and {out / RGB_KIND} (the recorded RGB)")
    print(f"next: marionette generate RUNS --pose {out / POSE_KIND} --first-frame {out / 'first.png'} --out painted.mp4")
    return 0


def register(sub) -> None:
    """Add survey, calibrate-depth, synth, ingest, inspect, export-chunk to ``sub`` (the ``marionette`` subparsers)."""
    _register_survey(sub)
    _register_calibrate_depth(sub)
    _register_synth(sub)
    _register_ingest(sub)
    _register_inspect(sub)
    _register_export_chunk(sub)


@dataclass(frozen=True, kw_only=True)
class SurveyOptions:
    """``marionette survey``'s options."""

    source: Path = option(MISSING, "a WildWorld recording tree (data_part*/<id>/)", parse=Path, positional=True)
    rigs_out: Path | None = option(None, "draft a rig per skeleton type and a scene per combination here", parse=Path)
    drop_shorter_than: float = option(
        0.0,
        "drafts drop helper joints whose median distance to their parent is below this, metres (0: keep all)",
        parse=non_negative_float,
    )
    frames_per_type: int = option(3000, "frames of each skeleton type read to draft it", parse=int_at_least(10))
    out: Path | None = option(None, "write the report (and the drafts' names) as JSON here", parse=Path)
    strict: bool = option(False, "exit 1 when a sample has missing or unreadable files or a draft failed", switch=True)
    quiet: bool = option(False, "no progress bar", switch=True)


def _register_survey(sub) -> None:
    s = command("survey", "report what a recording tree holds without building anything; draft rigs for its skeletons", sub)
    add_options(s, SurveyOptions)
    s.set_defaults(fn=cmd_survey)


@dataclass(frozen=True, kw_only=True)
class CalibrateDepthOptions:
    """``marionette calibrate-depth``'s options (``--scene`` with ``--rigs`` checked once both are parsed)."""

    source: Path = option(MISSING, "a WildWorld recording tree (data_part*/<id>/)", parse=Path, positional=True)
    scene: str = option(
        "auto",
        "scene layout: which rigs the skeletons are (auto: each recording's own, its types' rigs found by their edges key)",
        parse=scene_name,
    )
    rigs: Path | None = option(None, RIGS_HELP, parse=rigs_dir)
    frame_stride: int = option(5, "use every Nth frame", parse=positive_int)
    max_recordings: int | None = option(None, "use the first N recordings (default: all)", parse=positive_int)
    family: str = option(
        "auto",
        "the mapping's form (auto: the parametric one whose inliers scatter least)",
        choices=("auto", "inverse", "log", "linear", "table"),
    )
    out: Path | None = option(None, "write the mapping and the fit's report here (JSON)", parse=Path)
    plot: Path | None = option(None, "plot the pairs, the fits and the residuals here (.png)", parse=png_path)
    corpus: Path | None = option(None, "make the mapping this corpus's scan decoder (meta/scan.json)", parse=Path)
    contact_scale: bool = option(
        True,
        "keep the joints' fit as it is (by default every depth is scaled so that the ground stands where the "
        "characters' contact joints stood; a second pass over the recordings)",
        flag="--no-contact-scale",
        switch=True,
    )
    quiet: bool = option(False, "no progress bar", switch=True)


def _register_calibrate_depth(sub) -> None:
    s = command("calibrate-depth", "fit the unpublished 8-bit depth mapping from recorded skeletons and cameras", sub)
    add_options(s, CalibrateDepthOptions)
    s.add_check(scene_missing)
    s.set_defaults(fn=cmd_calibrate_depth)


@dataclass(frozen=True, kw_only=True)
class SynthOptions:
    """``marionette synth``'s own options (beside the synthetic data's, ``SyntheticData``): what the tree is like."""

    out: Path = option(MISSING, "directory to write the recordings under", parse=Path, positional=True)
    hidden_depth: bool = option(
        False,
        "encode depth with a mapping drawn from a family by --seed, written only to the truth (calibrate it with "
        "`marionette calibrate-depth`)",
        switch=True,
    )
    species: int = option(
        0,
        "monster species with generated skeletons (40–80 joints, recorded in no tree order); 0: the drake alone",
        parse=int_in(0, 20),
    )
    players: int = option(1, "player characters (one npc skeleton, each its own size)", parse=int_in(1, 4))
    weapons: int = option(1, "weapon types: the 5-point greatsword, then a 2-point short blade", parse=int_in(1, 2))
    stages: int = option(1, "stages: each further one the first's map turned 90° and raised 1.5 m", parse=int_in(1, 4))
    skins: bool = option(
        False,
        "each recording's monster and player in colours of their own (appearance a model must read from the "
        "video, as between the real game's variants and armour)",
        switch=True,
    )
    camera_pans: bool = option(
        False,
        "the player looks around now and then (the camera turned 120–180° for 2.5–4 s every 2–5 s): the bodies "
        "leave the view and come back",
        switch=True,
    )


def _register_synth(sub) -> None:
    s = command("synth", "write synthetic WildWorld-format recordings", sub)
    add_options(s, SyntheticData)
    add_options(s, SynthOptions)
    s.set_defaults(fn=cmd_synth)


def _register_ingest(sub) -> None:
    s = command("ingest", "ingest WildWorld recordings into a corpus (then finalize, scan terrain, render pose targets)", sub)
    add_options(s, IngestCommand)
    s.add_check(scene_missing)
    s.set_defaults(fn=cmd_ingest)


@dataclass(frozen=True, kw_only=True)
class InspectOptions:
    """``marionette inspect``'s options."""

    corpus: Path = option(MISSING, "a corpus directory", parse=Path, positional=True)
    segments: bool = option(False, "list the segments: id, split, frames, stage, video chunks", switch=True)
    split: str | None = option(None, "list only this split's segments, e.g. test (implies --segments)")
    json: bool = option(False, "print info.json (with --segments: the segment rows) as JSON", switch=True)
    scene: str | None = option(None, "in a corpus of several scenes: show this one's", parse=scene_name)


def _register_inspect(sub) -> None:
    s = command("inspect", "summarise a corpus, or list its segments", sub)
    add_options(s, InspectOptions)
    s.set_defaults(fn=cmd_inspect)


@dataclass(frozen=True, kw_only=True)
class ExportChunkOptions:
    """``marionette export-chunk``'s options."""

    corpus: Path = option(MISSING, "a corpus directory", parse=Path, positional=True)
    segment: str = option(MISSING, "segment id (`marionette inspect CORPUS --segments` lists them)")
    chunk: int | None = option(None, "chunk number in the segment (default: list its chunks)", parse=non_negative_int)
    out: Path | None = option(None, "directory for pose.gbz, first.png and rgb.mp4 (required with --chunk)", parse=Path)


def _register_export_chunk(sub) -> None:
    s = command("export-chunk", "take a video chunk's pose target and first frame out of a corpus (the inputs of generate)", sub)
    add_options(s, ExportChunkOptions)
    s.set_defaults(fn=cmd_export_chunk)
