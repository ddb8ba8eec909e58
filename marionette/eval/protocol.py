"""The evaluation on the state layer (its counts and lengths, the protocols, are ``eval.config``): held-out windows, generated-vs-recorded metrics,
the controllability probe and the rule ablation. Definitions are DESIGN's "Evaluation definitions"
(``metrics.py``); what this module adds, exactly:

- **Windows** (``select_windows``): a window is (segment, start) with ``seed_frames`` seed rows and
  ``horizon`` predicted rows of the segment's dynamics view (the model's rate). Segments come from the
  "test" split ("train" when the corpus has none). ``numpy.random.default_rng(seed)`` shuffles the
  segments long enough for a window; window k takes segment k mod their count and a start uniform in
  [0, frames − length]. A window longer than every segment (or than a named segment) is a ValueError. With
  ``engaged`` (metres; Tables 1 and 3 pass the cap's 6 m), the start is uniform over the starts whose seed ends with the
  two articulated entities within that horizontal distance (the fight the cap is for, as the paper's recorded sessions
  are), and over all starts in a segment that has none.
- **Rollouts** (``run_windows``): the windows of one stage run as one batch (``Rollout.start_batch``);
  rules the stage cannot run (the collider without a scanned stage, the cap without two articulated
  entities) are dropped and reported, never an error. Stream b's sampler is seeded ``_stream_seed(seed, b)``:
  at temperature 0 (the default) every stream is deterministic and equals a single ``rollout``.
- **State layer** (``window_metrics`` / ``state_layer``): per entity RA-MPJPE and root drift against the
  recorded rows of the same window (both 0 on the recorded side by definition), bone-length CV, foot
  skate over the rig's foot joints (``foot_joints``), CFR / MMP of the key joints against the stage's
  scanned terrain (NaN without one), the body's share of a follow-camera pose-control frame
  (``body_shares`` with the weapon counted for its owner; rendered at a small size), and the scene's
  root separation. Each generated number sits beside the same measurement on the recorded rows.

The probe (Table 2) is ``eval.probe``, the rule ablation (Table 3) ``eval.ablation``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette.bridge.kinematics import world_skeletons
from marionette.bridge.rules import enabled_rules
from marionette.checkpoint import read_meta
from marionette.corpus import MODEL_FPS, Corpus, as_corpus, fixed_rows, world_of_rows
from marionette.dynamics.controls import Force, forced_at
from marionette.dynamics.engine import Rollout, checkpoint_dir, open_terrain_field
from marionette.dynamics.rollout import rollout_table
from marionette.eval import metrics as M
from marionette.schema import Layout
from terrain_scan.store import segment_terrain

FOOT_NAMES = ("foot", "toe", "claw", "ankle", "heel", "paw", "hoof")  # a contact joint whose name holds one is a foot
ABLATION: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("no rule", ()),
    ("+ collider", ("collider",)),
    ("+ collider + cap", ("collider", "cap")),
)
Progress = Callable[[str, int, int], Any]  # progress(phase, done, total): told after each unit of a long loop


@dataclass(frozen=True)
class Window:
    """A held-out window: dynamics frames [start, start + seed_frames) seed the rollout, the next ``horizon`` are compared."""

    segment: str
    start: int
    seed_frames: int
    horizon: int
    stage: str

    @classmethod
    def at(cls, c: Corpus, segment: str, start: int, seed_frames: int, horizon: int) -> Window:
        """The window of ``segment`` from dynamics frame ``start``, on the stage the corpus gives the segment."""
        return cls(segment, int(start), seed_frames, horizon, str(c.segment_row(segment)["stage"]))

    @property
    def length(self) -> int:
        return self.seed_frames + self.horizon


def model_scene(ckpt: Path | str) -> str | None:
    """The scene a dynamics checkpoint (or training directory) was trained on, in a corpus of several (else None)."""
    return read_meta(checkpoint_dir(ckpt))["train_config"].get("scene")


def model_fps(ckpt: Path | str) -> float:
    """The frame rate (frames/s) a dynamics checkpoint (or training directory) was trained at."""
    return float(read_meta(checkpoint_dir(ckpt))["train_config"].get("fps", MODEL_FPS))


def select_windows(
    corpus: Corpus | Path | str,
    n: int,
    seed_frames: int = 64,
    horizon: int = 120,
    seed: int = 0,
    split: str = "test",
    segments: Sequence[str] | None = None,
    fps: float = MODEL_FPS,
    engaged: float | None = None,
) -> list[Window]:
    """``n`` windows (module doc), deterministic in ``seed``; ``segments`` names them instead of a split; ``engaged``
    (m) prefers starts whose seed ends with the pair within that horizontal distance."""
    c = as_corpus(corpus)
    if n < 1 or seed_frames < 1 or horizon < 1:
        raise ValueError(f"need n ≥ 1 windows of seed_frames ≥ 1 and horizon ≥ 1, not {n}, {seed_frames}, {horizon}")
    length = seed_frames + horizon
    if segments is None:
        segments = c.segment_ids(split) or c.segment_ids("train")
        if not segments:
            raise ValueError(f"{c.path}: no segment in split {split!r} nor 'train'")
        frames = {s: c.dynamics_segment(s, fps).num_rows for s in segments}
        fit = [s for s in segments if frames[s] >= length]
        if not fit:
            longest = max(frames, key=frames.get)
            raise ValueError(
                f"{c.path}: a window of {seed_frames} seed + {horizon} predicted frames ({length} at {fps:g} fps) "
                f"is longer than every segment; the longest, {longest!r}, has {frames[longest]} frames"
            )
    else:
        fit = list(segments)
        frames = {}
        for s in fit:
            view = c.dynamics_segment(s, fps)
            M.check_window(view, 0, length, where=f"{c.path}: window of segment {s!r} at {fps:g} fps")
            frames[s] = view.num_rows
    rng = np.random.default_rng(seed)
    order = [fit[i] for i in rng.permutation(len(fit))]
    out = []
    near: dict[str, np.ndarray] = {}  # segment → its engaged starts, read once however many windows take it
    for k in range(n):
        s = order[k % len(order)]
        starts = np.arange(frames[s] - length + 1)
        if engaged is not None and len(c.layout.articulated) == 2:
            if s not in near:
                ok = pair_separation(c.layout, c.dynamics_segment(s, fps))[starts + seed_frames - 1] <= engaged
                near[s] = starts[ok] if ok.any() else starts
            starts = near[s]
        out.append(Window.at(c, s, starts[rng.integers(0, len(starts))], seed_frames, horizon))
    return out


def pair_separation(layout: Layout, rows: pa.Table) -> np.ndarray:
    """Horizontal distance (m) between the two articulated entities' recorded world roots, per row (N,)."""
    a, b = (fixed_rows(rows[f"{e.name}.root_world"], 3) for e in layout.articulated)
    return M.separation(a, b)[1]


