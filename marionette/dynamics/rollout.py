"""Rollouts over a horizon: the seed rows of a segment's dynamics view, then ``horizon`` frames of the engine
(``engine.Rollout``) under forced tokens and scripted roots (``controls``), as one corpus-schema table
(``rollout_table``); ``write_rollout`` is the ``marionette rollout`` command (also ``python -m
marionette.dynamics.rollout``)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

from marionette.checkpoint import read_meta
from marionette.corpus import MODEL_FPS, Corpus, as_corpus, state_table
from marionette.dynamics.controls import (
    Force,
    RolloutOptions,
    add_rollout_arguments,
    forced_at,
    script_from_args,
    script_roots,
)
from marionette.dynamics.engine import Rollout, checkpoint_dir, open_terrain_field
from marionette.io import write_ipc
from marionette.knobs import option_values, options_from_args
from marionette.schema import state_schema
from terrain_scan.store import segment_terrain


def rollout(
    ckpt_dir: Path | str,
    corpus: Corpus | Path | str,
    segment: str,
    seed_frames: int = 64,
    horizon: int = 100,
    temperature: float = 0.0,
    seed: int = 0,
    force: Sequence[Force] = (),
    script_root: Any = None,
    rules: str | Sequence[str] = "auto",
    terrain_field: Any = None,
    start: int = 0,
    cached: bool = True,
    dtype: torch.dtype = torch.float32,
) -> pa.Table:
    """Seed rows + ``horizon`` predicted rows of ``segment`` (corpus state schema, 20 fps, world roots in m).

    The seed is the segment's dynamics frames [start, start + seed_frames). ``force``: (entity, start,
    end, token) with END exclusive, in predicted-frame indices; ``terrain_field`` defaults to the
    segment's scanned stage (None when it was never scanned). ``cached=False`` recomputes each frame
    (``ModelStream``); ``dtype`` is the models' (bfloat16 for the half-precision path)."""
    c = as_corpus(corpus)
    L = c.layout
    if terrain_field is None:
        terrain_field = open_terrain_field(c, segment)
    ro = Rollout(
        ckpt_dir, c, temperature=temperature, seed=seed, rules=rules, terrain_field=terrain_field, cached=cached, dtype=dtype
    )
    view = c.dynamics_segment(segment, ro.fps)
    if seed_frames < 1 or start < 0 or view.num_rows < start + seed_frames:
        raise ValueError(
            f"{c.path}: segment {segment} has {view.num_rows} dynamics frames; a seed of {seed_frames} frames "
            f"from frame {start} does not fit"
        )
    seed_rows = view.slice(start, seed_frames)
    names = [e.name for e in L.articulated]
    for name, first, end, token in force:
        if name not in names:
            raise ValueError(f"force: unknown entity {name!r}; the scene has {names}")
        if not 1 <= int(token) < ro.tokens.sizes[names.index(name)]:
            raise ValueError(
                f"force {name}:{first}:{end}:{token}: token outside 1..{ro.tokens.sizes[names.index(name)] - 1} "
                f"({name}'s vocabulary; 0 is 'no valid action')"
            )
        if not 0 <= int(first) < int(end) or int(first) >= horizon:
            raise ValueError(
                f"force {name}:{first}:{end}:{token}: frames [{first}, {end}) are empty, negative or past the horizon {horizon}"
            )
    scripted = script_roots(script_root, horizon, L, ro.config.root_dim)
    ro.start(seed_rows)
    states, roots, quats, toks, progs = [], [], [], [], []
    for t in range(horizon):
        forced, restart = forced_at(force, t, names)
        states.append(ro.step(forced, None if scripted is None else scripted[t], restart))
        roots.append(ro.roots_world)
        quats.append(ro.quats.copy())
        toks.append(ro.tok.copy())
        progs.append(ro.progress.copy())
    return rollout_table(
        c,
        ro,
        seed_rows,
        segment,
        seed,
        np.array(states).reshape(horizon, L.dim),
        np.array(roots).reshape(horizon, -1, 3),
        np.array(quats).reshape(horizon, -1, 4),
        np.array(toks).reshape(horizon, -1),
        np.array(progs).reshape(horizon, -1),
    )


