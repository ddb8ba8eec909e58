"""Compare two `marionette demo` runs made with the same options and the same --out path (one moved aside first).

Every file is compared byte for byte. A file that differs is explained when its difference is one two runs of the
same code also show, else listed: a sample record whose only difference is its input files' mtimes (the recordings
are synthesised anew), a checkpoint's optimizer file whose only difference is ``rng.torch`` (torch seeds each process
at random), TensorBoard event files (named by the time and pid). Then every value of ``evaluation/report.json``.
Exit status 1 when anything else differs.

    python scripts/compare_demo_runs.py BEFORE AFTER
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from safetensors.numpy import load_file

EVENTS = "events.out.tfevents."


def files(root: Path) -> set[str]:
    """Every file under ``root`` but TensorBoard's event files, relative to it."""
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and not p.name.startswith(EVENTS)}


def same_but_mtimes(a: bytes, b: bytes) -> bool:
    """Two sample records equal once each input file's [size, mtime_ns, sha256] loses its mtime."""
    ja, jb = json.loads(a), json.loads(b)
    for record in (ja, jb):
        for entry in record.get("files", {}).values():
            entry[1] = None
    return ja == jb


def same_but_rng(a: Path, b: Path) -> bool:
    """Two optimizer files with the same tensors but for ``rng.torch``."""
    ta, tb = load_file(a), load_file(b)
    return set(ta) == set(tb) and all(np.array_equal(ta[k], tb[k]) for k in ta if k != "rng.torch")


def flat(x: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted path, value) of every leaf of a JSON value."""
    if isinstance(x, dict):
        for k, v in x.items():
            yield from flat(v, f"{prefix}.{k}" if prefix else k)
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from flat(v, f"{prefix}[{i}]")
    else:
        yield prefix, x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    a = ap.parse_args(argv)
    fa, fb = files(a.before), files(a.after)
    one_side = sorted(fa ^ fb)
    same, mtimes, rng, other = 0, 0, 0, []
    for k in sorted(fa & fb):
        x, y = (a.before / k).read_bytes(), (a.after / k).read_bytes()
        if x == y:
            same += 1
        elif k.startswith("corpus/meta/samples/") and k.endswith(".json") and same_but_mtimes(x, y):
            mtimes += 1
        elif k.endswith("optimizer.safetensors") and same_but_rng(a.before / k, a.after / k):
            rng += 1
        else:
            other.append(k)
    print(f"files: {len(fa)} and {len(fb)} (TensorBoard event files left out); on one side only: {len(one_side)}")
    print(
        f"byte-identical: {same}; sample records differing only in their input files' mtimes: {mtimes}; "
        f"optimizer files differing only in rng.torch: {rng}; other differences: {len(other)}"
    )
    for k in one_side + other:
        print(f"  {k}")
    ra = dict(flat(json.loads((a.before / "evaluation" / "report.json").read_text())))
    rb = dict(flat(json.loads((a.after / "evaluation" / "report.json").read_text())))
    moved = [(k, ra.get(k), rb.get(k)) for k in sorted(set(ra) | set(rb)) if ra.get(k) != rb.get(k)]
    print(f"report.json: {len(set(ra) | set(rb))} values compared; values that differ: {len(moved)}")
    for k, x, y in moved:
        print(f"  {k}: {x!r} -> {y!r}")
    return 1 if one_side or other or moved else 0


if __name__ == "__main__":
    sys.exit(main())