def recorded_rows(corpus: Corpus, window: Window, fps: float = MODEL_FPS) -> pa.Table:
    """The recorded dynamics rows of a window's horizon (what the prediction is compared with)."""
    view = corpus.dynamics_segment(window.segment, fps)
    M.check_window(view, window.start, window.length, where=f"{corpus.path}: window {window}")
    return view.slice(window.start + window.seed_frames, window.horizon)


# -- rollouts ---------------------------------------------------------------------------------------------


def run_windows(
    ckpt: Path | str,
    corpus: Corpus | Path | str,
    windows: Sequence[Window],
    *,
    rules: str | Sequence[str] = "auto",
    force: Sequence[Sequence[Force]] | None = None,
    temperature: float = 0.0,
    seed: int = 0,
    batch: int = 16,
    progress: Progress | None = None,
    phase: str = "rollouts",
) -> tuple[list[pa.Table], dict[str, tuple[str, ...]]]:
    """Roll every window out (seed rows + horizon predicted rows, ``rollout``'s table) with optional
    per-window ``force``; returns the tables in window order and the rules that ran per stage.
    ``progress(phase, done, total)`` is told the predicted window-frames done after each frame step."""
    c = as_corpus(corpus)
    force = [()] * len(windows) if force is None else list(force)
    if len(force) != len(windows):
        raise ValueError(f"{len(windows)} windows but {len(force)} force lists")
    if len({w.seed_frames for w in windows}) > 1 or len({w.horizon for w in windows}) > 1:
        raise ValueError("run_windows: windows of one call share seed_frames and horizon")
    tables: list[pa.Table | None] = [None] * len(windows)
    ran: dict[str, tuple[str, ...]] = {}
    stages: dict[str, list[int]] = {}
    for i, w in enumerate(windows):
        stages.setdefault(w.stage, []).append(i)
    done, total = 0, sum(w.horizon for w in windows)
    for stage, idx in stages.items():
        field = open_terrain_field(c, windows[idx[0]].segment)
        want: Any = rules
        if rules not in ("auto", "none", None):
            possible = enabled_rules(c.layout, field)
            want = tuple(r for r in rules if r in possible)
        ro = Rollout(ckpt, c, temperature=temperature, seed=seed, rules=want, terrain_field=field)
        ran[stage] = ro.enabled
        names = [e.name for e in c.layout.articulated]
        for lo in range(0, len(idx), batch):
            part = idx[lo : lo + batch]
            seeds = []
            for i in part:
                w = windows[i]
                view = c.dynamics_segment(w.segment, ro.fps)
                M.check_window(view, w.start, w.length, where=f"{c.path}: window {w}")
                seeds.append(view.slice(w.start, w.seed_frames))
            ro.start_batch(seeds)
            H = windows[part[0]].horizon
            rec = {k: [[] for _ in part] for k in ("state", "roots", "quats", "tok", "prog")}
            for t in range(H):
                forced, restart = zip(*(forced_at(force[i], t, names) for i in part))
                states = ro.step_batch(list(forced), None, list(restart))
                for b, sc in enumerate(ro.streams):
                    for k, v in (
                        ("state", states[b]),
                        ("roots", ro.roots_of(sc)),
                        ("quats", sc.quats.copy()),
                        ("tok", sc.tok.copy()),
                        ("prog", sc.progress.copy()),
                    ):
                        rec[k][b].append(v)
                done += len(part)
                if progress is not None:
                    progress(phase, done, total)
            for b, i in enumerate(part):
                tables[i] = rollout_table(c, ro, seeds[b], windows[i].segment, seed, *(np.array(rec[k][b]) for k in rec))
    return tables, ran  # type: ignore[return-value]