def rollout_table(
    c: Corpus,
    ro: Rollout,
    seed_rows: pa.Table,
    segment: str,
    seed: int,
    states: np.ndarray,
    roots: np.ndarray,
    quats: np.ndarray,
    toks: np.ndarray,
    progs: np.ndarray,
    name: str | None = None,
) -> pa.Table:
    """The seed rows and the predicted rows of a rollout as one table (corpus state schema) whose segment is ``name``
    (default ``<segment>-rollout-s<seed>``)."""
    L, h = c.layout, len(states)
    schema = state_schema(L)
    name = name or f"{segment}-rollout-s{seed}"
    last = seed_rows.slice(seed_rows.num_rows - 1, 1).to_pylist()[0]
    step_frames = c.fps / ro.fps

    cols: dict[str, Any] = {
        "segment": name,
        "sample": last["sample"],
        "frame": [int(last["frame"]) + int(round((k + 1) * step_frames)) for k in range(h)],
        "t": float(last["t"]) + (np.arange(h) + 1) / ro.fps,
        "state": states,
    }
    for i, e in enumerate(L.articulated):
        tok = toks[:, i]
        clip = ro.tokens.clip_lengths[i][tok]
        cols[f"{e.name}.type_id"] = [
            int(ro.tokens.type_keys[i][k].split(":")[1]) if k else int(last[f"{e.name}.type_id"]) for k in tok
        ]
        cols[f"{e.name}.action"] = ro.tokens.composites[i][tok]
        frame = np.rint(progs[:, i] * clip)  # a clip's frames are 0 … clip − 1: a state action wraps, an event holds
        frame = np.where(ro.wraps(i, tok), frame % np.maximum(clip, 1), np.minimum(frame, np.maximum(clip - 1, 0)))
        cols[f"{e.name}.motion_frame"] = np.where(tok == 0, -1, frame).astype(np.int32)
        cols[f"{e.name}.hp"] = last[f"{e.name}.hp"]
        cols[f"{e.name}.root_world"] = roots[:, i]
        cols[f"{e.name}.rot_world"] = quats[:, i]
        cols[f"{e.name}.pos_check_m"] = np.full(h, np.nan, np.float32)
    for e in L.attachments:
        cols[f"{e.name}.type_id"] = last[f"{e.name}.type_id"]
    for name_, width in (("camera.K", 4), ("camera.pos", 3), ("camera.rot", 4)):
        cols[name_] = np.full((h, width), np.nan)
    cols["valid"] = True
    predicted = state_table(L, cols, n=h)
    seeded = seed_rows.cast(schema).set_column(0, "segment", pa.array([name] * seed_rows.num_rows))
    return pa.concat_tables([seeded, predicted])


def write_rollout(
    ckpt: Path,
    corpus: Corpus | Path,
    segment: str,
    out: Path,
    *,
    horizon: int,
    seed_frames: int = 64,
    temperature: float = 0.0,
    seed: int = 0,
    force: Sequence = (),
    script_root: Sequence = (),
    rules: str = "auto",
    render: Path | None = None,
    size: tuple[int, int] = (352, 640),
    log=print,
) -> pa.Table:
    """The rollout command: roll ``horizon`` frames out from ``segment``, write the table to ``out`` (and render it
    through the follow camera to ``render``); the keyword arguments are ``RolloutOptions``' fields, ``rules``
    "auto", "none" or a comma list."""
    rules_in = rules if rules in ("auto", "none") else tuple(r for r in rules.split(",") if r)
    trained = read_meta(checkpoint_dir(ckpt))["train_config"]
    c = as_corpus(corpus, trained.get("scene"))
    fps = float(trained.get("fps", MODEL_FPS))
    script = script_from_args(list(script_root), horizon, fps, c.layout)
    started = time.perf_counter()
    table = rollout(ckpt, c, segment, seed_frames, horizon, temperature, seed, list(force), script_root=script, rules=rules_in)
    took = time.perf_counter() - started
    write_ipc(out, table)
    log(f"{out}: {table.num_rows} rows ({horizon} predicted, {horizon / took:.0f} frames/s incl. loading)")
    if render is not None:
        from marionette.bridge.targets import TerrainScene, render_rows

        meta = render_rows(
            c.layout, table, render, TerrainScene.of_stage(segment_terrain(c, segment)), camera="follow", size=size
        )
        log(f"{render}: {meta.width}×{meta.height} at {meta.fps:g} fps (follow camera)")
    return table


def main(argv: list[str] | None = None) -> pa.Table:
    """``python -m marionette.dynamics.rollout DIR CORPUS --segment ID --horizon N --out STATES.arrow [...]``."""
    ap = argparse.ArgumentParser(prog="python -m marionette.dynamics.rollout", description=__doc__.splitlines()[0])
    add_rollout_arguments(ap)
    return write_rollout(**option_values(options_from_args(RolloutOptions, ap.parse_args(argv))))


if __name__ == "__main__":
    main()
