"""The controllability probe (the paper's Table 2) on held-out windows.

**Probe** (``controllability_probe``, Table 2): Free (no control), Force-GT (the recorded token stream of the
probe entity forced run by run, ``force_windows``), Force-Shuf (that stream permuted over frames with
``default_rng([seed, window])``, ``shuffle_frames``) and the run-level shuffle (its runs of one token permuted as
wholes with ``default_rng([seed, window, 1])``, ``shuffle_runs``: progress runs on within each run, so its gap to
Force-GT is the token's effect alone, Force-Shuf's also the restarted progress): mean ± std of the entity's
RA-MPJPE, and the windows where Force-GT < Force-Shuf (and < the run-level shuffle). **Per-class ratios**
(``class_ratios``, the headline): every predicted frame belongs to the class (vocab.json) of its recorded token;
per class, the mean per-frame RA-MPJPE of each condition over its frames (all windows pooled) and its ratio to
Force-GT's. **Per-class compliance** (secondary): each run of one recorded token of class c is one instance; the
motion over its frames is classified with the corpus's own rule (``corpus.vocab.classify`` on mean horizontal
root speed, peak root-frame body speed incl. owned attachments, frames); compliance = share of instances whose
motion classifies as c, for Force-GT, Free and the recorded motion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette.corpus import Corpus, as_corpus, fixed_rows, world_of_rows
from marionette.corpus.vocab import ActionTokens, classify
from marionette.dynamics.controls import Force, force_windows
from marionette.eval import metrics as M
from marionette.eval.protocol import Progress, Window, finite_mean, model_fps, predicted, recorded_rows, run_windows, summarise
from marionette.schema import Layout

PROBE_CONDITIONS = ("free", "force_gt", "force_shuf", "force_shuf_runs")


CLASSES = ("stationary", "locomotion", "attack", "other")


def _motion_stats(layout: Layout, entity: str, rows: pa.Table, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row (the first is the previous frame only): horizontal root speed and peak root-frame speed of any
    joint or owned attachment point (m/s) — the statistics ``ingest.sample.action_stats`` classifies on."""
    n = rows.num_rows
    state = fixed_rows(rows["state"], layout.dim).astype(np.float64)
    local = [state[:, layout.slice(f"{entity}.joints")].reshape(n, -1, 3)]
    local += [state[:, layout.slice(f"{o.name}.points")].reshape(n, -1, 3) for o in layout.attachments if o.owner == entity]
    p = np.concatenate(local, axis=1)
    body = np.zeros(n)
    body[1:] = np.linalg.norm(np.diff(p, axis=0), axis=-1).max(axis=1) * fps
    root = fixed_rows(rows[f"{entity}.root_world"], 3)
    speed = np.zeros(n)
    speed[1:] = np.linalg.norm(np.diff(root[:, [0, 2]], axis=0), axis=-1) * fps
    return speed, body


def token_classes(corpus: Corpus, entity: str) -> tuple[list[str], list[str]]:
    """Per entity token: its vocab class and kind ("none" for token 0)."""
    tokens = ActionTokens.from_corpus(corpus)
    i = tokens.entities.index(entity)
    types = corpus.vocab["entity_types"]
    cls, kind = [], []
    for t in range(tokens.sizes[i]):
        key, v = tokens.type_token(i, t)
        a = next((a for a in types.get(key, {}).get("actions", []) if a["token"] == v), {}) if t else {}
        cls.append(a.get("class", "none"))
        kind.append(a.get("kind", "none"))
    return cls, kind


def _complies(
    layout: Layout, entity: str, rows: pa.Table, runs: Sequence[Force], kinds: list[str], classes: list[str], fps: float
) -> list[tuple[str, bool]]:
    """(class, complies) per run; ``rows`` = last seed row + horizon rows."""
    speed, body = _motion_stats(layout, entity, rows, fps)
    out = []
    for _, s, t, tok in runs:  # predicted frames [s, t) are rows s + 1 .. t
        inst = [[float(speed[s + 1 : t + 1].mean()), float(body[s + 1 : t + 1].max()), int(t - s)]]
        out.append((classes[tok], classify(kinds[tok], inst) == classes[tok]))
    return out


def token_runs(tokens: Sequence[int]) -> list[tuple[int, int]]:
    """The runs [start, end) of equal consecutive tokens of a stream (one token per frame), in order."""
    t = np.asarray(tokens)
    cuts = np.flatnonzero(np.diff(t) != 0) + 1
    edges = np.concatenate([[0], cuts, [len(t)]]).astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def shuffle_frames(entity: str, tokens: np.ndarray, rng: np.random.Generator) -> list[Force]:
    """Force-Shuf: the stream permuted over frames, as force windows (one per run of the permuted stream)."""
    return force_windows(entity, np.asarray(tokens)[rng.permutation(len(tokens))])


def shuffle_runs(entity: str, tokens: np.ndarray, rng: np.random.Generator) -> list[Force]:
    """The run-level shuffle: the stream's runs of one token permuted as wholes, one force window per run (so
    progress runs on within each run and restarts at its first frame; token 0 runs left to the model)."""
    runs = token_runs(tokens)
    out, at = [], 0
    for k in rng.permutation(len(runs)):
        a, b = runs[k]
        if tokens[a] != 0:
            out.append((entity, at, at + b - a, int(tokens[a])))
        at += b - a
    return out


