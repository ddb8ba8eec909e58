"""The report's Markdown: its tables (the paper's Tables 1–3, the baselines, the protocol) from ``report.json``."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from marionette.eval import fvd
from marionette.io import read_json


def _num(x: float | None, digits: int = 4) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pm(s: dict) -> str:
    return "n/a" if s["mean"] is None or not math.isfinite(s["mean"]) else f"{s['mean']:.4f} ± {s['std']:.4f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


STATE_NAMES = {"free": "Free", "force_gt": "Force-GT", "force_shuf": "Force-Shuf", "force_shuf_runs": "run-level shuffle"}


def _fvd_cells(r: dict | None) -> list[str]:
    """value, bias-corrected interval, percentile interval of one Fréchet result (n/a cells when absent)."""
    if not r:
        return ["n/a"] * 3
    return [
        _num(r["value"], 3),
        f"[{_num(r['low'], 3)}, {_num(r['high'], 3)}]",
        f"[{_num(r['raw_low'], 3)}, {_num(r['raw_high'], 3)}]",
    ]


# (model key, baseline key, label, whether higher is better) of a dynamics training summary's held-out figures
_AGAINST = (
    ("action_accuracy", "copy_last_action_accuracy", "next-action accuracy against copy-last", True),
    ("action_accuracy", "most_frequent_action_accuracy", "next-action accuracy against the most frequent action", True),
    ("body_mse", "copy_last_body_mse", "body MSE against copy-last", False),
    ("root_mse", "constant_velocity_root_mse", "root MSE against constant velocity", False),
)


def training_against_baselines(dynamics_dir: Path | str) -> dict[str, Any] | None:
    """The dynamics training directory's held-out figures beside its trivial baselines (``summary.json``'s ``eval``
    and ``baselines``), one row per comparison with whether the model wins; None when the directory has none."""
    path = Path(dynamics_dir) / "summary.json"
    if not Path(dynamics_dir).is_dir() or not path.is_file():
        return None
    summary = read_json(path, max_bytes=1 << 20)
    ev, base = (summary.get(k) if isinstance(summary, dict) else None for k in ("eval", "baselines"))
    if not isinstance(ev, dict) or not isinstance(base, dict):
        return None
    rows = []
    for key, bkey, label, higher in _AGAINST:
        m, b = ev.get(key), base.get(bkey)
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (m, b)):
            raise ValueError(f"{path}: eval.{key} and baselines.{bkey} must be finite numbers, not {m!r} and {b!r}")
        rows.append({"what": label, "model": float(m), "baseline": float(b), "wins": m > b if higher else m < b})
    return {"steps": summary.get("steps"), "windows": ev.get("windows"), "rows": rows}


def _baseline_lines(report: dict) -> list[str]:
    """The report's first lines about the dynamics model against its trivial baselines (held-out, teacher-forced)."""
    tb = report.get("training")
    if not tb:
        return []
    lost = [r for r in tb["rows"] if not r["wins"]]
    head = (
        f"**The dynamics model does not beat every trivial baseline on held-out data** ({len(lost)} of {len(tb['rows'])} "
        "comparisons lost; its budget or its corpus is too small for the vocabulary):"
        if lost
        else "The dynamics model beats every trivial baseline on held-out data:"
    )
    rows = [[r["what"], _num(r["model"]), _num(r["baseline"]), "yes" if r["wins"] else "**no**"] for r in tb["rows"]]
    note = f"From the training run's summary: {tb['steps']} steps, {tb['windows']} held-out windows, one step ahead."
    return [head, "", _table(["comparison", "model", "baseline", "model wins"], rows), "", note, ""]


def _protocol_lines(report: dict) -> list[str]:
    """The report's first lines about its protocol: which counts and lengths are smaller than the paper's."""
    pr = report["protocol"]
    if pr["reduced"]:
        return [
            f"**Protocol `{pr['name']}` is smaller than the paper's**: " + "; ".join(pr["reduced"]) + ". "
            "Its numbers carry wider intervals than the paper's tables (docs/tradeoffs.md, evaluation protocol).",
            "",
        ]
    return [f"Protocol `{pr['name']}`: the paper's counts and lengths.", ""]