def predicted(table: pa.Table, window: Window) -> pa.Table:
    """The horizon rows of a window's rollout table."""
    return table.slice(window.seed_frames, window.horizon)


# -- the state layer ----------------------------------------------------------------------------------


def foot_joints(entity_rig) -> list[int]:
    """Kept-joint indices of a rig's feet: its contact joints named like a foot (``FOOT_NAMES``), else all of them."""
    feet = [i for n, i in zip(entity_rig.contact_joints, entity_rig.contact_index) if any(f in n.lower() for f in FOOT_NAMES)]
    return feet or list(entity_rig.contact_index)


def _follow_codes(
    layout: Layout, rows: pa.Table, times: np.ndarray | None, size: tuple[int, int], terrain: Any = None, start: Any = None
) -> tuple[np.ndarray, Any, Any]:
    """G-buffer codes (T, H, W, 3) uint16 (R, G, B) of ``rows`` at ``times`` (s; None: the rows' own) through the follow
    camera (``start``-seeded when given), with the cameras and the ``GBufferMeta`` to decode them."""
    from marionette.bridge.gbuffer import GBufferMeta, unpack_codes
    from marionette.bridge.render import Rasterizer
    from marionette.bridge.targets import RenderSettings, TerrainScene, chunk_inputs, follow_view, height_range, render_frames

    terrain = terrain or TerrainScene.empty()
    settings = RenderSettings()
    state, anchors, valid, t = chunk_inputs(layout, rows)
    times = t if times is None else np.asarray(times, np.float64)
    skel = world_skeletons(layout, state, anchors, valid, t, times)
    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else MODEL_FPS
    H, W = size
    cams = follow_view(layout, skel, fps, W, H, start=start)
    h = height_range(terrain, np.concatenate([skel.joints[e.name][:, 0, 1] for e in layout.articulated]), settings)
    with Rasterizer(W, H) as rast:
        rast.set_terrain(terrain.vertices, terrain.faces)
        codes = np.stack([unpack_codes(w) for w in render_frames(rast, layout, skel, cams, h, settings)])
    meta = GBufferMeta(h[0], h[1], settings.z_near, settings.z_far, W, H, fps)
    return codes, cams, meta


