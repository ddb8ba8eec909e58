"""The rule ablation (the paper's Table 3): the four driving states at the final frame.

**Driving states** (``ablation_rollouts`` / ``rule_ablation``, Table 3): recorded / no rule / + collider /
+ collider + cap on the same windows, seed and checkpoint: CFR (share of windows with a key joint below
H − 0.15 m), MMP, skate (``final_frame_skate``) and the root separation, all at the **final frame**, means over
windows and articulated entities; beside them the share of frames whose root is over scanned ground, and the
share of windows that end **beyond the cap**: a final horizontal separation above max(6 m, the separation at the
seed's last frame), the bound the cap holds (``beyond_cap``; 0 under the cap by construction).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette.bridge.rules import RuleParams
from marionette.corpus import MODEL_FPS, Corpus, as_corpus, world_of_rows
from marionette.dynamics.engine import open_terrain_field
from marionette.eval import metrics as M
from marionette.eval.protocol import (
    ABLATION,
    Progress,
    Window,
    finite_mean,
    foot_joints,
    model_fps,
    pair_separation,
    predicted,
    run_windows,
    summarise,
)
from marionette.schema import Layout


def final_frame_skate(feet_world: np.ndarray, fps: float) -> float:
    """Foot-skate (m/s) at the last frame: mean horizontal speed of the feet in contact there (contacts as
    ``metrics.foot_contacts`` over the whole sequence (N, F, 3)); NaN when no foot is in contact."""
    f = np.asarray(feet_world, np.float64)
    contact = M.foot_contacts(f, fps)[-1]
    d = f[-1] - f[-2]
    speed = np.hypot(d[:, 0], d[:, 2]) * fps
    return float(speed[contact].mean()) if contact.any() else float("nan")


def on_ground_share(roots_world: np.ndarray, field: Any) -> float:
    """Share of frames whose root (N, 3) stands over scanned ground (the field answers a height at its x, z); NaN without a field."""
    if field is None:
        return float("nan")
    r = np.asarray(roots_world, np.float64)
    return float(np.isfinite(field.query(r[:, 0], r[:, 2], r[:, 1])).mean())


def _ablation_row(
    layout: Layout, pairs: Sequence[tuple[pa.Table, Any]], fps: float, seed_seps: Sequence[float] | None = None
) -> dict[str, Any]:
    """At the final frame of each (rows, field) pair, window means: CFR (share of windows with a key joint below
    H − 0.15 m), MMP (m), skate (m/s) per articulated entity and their means over entities, and the horizontal
    (and 3-D) root separation (m); beside them the share of frames whose root is on scanned ground and, given each
    window's separation at its seed's last frame (``seed_seps``, m), the share of windows ending beyond the cap's bound
    max(cap, that separation)."""
    keys = ("cfr", "mmp_m", "skate_mps", "on_ground")
    per: dict[str, dict[str, list[float]]] = {e.name: {k: [] for k in keys} for e in layout.articulated}
    sep, sep3 = [], []
    cap = RuleParams().max_separation_m
    for rows, field in pairs:
        w = world_of_rows(layout, rows)
        for e in layout.articulated:
            j = w[e.name]
            clear = M.key_joint_clearances(j[-1:], e.rig, field) if field is not None else np.full((1, 1), np.nan)
            per[e.name]["cfr"].append(M.contact_failure_rate(clear))
            per[e.name]["mmp_m"].append(M.mean_max_penetration(clear))
            per[e.name]["skate_mps"].append(final_frame_skate(j[:, foot_joints(e.rig)], fps))
            per[e.name]["on_ground"].append(on_ground_share(j[:, 0], field))
        if len(layout.articulated) == 2:
            a, b = (e.name for e in layout.articulated)
            d3, dh = M.separation(w[a][-1, 0], w[b][-1, 0])
            sep.append(float(dh))
            sep3.append(float(d3))
    entity = {n: {k: summarise(v)["mean"] for k, v in d.items()} for n, d in per.items()}
    row = {k: finite_mean([entity[n][k] for n in entity]) for k in keys}
    beyond = float("nan")
    if sep and seed_seps is not None:
        beyond = float(np.mean([d > max(cap, s0) + 1e-6 for d, s0 in zip(sep, seed_seps)]))
    return {
        **row,
        "sep_m": summarise(sep)["mean"],
        "sep_3d_m": summarise(sep3)["mean"],
        "beyond_cap": beyond,
        "per_entity": entity,
    }


def recorded_window(corpus: Corpus, window: Window, fps: float = MODEL_FPS) -> pa.Table:
    """The recorded dynamics rows of a whole window (seed + horizon): the "recorded" driving state, shaped like a rollout table."""
    view = corpus.dynamics_segment(window.segment, fps)
    M.check_window(view, window.start, window.length, where=f"{corpus.path}: window {window}")
    return view.slice(window.start, window.length)


def ablation_rollouts(
    ckpt: Path | str,
    corpus: Corpus | Path | str,
    windows: Sequence[Window],
    *,
    temperature: float = 0.0,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, dict[str, Any]]:
    """The four driving states on the same windows: condition → {"tables" (seed + horizon rows per window), "rules",
    "ran" (per stage), "note" (rules that could not run and why)}; "recorded" holds the recorded rows."""
    c = as_corpus(corpus)
    fps = model_fps(ckpt)
    out = {"recorded": {"tables": [recorded_window(c, w, fps) for w in windows], "rules": None, "ran": {}, "note": ""}}
    why = {"collider": "no terrain scan", "cap": "not two articulated entities"}
    for name, rules in ABLATION:
        tables, ran = run_windows(
            ckpt,
            c,
            windows,
            rules=rules or "none",
            temperature=temperature,
            seed=seed,
            progress=progress,
            phase=f"ablation: {name} rollouts",
        )
        missing = {st: [r for r in rules if r not in got] for st, got in ran.items()}
        note = "; ".join(f"stage {st}: " + ", ".join(f"{r} inactive ({why[r]})" for r in m) for st, m in missing.items() if m)
        out[name] = {"tables": tables, "rules": list(rules), "ran": {k: list(v) for k, v in ran.items()}, "note": note}
    return out


def rule_ablation(
    ckpt: Path | str,
    corpus: Corpus | Path | str,
    windows: Sequence[Window],
    *,
    temperature: float = 0.0,
    seed: int = 0,
    progress: Progress | None = None,
    rollouts: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Table 3's state columns: recorded / no rule / + collider / + collider + cap on the same windows, CFR, MMP, skate
    and Sep at the final frame (``_ablation_row``), the rules that actually ran and a note where a rule could not.
    ``rollouts``: ``ablation_rollouts`` already run on these windows (else they are run, ``progress`` told)."""
    c = as_corpus(corpus)
    fps = model_fps(ckpt)
    if rollouts is None:
        rollouts = ablation_rollouts(ckpt, c, windows, temperature=temperature, seed=seed, progress=progress)
    fields = {w.stage: open_terrain_field(c, w.segment) for w in windows}
    seed_seps = None
    if len(c.layout.articulated) == 2:
        seed_seps = [
            float(pair_separation(c.layout, t.slice(w.seed_frames - 1, 1))[0])
            for t, w in zip(rollouts["recorded"]["tables"], windows)
        ]
    rows = []
    for name, r in rollouts.items():
        pairs = [(predicted(t, w), fields[w.stage]) for t, w in zip(r["tables"], windows)]
        row = _ablation_row(c.layout, pairs, fps, seed_seps)
        rows.append({"condition": name, **{k: r[k] for k in ("rules", "ran", "note")}, **row})
    return {"conditions": rows, "windows": [asdict(w) for w in windows], "at": "final frame"}
