"""What ``marionette inspect`` says of a corpus (a summary, its segment rows) and the checked lookups the commands
share (a segment's row, a stage id), whose errors name the near ids and the command that lists them all."""

from __future__ import annotations

from pathlib import Path

from marionette.corpus import Corpus, paths
from marionette.corpus.play_stats import play_stats, play_stats_lines
from marionette.io import printable
from marionette.options import near_ids


def inspect_text(corpus_path: Path, play_shards: int = 64, scene: str | None = None) -> str:
    """A human summary of a corpus: segments, frames, hours, splits, vocab, recorded play statistics (separation,
    class mix, tokens played; read from the first ``play_shards`` state shards), layout, shards, quarantine. In a
    corpus of several scenes: the scenes, and with ``scene`` that scene's layout, vocab and play."""

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
    lines.append(f"shards   {len(info.shards)} state + video: {paths.state_dir(c.path)}, {paths.video_dir(c.path)}")
    from terrain_scan.options import ScanOptions

    scanned = ScanOptions.stored(c.path)
    if scanned is None:
        lines.append("terrain  not scanned yet")
    else:
        lines.append(f"terrain  scanned with {scanned.describe()} ({paths.meta(c.path, paths.SCAN)})")
    q = c.quarantine.to_pylist()
    lines.append(f"quarantine {len(q)}")
    for r in q:
        lines.append(printable(f"  {r['sample']}: {r['reason']}"))
    skipped = [r for r in c.samples.to_pylist() if r["status"] == "skipped"]
    if skipped:
        lines.append(f"skipped  {len(skipped)} (outside the requested slice)")
        for r in skipped:
            lines.append(printable(f"  {r['sample']}: {r['reason']}"))
    return "\n".join(lines)


SEGMENT_COLUMNS = ("segment", "split", "frames", "stage", "chunks")


def segment_rows(corpus_path: Path, split: str | None = None) -> list[dict]:
    """The corpus's segments (id, split, frames, stage, video chunks), of one split when given; an unknown split is a ValueError."""

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


def check_stage(corpus_path: Path, stage: str) -> None:
    """A ValueError naming the corpus's stages (the nearest first) when ``stage`` is none of them."""

    c = Corpus(corpus_path)
    stages = sorted(set(c.segments["stage"].to_pylist()))
    if stage not in stages:
        raise ValueError(f"{c.path}: no stage {stage!r}{near_ids(stages, stage)} (its stages: {', '.join(stages) or 'none'})")
