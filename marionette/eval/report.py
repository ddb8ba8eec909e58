"""The evaluation report: run a protocol on a checkpoint and write a directory of the paper's tables and plots.

``evaluate`` takes a protocol (``config.EvalProtocol``: "paper" or "quick", fields overridable) and runs:

- on ``probe_windows`` held-out windows (``seed_frames`` + ``horizon``): the Free rollouts (rules "auto") and their
  state-layer metrics beside the recorded rows, and **Table 2**, the controllability probe (Free / Force-GT /
  Force-Shuf / run-level shuffle, GT < Shuf counts, per-class Shuf/GT ratios, compliance);
- on ``state_rollouts`` long held-out windows (``state_seconds``): the four driving states (``ablation_rollouts``)
  and **Table 3** at their final frame and the long-horizon curves (``video.long_horizon_curves``); on the first
  ``rollouts`` of them cut to ``rollout_seconds`` of video, with an observation model (and a pixel-AR baseline),
  **Table 1** and Table 3's FVD column (``video.video_tables``); a corpus with no segment long enough for
  ``state_seconds`` gets state rollouts as long as the painted ones (the table says so), one with none long enough
  for those gets the tables "not run" with the reason, the rest of the report still;
- then writes ``<out>/report.md`` (its first lines say which counts are smaller than the paper's), ``report.json``,
  the PNG plots and the contact sheet. The directory is built beside ``out`` and renamed into place, so a reader
  never sees half a report; an existing ``out`` is replaced only if it holds a previous report (or nothing).

The clips and whole-clip proxy-FVD rows are ``eval.clips``, the Markdown ``eval.markdown``, the plots ``eval.plots``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from marionette.bridge.rules import RuleParams
from marionette.corpus import Corpus
from marionette.eval import fvd
from marionette.eval.ablation import ablation_rollouts, rule_ablation
from marionette.eval.config import EvalProtocol, parse_protocol
from marionette.eval.markdown import render_markdown, training_against_baselines
from marionette.eval.plots import plot_all
from marionette.eval.probe import controllability_probe
from marionette.eval.protocol import Progress, Window, model_fps, model_scene, run_windows, select_windows, state_layer
from marionette.eval.video import long_horizon, long_horizon_curves, video_tables
from marionette.io import atomic_dir, read_json, write_bytes, write_json

PLOTS = ("contact_sheet", "ablation", "class_ratios", "compliance", "drift", "fvd_per_chunk")


def _plain(x: Any) -> Any:
    """JSON-ready: arrays to lists, NaN/inf to None, tuples to lists."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return _plain(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _check_replaceable(out: Path) -> None:
    """Fail unless ``out`` is absent, empty, or a previous report directory."""
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "report.json").exists())):
        raise FileExistsError(f"{out}: exists and is not a previous report; refusing to replace it")


def headline(report: dict) -> dict[str, float | int | None]:
    """The few numbers a dashboard shows: probe means, the GT < Shuf counts, per-class Shuf/GT, Table 1 and Table 3."""
    pr = report["probe"]
    h: dict[str, Any] = {"windows": len(report["windows"]), "protocol": report["protocol"]["name"]}
    for k, v in pr["conditions"].items():
        h[f"{pr['entity']}_ra_mpjpe_{k}_m"] = v["mean"]
    h["force_gt_beats_shuf"] = pr["force_gt_beats_shuf"]
    h["force_gt_beats_shuf_runs"] = pr["force_gt_beats_shuf_runs"]
    for c, v in pr["class_ratios"].items():
        h[f"shuf_over_gt_{c}"] = v["force_shuf/force_gt"]
    for r in report["ablation"]["conditions"]:
        slug = r["condition"].replace("+ ", "").replace(" ", "_")
        h[f"cfr_{slug}"], h[f"mmp_{slug}_m"], h[f"sep_{slug}_m"] = r["cfr"], r["mmp_m"], r["sep_m"]
    v = report["video"]
    if v.get("run"):
        for col, r in v["table1"].items():
            if "fvd16" in r:  # "fvd" only from the I3D extractor, else "proxy_fvd"
                name = "fvd" if r["metric"] == fvd.FVD_LABEL else "proxy_fvd"
                h[f"{name}16_{col}"], h[f"{name}_final_{col}"] = r["fvd16"]["value"], r["final_chunk"]["value"]
    return _plain(h)