def class_ratios(
    errors: dict[str, Sequence[np.ndarray]], classes: Sequence[np.ndarray], base: str = "force_gt"
) -> dict[str, dict[str, Any]]:
    """Per class of the recorded token at each frame: frames, mean per-frame RA-MPJPE (m) of every condition over those
    frames (all windows pooled) and each condition's ratio to ``base``'s. ``errors``: condition → per window (H,);
    ``classes``: per window (H,) class names ("none", token 0's, left out)."""
    cls = np.concatenate([np.asarray(c) for c in classes])
    out: dict[str, dict[str, Any]] = {}
    for c in [c for c in CLASSES if c in set(cls)] + sorted(set(cls) - set(CLASSES) - {"none"}):  # "none": token 0, no class
        on = cls == c
        row: dict[str, Any] = {"frames": int(on.sum())}
        for cond, per in errors.items():
            v = np.concatenate([np.asarray(e, np.float64) for e in per])[on]
            row[cond] = finite_mean(v)
        for cond in errors:
            if cond != base:
                row[f"{cond}/{base}"] = row[cond] / row[base] if row[base] and np.isfinite(row[base]) else float("nan")
        out[c] = row
    return out


def controllability_probe(
    ckpt: Path | str,
    corpus: Corpus | Path | str,
    windows: Sequence[Window],
    *,
    entity: str = "hunter",
    temperature: float = 0.0,
    seed: int = 0,
    rules: str | Sequence[str] = "auto",
    free: Sequence[pa.Table] | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Free / Force-GT / Force-Shuf / run-level shuffle over ``windows`` (module doc); ``free`` reuses Free rollouts
    already run with the same ``rules``. Returns RA-MPJPE (m) summaries and per-window values per condition, the
    Force-GT < Force-Shuf count (and < run-shuffle), the per-class Shuf/GT ratios of per-frame RA-MPJPE and per-class
    compliance. ``progress`` is told each condition's rollouts (``run_windows``)."""
    c = as_corpus(corpus)
    L = c.layout
    names = [e.name for e in L.articulated]
    if entity not in names:
        raise ValueError(f"probe entity {entity!r} is not an articulated entity of scene {L.scene!r} ({names})")
    fps = model_fps(ckpt)
    tokens = ActionTokens.from_corpus(c)
    i = tokens.entities.index(entity)
    rec = [recorded_rows(c, w, fps) for w in windows]
    gt_streams = [tokens.encode(L, r, where=str(c.path))[0][:, i] for r in rec]
    gt = [force_windows(entity, s) for s in gt_streams]
    shuf = [shuffle_frames(entity, s, np.random.default_rng([seed, k])) for k, s in enumerate(gt_streams)]
    runs = [shuffle_runs(entity, s, np.random.default_rng([seed, k, 1])) for k, s in enumerate(gt_streams)]
    run = dict(temperature=temperature, seed=seed, rules=rules, progress=progress)
    phase = "probe: {} rollouts".format
    tables = {
        "free": list(free) if free is not None else run_windows(ckpt, c, windows, phase=phase("Free"), **run)[0],
        "force_gt": run_windows(ckpt, c, windows, force=gt, phase=phase("Force-GT"), **run)[0],
        "force_shuf": run_windows(ckpt, c, windows, force=shuf, phase=phase("Force-Shuf"), **run)[0],
        "force_shuf_runs": run_windows(ckpt, c, windows, force=runs, phase=phase("run-shuffle"), **run)[0],
    }
    conditions, frames = {}, {}
    for cond, tabs in tables.items():
        frames[cond] = [
            M.ra_mpjpe_frames(world_of_rows(L, predicted(t, w))[entity], world_of_rows(L, r)[entity])
            for t, w, r in zip(tabs, windows, rec)
        ]
        vals = [finite_mean(f) for f in frames[cond]]
        conditions[cond] = {**summarise(vals), "per_window": vals}
    g = np.array(conditions["force_gt"]["per_window"])
    s, sr = (np.array(conditions[k]["per_window"]) for k in ("force_shuf", "force_shuf_runs"))
    classes, kinds = token_classes(c, entity)
    frame_classes = [np.array([classes[t] for t in st]) for st in gt_streams]
    ratios = class_ratios(frames, frame_classes)
    counts: dict[str, dict[str, list[bool]]] = {}
    for k, w in enumerate(windows):
        last_seed = tables["free"][k].slice(w.seed_frames - 1, 1)
        sources = {"recorded": pa.concat_tables([last_seed, rec[k].cast(last_seed.schema)])}
        sources.update({cond: tables[cond][k].slice(w.seed_frames - 1, w.horizon + 1) for cond in ("free", "force_gt")})
        for src, rows in sources.items():
            for cls, ok in _complies(L, entity, rows, gt[k], kinds, classes, fps):
                counts.setdefault(cls, {}).setdefault(src, []).append(ok)
    per_class = {
        cls: {"runs": len(v["recorded"]), **{src: float(np.mean(v[src])) for src in ("free", "force_gt", "recorded")}}
        for cls, v in sorted(counts.items(), key=lambda kv: CLASSES.index(kv[0]) if kv[0] in CLASSES else len(CLASSES))
    }
    return {
        "entity": entity,
        "windows": [asdict(w) for w in windows],
        "conditions": conditions,
        "force_gt_beats_shuf": int((g < s).sum()),
        "force_gt_beats_shuf_runs": int((g < sr).sum()),
        "compared": int(len(g)),
        "class_ratios": ratios,
        "compliance": per_class,
        "temperature": temperature,
        "seed": seed,
    }