def _table1_lines(report: dict) -> list[str]:
    """Table 1: FVD16 and final-chunk FVD of the Marionette column beside the pixel-AR baseline."""
    v, p = report["video"], report["protocol"]
    out = ["## Table 1 — observation layer", ""]
    if not v.get("run"):
        return out + [f"Not run: {v['reason']}.", ""]
    t1 = v["table1"]
    metric = next((r["metric"] for r in t1.values() if r.get("run", True) and "metric" in r), fvd.PROXY_LABEL)
    rows = []
    for key, label in (
        ("marionette", "Marionette (dynamics → bridge → observation, collider on)"),
        ("baseline", "pixel-AR baseline"),
    ):
        r = t1[key]
        if "fvd16" not in r:
            rows.append([label, "n/a", "n/a", "n/a", "n/a", "n/a", "n/a", r.get("reason", "")])
            continue
        rows.append(
            [
                label,
                *_fvd_cells(r["fvd16"]),
                *_fvd_cells(r["final_chunk"]),
                f"{r['rollouts']} rollouts, {r['fvd16']['clips']} clips",
            ]
        )
    out += [
        f"{metric} over {len(v['windows'])} held-out rollouts of {p['rollout_seconds']:g} s ({v['frames']} video frames), "
        f"{p['clips_per_rollout']} clips of {p['clip_frames']} frames per rollout; final chunk = the last {p['final_frames']} "
        f"frames; {p['fvd_steps']} sampling steps; {p['resamples']} clip-bootstrap resamples (95 %).",
        "",
        _table(
            [
                "column",
                f"FVD{p['clip_frames']}",
                "bias-corrected",
                "percentile",
                "final chunk",
                "bias-corrected",
                "percentile",
                "over",
            ],
            rows,
        ),
        "",
    ]
    if metric == fvd.PROXY_LABEL:
        out += [
            "Proxy-FVD uses a fixed random feature extractor (not I3D): comparable only with itself; it is not FVD (--i3d gives FVD).",
            "",
        ]
    out += [f"- window {r['window']} ({r['segment']}, dynamics frame {r['start']}) skipped: {r['reason']}" for r in v["skipped"]]
    return out + [""]


def _table2_lines(report: dict) -> list[str]:
    """Table 2: Free / Force-GT / Force-Shuf / run-level shuffle, the win counts and the per-class Shuf/GT ratios."""
    pr = report["probe"]
    e = pr["entity"]
    out = [f"## Table 2 — Controllability probe ({e})", ""]
    out += [
        _table(
            ["condition", f"{e} RA-MPJPE (m)", "windows"],
            [[STATE_NAMES[k], _pm(v), str(v["n"])] for k, v in pr["conditions"].items()],
        ),
        "",
        f"Force-GT < Force-Shuf on **{pr['force_gt_beats_shuf']} of {pr['compared']}** windows "
        f"(< run-level shuffle on {pr['force_gt_beats_shuf_runs']}). The run-level shuffle permutes whole action runs, "
        "so progress within a run is intact: its gap to Force-GT is the token's effect alone.",
        "",
        f"Per class of the recorded token at each frame: mean per-frame {e} RA-MPJPE (m) over those frames, all windows pooled.",
        "",
    ]
    rows = [
        [
            c,
            str(v["frames"]),
            _num(v["force_gt"]),
            _num(v["force_shuf"]),
            _num(v["force_shuf/force_gt"], 2),
            _num(v["force_shuf_runs/force_gt"], 2),
        ]
        for c, v in pr["class_ratios"].items()
    ]
    out += [_table(["class", "frames", "Force-GT", "Force-Shuf", "Shuf/GT", "run-shuffle/GT"], rows), ""]
    out += [
        "Compliance (secondary): share of the recorded action runs whose motion the corpus's own class rule puts in the forced class.",
        "",
        _table(
            ["class", "runs", "Free", "Force-GT", "recorded"],
            [
                [c, str(v["runs"]), _num(v["free"], 2), _num(v["force_gt"], 2), _num(v["recorded"], 2)]
                for c, v in pr["compliance"].items()
            ],
        ),
        "",
    ]
    return out


def _table3_lines(report: dict) -> list[str]:
    """Table 3: the four driving states at the final frame, with the FVD of each painted by the same observation model."""
    ab, v = report["ablation"], report["video"]
    if not ab.get("run", True):
        return ["## Table 3 — driving states", "", f"Not run: {ab['reason']}.", ""]
    t3 = v.get("table3", {}) if v.get("run") else {}
    rows = []
    for r in ab["conditions"]:
        f = t3.get(r["condition"], {}).get("fvd16")
        rows.append(
            [
                r["condition"],
                _num(r["cfr"], 3),
                _num(r["mmp_m"]),
                _num(r["skate_mps"]),
                _num(r["sep_m"], 2),
                _num(r.get("beyond_cap", float("nan")), 2),
                "n/a" if not f else f"{_num(f['value'], 3)} [{_num(f['low'], 3)}, {_num(f['high'], 3)}]",
                _num(r["on_ground"], 3),
                r["note"],
            ]
        )
    p = report["protocol"]
    segments = len({w["segment"] for w in ab["windows"]})
    seconds = ab.get("seconds", p["rollout_seconds"])
    painted = ""
    if v.get("run") and (len(v["windows"]) < len(ab["windows"]) or seconds > p["rollout_seconds"]):
        painted = f"the first {len(v['windows'])} of them (Table 1's painted rollouts, {p['rollout_seconds']:g} s), "
    return [
        "## Table 3 — driving states",
        "",
        f"{len(ab['windows'])} long rollouts of {seconds:g} s from {segments} held-out segment{'s' * (segments > 1)}; "
        "CFR, MMP, skate and Sep at the **final frame** "
        "(CFR: share of rollouts with a key joint below H − 0.15 m there; means over the articulated entities, per entity in "
        "report.json; Sep horizontal; beyond cap: share of rollouts ending farther apart than max(6 m, their separation at the "
        "seed's last frame), the bound the cap holds; every rollout starts with the pair within 6 m where its segment "
        f"allows). FVD{p['clip_frames']}: {painted}each state painted by the same observation model "
        "(bias-corrected 95 % interval); root on ground: share of frames whose root stands over scanned ground.",
        "",
        *([f"Note: {ab['cut']}.", ""] if ab.get("cut") else []),
        _table(
            [
                "state",
                "CFR",
                "MMP (m)",
                "Skate (m/s)",
                "Sep (m)",
                "beyond cap",
                f"FVD{p['clip_frames']}",
                "root on ground",
                "note",
            ],
            rows,
        ),
        "",
    ]


