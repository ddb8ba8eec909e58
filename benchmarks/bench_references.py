"""Persistent entity references against appearance drift: the small observation DiT with and without them.

    .venv/bin/python benchmarks/bench_references.py [--recordings 12] [--seconds 40] [--steps 3000] [--out DIR]
        [--reduce 2 --patch 2] [--arms default,drift,references,tokens,handoff,references-handoff] [--given-only]
        [--handoff SIGMA] [--seeds 0,1,2]

A synthetic tree where appearance must be read from the video — each recording's monster and player in colours
of their own (``synth --skins``) and a player who looks around, so that the bodies leave the view and come back
(``synth --camera-pans``) — ingested at 36 × 64, its terrain scanned and its pose targets rendered. Arms of
the tests' observation recipe (18 × 32 and patch 2 unless ``--reduce``/``--patch`` say otherwise, 5-frame clips,
batch 4, lr 1e-3, a fifth of the clips given another chunk's first frame), differing only in what is named: the default model; the same with its first
frames' bodies drifted in colour (σ 0.3, ``--first-frame-drift``); and with references and that drift
(``--references``: each entity's crop read as tokens and laid over its body in every frame); and the same with the
crops only read as tokens (``--no-reference-paint``); the drift arm and the reference arm with hand-off noise 0.4
(``--handoff-noise``: relayed at the model's σ, or ``--handoff``'s). Each relays every held-out video of 161 frames
(40 chunks, 8 sampling steps) from its recorded first frame (``quality.relay_videos``, ``quality.entity_drift``); the
reference arms also without their references (unless ``--given-only``).

Printed: per arm, the per-entity colour error (|mean generated − mean recorded RGB| over the entity's mask, RGB
in [−1, 1]) over the first and the last quarter of the relay's chunks and their difference (the growth), the
colour error where the entity stayed in view and where it left the view and came back, and the pixel error's
growth; and the same colour error with every chunk started from its recorded frame (``forced``: no relay, the
references from the recorded frames) — its growth is what the later frames ask anyway (bodies turned from their first
look, back into view), and the growth of relayed − forced is the relay's own drift; and the colour error of the
bodies the relay's first frame showed (whose look it was given: their drift, relayed and forced) apart from the
others' (a look the relay must invent). ``--seeds 0,1,2``: every arm trained from each seed, and two more tables: each arm's
mean ± standard deviation over the seeds, and each arm less the first arm seed by seed (the growth of one seed's run
moves by about 0.02 between seeds, more than the arms' margins: docs/tradeoffs.md). ``--out`` keeps the corpus, the
runs and their relays' measures (a second run with the same --out reuses them).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import preamble, table  # noqa: I001  (benchmarks/ on sys.path)

from marionette.corpus import Corpus
from marionette.ingest import IngestOptions, VideoSettings, build_corpus
from marionette.observation.config import ObservationTrainConfig
from marionette.observation.data import ClipSource
from marionette.observation.quality import drift_growth, entity_drift, quarters, relay_videos
from marionette.observation.references import layout_bands
from marionette.observation.train import load_model, train

RECIPE = ObservationTrainConfig(preset="tiny", batch_size=4, frames=5, reduce=2, patch=2, lr=1e-3, warmup=20)
ARMS = {  # key: (row name, knobs)
    "default": ("default", {}),
    "drift": ("first-frame drift 0.3", {"first_frame_drift": 0.3}),
    "references": ("references + drift 0.3", {"references": True, "first_frame_drift": 0.3}),
    "tokens": ("reference tokens only + drift 0.3", {"references": True, "reference_paint": False, "first_frame_drift": 0.3}),
    "handoff": ("drift 0.3 + hand-off noise 0.4", {"first_frame_drift": 0.3, "handoff_noise": 0.4}),
    "references-handoff": (
        "references + drift 0.3 + hand-off noise 0.4",
        {"references": True, "first_frame_drift": 0.3, "handoff_noise": 0.4},
    ),
}


def build(root: Path, recordings: int, seconds: float) -> Path:
    from marionette.bridge.targets import render_pose_targets
    from marionette.synth import generate
    from terrain_scan.options import ScanOptions
    from terrain_scan.scan import scan_stages

    corpus = root / "corpus"
    if (corpus / "meta" / "info.json").exists():
        return corpus
    generate(
        root / "recordings", recordings=recordings, seconds=seconds, seed=21, width=96, height=54, workers=2, skins=True,
        camera_pans=True,
    )  # fmt: skip
    options = IngestOptions(video=VideoSettings(height=36, width=64, chunk_frames=81, crf=28))
    build_corpus(root / "recordings", corpus, options, workers=2, progress=False)
    scan_stages(corpus, incremental=True, options=ScanOptions(frame_stride=4), log=lambda *_: None)
    render_pose_targets(corpus)
    return corpus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--steps", type=int, default=3000, help="training steps per arm")
    ap.add_argument("--chunks", type=int, default=40, help="relay chunks per held-out video")
    ap.add_argument("--out", type=Path, default=None, help="keep the corpus and runs here (default: a temp dir)")
    ap.add_argument("--reduce", type=int, default=2, help="the 36 × 64 chunks divided by this for the model")
    ap.add_argument("--patch", type=int, default=2, help="the model's patch side in pixels")
    ap.add_argument("--arms", default=",".join(ARMS), help=f"which arms, of {', '.join(ARMS)}")
    ap.add_argument(
        "--seeds", default="0", help="the arms' training seeds, comma-separated (weights, clips, noise); more than one "
        "adds each arm's mean ± spread over them and each arm less the first, seed by seed"
    )  # fmt: skip
    ap.add_argument("--handoff", type=float, default=None, help="hand-off noise arms: the relay's σ (default: the model's)")
    ap.add_argument("--given-only", action="store_true", help="reference arms: skip the relays with references withheld")
    a = ap.parse_args()
    if a.handoff is not None and not 0 <= a.handoff <= 2:
        ap.error(f"--handoff {a.handoff}: a noise σ within [0, 2]")
    arms = a.arms.split(",")
    if not arms or any(k not in ARMS for k in arms):
        ap.error(f"--arms {a.arms!r}: a comma-separated choice of {', '.join(ARMS)}")
    if 36 % a.reduce or 64 % a.reduce or (36 // a.reduce) % a.patch or (64 // a.reduce) % a.patch:
        ap.error(f"--reduce {a.reduce} --patch {a.patch}: 36 × 64 must reduce to whole patches")
    try:
        seeds = [int(x) for x in a.seeds.split(",")]
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0 or len(set(seeds)) < len(seeds):
        ap.error(f"--seeds {a.seeds!r}: distinct whole numbers ≥ 0, comma-separated")
    recipe = replace(RECIPE, reduce=a.reduce, patch=a.patch)
    size = (36 // a.reduce, 64 // a.reduce)
    root = a.out or Path(tempfile.mkdtemp(prefix="bench-references-"))
    t0 = time.perf_counter()
    corpus = build(root, a.recordings, a.seconds)
    print(f"corpus {corpus} ready in {time.perf_counter() - t0:.0f} s")
    c = Corpus(corpus)
    bands = layout_bands(c.layouts.values())
    videos = relay_videos(ClipSource(c, "test", RECIPE.frames, size), 1 + 4 * a.chunks, 2 * a.chunks)
    torch.set_num_threads(1)
    rows, runs = [], {}  # runs: (row name, seed) -> relay measures
    for seed in seeds:
        for key in arms:
            name, knobs = ARMS[key]
            shape = ("" if (a.reduce, a.patch) == (2, 2) else f"-r{a.reduce}p{a.patch}") + (f"-seed{seed}" if seed else "")
            run = root / f"run-{a.steps}{shape}-{name.replace(' ', '-').replace('+', 'and')}"
            if not (run / "summary.json").exists():
                t0 = time.perf_counter()
                cfg = replace(recipe, seed=seed, steps=a.steps, **knobs)
                summary = train(corpus, run, cfg, log=lambda *_: None)
                held_out = summary["evals"][-1]["held_out_loss"]
                print(f"{name}, seed {seed}: trained in {time.perf_counter() - t0:.0f} s, held-out loss {held_out:.4f}")
            model = load_model(run)
            for given in (True, False) if model.config.references and not a.given_only else (True,):
                handoff = a.handoff if model.config.handoff_noise else None
                m = measure(run, model, videos, bands, a.chunks, given, handoff)
                label = name + ("" if given else ", references withheld")
                runs[label, seed] = m
                rows.append(row(label + (f", seed {seed}" if len(seeds) > 1 else ""), m))
                print(rows[-1], flush=True)
    print(preamble("Persistent entity references: per-entity appearance error over relays (measured)"))
    print(
        f"{len(videos)} held-out videos of {1 + 4 * a.chunks} frames ({a.chunks} chunks of 5) at {size[0]} × {size[1]}, "
        f"patch {a.patch}, {a.recordings} × {a.seconds:.0f} s recordings, {a.steps} steps per arm, training seeds "
        f"{', '.join(map(str, seeds))}; pairs {m['pairs']}"
    )
    print(table(HEAD, rows))
    if len(seeds) > 1:
        print(over_seeds(runs, seeds))


HEAD = [
    "arm",
    "colour, first ¼",
    "colour, last ¼",
    "growth",
    "forced: first ¼ → last ¼",
    "forced growth",
    "the relay's growth",
    "stayed in view",
    "after leaving the view",
    "pixel growth",
    "shown in the first frame: first ¼ → last ¼",
    "its growth",
    "its forced growth",
    "not shown in the first frame: first ¼ → last ¼",
]


def measure(run: Path, model, videos, bands, chunks: int, given: bool, handoff: float | None) -> dict:
    """``entity_drift`` relayed and forced, kept in the run's directory (keyed by chunks, references, hand-off σ) so
    that a later call — another seed's, or the summary over seeds — reads it instead of relaying again."""
    cache = run / f"relay-{chunks}c-{'references' if given else 'withheld'}-handoff{handoff}.npz"
    if cache.exists():
        with np.load(cache, allow_pickle=False) as z:
            m = {k: z[k] for k in z.files}
        m["pairs"] = {"in_view": int(m.pop("pairs_in_view")), "after_gap": int(m.pop("pairs_after_gap"))}
        return m
    d = entity_drift(model, videos, bands, steps=8, references=given, handoff=handoff)
    forced = entity_drift(model, videos, bands, steps=8, references=given, forced=True)
    m = {k: np.asarray(d[k]) for k in ("colour", "pixel", "known", "unknown", "in_view", "after_gap")}
    m |= {"forced_colour": np.asarray(forced["colour"]), "forced_known": np.asarray(forced["known"])}
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, pairs_in_view=d["pairs"]["in_view"], pairs_after_gap=d["pairs"]["after_gap"], **m)
    tmp.replace(cache)
    return m | {"pairs": d["pairs"]}