def evaluate(
    dynamics_dir: Path | str,
    corpus: Path | str,
    out_dir: Path | str,
    *,
    protocol: EvalProtocol | str = "paper",
    observation: Path | str | None = None,
    baseline: Path | str | None = None,
    seed: int = 0,
    log: Callable[[str], Any] = print,
    entity: str = "hunter",
    render_size: tuple[int, int] = (72, 128),
    i3d: Path | str | None = None,
    progress: Progress | None = None,
    **overrides: Any,
) -> dict[str, Any]:
    """Run the protocol (``config.PROTOCOLS`` name or an ``EvalProtocol``; ``overrides`` change its fields) and write the
    report directory ``out_dir`` (module doc).

    Returns {"out_dir", "report_md", "report_json", "plots" (name → path), "headline" (name → number), "windows"
    (probe windows)}. ``observation``: the observation model (Tables 1 and 3's FVD); ``baseline``: a pixel-AR baseline
    checkpoint (control "actions") for Table 1's second column; ``i3d``: an Inception-I3D safetensors file, for FVD
    proper instead of the proxy; ``progress(phase, done, total)`` is told the progress of every long loop."""
    proto = parse_protocol(protocol, **overrides)
    c = Corpus(Path(corpus), scene=model_scene(dynamics_dir))  # the scene the model was trained on
    out = Path(out_dir)
    _check_replaceable(out)  # before any compute
    extractor = fvd.extractor_for(Path(i3d)) if i3d is not None else None  # a bad I3D file fails here too
    models = _load_models(observation, baseline)
    fps = model_fps(dynamics_dir)
    proto.video_frames(float(c.fps))  # a protocol whose rollouts cannot hold its clips fails before any compute
    split = "test" if c.segment_ids("test") else "train"
    temp = proto.temperature
    windows = select_windows(c, proto.probe_windows, proto.seed_frames, proto.horizon, seed, split=split, fps=fps)
    horizon_long = long_horizon(proto, float(c.fps), fps, [m.config.frames for m in models.values()])
    long, why_not = long_windows(c, proto, horizon_long, seed + 1, split, fps)
    names = [e.name for e in c.layout.articulated]
    entity = entity if entity in names else names[-1]
    log(
        f"evaluate: protocol {proto.name!r}; {len(windows)} probe windows of {proto.seed_frames} + {proto.horizon} frames, "
        f"{len(long)} long rollouts of {long[0].horizon if long else 0} frames (the first {min(len(long), proto.rollouts)} "
        f"painted over {horizon_long}), split {split!r}"
    )
    free, ran = run_windows(
        dynamics_dir, c, windows, rules="auto", temperature=temp, seed=seed, progress=progress, phase="Free rollouts"
    )
    log(f"evaluate: Free rollouts done (rules per stage {ran}); state-layer metrics")
    state = state_layer(dynamics_dir, c, windows, free, render_size=render_size, progress=progress)
    log("evaluate: controllability probe (Table 2)")
    probe = controllability_probe(
        dynamics_dir, c, windows, entity=entity, temperature=temp, seed=seed, free=free, progress=progress
    )
    painted = (horizon_long, models, extractor)
    ablation, curves, video = _long_tables(dynamics_dir, c, long, why_not, proto, painted, seed, log, progress)
    sheet = video.pop("sheet", None)
    video.update({k: str(v) for k, v in (("observation", observation), ("baseline", baseline)) if v is not None})
    report = {
        "dynamics": str(dynamics_dir),
        "corpus": str(c.path),
        "protocol": {**proto.to_json(), "reduced": proto.reduced()},
        "split": split,
        "fps": fps,
        "seed": seed,
        "seed_frames": proto.seed_frames,
        "horizon": proto.horizon,
        "temperature": temp,
        "render_size": list(render_size),
        "windows": [asdict(w) for w in windows],
        "rules_free": ran,
        "state_layer": state,
        "probe": probe,
        "ablation": ablation,
        "long_horizon": curves,
        "video": video,
        "training": training_against_baselines(dynamics_dir),
    }
    report = _write_report(_plain(report), sheet, out)
    log(f"evaluate: report in {out}")
    return {
        "out_dir": str(out),
        "report_md": str(out / "report.md"),
        "report_json": str(out / "report.json"),
        "plots": {k: str(out / v) for k, v in report["plots"].items()},
        "headline": report["headline"],
        "windows": len(windows),
    }


