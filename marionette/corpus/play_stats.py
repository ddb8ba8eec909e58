"""Recorded play statistics of a corpus: how far apart its characters fight, what they do, how much of the vocabulary they use.

These are the figures an evaluation compares a model's play against (and the synthetic game is tuned to
resemble real recordings by): per pair of articulated entities the root separation (3-D distance between
the recorded roots, DESIGN "Evaluation definitions") as a median over all frames, over the frames after
the approach (from the first frame of a segment where the separation falls to ``APPROACH_M`` or less) and
at the segments' last frames; per entity the share of frames in each action class (the corpus's own class
rule, read from ``meta/vocab.json``); and per entity the vocabulary's tokens, per class, and how many of
them the rows read actually play. Generic over layouts: every articulated entity, every pair of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
import pyarrow.compute as pc

from marionette.corpus import Corpus, fixed_rows

APPROACH_M = 8.0  # a segment's approach ends at its first frame with the roots this close (m)
CLASSES = ("stationary", "locomotion", "attack", "other", "none")
MIN_INSTANCES = 3  # a token "played often" has at least this many played instances in the vocab


@dataclass
class Separation:
    """Root separation of one pair of entities (m), over the frames where both roots are known."""

    pair: tuple[str, str]
    frames: int
    median_m: float
    median_horizontal_m: float
    after_approach_frames: int
    median_after_approach_m: float
    segment_ends: int
    median_at_segment_end_m: float


@dataclass
class Tokens:
    """One entity's action tokens: in the vocabulary (per class), played in the rows read, played ≥ MIN_INSTANCES times."""

    vocab: int
    vocab_per_class: dict[str, int]
    used: int
    used_per_class: dict[str, int]
    often: int


@dataclass
class PlayStats:
    """A corpus's recorded play statistics (module doc)."""

    segments: int
    frames: int
    shards_read: int
    shards_total: int
    separation: list[Separation] = field(default_factory=list)
    class_share: dict[str, dict[str, float]] = field(default_factory=dict)
    tokens: dict[str, Tokens] = field(default_factory=dict)


def _median(x: np.ndarray) -> float:
    return float(np.median(x)) if len(x) else float("nan")


def _action_classes(corpus: Corpus) -> dict[str, dict[tuple[int, int], dict]]:
    """Per rig name: (type_id, composite) → that vocab action's entry."""
    out: dict[str, dict[tuple[int, int], dict]] = {}
    for key, v in corpus.vocab.get("entity_types", {}).items():
        rig, type_id = key.split(":", 1)
        for a in v["actions"]:
            out.setdefault(rig, {})[(int(type_id), int(a["composite"]))] = a
    return out