def row(label: str, m: dict) -> list[str]:
    def span(errors: np.ndarray) -> str:
        return "{:.4f} → {:.4f}".format(*quarters(errors))

    colour, f, known = m["colour"], m["forced_colour"], m["known"]
    return [
        label,
        *(f"{x:.4f}" for x in quarters(colour)),
        f"{drift_growth(colour):+.4f}",
        span(f),
        f"{drift_growth(f):+.4f}",
        f"{drift_growth(colour - f):+.4f}",
        f"{float(m['in_view']):.4f}",
        f"{float(m['after_gap']):.4f}",
        f"{drift_growth(m['pixel']):+.4f}",
        span(known),
        f"{drift_growth(known):+.4f}",
        f"{drift_growth(m['forced_known']):+.4f}",
        span(m["unknown"]),
    ]


def over_seeds(runs: dict, seeds: list[int]) -> str:
    """Two tables over the training seeds: each arm's mean ± standard deviation, and each arm less the first arm
    seed by seed (a paired difference: both trained from the same seed), with the mean difference's standard error
    and in how many seeds the arm's value is the lower."""
    measures = {
        "growth": lambda m: drift_growth(m["colour"]),
        "known growth": lambda m: drift_growth(m["known"]),
        "relay's growth": lambda m: drift_growth(m["colour"] - m["forced_colour"]),
        "colour, last ¼": lambda m: quarters(m["colour"])[1],
        "known, last ¼": lambda m: quarters(m["known"])[1],
    }
    labels = list(dict.fromkeys(label for label, _ in runs))
    values = {(label, k): np.array([f(runs[label, s]) for s in seeds]) for label in labels for k, f in measures.items()}
    spread = [
        [label]
        + [f"{values[label, k].mean():{'+' if 'growth' in k else ''}.4f} ± {values[label, k].std(ddof=1):.4f}" for k in measures]
        for label in labels
    ]
    n, base, paired = len(seeds), labels[0], []
    for label in labels[1:]:
        cells = []
        for k in measures:
            diff = values[label, k] - values[base, k]
            cells.append(f"{diff.mean():+.4f} ± {diff.std(ddof=1) / np.sqrt(n):.4f} ({int((diff < 0).sum())}/{n} lower)")
        paired.append([f"{label} − {base}"] + cells)
    out = f"Over {n} training seeds: mean ± standard deviation\n\n" + table(["arm", *measures], spread)
    if paired:
        out += "\n\nSeed by seed, less the first arm: mean ± standard error (seeds where it is lower)\n\n"
        out += table(["arms", *measures], paired)
    return out


if __name__ == "__main__":
    main()