def long_windows(c: Corpus, proto: EvalProtocol, painted: int, seed: int, split: str, fps: float) -> tuple[list[Window], str]:
    """The long rollouts' windows: ``proto.state_count`` of ``proto.state_length_s`` (at least ``painted`` predicted
    frames), started in the fight the cap is for; when no held-out segment holds that length, of ``painted`` frames
    instead. Returns (windows, why): no windows and the reason when not even ``painted`` fits, else why they were cut."""
    engaged = RuleParams().max_separation_m
    want = max(painted, math.ceil(proto.state_length_s * fps))
    why = ""
    for horizon in dict.fromkeys((want, painted)):
        try:
            got = select_windows(c, proto.state_count, proto.seed_frames, horizon, seed, split=split, fps=fps, engaged=engaged)
        except ValueError as err:  # a corpus of short segments: Table 3's rollouts are cut, or Tables 1 and 3 not run
            why = why or str(err)
            continue
        cut = f"state rollouts cut to the painted {painted / fps:g} s: {why}" if why else ""
        return got, cut
    return [], why


def painted_rollouts(
    long: Sequence[Window], tables: dict[str, list[pa.Table]], rollouts: int, horizon: int
) -> tuple[list[Window], dict[str, list[pa.Table]]]:
    """The painted rollouts of the state rollouts: the first ``rollouts`` windows cut to ``horizon`` predicted frames,
    and each driving state's tables cut to match."""
    windows = [replace(w, horizon=horizon) for w in long[:rollouts]]
    return windows, {k: [t.slice(0, w.length) for t, w in zip(v, windows)] for k, v in tables.items()}


def _long_tables(
    dynamics_dir: Path | str,
    c: Corpus,
    long: Sequence[Window],
    why_not: str,
    proto: EvalProtocol,
    painted: tuple[int, dict[str, Any], Any],
    seed: int,
    log: Callable[[str], Any],
    progress: Progress | None,
) -> tuple[dict, dict, dict]:
    """Table 3's state columns and the long-horizon curves over the long rollouts, the video tables over the first
    ``proto.rollouts`` of them cut to the ``painted`` = (predicted frames, models, extractor) the observation layer
    paints; with no long rollouts each is marked not run with ``why_not``, with some it says why they were cut."""
    fps = model_fps(dynamics_dir)
    horizon, models, extractor = painted
    if not long:
        log(f"evaluate: Tables 1 and 3 not run: {why_not}")
        return (
            {"run": False, "reason": why_not, "conditions": [], "windows": []},
            {"run": False, "reason": why_not, "fps": fps, "drift_m": {}, "body_share": {}},
            {"run": False, "reason": why_not},
        )
    log("evaluate: the driving states on the long rollouts (Table 3)")
    states = ablation_rollouts(dynamics_dir, c, long, temperature=proto.temperature, seed=seed, progress=progress)
    ablation = rule_ablation(dynamics_dir, c, long, rollouts=states) | {"seconds": long[0].horizon / fps, "cut": why_not}
    tables = {k: v["tables"] for k, v in states.items()}
    curves = long_horizon_curves(c, long, tables, proto, fps)
    log("evaluate: the observation layer (Tables 1 and 3)" if models else "evaluate: no observation model: no FVD")
    obs, base = models.get("observation"), models.get("baseline")
    windows, cut = painted_rollouts(long, tables, proto.rollouts, horizon)
    video = video_tables(c, windows, cut, proto, obs, base, extractor=extractor, seed=seed, progress=progress)
    return ablation, curves, video


def _write_report(report: dict, sheet: dict | None, out: Path) -> dict:
    """Write the plots, report.json and report.md to a temp directory beside ``out`` and rename it into place;
    returns the report with its "plots" and "headline"."""
    _check_replaceable(out)
    with atomic_dir(out) as tmp:
        report["plots"] = plot_all(report, sheet, tmp)
        if sheet is not None:
            report["video"]["sheet"] = {k: v for k, v in sheet.items() if k != "rows"} | {"rows": list(sheet["rows"])}
        report["headline"] = headline(report)
        write_json(tmp / "report.json", report)
        write_bytes(tmp / "report.md", render_markdown(report).encode())
    return report


def _load_models(observation: Path | str | None, baseline: Path | str | None) -> dict[str, Any]:
    """The observation model (control "pose") and the baseline (control "actions") given, each checked for its control."""
    from marionette.observation.train import load_model

    out = {}
    for key, path, want in (("observation", observation, "pose"), ("baseline", baseline, "actions")):
        if path is not None:
            m = load_model(path)
            if m.config.control != want:
                raise ValueError(f"{path}: a {key} model is trained with control {want!r}, this one with {m.config.control!r}")
            out[key] = m
    return out


def load_report(out_dir: Path | str) -> dict[str, Any]:
    """A written report's report.json."""
    return read_json(Path(out_dir) / "report.json")
