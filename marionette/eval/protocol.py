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
- **Probe** (``controllability_probe``, Table 2): Free (no control), Force-GT (the recorded token stream of the
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
- **Driving states** (``ablation_rollouts`` / ``rule_ablation``, Table 3): recorded / no rule / + collider /
  + collider + cap on the same windows, seed and checkpoint: CFR (share of windows with a key joint below
  H − 0.15 m), MMP, skate (``final_frame_skate``) and the root separation, all at the **final frame**, means over
  windows and articulated entities; beside them the share of frames whose root is over scanned ground, and the
  share of windows that end **beyond the cap**: a final horizontal separation above max(6 m, the separation at the
  seed's last frame), the bound the cap holds (``beyond_cap``; 0 under the cap by construction).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette.bridge.rules import RuleParams, enabled_rules
from marionette.checkpoint import read_meta
from marionette.corpus import Corpus, as_corpus, fixed_rows, world_of_rows
from marionette.corpus.vocab import ActionTokens, classify
from marionette.dynamics.rollout import (
    Force,
    Rollout,
    checkpoint_dir,
    force_windows,
    forced_at,
    open_terrain_field,
    rollout_table,
)
from marionette.eval import metrics as M
from marionette.schema import Layout
from terrain_scan.store import segment_terrain

FOOT_NAMES = ("foot", "toe", "claw", "ankle", "heel", "paw", "hoof")  # a contact joint whose name holds one is a foot
ABLATION: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("no rule", ()),
    ("+ collider", ("collider",)),
    ("+ collider + cap", ("collider", "cap")),
)
PROBE_CONDITIONS = ("free", "force_gt", "force_shuf", "force_shuf_runs")
CLASSES = ("stationary", "locomotion", "attack", "other")
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
    return float(read_meta(checkpoint_dir(ckpt))["train_config"].get("fps", 20.0))


def select_windows(
    corpus: Corpus | Path | str,
    n: int,
    seed_frames: int = 64,
    horizon: int = 120,
    seed: int = 0,
    split: str = "test",
    segments: Sequence[str] | None = None,
    fps: float = 20.0,
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


def recorded_rows(corpus: Corpus, window: Window, fps: float = 20.0) -> pa.Table:
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
                for b, sc in enumerate(ro.scenes):
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
    from marionette.bridge.gbuffer import GBufferMeta
    from marionette.bridge.kinematics import world_skeletons
    from marionette.bridge.render import Rasterizer
    from marionette.bridge.targets import RenderSettings, TerrainScene, chunk_inputs, follow_view, height_range, render_frames

    terrain = terrain or TerrainScene.empty()
    settings = RenderSettings()
    state, anchors, valid, t = chunk_inputs(layout, rows)
    times = t if times is None else np.asarray(times, np.float64)
    skel = world_skeletons(layout, state, anchors, valid, t, times)
    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 20.0
    H, W = size
    cams = follow_view(layout, skel, fps, W, H, start=start)
    h = height_range(terrain, np.concatenate([skel.joints[e.name][:, 0, 1] for e in layout.articulated]), settings)
    with Rasterizer(W, H) as rast:
        rast.set_terrain(terrain.vertices, terrain.faces)
        planes = np.stack(list(render_frames(rast, layout, skel, cams, h, settings)))  # (T, 3, H, W) in G, B, R order
    meta = GBufferMeta(h[0], h[1], settings.z_near, settings.z_far, W, H, fps)
    return np.ascontiguousarray(planes[:, [2, 0, 1]].transpose(0, 2, 3, 1)), cams, meta


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
    its size is the render's). Returns the G-buffer codes (T, H, W, 3) uint16 (R, G, B: what a ``pose.mkv``
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


# -- the controllability probe -----------------------------------------------------------------------------


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
            row[cond] = _nanmean(v)
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
        vals = [_nanmean(f) for f in frames[cond]]
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


# -- the rule ablation -------------------------------------------------------------------------------------------


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
    row = {k: _nanmean([entity[n][k] for n in entity]) for k in keys}
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


def _nanmean(v: Sequence[float]) -> float:
    a = np.asarray(v, np.float64)
    return float(a[np.isfinite(a)].mean()) if np.isfinite(a).any() else float("nan")


def recorded_window(corpus: Corpus, window: Window, fps: float = 20.0) -> pa.Table:
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