def body_share_frames(
    layout: Layout, rows: pa.Table, terrain: Any = None, size: tuple[int, int] = (72, 128)
) -> dict[str, np.ndarray]:
    """Per articulated entity, its share (N,) of each pose-control frame of ``rows`` (follow camera, the rows'
    own rate, ``size`` H × W, the weapon counted for its owner); ``terrain`` a ``TerrainScene`` (none: empty)."""
    from marionette.bridge.gbuffer import decode_codes

    codes, _, meta = _follow_codes(layout, rows, None, size, terrain)
    return M.body_shares(np.stack([decode_codes(c, meta).id for c in codes]), layout, include_attachments=True)


def rollout_pose_codes(
    layout: Layout, rows: pa.Table, times: np.ndarray, start: Any, terrain: Any = None
) -> tuple[np.ndarray, Any]:
    """The pose-control video of rollout ``rows`` (a rollout table, or any state rows) at ``times`` (s, inside
    the rows' span; e.g. the recorded video's frame times): skeletons interpolated in time, seen through the
    follow camera seeded at ``start`` (a one-frame ``Cameras``, e.g. the recorded camera of the first time;
    its size is the render's). Returns the G-buffer codes (T, H, W, 3) uint16 (R, G, B: what a ``pose.gbz``
    decodes to) and the cameras used."""
    t = rows["t"].to_numpy().astype(np.float64)
    times = np.asarray(times, np.float64)
    if len(times) < 2 or not np.all(np.diff(times) > 0) or times[0] < t[0] - 1e-6 or times[-1] > t[-1] + 1e-6:
        span = f"[{t[0]:.4f}, {t[-1]:.4f}] s"
        raise ValueError(f"render times {times[:1]}..{times[-1:]} s must increase inside the rows' span {span}")
    codes, cams, _ = _follow_codes(layout, rows, times, (start.height, start.width), terrain, start)
    return codes, cams


