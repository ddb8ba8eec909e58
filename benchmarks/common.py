"""Shared helpers for the hand-run benchmarks: machine description, timing, markdown tables.

Benchmarks are scripts (``.venv/bin/python benchmarks/bench_x.py``), not tests: each makes its own
seeded synthetic input in a temp dir and prints markdown tables to paste into ``docs/tradeoffs.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOAD_AT_START = os.getloadavg()[0]
if str(ROOT) not in sys.path:  # `python benchmarks/bench_x.py` puts benchmarks/ on sys.path, not the repo root
    sys.path.insert(0, str(ROOT))


def single_thread_env() -> None:
    """Pin BLAS/OpenMP pools to one thread; call before numpy is imported."""
    for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[v] = "1"


def psnr(ref, got) -> float:
    """Peak signal-to-noise ratio (dB) of two uint8 arrays of one shape (an image, or frames (T, H, W, 3)) over all
    their values, the squared errors summed exactly a leading slice at a time."""
    import numpy as np  # here: a benchmark pins its thread pools before numpy loads (``single_thread_env``)

    se = sum(int(np.square(np.subtract(x, y, dtype=np.int32)).sum()) for x, y in zip(ref, got, strict=True))
    mse = se / np.asarray(ref).size
    return float(10 * np.log10(255**2 / max(mse, 1e-12)))


def machine() -> str:
    """One line: CPU model, logical cores, RAM, Python and library versions."""
    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram = "?"
    try:
        kb = int(next(x for x in Path("/proc/meminfo").read_text().splitlines() if x.startswith("MemTotal")).split()[1])
        ram = f"{kb / 2**20:.1f} GiB"
    except (OSError, StopIteration):
        pass
    import numpy
    import pyarrow

    return (
        f"{cpu}, {os.cpu_count()} logical cores, {ram} RAM; Python {platform.python_version()}, "
        f"numpy {numpy.__version__}, pyarrow {pyarrow.__version__}"
    )


def command() -> str:
    """The command line that ran this benchmark, as typed from the repo root."""
    return " ".join([".venv/bin/python", os.path.relpath(sys.argv[0], ROOT), *sys.argv[1:]])


def time_call(fn: Callable[[], object], repeats: int, warmup: int = 1) -> tuple[float, object]:
    """Median wall time (s) of ``fn()`` over ``repeats`` runs after ``warmup`` runs; and its last result."""
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def size_hw(text: str) -> tuple[int, int]:
    """An image size given as HxW (e.g. 176x320) → (height, width); an argparse error for anything else."""
    h, sep, w = text.lower().partition("x")
    if not (sep and h.isdigit() and w.isdigit() and int(h) > 0 and int(w) > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: a size is HxW in pixels, e.g. 176x320")
    return int(h), int(w)


def table(header: list[str], rows: list[list[object]]) -> str:
    """A markdown table; floats are printed as given (format them before)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def load_average() -> str:
    """1-minute load average at the start and now (this run included), against the core count:
    figures taken while other work ran are suspect."""
    return f"{LOAD_AT_START:.2f} at start, {os.getloadavg()[0]:.2f} at end, {os.cpu_count()} cores"


def revision() -> str:
    """The measured code: git HEAD, and whether the library's working tree differs from it."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "marionette", "flows"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        return "unknown"
    return f"{head}{' + uncommitted library changes' if dirty else ''}"


def preamble(title: str) -> str:
    """Heading lines every benchmark prints: title, machine, command, load average."""
    return (
        f"## {title}\n\nmachine: {machine()}\n\ncode: {revision()}\n\n"
        f"command: `{command()}` (1-min load average: {load_average()})\n"
    )