def play_stats(corpus: Corpus, split: str | None = None, max_shards: int | None = None) -> PlayStats:
    """Play statistics (module doc) over the segments of ``split`` (all when None) in the first ``max_shards``
    state shards (all when None); separations in metres, class shares as fractions of valid frames."""
    entities = list(corpus.layout.articulated)
    names = [e.name for e in entities]
    actions = _action_classes(corpus)
    shards = corpus.shard_ids()
    read = shards if max_shards is None else shards[:max_shards]
    wanted = set(corpus.segment_ids(split)) if split is not None else None
    pairs = list(combinations(range(len(entities)), 2))
    sep: dict[tuple[int, int], dict[str, list]] = {p: {"all": [], "hor": [], "after": [], "end": []} for p in pairs}
    frames_per_class = {n: dict.fromkeys(CLASSES, 0) for n in names}
    used: dict[str, set[tuple[int, int]]] = {n: set() for n in names}
    n_frames = n_segments = 0
    for shard in read:
        table = corpus.read_shard(shard)
        for seg in pc.unique(table["segment"]).to_pylist():
            if wanted is not None and seg not in wanted:
                continue
            t = table.filter(pc.equal(table["segment"], seg))
            valid = t["valid"].to_numpy(zero_copy_only=False).astype(bool)
            n_segments += 1
            n_frames += int(valid.sum())
            roots = [fixed_rows(t[f"{n}.root_world"], 3).astype(np.float64) for n in names]
            for e in entities:
                types = t[f"{e.name}.type_id"].to_numpy().astype(np.int64)[valid]
                acts = t[f"{e.name}.action"].to_numpy().astype(np.int64)[valid]
                table_e = actions.get(e.rig.name, {})
                for (ty, cid), count in zip(*np.unique(np.stack([types, acts], 1), axis=0, return_counts=True)):
                    a = table_e.get((int(ty), int(cid)))
                    cls = a["class"] if a is not None and cid != 0 else "none"
                    frames_per_class[e.name][cls if cls in CLASSES else "other"] += int(count)
                    if cid != 0:
                        used[e.name].add((int(ty), int(cid)))
            for p in pairs:
                a, b = roots[p[0]], roots[p[1]]
                ok = valid & np.isfinite(a).all(1) & np.isfinite(b).all(1)
                if not ok.any():
                    continue
                d = np.linalg.norm(a[ok] - b[ok], axis=1)
                sep[p]["all"].append(d)
                sep[p]["hor"].append(np.linalg.norm((a[ok] - b[ok])[:, [0, 2]], axis=1))
                close = np.flatnonzero(d <= APPROACH_M)
                if len(close):
                    sep[p]["after"].append(d[close[0] :])
                sep[p]["end"].append(d[-1:])
    out = PlayStats(n_segments, n_frames, len(read), len(shards))
    for p in pairs:
        s = {k: np.concatenate(v) if v else np.zeros(0) for k, v in sep[p].items()}
        out.separation.append(
            Separation(
                (names[p[0]], names[p[1]]),
                len(s["all"]),
                _median(s["all"]),
                _median(s["hor"]),
                len(s["after"]),
                _median(s["after"]),
                len(s["end"]),
                _median(s["end"]),
            )
        )
    for e in entities:
        total = sum(frames_per_class[e.name].values())
        out.class_share[e.name] = {k: v / total for k, v in frames_per_class[e.name].items() if v} if total else {}
        vocab = [(k, a) for k, a in actions.get(e.rig.name, {}).items() if k[1] != 0]
        per_class = {c: sum(1 for _, a in vocab if a["class"] == c) for c in CLASSES[:-1]}
        used_cls = {c: sum(1 for k, a in vocab if a["class"] == c and k in used[e.name]) for c in CLASSES[:-1]}
        often = sum(1 for _, a in vocab if int(a.get("instances", 0)) >= MIN_INSTANCES)
        out.tokens[e.name] = Tokens(len(vocab), per_class, len(used[e.name]), used_cls, often)
    return out


def play_stats_lines(stats: PlayStats) -> list[str]:
    """The statistics as text lines (metres, percentages of frames, token counts), for ``marionette inspect``."""
    capped = f" (first {stats.shards_read} of {stats.shards_total} shards)" if stats.shards_read < stats.shards_total else ""
    lines = [f"play     {stats.segments} segments, {stats.frames} valid frames{capped}"]
    for s in stats.separation:
        lines.append(
            f"  separation {s.pair[0]}–{s.pair[1]}: median {s.median_m:.2f} m (horizontal {s.median_horizontal_m:.2f}), "
            f"after the approach (≤ {APPROACH_M:g} m) {s.median_after_approach_m:.2f} m over {s.after_approach_frames} frames, "
            f"at segment ends {s.median_at_segment_end_m:.2f} m ({s.segment_ends} ends)"
        )
    for name, share in stats.class_share.items():
        mix = ", ".join(f"{c} {100 * share[c]:.1f}%" for c in CLASSES if c in share)
        lines.append(f"  classes {name}: {mix}")
    for name, t in stats.tokens.items():
        per = ", ".join(f"{c} {t.used_per_class[c]}/{t.vocab_per_class[c]}" for c in CLASSES[:-1])
        lines.append(f"  tokens {name}: {t.used} of {t.vocab} played ({per}); {t.often} with ≥ {MIN_INSTANCES} instances")
    return lines