def _long_lines(report: dict) -> list[str]:
    """The long-horizon figures as tables: root divergence at whole seconds, FVD per chunk index, body share first/last chunk."""
    lh = report["long_horizon"]
    out = ["## Long horizon", ""]
    if not lh.get("run", True):
        return out + [f"Not run: {lh['reason']}.", ""]
    fps = lh["fps"]
    for name, d in lh["drift_m"].items():
        at = [k for k in range(len(d)) if (k + 1) % int(round(fps)) == 0]
        out += [f"Root divergence of the {name} (m, Marionette state against the recorded rows, mean of the rollouts):", ""]
        out += [
            _table(["horizon (s)"] + [f"{(k + 1) / fps:g}" for k in at], [["divergence (m)"] + [_num(d[k], 3) for k in at]]),
            "",
        ]
    v = report["video"]
    if v.get("run"):
        series = [(k, r) for k, r in v["table1"].items() if "per_chunk" in r]
        if series:
            spans = series[0][1]["per_chunk"]
            out += [f"{series[0][1]['metric']} per chunk index ({report['protocol']['final_frames']} frames each):", ""]
            out += [
                _table(
                    ["column"] + [f"chunk {c['chunk']} ({c['frames'][0]}–{c['frames'][1]})" for c in spans],
                    [[k] + [_num(c["value"], 3) for c in r["per_chunk"]] for k, r in series],
                ),
                "",
            ]
    bs = lh["body_share"]
    rows = [[s, n, _num(x["first"], 4), _num(x["last"], 4)] for s, per in bs.items() for n, x in per.items()]
    out += ["Body share of the pose-control frame (follow camera) in the first and the last chunk:", ""]
    return out + [_table(["state", "entity", "first chunk", "last chunk"], rows), ""]


def render_markdown(report: dict) -> str:
    """The report's markdown: the protocol, Tables 1–3, the long-horizon figures, the state layer, the contact sheet."""
    st = report["state_layer"]
    ws = report["windows"]
    out = [f"# Evaluation of `{report['dynamics']}`", ""] + _protocol_lines(report) + _baseline_lines(report)
    out += [
        f"Corpus `{report['corpus']}`; probe windows: {len(ws)} of {report['seed_frames']} seed + {report['horizon']} "
        f"predicted frames at {report['fps']:g} fps (split {report['split']!r}, window seed {report['seed']}, temperature "
        f"{report['temperature']:g}).",
        "",
    ]
    out += _table1_lines(report) + _table2_lines(report) + _table3_lines(report) + _long_lines(report)
    out += ["## State layer (Free rollouts of the probe windows, rules auto)", ""]
    rows = [
        [k.split("/")[0], k.split("/")[1], _pm(v["generated"]), _pm(v["recorded"]), str(v["generated"]["n"])]
        for k, v in st["metrics"].items()
    ]
    out += [_table(["metric", "entity", "generated", "recorded", "windows"], rows), ""]
    out += [f"- {n}" for n in st["notes"]] + [
        "- RA-MPJPE and root drift compare with the recorded rows: 0 on the recorded side by definition.",
        "- body share: follow camera, pose-control frame rendered at "
        f"{report['render_size'][0]}×{report['render_size'][1]}, weapon counted for its owner.",
        "",
    ]
    if "contact_sheet" in report["plots"]:
        sheet = report["video"]["sheet"]
        out += [
            "## Contact sheet",
            "",
            f"The first long rollout at video frames {sheet['frames']} (source frames from {sheet['source_frames'][0]}): "
            "pose-control frames, painted frames and the recorded RGB, top to bottom.",
            "",
            f"![contact sheet]({report['plots']['contact_sheet']})",
            "",
        ]
    out += ["## Plots", ""] + [f"![{k}]({v})" for k, v in report["plots"].items() if k != "contact_sheet"] + [""]
    return "\n".join(out)
