"""Depth calibration: its error against the frames it uses and the share of invalid cameras, and the terrain's error
against the calibration's.

    .venv/bin/python benchmarks/bench_calibration.py [--seeds 0,3] [--recordings 2] [--seconds 10] [--size 160x90]
        [--strides 1,3,10,30] [--invalid 0,0.5,0.9]

For each seed, a synthetic source whose game hides its depth mapping (``marionette synth --hidden-depth``: the
seed draws the kind, log or inverse, and the planes), made in a temp dir and not timed. Its (code, joint) pairs are
gathered once at every frame; each row keeps every ``stride``-th frame, drops a share ``invalid`` of the frames
(seeded) as if their cameras were invalid, fits (``terrain_scan.depth_fit.fit``) and reports the largest relative
depth error of the fitted mapping against the hidden one over 2–20 m (what the scan reads: its ``max_depth_m`` is 20)
and over 2–100 m, its seconds, and the terrain RMSE (away from steps, one recording scanned at frame stride 2) that
scanning with it gives, beside the RMSE with the true mapping; then the same two after the contact scale
(``fit_contact_scale``: the ground where the feet stood; its pass reads every ``stride``-th frame, all cameras valid),
which ``marionette calibrate-depth`` applies unless ``--no-contact-scale``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from common import preamble, table  # noqa: E402

from marionette.recordings.wildworld import discover  # noqa: E402
from marionette.schema import load_scene  # noqa: E402
from marionette.synth import generate, load_truth  # noqa: E402
from marionette.synth import terrain as synth_terrain  # noqa: E402
from terrain_scan import calibrate, contact_scale, depth_fit  # noqa: E402
from terrain_scan.accumulate import scan_recording  # noqa: E402
from terrain_scan.depth import DepthDecoder  # noqa: E402
from terrain_scan.options import ScanOptions


def max_error(dec: DepthDecoder, truth: DepthDecoder, lo: float, hi: float) -> float:
    z = np.geomspace(max(lo, truth.z_near), min(hi, truth.z_far), 400)
    return float(np.max(np.abs(dec.depth_of(truth.code_of(z)) - z) / z))


def terrain_rmse(ref, layout, dec: DepthDecoder) -> float:
    obs = scan_recording(ref, layout, dec, frame_stride=2).observations
    x, z = obs.gx + 0.5, obs.gz + 0.5
    d = obs.h - synth_terrain.surface_height(x, z, obs.h)
    away = ~synth_terrain.near_step(x, z, 0.6)
    return float(np.sqrt(np.mean(d[away] ** 2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=lambda s: [int(v) for v in s.split(",")], default=[0, 3])
    ap.add_argument("--recordings", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--size", default="160x90", help="WxH of the synthetic recordings")
    ap.add_argument("--strides", type=lambda s: [int(v) for v in s.split(",")], default=[1, 3, 10, 30])
    ap.add_argument("--invalid", type=lambda s: [float(v) for v in s.split(",")], default=[0.0, 0.5, 0.9])
    args = ap.parse_args()
    w, _, h = args.size.partition("x")
    if min(args.strides) < 1 or not all(0 <= v < 1 for v in args.invalid) or args.recordings < 1:
        ap.error("--strides ≥ 1, --invalid in [0, 1), --recordings ≥ 1")
    layout = load_scene("duel")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_calibration_") as tmp:
        for seed in args.seeds:
            root = Path(tmp) / f"seed{seed}"
            generate(root, args.recordings, args.seconds, seed, int(w), int(h), hidden_depth=True, workers=2)
            refs = discover(root)
            truth = DepthDecoder.from_json(load_truth(root, refs[0].part, refs[0].sample_id)["depth_encoding"])
            every = depth_fit.Pairs.concat(list(calibrate.iter_pairs(refs, layout, 1)))
            true_rmse = terrain_rmse(refs[0], layout, truth)
            label = f"{truth.kind}, near {truth.z_near:g} m, far {truth.z_far:g} m"
            rows.append([str(seed), label, "true mapping", "", "", "", "", "", f"{true_rmse:.4f}", "", ""])
            frames = np.unique(every.frame)
            for stride in args.strides:
                for share in args.invalid:
                    rng = np.random.default_rng(seed)
                    kept = frames[(frames % 10_000_000) % stride == 0]
                    kept = kept[rng.random(len(kept)) >= share]
                    pairs = every.take(np.isin(every.frame, kept))
                    pairs.offset = pairs.offset.copy()
                    head = [str(seed), label, str(stride), f"{share:.0%}", str(len(kept)), f"{len(pairs):,}"]
                    t = time.perf_counter()
                    try:
                        cal = depth_fit.fit(pairs)
                    except ValueError as exc:
                        rows.append([*head, str(exc)[:40], "", "", "", ""])
                        continue
                    secs = time.perf_counter() - t
                    errors = [100 * max_error(cal.chosen, truth, 2, hi) for hi in (20, 100)]
                    rmse = terrain_rmse(refs[0], layout, cal.chosen)
                    points = calibrate.iter_contact_points(refs, layout, cal.chosen, stride, ScanOptions().scan_kwargs())
                    cs = contact_scale.fit_contact_scale([p for p in points if not isinstance(p, str)])
                    scaled = cal.with_contact_scale(cs).chosen
                    after = [100 * max_error(scaled, truth, 2, hi) for hi in (20, 100)]
                    rows.append(
                        [
                            *head,
                            f"{cal.chosen.kind} {errors[0]:.2f} % / {errors[1]:.2f} %",
                            f"{secs:.2f}",
                            f"{rmse:.4f}",
                            f"× {cs.scale:.4f}: {after[0]:.2f} % / {after[1]:.2f} %" if cs.applied else cs.note[:40],
                            f"{terrain_rmse(refs[0], layout, scaled):.4f}",
                        ]
                    )
                    print(rows[-1], file=sys.stderr, flush=True)
    print(preamble("Depth calibration: error against frames and invalid cameras; terrain error against it"))
    header = ["seed", "hidden mapping", "frame stride", "invalid cameras", "frames", "pairs"]
    header += ["fitted: max error 2–20 m / 2–100 m", "fit s", "terrain RMSE away m"]
    header += ["contact scale: max error 2–20 m / 2–100 m", "terrain RMSE away m, contact scale"]
    print(table(header, rows))


if __name__ == "__main__":
    main()
