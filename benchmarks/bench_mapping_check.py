"""The scan's check of the depth mapping: how far each recording's scanned ground stands from where its characters'
feet stood, with the true mapping, the default decoder and the calibrated mapping.

    .venv/bin/python benchmarks/bench_mapping_check.py [--seeds 0,1,3] [--recordings 4] [--seconds 6] [--size 128x72]

For each seed, a synthetic source of two stages whose game hides its depth mapping (``marionette synth --stages 2
--hidden-depth``: the seed draws the kind and the planes), made in a temp dir. Each recording is scanned (every frame)
with the true mapping, with the default decoder (what a new user scans with) and with the mapping
``calibrate-depth`` fits from the whole source; each row gives the gap (``ScanResult.contact_gap_m``: over the
0.5 m cells holding both, the median of the depth's ground height less the contacts' height), the cells holding
both, the cells holding a contact, and whether the scan's check (``ScanOptions.max_contact_gap_m``, 0.5 m; or no
ground on ten or more contact cells) lets the recording into the terrain.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import preamble, size_hw, table  # noqa: E402

from marionette.recordings.wildworld import discover  # noqa: E402
from marionette.schema import load_scene  # noqa: E402
from marionette.synth import generate, load_truth  # noqa: E402
from terrain_scan import calibrate  # noqa: E402
from terrain_scan.accumulate import scan_recording  # noqa: E402
from terrain_scan.depth import DepthDecoder  # noqa: E402
from terrain_scan.options import MAX_CONTACT_GAP_M, ScanOptions  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,3")
    ap.add_argument("--recordings", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--size", type=size_hw, default=(72, 128), help="HxW")
    a = ap.parse_args()
    print(preamble("The scan's depth-mapping check"))
    layout, rows = load_scene("duel"), []
    for seed in (int(s) for s in a.seeds.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            src = Path(tmp) / "src"
            h, w = a.size
            generate(src, recordings=a.recordings, seconds=a.seconds, seed=seed, width=w, height=h, stages=2, hidden_depth=True)
            refs = discover(src)
            fitted = calibrate.calibrate_recordings(refs, layout, 3, knobs=ScanOptions().scan_kwargs())[0].chosen
            for ref in refs:
                truth = DepthDecoder.from_json(load_truth(src, ref.part, ref.sample_id)["depth_encoding"])
                for name, dec in (("true", truth), ("default", DepthDecoder.synthetic()), ("calibrated", fitted)):
                    r = scan_recording(ref, layout, dec)
                    gap = r.contact_gap_m
                    rows.append(
                        [
                            seed,
                            truth.kind,
                            ref.sample_id,
                            name,
                            "—" if gap != gap else f"{gap:+.3f}",
                            r.contact_gap_cells,
                            r.contact_cells,
                            "kept" if r.mapping_misfit(MAX_CONTACT_GAP_M) is None else "refused",
                        ]
                    )
    print(table(["seed", "hidden kind", "recording", "mapping", "gap (m)", "cells with both", "contact cells", "check"], rows))


if __name__ == "__main__":
    main()