def window_metrics(
    layout: Layout,
    generated: pa.Table,
    recorded: pa.Table,
    fps: float,
    field: Any = None,
    terrain: Any = None,
    render_size: tuple[int, int] | None = (72, 128),
) -> dict[str, Any]:
    """The state-layer metrics of one window: ``generated`` and ``recorded`` are the horizon rows (equal
    counts). Returns {"metrics": {"<metric>/<entity>": {"generated", "recorded"}}, "drift": {entity: (H,)}}."""
    M.check_rollout_table(generated, layout, "generated rows")
    M.check_rollout_table(recorded, layout, "recorded rows")
    if generated.num_rows != recorded.num_rows:
        raise ValueError(f"generated rows ({generated.num_rows}) and recorded rows ({recorded.num_rows}) differ in length")
    wg, wr = world_of_rows(layout, generated), world_of_rows(layout, recorded)
    out: dict[str, dict[str, float]] = {}
    drift: dict[str, np.ndarray] = {}

    def put(metric: str, entity: str, g: float, r: float) -> None:
        out[f"{metric}/{entity}"] = {"generated": float(g), "recorded": float(r)}

    for e in layout.articulated:
        g, r = wg[e.name], wr[e.name]
        put("ra_mpjpe_m", e.name, M.ra_mpjpe(g, r), M.ra_mpjpe(r, r))
        drift[e.name] = M.root_drift(g[:, 0], r[:, 0])
        put("root_drift_final_m", e.name, drift[e.name][-1], 0.0)
        put("bone_length_cv", e.name, M.bone_length_cv(g, e.rig.parents), M.bone_length_cv(r, e.rig.parents))
        feet = foot_joints(e.rig)
        put("foot_skate_mps", e.name, M.foot_skate(g[:, feet], fps), M.foot_skate(r[:, feet], fps))
        if field is not None:
            cg, cr = M.key_joint_clearances(g, e.rig, field), M.key_joint_clearances(r, e.rig, field)
            put("cfr", e.name, M.contact_failure_rate(cg), M.contact_failure_rate(cr))
            put("mmp_m", e.name, M.mean_max_penetration(cg), M.mean_max_penetration(cr))
        else:
            put("cfr", e.name, np.nan, np.nan)
            put("mmp_m", e.name, np.nan, np.nan)
    if len(layout.articulated) == 2:
        a, b = (e.name for e in layout.articulated)
        (g3, gh), (r3, rh) = M.separation(wg[a][:, 0], wg[b][:, 0]), M.separation(wr[a][:, 0], wr[b][:, 0])
        put("separation_m", "scene", g3.mean(), r3.mean())
        put("separation_horizontal_m", "scene", gh.mean(), rh.mean())
    if render_size is not None:
        sg, sr = (
            body_share_frames(layout, generated, terrain, render_size),
            body_share_frames(layout, recorded, terrain, render_size),
        )
        for name in sg:
            put("body_share", name, sg[name].mean(), sr[name].mean())
    return {"metrics": out, "drift": drift}


def summarise(values: Sequence[float]) -> dict[str, Any]:
    """Mean, population std and count of the finite values (NaN mean and std when none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return {
        "mean": float(v.mean()) if len(v) else float("nan"),
        "std": float(v.std()) if len(v) else float("nan"),
        "n": int(len(v)),
    }


def state_layer(
    ckpt: Path | str,
    corpus: Corpus | Path | str,
    windows: Sequence[Window],
    tables: Sequence[pa.Table],
    *,
    render_size: tuple[int, int] | None = (72, 128),
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The state-layer table over windows: per "<metric>/<entity>" the generated and recorded summaries,
    per-window values, and per entity the root drift (windows, horizon) for curves (``progress`` told per window)."""
    c = as_corpus(corpus)
    fps = model_fps(ckpt)
    per = []
    scenes: dict[str, tuple[Any, Any]] = {}
    for w, table in zip(windows, tables):
        if w.stage not in scenes:
            field = open_terrain_field(c, w.segment)
            scenes[w.stage] = (field, terrain_scene(c, w.segment) if render_size else None)
        field, terrain = scenes[w.stage]
        per.append(window_metrics(c.layout, predicted(table, w), recorded_rows(c, w, fps), fps, field, terrain, render_size))
        if progress is not None:
            progress("state-layer metrics", len(per), len(windows))
    rows = {}
    for key in per[0]["metrics"]:
        g = [p["metrics"][key]["generated"] for p in per]
        r = [p["metrics"][key]["recorded"] for p in per]
        rows[key] = {"generated": summarise(g), "recorded": summarise(r), "per_window": {"generated": g, "recorded": r}}
    drift = {name: np.stack([p["drift"][name] for p in per]) for name in per[0]["drift"]}
    notes = []
    if not any(f is not None for f, _ in scenes.values()):
        notes.append("CFR/MMP not measured: no stage of these windows has a terrain scan")
    return {"metrics": rows, "drift": drift, "fps": fps, "notes": notes}


def terrain_scene(c: Corpus, segment: str) -> Any:
    """The segment's stage terrain as the bridge renders it (empty when the stage is unscanned)."""
    from marionette.bridge.targets import TerrainScene

    return TerrainScene.of_stage(segment_terrain(c, segment))


def finite_mean(v: Sequence[float]) -> float:
    """The mean of the finite values of ``v`` (NaN when none is)."""
    a = np.asarray(v, np.float64)
    return float(a[np.isfinite(a)].mean()) if np.isfinite(a).any() else float("nan")
